"""Frames with effects the inversion does not model, one family at a time:
`python benchmarks/mismatch_families.py [--frames 24] [--families scene,duty] [--json]`.

Every family renders `mixed` loads of the same unit through the `high`-fidelity simulator
with one thing changed that the inversion's model lacks or holds at a nominal value; the
inversion gets the nominal design and the unit's own no-contact frames as its reference,
and no calibration. Families:

- `control`: the simulator's defaults (binary gratings, distortion 0.004, grating phase
  error 0.05 rad, shot and read noise, 8 bits): what every other family is compared with;
- `scene`: a different natural scene behind the sensor in every frame (a blurred crop of one
  of scikit-image's bundled photographs multiplying the light, 0.5 to 1.2), the reference
  frames with scenes of their own;
- `no_glow`: an elastomer that scatters no light under a contact (no glow, no rim);
- `strong_glow`: three times the glow, twice as wide, and three times the rim;
- `distortion`: five times the residual lens distortion (0.02 at the corner);
- `duty`: gratings whose open fractions are 0.5 and 0.7 where the design says 0.6 and 0.6;
- `phase_error`: three times the upper grating's slit placement error (0.15 rad);
- `blur`: twice the lens PSF (1.2 px) and three times the far grating's defocus (0.06 mm).

Per family: R² and 95% interval coverage per axis over the loaded frames, how many loaded
frames came back "no contact", the status counts, and the seconds per frame. With
`--baseline N` (default 100; 0 skips it) the cross-validated pixel-ridge baseline that
`calibrate` reports is trained on N `paper`-protocol frames of the same family and scored
on the same loads, in the same table.

With `--calibrate N` each family's unit is also calibrated as a lab would: N `paper`-protocol
frames of it (isolated axes only) and its no-contact frames are written as a dataset,
`moirejax calibrate` fits it from the nominal design (the `unit` recipe, timed), and
`moirejax evaluate` scores the fit on the same mixed loads: held-out R² and coverage with
the residual head and from the calibrated physics alone, the fitted parameters, and the
pixel baseline that `calibrate` cross-validates on those frames.
"""

import argparse
import contextlib
import csv
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import skimage.data

import moirejax as mj


FAMILIES = ("control", "scene", "no_glow", "strong_glow", "distortion", "duty", "phase_error", "blur")
_PHOTOGRAPHS = ("camera", "astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry")
_REFERENCE_FRAMES = 4


def _unit_and_camera(family: str, nominal: mj.Device) -> tuple[mj.Device, mj.HighFidelity]:
    optics = nominal.optics
    if family == "no_glow":
        optics = eqx.tree_at(lambda o: (o.glow_gain, o.rim_gain), optics, (optics.glow_gain * 0, optics.rim_gain * 0))
    elif family == "strong_glow":
        optics = eqx.tree_at(
            lambda o: (o.glow_gain, o.glow_width, o.rim_gain),
            optics,
            (optics.glow_gain * 3, optics.glow_width * 2, optics.rim_gain * 3),
        )
    elif family == "blur":
        optics = eqx.tree_at(lambda o: (o.psf_sigma, o.defocus), optics, (optics.psf_sigma * 2, optics.defocus * 3))
    unit = dataclasses.replace(nominal, optics=optics)
    if family == "duty":
        unit = dataclasses.replace(unit, duty1=0.5, duty2=0.7)
    camera = mj.HighFidelity()
    if family == "distortion":
        camera = mj.HighFidelity(distortion=0.02)
    elif family == "phase_error":
        camera = mj.HighFidelity(phase_error=0.15)
    return unit, camera


def _scene(rng: np.random.Generator, shape: tuple[int, int], px_per_mm: float) -> np.ndarray:
    """A natural scene's light behind the sensor: a random crop of a bundled photograph,
    blurred as an object a few mm off the focal plane is, scaled to 0.5..1.2."""
    image = getattr(skimage.data, _PHOTOGRAPHS[rng.integers(len(_PHOTOGRAPHS))])()
    if image.ndim == 3:
        image = image[..., :3].mean(axis=-1)
    image = image.astype(np.float32)
    h, w = shape
    scale = rng.uniform(1.0, 2.0) * max(h / image.shape[0], w / image.shape[1])
    image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)
    top = rng.integers(0, image.shape[0] - h + 1)
    left = rng.integers(0, image.shape[1] - w + 1)
    crop = image[top : top + h, left : left + w]
    crop = cv2.GaussianBlur(crop, (0, 0), sigmaX=float(rng.uniform(0.5, 1.5) * px_per_mm))
    crop = (crop - crop.min()) / max(float(np.ptp(crop)), 1e-6)
    return (0.5 + 0.7 * crop).astype(np.float32)


