"""Accuracy on frames moirejax did not render: the independent ray-casting renderer.

    python benchmarks/peer_frames.py --data DIR [--json]
    python benchmarks/peer_frames.py --render 200 --seed 3 [--supersample 12] [--contacts shaped] [--json]
    python benchmarks/peer_frames.py --data DIR --calibrate 200 [--calibration-seed 11] [--json]

`--data` reads a folder written by the peer renderer (`frames/*.png`, `wrench.csv` with a
`contact` column); `--render N` runs the renderer first, when `../shared/peer/raycast_sensor.py`
sits beside the checkout. Every frame is inverted cold with the nominal Mid design as the
renderer describes it (line gratings, duty 0.5; `--design` for the paper's others: the
renderer then draws that design's pitches) and no calibration; the no-contact frames
are the reference. Prints R² per axis over the loaded frames, how many were called "no
contact", the status counts, the 95% interval coverage, and the time per frame.

With `--calibrate N` the renderer also draws N other mixed loads (`--calibration-seed`), `calibrate`
fits the unit on them (the default `unit` recipe) and `evaluate` scores the fit on the
loads of `--data`: the report gains the held-out R² and coverage with and without the
residual head, the pixel baseline cross-validated on the calibration frames, and the
calibration's and the evaluation's wall time.
"""

import argparse
import csv
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj


AXES = mj.WRENCH_AXES
PEER = Path(__file__).resolve().parents[2] / "shared" / "peer" / "raycast_sensor.py"
# The upper and lower grating pitches (mm) of the paper's designs, as `mj.preset` draws them.
DESIGN_PITCHES = {
    name: (round(float(mj.preset(name).p1), 6), round(float(mj.preset(name).p2), 6))
    for name in ("dense", "mid", "sparse")
}


def read_peer(folder: Path):
    rows = list(csv.DictReader(open(folder / "wrench.csv")))
    frames = np.stack([cv2.imread(str(folder / "frames" / r["frame"]), cv2.IMREAD_UNCHANGED) / 255.0 for r in rows])
    wrench = np.array([[float(r[a]) for a in AXES] for r in rows])
    contact = np.array([int(r["contact"]) for r in rows], dtype=bool)
    return frames, wrench, contact


# Loads the renderer can draw beyond its own mixed ones (`--contacts`), as code run in its
# process: each takes a load it drew and changes what the inversion's contact model lacks
# (`shaped`: elliptic patches and pressure tilted across them; moirejax's patch is round) or
# what the paper's calibration range leaves out (`heavy`: up to 5 N, 0.5 N of shear and
# 0.02 N·m of twist on wider patches).
CONTACTS = {
    "paper": "",
    "shaped": "c.ellipticity = rng.uniform(-0.35, 0.35); c.tilt = tuple(rng.uniform(-0.4, 0.4, 2))",
    "heavy": (
        "c.fz = rng.uniform(1.5, 5.0); c.radius = rng.uniform(3.0, 5.0); "
        "c.shear = tuple(rng.uniform(-0.5, 0.5, 2)); c.tz = rng.uniform(-0.02, 0.02)"
    ),
}


