"""Inverting a recording on a local Dask cluster: `python benchmarks/cluster_invert.py --json`.

A `sequence` recording of `--frames` frames of the Mid design (`model` fidelity, 1 % noise
added by the simulator's camera) is inverted in segments of `--segment` frames: in this
process ([`mj.invert_recording`] with `restart_every`, the floor), then by
[`mj.invert_distributed`] on local clusters of 1, 2 and 4 worker processes
(`--workers`). Every run starts from a warm persistent compilation cache (a first,
untimed run fills it), so the times are the inversion's plus the cluster's start and the
workers' loading of the compiled programs; that overhead is reported separately as the
time of a run on a one-segment recording. Printed: seconds, frames/s, the speed-up over
one worker and the scaling efficiency (speed-up / workers), whether each output equals the
single-process file, and the peak memory of this process.
"""

import argparse
import json
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import jax
from _device import device_summary

import moirejax as mj


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, default=96)
    parser.add_argument("--segment", type=int, default=24)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--size", type=int, default=512, help="frame side in pixels (Mid's field at any size)")
    args = parser.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="moirejax-distributed-"))
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(work / "jax-cache"))
    jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
    try:
        device = mj.preset("mid", height=args.size, width=args.size, px_per_mm=16.0 * args.size / 512)
        mj.simulate_dataset(work / "seq", device, "sequence", args.frames, seed=3, fidelity="model", progress=False)
        reference = mj.dataset_reference(mj.open_dataset(work / "seq"))
        inverter = mj.Inverter(device, reference=reference)

        start = time.perf_counter()
        mj.invert_recording(inverter, work / "seq", work / "warm.csv", restart_every=args.segment, progress=False)
        compile_s = time.perf_counter() - start
        start = time.perf_counter()
        mj.invert_recording(inverter, work / "seq", work / "local.csv", restart_every=args.segment, progress=False)
        local_s = time.perf_counter() - start
        local = (work / "local.csv").read_text()

        # The cluster's own cost: start, ship the inverter, load the programs, one small segment.
        mj.simulate_dataset(work / "one", device, "sequence", 2, seed=4, fidelity="model", progress=False)
        start = time.perf_counter()
        mj.invert_distributed(inverter, work / "one", work / "one.csv", segment=2, workers=1, progress=False)
        overhead_s = time.perf_counter() - start

        runs = []
        for workers in args.workers:
            out = work / f"dask{workers}.csv"
            start = time.perf_counter()
            mj.invert_distributed(inverter, work / "seq", out, segment=args.segment, workers=workers, progress=False)
            seconds = time.perf_counter() - start
            runs.append(
                {
                    "workers": workers,
                    "s": seconds,
                    "fps": args.frames / seconds,
                    "same_as_local": out.read_text() == local,
                }
            )
        base = runs[0]["fps"] if runs and runs[0]["workers"] == 1 else None
        for run in runs:
            if base is not None:
                run["speedup"] = run["fps"] / base
                run["efficiency"] = run["speedup"] / run["workers"]
        result = {
            "frames": args.frames,
            "frame_shape": [device.height, device.width],
            "segment": args.segment,
            "cpu_count": os.cpu_count(),
            "local_s": local_s,
            "local_fps": args.frames / local_s,
            "local_first_run_s": compile_s,
            "cluster_overhead_s": overhead_s,
            "runs": runs,
            "floor": "the same segments inverted in this process (local_fps), measured in the same run",
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            **device_summary(),
        }
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k:20s} {v}")


if __name__ == "__main__":
    main()
