"""Per-frame inversion speed on 512x512 frames: `python benchmarks/invert_speed.py --json`.

Prints the streaming single-frame latency (median, p90: `frame_tracker`, each frame
continuing from the last, as `moirejax live` and `moirejax invert` run; and through
`Inverter.track` under `eqx.filter_jit`, which flattens the inverter at every call), the
cold-start latency (Levenberg–Marquardt from the brightness guess), the throughput of a
recording inverted in vectorised chunks (`invert(..., sequence=True)`), the compile time, peak memory, and the floor: the same frame
demodulated by the plain numpy/OpenCV Fourier-transform method, which any pipeline pays
before it can solve anything. Frames carry 1% pixel noise and 8-bit quantisation.
"""

import argparse
import json
import resource
import time

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from _device import device_summary

import moirejax as mj
from moirejax import (
    axis_ranges,
    Contact,
    frame_tracker,
    invert,
    Inverter,
    load_schedule,
    NumpyDemodulator,
    render_frame,
)


def _percentiles(times):
    times = np.asarray(times) * 1e3
    return float(np.median(times)), float(np.percentile(times, 90))


def _stream(inverter, device, frames, wrenches) -> dict:
    """Frame-by-frame latencies: the stream, the stream through a generic jit, cold starts."""
    step = frame_tracker(inverter)
    start = time.perf_counter()
    estimate, track = step(frames[0], inverter.cold_track())
    estimate.wrench.block_until_ready()
    compile_s = time.perf_counter() - start

    times, steps, errors, stream_wrenches = [], [], [], []
    for i, frame in enumerate(frames[1:], start=1):
        start = time.perf_counter()
        estimate, track = step(frame, track)
        estimate.wrench.block_until_ready()
        times.append(time.perf_counter() - start)
        steps.append(int(estimate.steps))
        errors.append(np.asarray(estimate.wrench) - wrenches[i])
        stream_wrenches.append(np.asarray(estimate.wrench))
    median_ms, p90_ms = _percentiles(times)

    # The same stream through a generic jit of the per-frame function (the inverter flattened
    # at every call).
    track_frame = eqx.filter_jit(Inverter.track)
    _, track = track_frame(inverter, frames[0], inverter.cold_track())
    generic_times = []
    for frame in frames[1:]:
        start = time.perf_counter()
        estimate, track = track_frame(inverter, frame, track)
        estimate.wrench.block_until_ready()
        generic_times.append(time.perf_counter() - start)
    track_frame_median_ms, _ = _percentiles(generic_times)

    # Cold-start latency (a jump to an unrelated load).
    mixed = load_schedule("mixed", 12, seed=4)
    cold_times = []
    for i in range(len(mixed)):
        frame = render_frame(device, jnp.asarray(mixed.wrench[i]), mixed.contact_at(i))
        start = time.perf_counter()
        invert(inverter, frame).wrench.block_until_ready()
        cold_times.append(time.perf_counter() - start)
    cold_median_ms, cold_p90_ms = _percentiles(cold_times)

    return {
        "median_ms": median_ms,
        "p90_ms": p90_ms,
        "fps_single": 1e3 / median_ms,
        "track_frame_median_ms": track_frame_median_ms,
        "median_steps": float(np.median(steps)),
        "max_steps": int(np.max(steps)),
        "stream_rmse_over_range": (np.sqrt(np.mean(np.square(errors), axis=0)) / np.asarray(axis_ranges()))
        .round(4)
        .tolist(),
        "cold_median_ms": cold_median_ms,
        "cold_p90_ms": cold_p90_ms,
        "compile_s": compile_s,
        "stream_wrenches": stream_wrenches,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument(
        "--batched-only",
        action="store_true",
        help="only the chunked recording's throughput and the floor (an accelerator's quick measure)",
    )
    args = parser.parse_args(argv)

    device = mj.preset("mid")
    inverter = Inverter(device, reference=render_frame(device, jnp.zeros(6), Contact()))
    # A stream: a press and twist at camera rate, so consecutive frames are close.
    n = args.frames
    t = np.linspace(0, 1, n)
    wrenches = np.stack([0.05 * t, 0 * t, 0.3 + 0.6 * t, 0 * t, 0 * t, 0.004 * t], axis=1)
    rng = np.random.default_rng(0)

    def camera(frame):
        noisy = np.asarray(frame) + rng.normal(0, 0.01, frame.shape)
        return (np.round(np.clip(noisy, 0, 1) * 255) / 255).astype(np.float32)

    frames = [camera(render_frame(device, jnp.asarray(w), Contact(1.0, -0.5, 3.5))) for w in wrenches]

    result = {"frame_shape": [device.height, device.width]}
    if not args.batched_only:
        result.update(_stream(inverter, device, frames, wrenches))
    start = time.perf_counter()
    invert(inverter, frames[: args.batch], sequence=True, batch=args.batch)
    batch_compile_s = time.perf_counter() - start
    # The whole recording, its first frame a cold start, as `moirejax invert --batch` runs it.
    # Three passes, the median reported: the first pass after compiling reads 5-10% slower.
    passes = []
    for _ in range(3):
        start = time.perf_counter()
        chunked = invert(inverter, frames, sequence=True, batch=args.batch)
        passes.append(len(frames) / (time.perf_counter() - start))
    batched_fps = float(np.median(passes))
    if "stream_wrenches" in result:
        # The chunked recording should agree with the stream to within the estimates' sigma.
        stream = np.asarray(result.pop("stream_wrenches"))
        result["sequence_minus_stream_max_sigmas"] = float(
            np.max(np.abs(chunked.wrench[1:] - stream) / chunked.sigma[1:])
        )

    floor = NumpyDemodulator(inverter.demodulator, np.float32)
    frame_np = np.asarray(frames[-1], dtype=np.float32)
    floor(frame_np)
    floor_times = []
    for _ in range(50):
        start = time.perf_counter()
        floor(frame_np)
        floor_times.append(time.perf_counter() - start)
    floor_median_ms, _ = _percentiles(floor_times)

    result.update(
        {
            "batched_fps": batched_fps,
            "batched_fps_passes": passes,
            "batch": args.batch,
            "frames": len(frames),
            "batched_fps_method": "invert(sequence=True): chunks vectorised from the previous chunk's solution, "
            "the first frame a cold start",
            "batch_compile_s": batch_compile_s,
            "floor_median_ms": floor_median_ms,
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            **device_summary(),
        }
    )
    if "median_ms" in result:
        result["ratio_to_floor"] = result["median_ms"] / floor_median_ms
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k:18s} {v}")


if __name__ == "__main__":
    main()
