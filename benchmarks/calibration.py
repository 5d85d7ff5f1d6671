"""Calibration, transfer and the learned baseline: `python benchmarks/calibration.py --json`.

Two `high`-fidelity units of the Mid design (seeds 3 and 43) whose true parameters deviate
from nominal (pitch ±2%, angle ±0.5°, separation ±5%, stiffness ±30%, binary gratings,
distortion, blur, noise); nothing after the simulation is told the deviations.

1. unit A: `--frames` `paper`-protocol calibration frames, `calibrate` (timed), then
   `evaluate` on `--heldout` held-out `mixed` loads: R², MAE, coverage, physics only and
   with the residual head;
2. the ridge baseline trained on 20, 100 and `--frames` of A's calibration frames, scored
   on the same held-out loads;
3. unit B: `transfer` from A's fit with 20 of B's `paper` frames (timed), `evaluate` on B's
   held-out loads, beside A's fit applied to B unchanged and the ridge baseline on B's 20.

`--keep DIR` keeps the datasets, fits and report plots there (default: a temporary folder).
"""

import argparse
import json
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from _device import device_summary

import moirejax as mj
from moirejax import calibrate, evaluate, heldout_ridge_r2, simulate_dataset, transfer


def _rounded(metrics: dict, keys=("r2", "mae", "coverage95")) -> dict:
    return {k: {a: float(np.round(v, 5)) for a, v in metrics[k].items()} for k in keys}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, default=500, help="calibration frames of unit A")
    parser.add_argument("--heldout", type=int, default=100, help="held-out mixed frames per unit")
    parser.add_argument("--transfer-frames", type=int, default=20)
    parser.add_argument("--keep", metavar="DIR")
    args = parser.parse_args(argv)

    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="moirejax-calibration-"))
    root.mkdir(parents=True, exist_ok=True)
    nominal = mj.preset("mid")
    mj.save_device(root / "mid.json", nominal)
    seed_a, seed_b = 3, 43
    t0 = time.perf_counter()
    # One seed per unit: it draws the unit's deviations and fabrication; the protocols draw
    # different loads from it.
    for unit, seed, n_cal in (("a", seed_a, args.frames), ("b", seed_b, max(args.transfer_frames + 8, 40))):
        simulate_dataset(root / f"{unit}_cal", nominal, "paper", n_cal, seed=seed, overwrite=True)
        simulate_dataset(root / f"{unit}_test", nominal, "mixed", args.heldout, seed=seed, overwrite=True)
    simulate_s = time.perf_counter() - t0

    before = evaluate(root / "mid.json", root / "a_test", root / "a_before")
    # A kept folder may hold the parts of an interrupted run, which calibrate would resume.
    shutil.rmtree(root / "fit_a.json.parts", ignore_errors=True)
    t0 = time.perf_counter()
    summary = calibrate(root / "mid.json", root / "a_cal", root / "fit_a.json", baseline_sizes=())
    calibrate_s = time.perf_counter() - t0
    after = evaluate(root / "fit_a.json", root / "a_test", root / "a_after")
    ridge_a = heldout_ridge_r2(root / "a_cal", root / "a_test", (20, 100, args.frames))

    untransferred = evaluate(root / "fit_a.json", root / "b_test", root / "b_untransferred")
    t0 = time.perf_counter()
    transfer(root / "fit_a.json", root / "b_cal", root / "fit_b.json", max_frames=args.transfer_frames)
    transfer_s = time.perf_counter() - t0
    transferred = evaluate(root / "fit_b.json", root / "b_test", root / "b_after")
    ridge_b = heldout_ridge_r2(root / "b_cal", root / "b_test", (args.transfer_frames,))

    result = {
        "calibration_frames": args.frames,
        "heldout_frames": args.heldout,
        "simulate_s": round(simulate_s, 1),
        "calibrate_s": round(calibrate_s, 1),
        "transfer_s": round(transfer_s, 1),
        "unit_a": {
            "before_calibration": _rounded(before),
            "physics_only": _rounded(after["physics_only"]) if "physics_only" in after else None,
            "calibrated": _rounded(after),
            "parameters": summary["parameters"],
            "ridge_r2": ridge_a,
        },
        "unit_b": {
            "a_fit_unchanged": _rounded(untransferred),
            "transferred": _rounded(transferred),
            "ridge_r2": ridge_b,
        },
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        **device_summary(),
        "folder": str(root),
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for unit, entries in (("A", result["unit_a"]), ("B", result["unit_b"])):
            for name, metrics in entries.items():
                if isinstance(metrics, dict) and "r2" in metrics:
                    print(f"unit {unit} {name:20s} R2 " + " ".join(f"{a} {v:.4f}" for a, v in metrics["r2"].items()))
        print(f"calibrate {calibrate_s:.0f} s, transfer {transfer_s:.0f} s")
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