def _render(family, unit, camera, schedule, seed):
    render = eqx.filter_jit(mj.render_frame_high)
    rng = np.random.default_rng(seed)
    key = jr.PRNGKey(seed)
    fabrication = jr.PRNGKey(7)
    shape = (unit.height, unit.width)
    frames = []
    for i in range(len(schedule)):
        exposure = _scene(rng, shape, float(unit.px_per_mm)) if family == "scene" else jnp.ones(shape)
        frame = render(
            jr.fold_in(key, i),
            unit,
            jnp.asarray(schedule.wrench[i]),
            schedule.contact_at(i),
            camera,
            exposure=jnp.asarray(exposure),
            fabrication_key=fabrication,
        )
        frames.append(np.asarray(frame, np.float32))
    return np.stack(frames)


def _at_rest(n: int) -> mj.LoadSchedule:
    zeros = np.zeros(n)
    return mj.LoadSchedule(np.zeros((n, 6)), zeros, zeros, zeros + 3.0, np.zeros(n, bool))


def _write_dataset(folder: Path, nominal: mj.Device, rest: np.ndarray, frames: np.ndarray, schedule) -> Path:
    """A dataset of the no-contact frames `rest` followed by `frames` under `schedule`'s loads."""
    with mj.DatasetWriter(folder, device=mj.device_to_json(nominal), source="mismatch_families") as writer:
        for frame in rest:
            writer.add(np.round(frame * 255).astype(np.uint8), np.zeros(6), contact=False)
        for i, frame in enumerate(frames):
            writer.add(np.round(frame * 255).astype(np.uint8), schedule.wrench[i], contact=bool(schedule.contact[i]))
    return folder


def _calibrated(family, nominal, unit, camera, schedule, test, rest, n, seed) -> dict:
    """Calibrate the family's unit on `n` paper-protocol frames and score it on `test`."""
    paper = mj.load_schedule("paper", n, seed=seed + 3)
    with tempfile.TemporaryDirectory(prefix=f"mismatch-{family}-") as folder:
        root = Path(folder)
        mj.save_device(root / "nominal.json", nominal)
        _write_dataset(root / "cal", nominal, rest, _render(family, unit, camera, paper, seed + 3000), paper)
        _write_dataset(root / "test", nominal, rest, test, schedule)
        start = time.perf_counter()
        fit = mj.calibrate(root / "nominal.json", root / "cal", root / "fit.json", max_frames=None, progress=False)
        calibrate_s = time.perf_counter() - start
        held_out = mj.evaluate(root / "fit.json", root / "test", root / "evaluation", progress=False)
    physics = held_out.get("physics_only", held_out)
    return {
        "calibration_frames": n,
        "calibrate_s": round(calibrate_s, 1),
        "held_out_r2": held_out["r2"],
        "held_out_coverage95": held_out["coverage95"],
        "held_out_r2_physics_only": physics["r2"],
        "parameters": {p["parameter"]: round(p["fitted"], 5) for p in fit["parameters"]},
        "pixel_baseline_r2_crossvalidated": fit["baselines"],
        "verdict": fit["verdict"],
    }


