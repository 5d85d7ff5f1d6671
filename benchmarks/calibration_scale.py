"""Calibration time and peak memory against the number of frames:
`python benchmarks/calibration_scale.py --json --frames 100 200 500`.

For each count, a fresh process simulates that many `paper`-protocol frames of one
`high`-fidelity Mid unit (seed 3: its deviations from the design are drawn from the seed),
runs `calibrate` on them, and scores the fit on `--heldout` mixed loads of the same unit.
Reported per count: the time of the whole calibration (fitting the physical parameters,
then inverting every calibration frame cold for the residual head), its peak resident
memory (host) and the device allocator's peak, and the held-out R² with the residual head. Each count runs in its own process so that its peak
memory is its own. The floor it compares with is the time of the cold inversion of one
frame, measured in the same process: the head's stage cannot cost less than one such
solve per frame.
"""

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _device import device_summary

import moirejax as mj


def _stage(name: str, since: float) -> float:
    """Print a finished stage and its seconds (stderr, so a run cut short still shows them)."""
    now = time.perf_counter()
    print(f"{name}: {now - since:.1f} s", file=sys.stderr, flush=True)
    return now


def _one(n: int, heldout: int) -> dict:
    root = Path(tempfile.mkdtemp(prefix="moirejax-calibration-scale-"))
    nominal = mj.preset("mid")
    mj.save_device(root / "mid.json", nominal)
    t0 = time.perf_counter()
    mj.simulate_dataset(root / "cal", nominal, "paper", n, seed=3, overwrite=True, progress=False)
    mj.simulate_dataset(root / "test", nominal, "mixed", heldout, seed=3, overwrite=True, progress=False)
    simulate_s = time.perf_counter() - t0
    _stage(f"simulate {n} + {heldout} frames", t0)

    # The floor: cold solves of loaded calibration frames with the nominal device (after
    # the compile), one per frame being what the head's stage of a calibration pays.
    dataset = mj.Dataset(root / "cal")
    inverter = mj.Inverter(nominal, reference=mj.dataset_reference(dataset), match_reference=False)
    loaded = np.argsort(-np.abs(dataset.wrenches[:, 2]))[:5]
    t0 = time.perf_counter()
    mj.invert(inverter, dataset.frame(int(loaded[0]))).wrench.block_until_ready()
    solve_compile_s = time.perf_counter() - t0
    times = []
    for i in loaded:
        frame = dataset.frame(int(i))
        t0 = time.perf_counter()
        mj.invert(inverter, frame).wrench.block_until_ready()
        times.append(time.perf_counter() - t0)
    _stage(f"cold solves (compile {solve_compile_s:.1f} s, median {np.median(times):.2f} s)", t0)

    t0 = time.perf_counter()
    mj.calibrate(root / "mid.json", root / "cal", root / "fit.json", max_frames=None, baseline_sizes=(), progress=True)
    calibrate_s = time.perf_counter() - t0
    _stage("calibrate", t0)
    t0 = time.perf_counter()
    scored = mj.evaluate(root / "fit.json", root / "test", root / "after", progress=False)
    evaluate_s = time.perf_counter() - t0
    return {
        "frames": n,
        "simulate_s": round(simulate_s, 1),
        "calibrate_s": round(calibrate_s, 1),
        "evaluate_s": round(evaluate_s, 1),
        "cold_solve_floor_ms": round(1e3 * float(np.median(times)), 1),
        "cold_solve_compile_s": round(solve_compile_s, 1),
        "frames_per_s": round(n / calibrate_s, 2),
        "heldout_r2": {a: round(float(v), 4) for a, v in scored["r2"].items()},
        "heldout_frames": heldout,
        "peak_memory_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
        **device_summary(),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, nargs="+", default=[100, 200, 500])
    parser.add_argument("--heldout", type=int, default=40)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one is not None:
        print(json.dumps(_one(args.one, args.heldout)))
        return
    rows = []
    for n in args.frames:
        command = [sys.executable, __file__, "--one", str(n), "--heldout", str(args.heldout)]
        # The stages' progress goes straight to this process's stderr.
        done = subprocess.run(command, stdout=subprocess.PIPE, text=True)
        if done.returncode != 0:
            rows.append({"frames": n, "failed": f"exit code {done.returncode}"})
        else:
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps({"runs": rows}, indent=2))
    else:
        for row in rows:
            print(row)


if __name__ == "__main__":
    main()
