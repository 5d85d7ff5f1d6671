"""Inversion accuracy of a known unit: `python benchmarks/invert_accuracy.py --json`.

`mixed` loads of the Mid design (`--frames`, in contact), each inverted independently from
a cold start, in three cases:

1. `noise_free`: `model`-fidelity frames (the inversion's own forward model, no noise);
2. `noisy`: the same frames with Gaussian pixel noise (`--noise`, fraction of full scale)
   and 8-bit quantisation: R² and how often the 95% intervals cover the truth;
3. `high_fidelity_uncalibrated`: `high`-fidelity frames of a unit that deviates from its
   design (seed 3), inverted with the nominal design and the unit's own reference frame,
   before any calibration.

Per axis: R², RMSE, 95% coverage; and the contact-centre error (mm) for the model frames.
"""

import argparse
import json
import tempfile
import time
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj
from moirejax import (
    Contact,
    dataset_reference,
    invert,
    Inverter,
    load_schedule,
    render_frame,
    simulate_dataset,
    wrench_metrics,
)


def _summary(truth, result, schedule=None) -> dict:
    metrics = wrench_metrics(truth, result.wrench, result.sigma)
    out = {k: {a: round(v, 5) for a, v in metrics[k].items()} for k in ("r2", "rmse", "coverage95")}
    statuses, counts = np.unique(result.status, return_counts=True)
    out["status_counts"] = {mj.Status(int(s)).name.lower(): int(c) for s, c in zip(statuses, counts)}
    if schedule is not None:
        centre = np.hypot(result.contact.x0 - schedule.x0, result.contact.y0 - schedule.y0)
        out["centre_error_mm"] = {"median": float(np.median(centre)), "max": float(np.max(centre))}
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--model-shape", type=int, default=None, help="inversion model grid (default: model_grid_for)")
    args = parser.parse_args(argv)
    grid = None if args.model_shape is None else (args.model_shape, args.model_shape)

    device = mj.preset("mid")
    schedule = load_schedule("mixed", args.frames + 8, seed=11)
    keep = np.flatnonzero(schedule.contact)[: args.frames]
    render = jax.jit(lambda w, x0, y0, r: jnp.clip(render_frame(device, w, Contact(x0, y0, r)), 0.0, 1.0))
    clean = [
        np.asarray(render(jnp.asarray(schedule.wrench[i]), schedule.x0[i], schedule.y0[i], schedule.radius[i]))
        for i in keep
    ]
    reference = np.asarray(render(jnp.zeros(6), 0.0, 0.0, 3.5))
    rng = np.random.default_rng(0)

    def noisy(frame):
        return np.round(np.clip(frame + rng.normal(0.0, args.noise, frame.shape), 0, 1) * 255) / 255

    truth = schedule.wrench[keep]
    sub = types.SimpleNamespace(x0=schedule.x0[keep], y0=schedule.y0[keep])
    result = {}
    start = time.perf_counter()
    inverter = Inverter(device, reference=reference, model_shape=grid)
    result["noise_free"] = _summary(truth, invert(inverter, clean), sub)
    reference_noisy = np.mean([noisy(reference) for _ in range(8)], axis=0)
    inverter = Inverter(device, reference=reference_noisy, model_shape=grid)
    result["noisy"] = _summary(truth, invert(inverter, [noisy(f) for f in clean]), sub)

    with tempfile.TemporaryDirectory() as tmp:
        data = simulate_dataset(Path(tmp) / "unit", device, "mixed", args.frames + 8, seed=3, progress=False)
        dataset = mj.Dataset(data)
        idx = np.flatnonzero(dataset.contact)[: args.frames]
        inverter = Inverter(device, reference=dataset_reference(dataset), model_shape=grid)
        inverted = invert(inverter, [dataset.frame(int(i)) for i in idx])
        result["high_fidelity_uncalibrated"] = _summary(dataset.wrenches[idx], inverted)
    result["frames"] = int(len(keep))
    result["model_grid"] = list(inverter.model_shape)
    result["noise"] = args.noise
    result["elapsed_s"] = round(time.perf_counter() - start, 1)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for case in ("noise_free", "noisy", "high_fidelity_uncalibrated"):
            print(f"{case:28s} R2 " + " ".join(f"{a} {v:.4f}" for a, v in result[case]["r2"].items()))


if __name__ == "__main__":
    main()
