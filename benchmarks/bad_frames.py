"""Frames outside the model's validity, and corrupted inputs: what the inversion believes.

    python benchmarks/bad_frames.py [--n 8] [--seed 0] [--json] [--no-files] [--no-frames] [--fuzz 200] [--kills 30]

A unit of the Mid design (`mj.preset("mid")`, `high`-fidelity frames with a fixed
fabrication error) is inverted cold, frame by frame ([`mj.invert`]) with the
nominal design and the mean of four of its own unloaded frames as the reference. Each case
draws `--n` random instances:

- **invalid** frames, which must not get a believed wrench (status `converged` or
  `max_steps`): uniform and Gaussian pixel noise; a natural image from `skimage.data`
  (a random crop, resized to the frame); loaded frames of another design (`dense`,
  `sparse`) = the wrong unit; black; white; an over-exposed loaded frame (gain 4,
  clipped); a dark blob over half the field of a loaded frame; a loaded frame rolled by
  3-12 pixels on each axis (a camera that moved); a loaded frame with 0.5 % NaN pixels; a
  loaded frame with random 8-bit pixels pasted over a rectangle of 1-25 % of the field.
- **valid** frames, which must: noisy loaded frames of the unit (loads of the `mixed`
  schedule, inside the paper's ranges) must get a believed wrench, and unloaded frames
  must be called `no_contact`.

Per case: the count of each status, the false-accept rate (invalid frames with a believed
wrench) or false-reject rate, crashes (exceptions escaping `invert`), and, for the
invalid frames that were believed, the median and maximum of |Fz| and of the largest
|wrench axis| / that axis' calibrated range (`mj.axis_ranges`), and, for those made from a
loaded frame (overexposed, occluded, rolled, NaN pixels), the largest error against that
load over the range. `unexplained` keeps a flagged wrench and counts as not believed.

Unless `--no-files`, file-level faults go through the command line (`moirejax invert`,
called in-process as `moirejax.cli.main`): a dataset and a folder of frames holding
truncated, bit-flipped, empty, header-only and garbage PNGs (and, in the folder, a
wrong-size, an RGB and a 16-bit PNG), a dataset whose first contact-free (reference) frame
is truncated, a truncated `--reference` image and a truncated `manifest.json`. Counted:
crashes (an exception escaping `main`, a traceback on stderr, exit code 1 or one
docs/errors.md does not list), lost or partial output (a CSV missing, or with fewer rows
than there are frames), and corrupt files that got a believed wrench. Each `invert` run
compiles its own stream inversion, so this part adds two compiles.

`--fuzz N` writes N random corruptions of the unit's PNG frames into one folder (each
cut at a random byte, random bytes overwritten, a header byte flipped, random bytes, a
valid image of another size, or a valid image with a random patch of other pixels) and
inverts the folder with `moirejax invert` (one more compile): counted are crashes, rows
missing from the CSV, the statuses by kind of corruption, and files that do not decode to
a frame of the unit's size yet got a believed wrench. `--kills K` runs `moirejax import
--overwrite` of one recording over a dataset of another, in a subprocess killed with
SIGKILL at a random moment past the interpreter's start, K times: afterwards the folder
must open as the old dataset or the new one with all its frames (`lost` counts the
others). `--no-frames` skips the in-process frame cases.

Time per frame, the compile time of the first frame and the peak memory are printed too.
The inversion grid is the default ([`mj.model_grid_for`]); set `MOIREJAX_MODEL_GRID`
(e.g. `64`) to trade accuracy for a faster run: the JSON records the grid used. Frames the
model cannot explain run every fallback start of a cold solve and cost far more than
valid ones: start with a small `--n`.
"""

import argparse
import contextlib
import csv
import io
import json
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import skimage.data
import skimage.transform

import moirejax as mj


BELIEVED = (mj.Status.CONVERGED, mj.Status.MAX_STEPS)
EXIT_CODES = (0, 2, 3, 4, 130)  # docs/errors.md; 1 is an internal error (a bug)
NATURAL = ("camera", "astronaut", "coins", "moon", "page", "text", "brick", "grass", "gravel", "horse", "coffee")