def run_family(
    family: str,
    nominal: mj.Device,
    frames: int,
    baseline: int,
    seed: int,
    rows: csv.DictWriter | None = None,
    calibrate: int = 0,
) -> dict:
    unit, camera = _unit_and_camera(family, nominal)
    schedule = mj.load_schedule("mixed", frames, seed=seed)
    loaded = np.asarray(schedule.contact, bool)
    test = _render(family, unit, camera, schedule, seed)
    rest = _render(family, unit, camera, _at_rest(_REFERENCE_FRAMES), seed + 1000)
    reference = rest.mean(axis=0)
    start = time.perf_counter()
    inverter = mj.Inverter(nominal, reference)
    first = mj.invert(inverter, jnp.asarray(test[0]))
    jax.block_until_ready(first.wrench)
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    estimate = jax.device_get(mj.invert(inverter, jnp.asarray(test), progress=True, desc=family))
    per_frame = (time.perf_counter() - start) / len(test)
    status = np.asarray(estimate.status)
    if rows is not None:
        for i in range(len(test)):
            rows.writerow(
                {
                    "family": family,
                    "frame": i,
                    "status": mj.Status(int(status[i])).name.lower(),
                    "misfit": float(estimate.misfit[i]),
                    "contacts": int(estimate.contacts[i]),
                    **{f"true_{a}": float(schedule.wrench[i, k]) for k, a in enumerate(mj.WRENCH_AXES)},
                    **{a: float(estimate.wrench[i, k]) for k, a in enumerate(mj.WRENCH_AXES)},
                    **{f"sigma_{a}": float(estimate.sigma[i, k]) for k, a in enumerate(mj.WRENCH_AXES)},
                }
            )
    metrics = mj.wrench_metrics(schedule.wrench[loaded], estimate.wrench[loaded], estimate.sigma[loaded])
    out = {
        "family": family,
        "loaded_frames": int(loaded.sum()),
        "r2": metrics["r2"],
        "coverage95": metrics["coverage95"],
        "no_contact_of_loaded": int(np.sum(status[loaded] == mj.Status.NO_CONTACT)),
        "statuses": {mj.Status(int(s)).name.lower(): int(np.sum(status == s)) for s in np.unique(status)},
        "seconds_per_frame": round(per_frame, 3),
        "compile_s": round(compile_s, 1),
    }
    if calibrate:
        out["calibrated"] = _calibrated(family, nominal, unit, camera, schedule, test, rest, calibrate, seed)
    if baseline:
        paper = mj.load_schedule("paper", baseline, seed=seed + 1)
        train = _render(family, unit, camera, paper, seed + 2000)
        in_contact = np.asarray(paper.contact, bool)
        predicted = mj.ridge_baseline(train[in_contact], paper.wrench[in_contact], test[loaded], reference)
        out["pixel_baseline_r2"] = mj.wrench_metrics(schedule.wrench[loaded], predicted)["r2"]
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=24, help="mixed loads per family")
    parser.add_argument("--families", default=",".join(FAMILIES), help="comma-separated subset of the families")
    parser.add_argument("--layout", choices=("crossed", "lines"), default="crossed")
    parser.add_argument("--baseline", type=int, default=100, help="paper frames for the pixel baseline (0: none)")
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument(
        "--calibrate", type=int, default=0, help="also calibrate each family's unit on this many paper frames"
    )
    parser.add_argument("--json", action="store_true")
    parser.add_argument(
        "--per-frame", type=Path, help="also write each frame's truth, estimate, sigma, status and misfit (CSV)"
    )
    args = parser.parse_args(argv)
    families = [f.strip() for f in args.families.split(",") if f.strip()]
    unknown = sorted(set(families) - set(FAMILIES))
    if unknown:
        parser.error(f"--families: unknown {', '.join(unknown)}; choose from {', '.join(FAMILIES)}")
    nominal = mj.preset("mid", layout=args.layout)
    results = []
    with contextlib.ExitStack() as stack:
        writer = None
        if args.per_frame:
            columns = ["family", "frame", "status", "misfit", "contacts"]
            columns += [f"true_{a}" for a in mj.WRENCH_AXES] + list(mj.WRENCH_AXES)
            columns += [f"sigma_{a}" for a in mj.WRENCH_AXES]
            writer = csv.DictWriter(stack.enter_context(open(args.per_frame, "w", newline="")), columns)
            writer.writeheader()
        for family in families:
            result = run_family(family, nominal, args.frames, args.baseline, args.seed, writer, args.calibrate)
            results.append(result)
            if not args.json:
                r2 = " ".join(f"{a} {result['r2'][a]:+.3f}" for a in mj.WRENCH_AXES)
                print(
                    f"{family:12s} R² {r2}  no-contact {result['no_contact_of_loaded']}  {result['statuses']}",
                    flush=True,
                )
    if args.json:
        print(json.dumps({"layout": args.layout, "frames": args.frames, "families": results}, indent=1))


if __name__ == "__main__":
    main()
