"""Which JAX device a benchmark ran on, and the peak memory it held there.

Host memory (`ru_maxrss`) misses what lives on an accelerator, so GPU runs report the
device allocator's own peak beside it.
"""

import jax


def device_summary() -> dict:
    device = jax.local_devices()[0]
    stats = device.memory_stats() or {}
    peak = stats.get("peak_bytes_in_use")
    return {
        "backend": jax.default_backend(),
        "device": device.device_kind,
        "device_peak_mb": None if peak is None else peak / 2**20,
    }