def _render(device: mj.Device, fabrication: jax.Array):
    """A jitted `high`-fidelity renderer of `device`: `(key, wrench, x0, y0, radius) -> frame`."""

    def render(key, wrench, x0, y0, radius):
        contact = mj.Contact(x0=x0, y0=y0, radius=radius)
        return mj.render_frame_high(key, device, wrench, contact, fabrication_key=fabrication)

    return jax.jit(render)


def _natural(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A random crop of a `skimage.data` image, resized to `shape`, in [0, 1] (8-bit)."""
    name = NATURAL[rng.integers(len(NATURAL))]
    image = np.asarray(getattr(skimage.data, name)(), dtype=float)
    if image.ndim == 3:
        image = image[..., :3] @ np.array([0.2125, 0.7154, 0.0721])
    image = image / max(float(image.max()), 1.0)
    h, w = image.shape
    side = int(rng.uniform(0.5, 1.0) * min(h, w))
    top, left = rng.integers(h - side + 1), rng.integers(w - side + 1)
    crop = skimage.transform.resize(image[top : top + side, left : left + side], shape, anti_aliasing=True)
    return np.round(np.clip(crop, 0, 1) * 255) / 255


def _blob(rng: np.random.Generator, frame: np.ndarray) -> np.ndarray:
    """`frame` with a dark, soft-edged ellipse over about half of the field."""
    h, w = frame.shape
    yy, xx = np.mgrid[:h, :w] / np.array([h, w])[:, None, None]
    cy, cx = rng.uniform(0.25, 0.75, 2)
    angle = rng.uniform(0, np.pi)
    ratio = rng.uniform(0.6, 1.0)
    u = (xx - cx) * np.cos(angle) + (yy - cy) * np.sin(angle)
    v = -(xx - cx) * np.sin(angle) + (yy - cy) * np.cos(angle)
    # Semi-axes (r, r * ratio) cover about half of the unit square: pi r^2 ratio = 0.5.
    r = np.sqrt(0.5 / (np.pi * ratio))
    distance = np.sqrt((u / r) ** 2 + (v / (r * ratio)) ** 2)
    mask = np.clip((1.05 - distance) / 0.1, 0, 1)
    dark = 0.04 + rng.normal(0, 0.01, frame.shape)
    return np.clip(frame * (1 - mask) + dark * mask, 0, 1)


def _stats(values: list[float]) -> dict | None:
    return {"median": float(np.median(values)), "max": float(np.max(values))} if values else None


def _invert_cases(inverter, frames_by_case):
    """Invert every frame of every case; returns the per-case report and the timings."""
    ranges = np.asarray(mj.axis_ranges())
    seconds: list[float] = []
    report = {}
    for case, (kind, frames, truths) in frames_by_case.items():
        statuses, crashes, errors = [], 0, []
        accepted_fz, accepted_over_range, loaded_error = [], [], []
        for frame, truth in zip(frames, truths):
            t = time.perf_counter()
            try:
                estimate = jax.device_get(mj.invert(inverter, jnp.asarray(frame, jnp.float32)))
            except Exception as e:  # a crash is what the benchmark counts
                crashes += 1
                errors.append(f"{type(e).__name__}: {e}"[:200])
                continue
            seconds.append(time.perf_counter() - t)
            status = mj.Status(int(estimate.status))
            statuses.append(status)
            wrench = np.asarray(estimate.wrench, dtype=float)
            if status in BELIEVED and kind == "invalid":
                accepted_fz.append(abs(float(wrench[2])))
                accepted_over_range.append(float(np.max(np.abs(wrench) / ranges)))
            if status in BELIEVED and truth is not None:
                loaded_error.append(float(np.max(np.abs(wrench - truth) / ranges)))
        believed = sum(s in BELIEVED for s in statuses)
        counts = {s.name.lower(): statuses.count(s) for s in mj.Status if s in statuses}
        entry: dict = {"kind": kind, "frames": len(frames), "status_counts": counts, "crashes": crashes}
        if kind == "invalid":
            entry["false_accepts"] = believed
            entry["false_accept_rate"] = believed / len(frames)
            entry["accepted_abs_fz_n"] = _stats(accepted_fz)
            entry["accepted_max_abs_wrench_over_range"] = _stats(accepted_over_range)
            # Invalid frames made from loaded ones: how far a believed wrench is from that load.
            entry["accepted_max_error_over_range"] = _stats(loaded_error)
        elif kind == "loaded":
            entry["false_rejects"] = len(frames) - believed
            entry["false_reject_rate"] = (len(frames) - believed) / len(frames)
            entry["believed_max_error_over_range"] = _stats(loaded_error)
        else:
            missed = len(frames) - statuses.count(mj.Status.NO_CONTACT)
            entry["false_rejects"] = missed
            entry["false_reject_rate"] = missed / len(frames)
        if errors:
            entry["errors"] = errors[:3]
        report[case] = entry
    return report, seconds


def _png_faults(rng: np.random.Generator, good: bytes) -> dict[str, bytes]:
    """Corrupted versions of the PNG bytes `good`."""
    flipped = bytearray(good)
    for i in rng.integers(64, len(good), 64):
        flipped[i] ^= 1 << int(rng.integers(8))
    return {
        "truncated": good[: len(good) * 2 // 5],
        "bit_flipped": bytes(flipped),
        "empty": b"",
        "header_only": good[:33],
        "garbage": rng.bytes(len(good) // 4),
    }


def _run_cli(argv: list[str]) -> dict:
    """Run `moirejax` in-process; what came back, and whether it crashed."""
    from moirejax.cli import main

    stderr = io.StringIO()
    escaped = None
    code: int | str | None
    with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as e:
            code = e.code
        except BaseException as e:  # a crash is what the benchmark counts
            code, escaped = None, f"{type(e).__name__}: {e}"[:200]
    text = stderr.getvalue()
    crashed = escaped is not None or "Traceback" in text or code not in EXIT_CODES
    return {"exit": code, "crashed": crashed, "escaped": escaped, "stderr": text.strip().splitlines()[-1:]}


def _read_out(path: Path) -> dict[str, str] | None:
    if not path.exists():
        return None
    with open(path, newline="") as f:
        return {row["frame"]: row["status"] for row in csv.DictReader(f)}


def _file_cases(rng, device, loaded, unloaded, wrenches, tmp: Path) -> dict:
    """File-level faults through `moirejax invert`."""
    device_file = tmp / "mid.json"
    mj.save_device(device_file, device)
    to8 = [_to8(f) for f in (*unloaded[:2], *loaded[:2])]
    good = cv2.imencode(".png", to8[2])[1].tobytes()
    faults = _png_faults(rng, good)
    runs: dict = {}

    # A dataset: two contact-free frames (the first truncated, so the reference falls back to
    # the second), two good loaded frames and one loaded frame per fault.
    dataset = tmp / "dataset"
    with mj.DatasetWriter(dataset, device=mj.device_to_json(device)) as writer:
        names = [writer.add(f, np.zeros(6), contact=0) for f in to8[:2]]
        names += [writer.add(f, wrenches[i], contact=1) for i, f in enumerate(to8[2:])]
        corrupt = {writer.add(to8[2], wrenches[0], contact=1): kind for kind in faults}
    (dataset / "frames" / names[0]).write_bytes(faults["truncated"])
    for name, kind in corrupt.items():
        (dataset / "frames" / name).write_bytes(faults[kind])
    corrupt[names[0]] = "truncated reference"
    runs["dataset"] = (["--data", str(dataset)], len(names) + len(faults), corrupt)

    # A folder of frames, with a good --reference image.
    folder = tmp / "folder"
    folder.mkdir()
    cv2.imwrite(str(tmp / "reference.png"), to8[1])
    for i, f in enumerate(to8[2:]):
        cv2.imwrite(str(folder / f"good{i}.png"), f)
    odd = {"wrong_size.png": to8[2][:256, :300], "rgb.png": np.repeat(to8[2][..., None], 3, axis=2)}
    odd["sixteen_bit.png"] = to8[2].astype(np.uint16) * 257
    for name, image in odd.items():
        cv2.imwrite(str(folder / name), image)
    folder_corrupt = {f"{kind}.png": kind for kind in faults}
    for name, kind in folder_corrupt.items():
        (folder / name).write_bytes(faults[kind])
    folder_corrupt["wrong_size.png"] = "wrong size"
    runs["folder"] = (
        ["--data", str(folder), "--reference", str(tmp / "reference.png")],
        2 + len(odd) + len(faults),
        folder_corrupt,
    )

    # Failures before the work: a truncated --reference and a truncated manifest.
    (tmp / "bad_reference.png").write_bytes(faults["truncated"])
    runs["truncated_reference"] = (["--data", str(folder), "--reference", str(tmp / "bad_reference.png")], 0, {})
    broken = tmp / "broken"
    broken.mkdir()
    (broken / "frames").symlink_to(dataset / "frames")
    (broken / "wrench.csv").write_bytes((dataset / "wrench.csv").read_bytes())
    manifest = (dataset / "manifest.json").read_bytes()
    (broken / "manifest.json").write_bytes(manifest[: len(manifest) // 2])
    runs["truncated_manifest"] = (["--data", str(broken)], 0, {})

    report: dict = {}
    for case, (data_args, expected_rows, corrupt_names) in runs.items():
        out = tmp / f"{case}.csv"
        t = time.perf_counter()
        result = _run_cli(["invert", "--device", str(device_file), *data_args, "--out", str(out), "--quiet"])
        result["seconds"] = round(time.perf_counter() - t, 1)
        rows = _read_out(out)
        if expected_rows:
            result["rows"] = None if rows is None else len(rows)
            result["lost_output"] = rows is None or len(rows) < expected_rows
            statuses = {} if rows is None else {n: rows.get(n, "missing") for n in corrupt_names}
            result["corrupt_statuses"] = {corrupt_names[n]: s for n, s in statuses.items()}
            result["corrupt_believed"] = sum(s in ("converged", "max_steps") for s in statuses.values())
        else:
            # Must fail as bad input (exit 3), in one line, before writing anything.
            result["lost_output"] = False
            result["wrong_exit"] = result["exit"] != 3
            result["wrote_output"] = rows is not None
        report[case] = result
    report["crashes"] = sum(r["crashed"] for r in report.values())
    report["lost_outputs"] = sum(r["lost_output"] for r in report.values() if isinstance(r, dict))
    report["corrupt_believed"] = sum(r.get("corrupt_believed", 0) for r in report.values() if isinstance(r, dict))
    return report


def _to8(frame: np.ndarray) -> np.ndarray:
    """A frame in [0, 1] as the 8-bit image a camera would write."""
    return np.round(np.clip(frame, 0, 1) * 255).astype(np.uint8)


def _random_fault(rng: np.random.Generator, good: bytes, frame8: np.ndarray) -> tuple[str, bytes]:
    """One random corruption of the PNG bytes `good` of the 8-bit frame `frame8`: its kind and bytes."""
    kind = ("cut", "bytes", "header", "garbage", "size", "pixels")[rng.integers(6)]
    if kind == "cut":
        return kind, good[: int(rng.integers(0, len(good)))]
    if kind == "bytes":
        data = bytearray(good)
        for i in rng.integers(0, len(good), int(rng.integers(1, 9))):
            data[i] = int(rng.integers(256))
        return kind, bytes(data)
    if kind == "header":
        data = bytearray(good)
        data[int(rng.integers(0, 33))] ^= 0xFF
        return kind, bytes(data)
    if kind == "garbage":
        return kind, rng.bytes(int(rng.integers(1, len(good))))
    if kind == "size":
        h, w = frame8.shape
        image = frame8[: int(rng.integers(h // 2, h)), : int(rng.integers(w // 2, w))]
        return kind, cv2.imencode(".png", image)[1].tobytes()
    return kind, cv2.imencode(".png", _paste_random_pixels(rng, frame8))[1].tobytes()


def _paste_random_pixels(rng: np.random.Generator, frame8: np.ndarray) -> np.ndarray:
    """A copy of the 8-bit `frame8` with random pixels over a rectangle of 1-25 % of the field."""
    image = frame8.copy()
    h, w = image.shape
    ph, pw = int(h * rng.uniform(0.1, 0.5)), int(w * rng.uniform(0.1, 0.5))
    top, left = int(rng.integers(0, h - ph)), int(rng.integers(0, w - pw))
    image[top : top + ph, left : left + pw] = rng.integers(0, 256, (ph, pw), dtype=np.uint8)
    return image


def _fuzz_files(rng, device, loaded, unloaded, wrenches, count: int, tmp: Path) -> dict:
    """`count` random corruptions of the unit's PNG frames in one folder, through `moirejax
    invert` (one compile): crashes, rows lost, frames that no reader can decode, or decode
    at another size, but got a believed wrench, and how far the believed wrenches of the
    frames that still decode (a patch of other pixels) are from their frame's load."""
    device_file = tmp / "mid.json"
    mj.save_device(device_file, device)
    frames8 = [_to8(f) for f in (*loaded, *unloaded[1:])]
    truths = [*wrenches, *[np.zeros(6)] * (len(unloaded) - 1)]
    folder = tmp / "fuzz"
    folder.mkdir()
    cv2.imwrite(str(tmp / "fuzz_reference.png"), _to8(unloaded[0]))
    kinds = {}
    for i in range(count):
        pick = int(rng.integers(len(frames8)))
        frame8 = frames8[pick]
        kind, data = _random_fault(rng, cv2.imencode(".png", frame8)[1].tobytes(), frame8)
        name = f"{i:04d}.png"
        (folder / name).write_bytes(data)
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        readable = decoded is not None and decoded.shape == frame8.shape
        kinds[name] = (kind, readable, truths[pick])
    out = tmp / "fuzz.csv"
    t = time.perf_counter()
    argv = [
        "invert",
        "--device",
        str(device_file),
        "--data",
        str(folder),
        "--reference",
        str(tmp / "fuzz_reference.png"),
    ]
    result = _run_cli([*argv, "--out", str(out), "--quiet"])
    result["seconds"] = round(time.perf_counter() - t, 1)
    rows, wrenches_out = {}, {}
    if out.exists():
        with open(out, newline="") as f:
            for row in csv.DictReader(f):
                rows[row["frame"]] = row["status"]
                wrenches_out[row["frame"]] = np.array([float(row[a]) for a in mj.WRENCH_AXES])
    result["files"] = count
    result["rows_missing"] = sum(name not in rows for name in kinds)
    by_kind: dict = {}
    ranges = np.asarray(mj.axis_ranges())
    for name, (kind, readable, truth) in kinds.items():
        entry = by_kind.setdefault(kind, {"files": 0, "readable": 0, "statuses": {}})
        entry["files"] += 1
        entry["readable"] += readable
        status = rows.get(name, "missing")
        entry["statuses"][status] = entry["statuses"].get(status, 0) + 1
        if readable and status in ("converged", "max_steps"):
            error = float(np.max(np.abs(wrenches_out[name] - truth) / ranges))
            entry.setdefault("believed_max_error_over_range", []).append(round(error, 3))
    result["by_kind"] = by_kind
    # A wrench for a file that does not decode to a frame of the unit's size is a wrong one.
    result["unreadable_believed"] = sum(
        rows.get(name) in ("converged", "max_steps") for name, (_, readable, _) in kinds.items() if not readable
    )
    return result


def _kill_imports(rng, device, loaded, unloaded, kills: int, tmp: Path) -> dict:
    """`moirejax import --overwrite` of one recording over a dataset of another, killed
    (SIGKILL, which nothing can catch) at `kills` random moments of its run: afterwards the
    folder must hold the old dataset or the new one, whole."""
    device_file = tmp / "mid.json"
    mj.save_device(device_file, device)
    frames8 = [_to8(f) for f in (*unloaded, *loaded)]

    def recording(root: Path, n: int) -> None:
        (root / "images").mkdir(parents=True)
        lines = ["frame,fx,fy,fz,tx,ty,tz"]
        for i in range(n):
            cv2.imwrite(str(root / "images" / f"{i:04d}.png"), frames8[i % len(frames8)])
            lines.append(f"{i:04d}.png,0,0,{0.01 * i:.2f},0,0,0")
        (root / "ft.csv").write_text("\n".join(lines) + "\n")

    # Long enough that most of a run is the import's own work, not the interpreter's start.
    old_n, new_n = 40, 80
    recording(tmp / "old", old_n)
    recording(tmp / "new", new_n)
    home = tmp / "kills"
    home.mkdir()
    target = home / "ds"
    command = [sys.executable, "-c", "import sys; from moirejax.cli import main; sys.exit(main(sys.argv[1:]))"]

    def run_import(source: Path, overwrite: bool) -> subprocess.Popen:
        argv = ["import", "--frames", str(source / "images"), "--wrench", str(source / "ft.csv")]
        argv += ["--device", str(device_file), "--out", str(target)] + (["--overwrite"] if overwrite else [])
        return subprocess.Popen([*command, *argv], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def state() -> str:
        try:
            dataset = mj.open_dataset(target)
            whole = all((target / "frames" / name).is_file() for name in dataset.frame_names)
        except Exception:
            return "broken"
        return {old_n: "old", new_n: "new"}.get(len(dataset), "broken") if whole else "broken"

    assert run_import(tmp / "old", False).wait() == 0
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import moirejax.cli"], check=True)
    startup = time.perf_counter() - t
    t = time.perf_counter()
    assert run_import(tmp / "new", True).wait() == 0
    full = time.perf_counter() - t
    outcomes: dict = {"old": 0, "new": 0, "broken": 0}
    for _ in range(kills):
        shutil.rmtree(target)
        assert run_import(tmp / "old", False).wait() == 0
        process = run_import(tmp / "new", True)
        # Past the interpreter's start, when the import reads, writes and renames.
        time.sleep(rng.uniform(min(0.8 * startup, full), full))
        process.send_signal(signal.SIGKILL)
        process.wait()
        outcomes[state()] += 1
        # What SIGKILL leaves is hidden staging folders beside the dataset; none is the dataset.
        for stale in home.glob(".ds.staging-*"):
            shutil.rmtree(stale)
    return {
        "kills": kills,
        "import_s": round(full, 2),
        "interpreter_start_s": round(startup, 2),
        "outcomes": outcomes,
        "lost": outcomes["broken"],
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=8, help="random instances per case")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="one line of JSON")
    parser.add_argument("--no-files", action="store_true", help="skip the file-level faults (two compiles)")
    parser.add_argument("--no-frames", action="store_true", help="skip the in-process frame cases")
    parser.add_argument("--fuzz", type=int, default=0, help="random file corruptions through invert (one compile)")
    parser.add_argument("--kills", type=int, default=0, help="imports killed at random moments")
    args = parser.parse_args(argv)
    if args.n < 2:
        parser.error("--n must be >= 2")
    rng = np.random.default_rng(args.seed)
    key = jr.PRNGKey(args.seed)
    start = time.perf_counter()

    device = mj.preset("mid")
    shape = (device.height, device.width)
    fabrication = jr.PRNGKey(args.seed + 1000)
    render = _render(device, fabrication)
    # The `mixed` schedule holds unloaded frames too; the loaded cases take its first
    # `--n` loads (the unloaded ones are a case of their own).
    schedule = mj.load_schedule("mixed", 4 * args.n, seed=args.seed)
    pressed = np.flatnonzero(np.any(np.asarray(schedule.wrench) != 0, axis=1))[: args.n]
    if pressed.size < args.n:
        raise SystemExit(f"the mixed schedule has {pressed.size} loads, fewer than --n {args.n}")
    wrenches = np.asarray(schedule.wrench)[pressed]

    def unit_frames(key, wrenches, contacts, draw=render):
        keys = jr.split(key, len(wrenches))
        return [
            np.asarray(draw(k, jnp.asarray(w), float(x0), float(y0), float(r)), dtype=np.float64)
            for k, w, (x0, y0, r) in zip(keys, wrenches, contacts)
        ]

    contacts = [(schedule.x0[i], schedule.y0[i], schedule.radius[i]) for i in pressed]
    k_ref, k_loaded, k_free, k_other = jr.split(key, 4)
    zeros = [np.zeros(6)] * args.n
    centred = [(0.0, 0.0, 3.5)] * args.n
    reference = np.mean(unit_frames(k_ref, zeros[:4], centred[:4]), axis=0)
    loaded = unit_frames(k_loaded, wrenches, contacts)
    unloaded = unit_frames(k_free, zeros, centred)
    # The wrong unit: the other two designs under the same loads (half each).
    other = []
    for i, name in enumerate(("dense", "sparse")):
        draw = _render(mj.preset(name), jr.fold_in(fabrication, i))
        picks = list(range(i, args.n, 2))
        other += unit_frames(jr.fold_in(k_other, i), wrenches[picks], [contacts[j] for j in picks], draw)
    render_s = time.perf_counter() - start

    def noisy(frame):
        return np.round(np.clip(frame, 0, 1) * 255) / 255

    def rolled(frame):
        dy, dx = rng.integers(3, 13, 2) * rng.choice([-1, 1], 2)
        return np.roll(frame, (int(dy), int(dx)), axis=(0, 1))

    def with_nan(frame):
        frame = frame.copy()
        frame.flat[rng.choice(frame.size, frame.size // 200, replace=False)] = np.nan
        return frame

    n = args.n
    none = [None] * n
    truths = list(wrenches)
    cases = {
        "valid_loaded": ("loaded", loaded, truths),
        "valid_unloaded": ("unloaded", unloaded, none),
        "uniform_noise": ("invalid", [noisy(rng.uniform(0, 1, shape)) for _ in range(n)], none),
        "gaussian_noise": ("invalid", [noisy(rng.normal(0.5, 0.15, shape)) for _ in range(n)], none),
        "natural_image": ("invalid", [_natural(rng, shape) for _ in range(n)], none),
        "wrong_unit": ("invalid", other, none),
        "black": ("invalid", [noisy(np.abs(rng.normal(0, 0.01, shape))) for _ in range(n)], none),
        "white": ("invalid", [noisy(1 - np.abs(rng.normal(0, 0.01, shape))) for _ in range(n)], none),
        "overexposed": ("invalid", [noisy(4 * f) for f in loaded], truths),
        "occluded_half": ("invalid", [noisy(_blob(rng, f)) for f in loaded], truths),
        "rolled": ("invalid", [rolled(f) for f in loaded], truths),
        "nan_pixels": ("invalid", [with_nan(f) for f in loaded], truths),
        "random_patch": ("invalid", [_paste_random_pixels(rng, _to8(f)) / 255 for f in loaded], truths),
    }

    report: dict = {"n": n, "seed": args.seed}
    seconds: list[float] = []
    compile_s = None
    if not args.no_frames:
        t = time.perf_counter()
        inverter = mj.Inverter(device, reference)
        jax.block_until_ready(mj.invert(inverter, jnp.asarray(loaded[0], jnp.float32)).wrench)
        compile_s = time.perf_counter() - t
        frames_report, seconds = _invert_cases(inverter, cases)
        invalid = [c for c in frames_report.values() if c["kind"] == "invalid"]
        valid = [c for c in frames_report.values() if c["kind"] != "invalid"]
        report["model_grid"] = list(inverter.model_shape)
        report["summary"] = {
            "invalid_frames": sum(c["frames"] for c in invalid),
            "false_accepts": sum(c["false_accepts"] for c in invalid),
            "false_accept_rate": sum(c["false_accepts"] for c in invalid) / sum(c["frames"] for c in invalid),
            "valid_frames": sum(c["frames"] for c in valid),
            "false_rejects": sum(c["false_rejects"] for c in valid),
            "false_reject_rate": sum(c["false_rejects"] for c in valid) / sum(c["frames"] for c in valid),
            "crashes": sum(c["crashes"] for c in frames_report.values()),
            "cases_with_false_accepts": [k for k, c in frames_report.items() if c.get("false_accepts")],
        }
        report["cases"] = frames_report
    if not args.no_files:
        with tempfile.TemporaryDirectory(prefix="bad-frames-") as tmp:
            report["files"] = _file_cases(rng, device, loaded, unloaded, wrenches, Path(tmp))
    if args.fuzz:
        with tempfile.TemporaryDirectory(prefix="bad-frames-") as tmp:
            report["fuzz"] = _fuzz_files(rng, device, loaded, unloaded, wrenches, args.fuzz, Path(tmp))
    if args.kills:
        with tempfile.TemporaryDirectory(prefix="bad-frames-") as tmp:
            report["kills"] = _kill_imports(rng, device, loaded, unloaded, args.kills, Path(tmp))
    report.update(
        median_ms=float(np.median(seconds) * 1e3) if seconds else None,
        p90_ms=float(np.percentile(seconds, 90) * 1e3) if seconds else None,
        compile_s=compile_s,
        render_s=render_s,
        elapsed_s=time.perf_counter() - start,
        peak_memory_gb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
    )
    print(json.dumps(report, indent=None if args.json else 1))


if __name__ == "__main__":
    main()