def render_peer(
    n: int, seed: int, supersample: int | None = None, design: str = "mid", contacts: str = "paper"
) -> Path:
    """`n` mixed loads of the peer renderer in a new folder, for one of the paper's designs
    (its pitches; the renderer's own default is Mid); with `supersample`, its pixels sampled
    at that many points a side instead of its own 4; `contacts` one of `CONTACTS`. Its
    command line has no option for any of them, so its device's defaults and its load draw
    are replaced before its `main` runs."""
    folder = Path(tempfile.mkdtemp(prefix="peer-"))
    argv = [str(PEER), str(folder), "--n", str(n), "--seed", str(seed)]
    p_far, p_near = DESIGN_PITCHES[design]
    overrides = {"p_far": p_far, "p_near": p_near}
    if supersample is not None:
        overrides["supersample"] = int(supersample)
    script = (
        "import functools, sys\n"
        f"sys.path.insert(0, {str(PEER.parent)!r})\n"
        "import raycast_sensor as peer\n"
        f"peer.Device = functools.partial(peer.Device, **{overrides!r})\n"
        "_draw = peer.draw_contact\n"
        "def _drawn(kind, rng):\n"
        "    c = _draw(kind, rng)\n"
        f"    {CONTACTS[contacts] or 'pass'}\n"
        "    return c\n"
        "peer.draw_contact = _drawn\n"
        f"sys.argv = {argv!r}\n"
        "peer.main()\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True)
    return folder


def calibrated(device: mj.Device, test: Path, n: int, seed: int, design: str = "mid") -> dict:
    """Calibrate on `n` other loads of the renderer and score the fit on the loads in `test`."""
    work = Path(tempfile.mkdtemp(prefix="peer-calibration-"))
    train = render_peer(n, seed, design=design)
    mj.save_device(work / "nominal.json", device)
    for name, folder in (("train", train), ("test", test)):
        mj.import_recording(
            folder / "frames", folder / "wrench.csv", work / "nominal.json", work / name, progress=False
        )
    start = time.perf_counter()
    fit = mj.calibrate(work / "nominal.json", work / "train", work / "fit.json", max_frames=None, progress=False)
    calibrate_s = time.perf_counter() - start
    start = time.perf_counter()
    held_out = mj.evaluate(work / "fit.json", work / "test", work / "evaluation", progress=False)
    physics = held_out.get("physics_only", held_out)
    return {
        "calibration_frames": n,
        "held_out_r2": held_out["r2"],
        "held_out_coverage95": held_out["coverage95"],
        "held_out_r2_physics_only": physics["r2"],
        "pixel_baseline_r2_crossvalidated": fit["baselines"],
        "calibrate_s": round(calibrate_s, 1),
        "evaluate_s": round(time.perf_counter() - start, 1),
        "peak_memory_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="a folder written by the peer renderer")
    parser.add_argument("--render", type=int, default=0, help="render this many loaded frames with the peer first")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument(
        "--supersample",
        type=int,
        help="with --render: sample each pixel at this many points a side (the renderer's own is 4, which aliases"
        " its gratings' harmonics into the fringe bands; 12 or more does not, at about 30 s a frame)",
    )
    parser.add_argument(
        "--design",
        choices=sorted(DESIGN_PITCHES),
        default="mid",
        help="with --render and --calibrate: the paper's design the renderer draws (its grating pitches)",
    )
    parser.add_argument(
        "--contacts",
        choices=sorted(CONTACTS),
        default="paper",
        help="with --render: the renderer's own mixed loads (paper), elliptic patches with tilted pressure"
        " (shaped), or loads above the paper's range up to 5 N (heavy)",
    )
    parser.add_argument("--json", action="store_true")
    parser.add_argument(
        "--per-frame", type=Path, help="also write each frame's truth, estimate, sigma and status (CSV)"
    )
    parser.add_argument(
        "--calibrate", type=int, default=0, help="also calibrate on this many other loads of the renderer"
    )
    parser.add_argument("--calibration-seed", type=int, default=11, help="seed of the calibration loads")
    args = parser.parse_args()
    if args.calibrate and not PEER.exists():
        parser.error(f"--calibrate renders its loads with the peer renderer, expected at {PEER}")
    if args.data is None:
        if not args.render or not PEER.exists():
            parser.error(f"give --data DIR, or --render N with the peer renderer at {PEER}")
        args.data = render_peer(args.render, args.seed, args.supersample, args.design, args.contacts)
    frames, truth, contact = read_peer(args.data)
    device = mj.preset(args.design, layout="lines", duty1=0.5, duty2=0.5)
    start = time.perf_counter()
    inverter = mj.Inverter(device, frames[~contact].mean(axis=0))
    first = mj.invert(inverter, jnp.asarray(frames[0], jnp.float32))
    jax.block_until_ready(first.wrench)
    compile_s = time.perf_counter() - start
    estimates, seconds = [], []
    for frame in frames:
        t = time.perf_counter()
        e = mj.invert(inverter, jnp.asarray(frame, jnp.float32))
        jax.block_until_ready(e.wrench)
        seconds.append(time.perf_counter() - t)
        estimates.append(jax.device_get(e))
    wrench = np.stack([e.wrench for e in estimates])
    sigma = np.stack([e.sigma for e in estimates])
    status = np.array([int(e.status) for e in estimates])
    loaded = contact
    filled = np.nan_to_num(wrench[loaded])
    y = truth[loaded]
    r2 = 1 - ((y - filled) ** 2).sum(0) / ((y - y.mean(0)) ** 2).sum(0)
    coverage = np.mean(np.abs(wrench[loaded] - y) <= 1.96 * sigma[loaded], axis=0)
    report = {
        "data": str(args.data),
        "design": args.design,
        "contacts": args.contacts if args.render else None,
        "frames": int(len(frames)),
        "loaded": int(loaded.sum()),
        "r2": dict(zip(AXES, np.round(r2, 4).tolist())),
        "coverage95": dict(zip(AXES, np.round(coverage, 3).tolist())),
        "loaded_called_no_contact": int(np.sum(status[loaded] == mj.Status.NO_CONTACT)),
        "status_counts": {mj.Status(s).name.lower(): int(np.sum(status == s)) for s in np.unique(status)},
        "median_ms": float(np.median(seconds) * 1e3),
        "p90_ms": float(np.percentile(seconds, 90) * 1e3),
        "frames_per_s": float(1 / np.median(seconds)),
        "compile_s": compile_s,
        "peak_memory_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    }
    if args.calibrate:
        report["calibrated"] = calibrated(device, args.data, args.calibrate, args.calibration_seed, args.design)
    if args.per_frame:
        with open(args.per_frame, "w", newline="") as f:
            out = csv.writer(f)
            out.writerow(["frame", "status", *(f"true_{a}" for a in AXES), *AXES, *(f"sigma_{a}" for a in AXES)])
            for i in range(len(frames)):
                out.writerow([i, mj.Status(status[i]).name.lower(), *truth[i], *wrench[i], *sigma[i]])
    print(json.dumps(report, indent=None if args.json else 1))


if __name__ == "__main__":
    main()
