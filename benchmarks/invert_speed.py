"""Per-frame inversion speed on 512x512 frames: `python benchmarks/invert_speed.py --json`.

Prints the warm single-frame latency (median, p90), the batched throughput, the compile
time, peak memory, and the floor: the same frame demodulated by the plain numpy/OpenCV
Fourier-transform method, which any pipeline pays before it can solve anything.
"""

import argparse
import json
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj
from moirejax._contact import Contact
from moirejax._inversion import invert_batch, invert_frame, Inverter
from moirejax._observables import NumpyDemodulator
from moirejax._render import render_frame
from moirejax._simulate import load_schedule


def _percentiles(times):
    times = np.asarray(times) * 1e3
    return float(np.median(times)), float(np.percentile(times, 90))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--batch", type=int, default=16)
    args = parser.parse_args(argv)

    device = mj.preset("mid")
    inverter = Inverter(device, reference=render_frame(device, jnp.zeros(6), Contact()))
    # A stream: a slow press and twist, so consecutive frames are close, as at camera rate.
    n = args.frames
    t = np.linspace(0, 1, n)
    wrenches = np.stack([0.05 * t, 0 * t, 0.3 + 0.6 * t, 0 * t, 0 * t, 0.004 * t], axis=1)
    frames = [render_frame(device, jnp.asarray(w), Contact(1.0, -0.5, 3.5)) for w in wrenches]
    cold = jnp.full(10, jnp.nan)

    start = time.perf_counter()
    estimate = invert_frame(inverter, frames[0], cold)
    estimate.wrench.block_until_ready()
    compile_s = time.perf_counter() - start

    times, steps = [], []
    state = estimate.state
    for frame in frames[1:]:
        start = time.perf_counter()
        estimate = invert_frame(inverter, frame, state)
        estimate.wrench.block_until_ready()
        times.append(time.perf_counter() - start)
        steps.append(int(estimate.steps))
        state = estimate.state
    median_ms, p90_ms = _percentiles(times)

    # Cold-start latency (a jump to an unrelated load).
    mixed = load_schedule("mixed", 12, seed=4)
    cold_times = []
    for i in range(len(mixed)):
        frame = render_frame(device, jnp.asarray(mixed.wrench[i]), mixed.contact_at(i))
        start = time.perf_counter()
        invert_frame(inverter, frame, cold).wrench.block_until_ready()
        cold_times.append(time.perf_counter() - start)
    cold_median_ms, cold_p90_ms = _percentiles(cold_times)

    batch = jnp.stack([frames[i % len(frames)] for i in range(args.batch)])
    start = time.perf_counter()
    invert_batch(inverter, batch).wrench.block_until_ready()
    batch_compile_s = time.perf_counter() - start
    start = time.perf_counter()
    repeats = 3
    for _ in range(repeats):
        invert_batch(inverter, batch).wrench.block_until_ready()
    batched_fps = repeats * args.batch / (time.perf_counter() - start)

    floor = NumpyDemodulator(inverter.demodulator, np.float32)
    frame_np = np.asarray(frames[-1], dtype=np.float32)
    floor(frame_np)
    floor_times = []
    for _ in range(50):
        start = time.perf_counter()
        floor(frame_np)
        floor_times.append(time.perf_counter() - start)
    floor_median_ms, _ = _percentiles(floor_times)

    result = {
        "frame_shape": [device.height, device.width],
        "median_ms": median_ms,
        "p90_ms": p90_ms,
        "fps_single": 1e3 / median_ms,
        "median_steps": float(np.median(steps)),
        "cold_median_ms": cold_median_ms,
        "cold_p90_ms": cold_p90_ms,
        "batched_fps": batched_fps,
        "batch": args.batch,
        "compile_s": compile_s,
        "batch_compile_s": batch_compile_s,
        "floor_median_ms": floor_median_ms,
        "ratio_to_floor": median_ms / floor_median_ms,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "devices": [str(d) for d in jax.devices()],
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k:18s} {v}")


if __name__ == "__main__":
    main()
