"""Render-time benchmark of `model`-fidelity frames: single, vmapped batches, compile time, memory.

    python benchmarks/render.py            # table
    python benchmarks/render.py --json     # JSON
    python benchmarks/render.py --stages   # also time each stage of render_frame separately

Times are wall clock on whatever JAX backend is active (the CPU unless told otherwise).
`compile_s` is the first call (trace, compile and one run). Memory is the process's
peak resident set (`ru_maxrss`, monotone over the run, so cases go from small to large)
and the rise of that peak during the case.
"""

import argparse
import json
import os
import platform
import resource
import statistics
import sys
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj
from moirejax import Contact, deformation, render_frame
from moirejax.physics import camera_response, scene_radiance, separable_gaussian_blur


def _peak_mb() -> float:
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # Linux reports KiB, macOS bytes.
    return rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024


def _timings(fn, args, repeats: int) -> tuple[float, list[float]]:
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return compile_s, times


def _summary(times: list[float], frames_per_call: int) -> dict[str, float]:
    per_frame = np.asarray(times) / frames_per_call
    return {
        "median_ms": 1e3 * float(np.median(per_frame)),
        "p90_ms": 1e3 * float(np.percentile(per_frame, 90)),
        "min_ms": 1e3 * float(np.min(per_frame)),
        "frames_per_s": 1.0 / float(np.median(per_frame)),
    }


def _wrenches(batch: int) -> jax.Array:
    rng = np.random.default_rng(0)
    ranges = np.array([mj.PAPER_RANGES[axis] for axis in mj.WRENCH_AXES])
    w = rng.uniform(-1, 1, (batch, 6)) * ranges
    w[:, 2] = np.abs(w[:, 2])
    return jnp.asarray(w)


def bench_size(size: int, px_per_mm: float, batch: int, repeats: int, mechanics: int) -> dict:
    device = mj.preset("mid", height=size, width=size, px_per_mm=px_per_mm)
    contact = Contact(x0=jnp.asarray(0.0), y0=jnp.asarray(0.0), radius=jnp.asarray(3.5))
    wrenches = _wrenches(batch)
    shape = (mechanics, mechanics)
    out: dict = {"size": size, "px_per_mm": px_per_mm, "layout": device.layout, "mechanics_shape": list(shape)}

    single = eqx.filter_jit(lambda d, w, c: render_frame(d, w, c, mechanics_shape=shape))
    before = _peak_mb()
    compile_s, times = _timings(single, (device, wrenches[0], contact), repeats)
    out["single"] = {
        "compile_s": compile_s,
        **_summary(times, 1),
        "peak_mb": _peak_mb(),
        "peak_rise_mb": _peak_mb() - before,
    }

    batched = eqx.filter_jit(lambda d, w, c: jax.vmap(lambda wi: render_frame(d, wi, c, mechanics_shape=shape))(w))
    before = _peak_mb()
    compile_s, times = _timings(batched, (device, wrenches, contact), max(3, repeats // 2))
    out["batched"] = {
        "batch": batch,
        "compile_s": compile_s,
        **_summary(times, batch),
        "peak_mb": _peak_mb(),
        "peak_rise_mb": _peak_mb() - before,
    }
    return out


def bench_stages(size: int, px_per_mm: float, repeats: int, mechanics: int) -> dict[str, float]:
    """Median ms of each of the four stages of `render_frame`, each jitted on its own (fusion across stages is lost)."""
    device = mj.preset("mid", height=size, width=size, px_per_mm=px_per_mm)
    contact = Contact(x0=jnp.asarray(0.0), y0=jnp.asarray(0.0), radius=jnp.asarray(3.5))
    wrench = _wrenches(1)[0]
    shape = (device.height, device.width)

    mechanics_fn = eqx.filter_jit(lambda d, w, c: deformation(d, w, c, (mechanics, mechanics)))
    state = mechanics_fn(device, wrench, contact)

    def upsample(field):
        # The cubic interpolation render_frame applies from the mechanics grid to the pixels.
        return jax.image.resize(field, (*field.shape[:-2], *shape), method="cubic")

    upsample_fn = eqx.filter_jit(lambda s: (upsample(s.displacement), upsample(s.light)))
    displacement, light = upsample_fn(state)
    # render_deformed is these two stages: the scene radiance, then the lens PSF and the camera.
    radiance_fn = eqx.filter_jit(scene_radiance)
    radiance = radiance_fn(device, displacement, light)
    camera_fn = eqx.filter_jit(lambda d, r: camera_response(d, separable_gaussian_blur(r, d.optics.psf_sigma)))
    stages = {
        "mechanics (tractions, layer FFT solve, light)": (mechanics_fn, (device, wrench, contact)),
        "upsample displacement and light to the image": (upsample_fn, (state,)),
        "grating phases and Fourier transmissions": (radiance_fn, (device, displacement, light)),
        "PSF blur and camera response": (camera_fn, (device, radiance)),
    }
    out = {}
    for name, (fn, args) in stages.items():
        _, times = _timings(fn, args, repeats)
        out[name] = 1e3 * statistics.median(times)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON")
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 800])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--mechanics", type=int, default=128, help="mechanics grid (render_frame's default is 256)")
    parser.add_argument("--stages", action="store_true", help="time each stage of render_frame")
    args = parser.parse_args(argv)
    # The paper's rectified 800x800 frames are at 20 px/mm; 512x512 is the preset's 16 px/mm.
    resolution = {512: 16.0, 800: 20.0}
    result = {
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "jax": jax.__version__,
        "dtype": str(jnp.asarray(0.0).dtype),
        "target": "512x512 model frame <= 10 ms per frame, batched",
        "cases": [],
    }
    for size in sorted(args.sizes):
        case = bench_size(size, resolution.get(size, 16.0), args.batch, args.repeats, args.mechanics)
        if args.stages:
            case["stages_ms"] = bench_stages(size, resolution.get(size, 16.0), args.repeats, args.mechanics)
        result["cases"].append(case)
    result["peak_mb"] = _peak_mb()
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"backend {result['backend']} ({result['cpu_count']} cpus), jax {result['jax']}, {result['dtype']}")
    for case in result["cases"]:
        for mode in ("single", "batched"):
            r = case[mode]
            label = f"{case['size']}x{case['size']} {mode}" + (f" x{r['batch']}" if mode == "batched" else "")
            print(
                f"{label:22s} median {r['median_ms']:8.2f} ms/frame  p90 {r['p90_ms']:8.2f}  "
                f"{r['frames_per_s']:7.1f} frames/s  compile {r['compile_s']:5.2f} s  peak {r['peak_mb']:7.0f} MB"
            )
        for name, ms in case.get("stages_ms", {}).items():
            print(f"    {name:50s} {ms:8.2f} ms")
    print(f"process peak RSS {result['peak_mb']:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
