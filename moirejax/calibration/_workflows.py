"""The calibrate, evaluate and transfer jobs, from dataset folders to files and plots.

Outputs are checked before the long work starts, and written as a set at the end: staged
in a temporary folder beside them, then moved into place with the device file last, which
records the SHA-256 of the head and report it belongs with. An interrupted job (Ctrl-C, a
kill, a full disk) leaves the previous set as it was.

It is one module because the three jobs share that fit set (its staging, writing and
loading with the head), the report's tables and plots, and the pixel-ridge baseline every
report compares with.
"""

import hashlib
import importlib.metadata
import io
import json
import math
import shutil
import sys
import warnings
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._conventions import WRENCH_AXES, WRENCH_SCALE
from .._fileio import (
    ARGUMENT,
    atomic_write_bytes,
    atomic_write_text,
    check_output_file,
    check_output_folder,
    commit_staged,
    DataError,
    DataWarning,
    fingerprint,
    open_parts,
    read_json,
    sha256_file,
    staging_folder,
    write_json,
)
from ..data import Dataset
from ..inverse import default_carriers, default_model_shape, Estimate, invert, Inverter, Status
from ..physics import Device, device_from_json, device_to_json, load_device, save_device
from ._calibration import fit_physical_parameters, load_recipe, Recipe
from ._metrics import plot_parity, plot_residuals, wrench_metrics
from ._residual_head import head_features, load_head, ResidualHead, save_head, train_residual_head


def dataset_reference(dataset: Dataset, limit: int = 16) -> np.ndarray:
    """Mean of up to `limit` readable contact-free frames: the unit's no-contact reference
    (an unreadable one is skipped with a [`DataWarning`][moirejax.DataWarning])."""
    if dataset.contact is None or not np.any(~dataset.contact):
        raise DataError(f"{dataset.path}: no contact-free frame (column 'contact' = 0) to use as the reference")
    frames = []
    for i in np.flatnonzero(~dataset.contact):
        try:
            frames.append(dataset.frame(int(i)))
        except DataError as e:
            # A truncated or corrupt frame is skipped; the next contact-free one serves.
            warnings.warn(f"reference frame skipped: {e}", DataWarning, stacklevel=2)
            continue
        if len(frames) == limit:
            break
    if not frames:
        raise DataError(f"{dataset.path}: none of its contact-free frames (column 'contact' = 0) can be read")
    return np.mean(frames, axis=0)


def _head_path(device_path: Path) -> Path:
    return device_path.with_suffix(".head.eqx")


def _report_dir(device_path: Path) -> Path:
    stem = device_path.with_suffix("")
    return stem.parent / (stem.name + "_report")


def _check_fit_outputs(out: Path, *, report: bool) -> None:
    """Fail before the fit, not after it, when the device, head or report cannot be written."""
    check_output_file(out, argument="out")
    check_output_file(_head_path(out), argument="out")
    if report:
        check_output_folder(_report_dir(out), argument="out")


def _write_fit_set(
    out: Path,
    device: Device,
    calibration: dict,
    head: ResidualHead | None,
    write_report: Callable[[Path], None] | None = None,
) -> None:
    """Write the device file, its residual head and (calibrate) its report folder as a set.

    Everything is written and flushed in a staging folder beside `out`; then the report
    folder, the head and last the device file are moved into place by renames. The device
    file records the SHA-256 of every other file of the set (`calibration.files`), which
    [`load_calibrated`][] checks: a set left out of step (a kill between two of those
    renames) is refused by name, never used. An interruption before the renames, which is
    nearly all of the time, leaves the previous set as it was.
    """
    with staging_folder(out) as staging:
        files: dict[str, str] = {}
        moves = []
        if write_report is not None:
            report = _report_dir(out)
            write_report(staging / report.name)
            files[f"{report.name}/metrics.json"] = sha256_file(staging / report.name / "metrics.json")
            moves.append((staging / report.name, report))
        head_name = None
        if head is not None:
            head_name = _head_path(out).name
            save_head(staging / head_name, head)
            for name in (head_name, head_name + ".json"):
                files[name] = sha256_file(staging / name)
                moves.append((staging / name, out.parent / name))
        calibration = {**calibration, "residual_head": head_name, "files": files}
        save_device(staging / out.name, device, extra={"calibration": calibration})
        moves.append((staging / out.name, out))
        commit_staged(staging, moves)


def load_calibrated(device_path: str | Path) -> tuple[Device, ResidualHead | None]:
    """A device file and, when its calibration names one, its residual head.

    The head must be the one the device file records (`calibration.files` holds its
    SHA-256), else [`DataError`][] names both files. A calibration written flagged (its
    frames could not identify it; `calibrate --force`) loads with a
    [`DataWarning`][moirejax.DataWarning].
    """
    device_path = Path(device_path)
    obj = read_json(device_path, "device")
    device = device_from_json(obj, source=str(device_path))
    calibration = obj.get("calibration", {})
    for problem in calibration.get("flagged", []):
        warnings.warn(f"{device_path}: flagged calibration: {problem}", DataWarning, stacklevel=2)
    head_name = calibration.get("residual_head")
    if not head_name:
        return device, None
    recorded = calibration.get("files", {})
    for name in (head_name, head_name + ".json"):
        path = device_path.parent / name
        if not path.is_file():
            raise DataError(f"{path}: no such file, but {device_path} names it as its residual head")
        if name in recorded and sha256_file(path) != recorded[name]:
            raise DataError(
                f"{path}: is not the file {device_path} was written with (its SHA-256 differs): the set is out of "
                "step, e.g. after an interrupted calibrate; calibrate again"
            )
    return device, load_head(device_path.parent / head_name)


class _Solutions(NamedTuple):
    """What the calibration jobs keep of each frame's solve: the physical wrench, its
    standard errors and status, and the contact the residual head reads."""

    wrench: np.ndarray
    sigma: np.ndarray
    status: np.ndarray
    x0: np.ndarray
    y0: np.ndarray
    radius: np.ndarray

    @classmethod
    def of(cls, estimate: Estimate) -> "_Solutions":
        contact = estimate.contact
        return cls(
            *(np.asarray(a) for a in (estimate.wrench, estimate.sigma, estimate.status)),
            *(np.asarray(a) for a in (contact.x0, contact.y0, contact.radius)),
        )


def _apply_head(head: ResidualHead | None, result: _Solutions) -> tuple[np.ndarray, np.ndarray]:
    """The wrenches and their standard errors, corrected by the head where there is one."""
    wrench, sigma = np.array(result.wrench), np.array(result.sigma)
    if head is None:
        return wrench, sigma
    ok = np.all(np.isfinite(wrench), axis=1) & (result.status != Status.NO_CONTACT)
    if np.any(ok):
        wrench[ok] = head.correct(wrench[ok], result.x0[ok], result.y0[ok], result.radius[ok])
        sigma[ok] = head.corrected_sigma(sigma[ok])
    return wrench, sigma


# Calibration frames solved per part kept in `OUT.parts/`: what an interruption can lose.
_SOLVED_PER_PART = 16


def _physical_fit(parts: Path, nominal, reference, frames, wrenches, recipe, progress) -> tuple[Device, dict, list]:
    """The fitted device, its parameters' uncertainty and the fit's history: read from
    `parts` when an earlier run of the same calibration got that far, else fitted and kept
    there. The device always comes through its JSON, so a resumed run continues from the
    very numbers an uninterrupted one uses."""
    path = parts / "physical.json"
    try:
        kept = json.loads(path.read_text())
    except (OSError, ValueError):
        # Frames solved with another fit do not belong with this one.
        for part in parts.glob("solved-*.npz"):
            part.unlink()
        result = fit_physical_parameters(nominal, reference, frames, wrenches, recipe, progress=progress)
        kept = {
            "device": device_to_json(result.device),
            "uncertainty": result.uncertainty,
            "history": result.history,
        }
        # Python's JSON keeps a NaN (a degenerate forced fit), so both paths read the same.
        atomic_write_text(path, json.dumps(kept))
        kept = json.loads(path.read_text())
    return device_from_json(kept["device"], source=str(path)), kept["uncertainty"], kept["history"]


def _solve_calibration_frames(parts: Path, inverter: Inverter, frames, progress: bool) -> _Solutions:
    """Every calibration frame solved cold, `_SOLVED_PER_PART` frames to a part kept in
    `parts`: a rerun after an interruption solves only the parts that are missing."""
    from tqdm.auto import tqdm

    starts = range(0, len(frames), _SOLVED_PER_PART)
    kept: dict[int, _Solutions] = {}
    for start in starts:
        try:
            with np.load(parts / f"solved-{start:06d}.npz") as part:
                solutions = _Solutions(*(part[name] for name in _Solutions._fields))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            continue  # not solved yet, or a part that cannot be read: solved again
        if len(solutions.wrench) == min(_SOLVED_PER_PART, len(frames) - start):
            kept[start] = solutions
    initial = sum(len(s.wrench) for s in kept.values())
    bar = tqdm(total=len(frames), initial=initial, desc="invert calibration frames", unit="frame", disable=not progress)
    with bar:
        for start in starts:
            if start in kept:
                continue
            stop = min(start + _SOLVED_PER_PART, len(frames))
            kept[start] = _Solutions.of(invert(inverter, frames[start:stop]))
            buffer = io.BytesIO()
            np.savez(buffer, **kept[start]._asdict())
            atomic_write_bytes(parts / f"solved-{start:06d}.npz", buffer.getvalue())
            bar.update(stop - start)
    return _Solutions(*(np.concatenate(column) for column in zip(*(kept[start] for start in starts))))


def fit_tilt_matrix(x0: np.ndarray, y0: np.ndarray, moments: np.ndarray, device) -> tuple[np.ndarray, float]:
    """The paper's Eq. 9, `[Tx, Ty] ~ M (c - c0)`, by least squares; returns M and its R².

    `c` is the contact centre in the image (mm). The physics says the moments are the
    centre times Fz, so a constant M only holds at a fixed preload; the R² shows how well.
    """
    scale = float(device.Z / (device.Z + device.a))
    c = np.stack([x0, y0], axis=1) * scale
    design = np.concatenate([c, np.ones((len(c), 1))], axis=1)
    coef, *_ = np.linalg.lstsq(design, moments, rcond=None)
    residual = moments - design @ coef
    r2 = 1 - np.sum(residual**2) / max(np.sum((moments - moments.mean(0)) ** 2), 1e-30)
    return coef[:2].T, float(r2)


def ridge_features(frames, reference: np.ndarray, *, size: int = 24) -> np.ndarray:
    """The pixel-ridge baseline's features: `frame - reference` area-averaged to
    `size x size`, one row per frame of `frames` (any iterable of frames; each is read once)."""
    import cv2

    reference = np.asarray(reference, np.float32)
    rows = [
        cv2.resize(np.asarray(f, np.float32) - reference, (size, size), interpolation=cv2.INTER_AREA).ravel()
        for f in frames
    ]
    return np.stack(rows) if rows else np.zeros((0, size * size), np.float32)


def _ridge_predict(train_x: np.ndarray, train_y: np.ndarray, test_x: np.ndarray) -> np.ndarray:
    """Ridge regression from `train_x` to `train_y`, its regularisation chosen by
    leave-one-out (closed form for ridge), applied to `test_x`."""
    mean_x, mean_y = train_x.mean(0), train_y.mean(0)
    Xc, Yc = train_x - mean_x, train_y - mean_y
    U, s, Vt = np.linalg.svd(Xc, full_matrices=False)
    best = (np.inf, 1.0)
    for lam in 10.0 ** np.arange(-6, 3):
        d = s**2 / (s**2 + lam)
        hat_diag = np.sum(U**2 * d, axis=1)
        fitted = U @ (d[:, None] * (U.T @ Yc))
        loo = np.mean(((Yc - fitted) / np.maximum(1 - hat_diag, 1e-6)[:, None]) ** 2)
        if loo < best[0]:
            best = (loo, lam)
    lam = best[1]
    coef = Vt.T @ ((s / (s**2 + lam))[:, None] * (U.T @ Yc))
    return (test_x - mean_x) @ coef + mean_y


def ridge_baseline(train_frames, train_wrench, test_frames, reference, *, size: int = 24) -> np.ndarray:
    """A learned baseline: ridge regression from downsampled `frame - reference` to the wrench.

    The regularisation is chosen by leave-one-out (closed form for ridge).
    """
    train_x = ridge_features(train_frames, reference, size=size)
    return _ridge_predict(train_x, np.asarray(train_wrench), ridge_features(test_frames, reference, size=size))


def cross_validated_ridge_r2(
    features: np.ndarray, wrenches: np.ndarray, sizes: tuple[int, ...], *, folds: int = 5
) -> dict[str, dict[str, float]]:
    """Five-fold cross-validated R² of the [`ridge_baseline`][] trained on `n` frames, per `n`,
    from every frame's `ridge_features`.

    Each fold is predicted by a model trained on `n` random frames of the other folds (at
    most all of them), and R² is taken over the pooled predictions of every frame: a single
    small test split of a calibration protocol that loads one axis at a time can hold
    almost no variation of some axis, and its R² then means nothing.
    """
    rng = np.random.default_rng(1)
    fold = rng.permutation(len(features)) % folds
    out = {}
    for n in sizes:
        n_train = min(n, int(np.sum(fold != 0)))
        if n_train < 10:
            continue
        predicted = np.empty_like(wrenches)
        for k in range(folds):
            train = rng.permutation(np.flatnonzero(fold != k))[:n_train]
            test = fold == k
            predicted[test] = _ridge_predict(features[train], wrenches[train], features[test])
        out[str(n_train)] = wrench_metrics(wrenches, predicted)["r2"]
    return out


def heldout_ridge_r2(train: str | Path, test: str | Path, sizes: tuple[int, ...]) -> dict[str, dict[str, float]]:
    """Held-out R² of the [`ridge_baseline`][] trained on `n` random in-contact frames of
    dataset `train` (the same order for every `n`), for each `n` in `sizes`, tested on the
    in-contact frames of `test`."""
    train_set, test_set = Dataset(train), Dataset(test)
    reference = dataset_reference(train_set)
    train_idx = _select(train_set, None)
    train_idx = train_idx[np.random.default_rng(1).permutation(len(train_idx))[: max(sizes)]]
    train_x = ridge_features(train_set.frames(train_idx), reference)
    test_idx = _select(test_set, None)
    # Each unit's frames are taken relative to its own no-contact reference.
    shift = dataset_reference(test_set) - reference
    test_x = ridge_features((frame - shift for frame in test_set.frames(test_idx)), reference)
    out = {}
    for n in sizes:
        n = min(n, len(train_idx))
        predicted = _ridge_predict(train_x[:n], train_set.wrenches[train_idx[:n]], test_x)
        out[str(n)] = wrench_metrics(test_set.wrenches[test_idx], predicted)["r2"]
    return out


def spanning_frames(wrenches: np.ndarray, n: int) -> np.ndarray:
    """Indices of `n` frames whose wrenches span the load space: farthest-point sampling of
    the wrench scaled by the calibrated ranges, starting from the largest load.

    A random handful of an isolated-axis protocol is mostly normal presses (the paper's
    protocol presses in every frame), and a fit to them sees almost no shear or twist: 20
    random frames of one unit transferred its stiffness 15% off and its shear and twist
    with R² 0.96; 20 frames that load every axis fix both.
    """
    scaled = np.asarray(wrenches, float) / WRENCH_SCALE
    chosen = [int(np.argmax(np.linalg.norm(scaled, axis=1)))]
    distance = np.linalg.norm(scaled - scaled[chosen[0]], axis=1)
    for _ in range(min(n, len(scaled)) - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(scaled - scaled[chosen[-1]], axis=1))
    return np.sort(np.asarray(chosen))


def _select(dataset: Dataset, max_frames: int | None) -> np.ndarray:
    """The in-contact frames, or `max_frames` of them that span the load space."""
    idx = np.flatnonzero(dataset.contact) if dataset.contact is not None else np.arange(len(dataset))
    if max_frames is not None and len(idx) > max_frames:
        idx = idx[spanning_frames(dataset.wrenches[idx], max_frames)]
    return idx


def _parameter_table(nominal, fitted, uncertainty: dict, true_obj: dict | None) -> list[dict]:
    from ._calibration import _getter

    rows = []
    true = device_from_json(true_obj) if true_obj else None
    for name in uncertainty:
        row = {
            "parameter": name,
            "nominal": float(_getter(name)(nominal)),
            "fitted": float(_getter(name)(fitted)),
            "sd": uncertainty[name],
        }
        if true is not None:
            row["true"] = float(_getter(name)(true))
        rows.append(row)
    return rows


def _write_report(
    out_dir: Path, metrics: dict, true, estimate, sigma, *, title: str, extra: dict | None = None
) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    plot_parity(out_dir / "parity.png", true, estimate, sigma, title=title)
    plot_residuals(out_dir / "residuals.png", true, estimate, title=title)
    write_json(out_dir / "metrics.json", _finite_or_null({**metrics, **(extra or {})}), "metrics")


def _finite_or_null(obj):
    """`obj` with every non-finite float replaced by None: JSON has no NaN."""
    if isinstance(obj, dict):
        return {k: _finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite_or_null(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


MIN_HEAD_FRAMES = 50
MIN_CALIBRATION_FRAMES = 10
# An axis whose loads spread less than this fraction of its calibrated range is not excited:
# the frames say nothing about it.
_EXCITATION_FRACTION = 1e-3


def identification_problems(frames: np.ndarray | Sequence, wrenches: np.ndarray, reference: np.ndarray) -> dict:
    """What a set of calibration frames cannot identify, checked before the fit.

    `refuse` lists reasons no fit can be trusted: fewer than
    `MIN_CALIBRATION_FRAMES` distinct images (identical frames, a frozen camera), fewer
    than that many frames that differ from the no-contact reference at all, or no axis
    whose load varies. `axes_not_excited` names the axes whose load does not vary
    (less than 0.1% of the calibrated range): the fit cannot read them.
    """
    n = len(frames)
    refuse = []
    hashes, changed = set(), 0
    for frame in frames:  # one pass: a sequence that reads its frames reads each once
        frame = np.ascontiguousarray(frame)
        hashes.add(hashlib.sha1(frame).digest())
        changed += bool(np.any(frame != reference))
    distinct = len(hashes)
    if distinct < MIN_CALIBRATION_FRAMES:
        refuse.append(
            f"only {distinct} distinct images among {n} frames in contact (identical frames cannot identify a fit)"
        )
    if changed < MIN_CALIBRATION_FRAMES:
        refuse.append(f"only {changed} of {n} frames in contact differ from the no-contact reference")
    spread = np.std(np.asarray(wrenches, float), axis=0) / WRENCH_SCALE
    not_excited = [axis for axis, s in zip(WRENCH_AXES, spread) if not s > _EXCITATION_FRACTION]
    if len(not_excited) == len(WRENCH_AXES):
        refuse.append("no axis's load varies across the frames")
    return {"refuse": refuse, "axes_not_excited": not_excited}


def calibrate(
    nominal_path: str | Path | None,
    data: str | Path,
    out: str | Path,
    *,
    max_frames: int | None = 500,
    recipe: Recipe | str | Path = "unit",
    baseline_sizes: tuple[int, ...] = (20, 100, 500),
    progress: bool = True,
    force: bool = False,
) -> dict:
    """`moirejax calibrate`: fit a unit, train its residual head, write device, head and report.

    The outputs are checked before the fit, and written as a set after it (see
    `_write_fit_set`). Frames that cannot identify a fit ([`identification_problems`][]:
    identical images, no visible load, no varying load) are refused with a
    [`DataError`][] before the fit, unless `force`; a forced calibration, one with axes
    the frames do not excite, and one that reads an excited axis worse than the mean on its
    own frames (R² < 0) are written flagged: the reasons go in `calibration.flagged` of the
    device file (which then loads with a warning) and in the report's `verdict`.

    The work is kept as it is done in `OUT.parts/` beside the device file: the fitted
    physical parameters, then the calibration frames' cold solves, 16 frames to a part. A
    calibration interrupted (Ctrl-C, a kill, a lost machine) and run again with the same
    data, frames, nominal device and recipe starts where it stopped, and writes the same
    numbers as a run that was never interrupted; a rerun with other inputs drops the parts
    with a warning. The folder goes once the set is written.

    **Raises:** [`DataError`][] for unusable data, [`OutputError`][moirejax.OutputError]
    (before the fit) for outputs that cannot be written.
    """
    out = Path(out)
    _check_fit_outputs(out, report=True)
    recipe = load_recipe(recipe)
    dataset = Dataset(data)
    nominal = load_device(nominal_path) if nominal_path else device_from_json(dataset.device)
    reference = dataset_reference(dataset)
    idx = _select(dataset, max_frames)
    if len(idx) < MIN_CALIBRATION_FRAMES:
        raise DataError(
            f"{data}: only {len(idx)} frames in contact; calibration needs at least {MIN_CALIBRATION_FRAMES}"
        )
    frames = dataset.frames(idx)
    wrenches = dataset.wrenches[idx]
    identification = identification_problems(frames, wrenches, reference)
    if identification["refuse"] and not force:
        raise DataError(
            f"{data}: these frames cannot identify a calibration: {'; '.join(identification['refuse'])} "
            f"(pass {ARGUMENT} to write one anyway, flagged)",
            argument="force",
        )
    parts = Path(f"{out}.parts")
    plan = {
        "data": str(Path(data).resolve()),
        "frames": fingerprint(idx, wrenches, reference),
        "nominal": fingerprint(nominal),
        "recipe": recipe.to_json(),
        # What the environment changes in the solves (`MOIREJAX_MODEL_GRID`,
        # `MOIREJAX_CARRIERS`), and the code and backend that run them.
        "model_shape": list(default_model_shape(nominal)),
        "carriers": default_carriers(),
        "versions": [importlib.metadata.version("moirejax"), jax.__version__, jax.default_backend()],
    }
    if open_parts(parts, plan, argument="out", restart_other=True) and progress:
        print(f"resuming the calibration kept in {parts}", file=sys.stderr)
    fitted, uncertainty, history = _physical_fit(parts, nominal, reference, frames, wrenches, recipe, progress)
    inverter = Inverter(fitted, reference=reference, match_reference=False)
    # The head's frames, and the frames the fit is reported on: those of the calibration
    # frames that span the load space, at most the recipe's `head_frames`.
    solved = np.arange(len(idx))
    if len(idx) > recipe.head_frames:
        solved = spanning_frames(wrenches, recipe.head_frames)
    wrenches = wrenches[solved]
    # Cold starts, as the frames the head will correct are solved: started from their
    # reference wrench instead, the calibration frames were inverted 3x faster, but the head
    # then learned the error of a solver that knows the answer, and on an independent
    # renderer's held-out loads it corrected Fz and Ty less (R2 0.84 and 0.77 against 0.88
    # and 0.81).
    physical = _solve_calibration_frames(parts, inverter, dataset.frames(idx[solved]), progress)
    ok = np.all(np.isfinite(physical.wrench), axis=1) & (physical.status != Status.NO_CONTACT)
    features = head_features(physical.wrench[ok], physical.x0[ok], physical.y0[ok], physical.radius[ok])
    if ok.sum() >= MIN_HEAD_FRAMES:
        head, head_record = train_residual_head(features, (wrenches[ok] - physical.wrench[ok]) / WRENCH_SCALE)
    else:
        # A learned correction from a few dozen frames extrapolates badly to other loads.
        head, head_record = None, {"skipped": f"{int(ok.sum())} usable frames, fewer than {MIN_HEAD_FRAMES}"}
    corrected, corrected_sigma = _apply_head(head, physical)
    tilt, tilt_r2 = fit_tilt_matrix(physical.x0[ok], physical.y0[ok], wrenches[ok][:, 3:5], fitted)
    fitted_device = eqx_replace_tilt(fitted, tilt)
    metrics_physics = wrench_metrics(wrenches, physical.wrench, physical.sigma)
    metrics = wrench_metrics(wrenches, corrected, corrected_sigma)
    # Each frame is read once more for the baseline's features, and not at all without one;
    # the baseline learns from every calibration frame.
    features = ridge_features(frames, reference) if baseline_sizes else np.zeros((len(idx), 0))
    baselines = cross_validated_ridge_r2(features, dataset.wrenches[idx], baseline_sizes)
    report_dir = _report_dir(out)
    parameters = _parameter_table(nominal, fitted_device, uncertainty, dataset.true_device)
    worse_than_mean = [
        axis
        for axis in WRENCH_AXES
        if axis not in identification["axes_not_excited"] and not metrics["r2"][axis] >= 0.0
    ]
    flagged = [f"forced past: {reason}" for reason in identification["refuse"]]
    if identification["axes_not_excited"]:
        flagged.append(
            f"axes the frames do not load, so not identified: {', '.join(identification['axes_not_excited'])}"
        )
    if worse_than_mean:
        flagged.append(
            f"axes read worse than their mean on the calibration's own frames (R2 < 0): {', '.join(worse_than_mean)}"
        )
    verdict = {
        **calibration_verdict(metrics, baselines, parameters, recipe),
        "identified": not flagged,
        "flagged": flagged,
        "axes_not_excited": identification["axes_not_excited"],
        "axes_worse_than_mean": worse_than_mean,
    }
    for problem in flagged:
        warnings.warn(f"{out}: flagged calibration: {problem}", DataWarning, stacklevel=2)

    def write_report(folder: Path) -> None:
        _write_report(
            folder,
            metrics,
            wrenches,
            corrected,
            corrected_sigma,
            title=f"calibration fit ({len(solved)} of {len(idx)} frames, in-sample)",
            extra={
                "physics_only": metrics_physics,
                "residual_head": head_record,
                "parameters": parameters,
                "tilt_matrix": tilt.tolist(),
                "tilt_matrix_r2": tilt_r2,
                "ridge_baseline_r2_crossvalidated": baselines,
                "verdict": verdict,
                "history": history,
                "recipe": recipe.to_json(),
            },
        )
        _plot_parameters(folder / "parameters.png", parameters)

    calibration = {
        "dataset": str(data),
        "recipe": recipe.name,
        "uncertainty": uncertainty,
        "metrics": {"r2": metrics["r2"], "mae": metrics["mae"]},
        **({"flagged": flagged} if flagged else {}),
    }
    _write_fit_set(out, fitted_device, calibration, head, write_report)
    shutil.rmtree(parts, ignore_errors=True)
    return {
        "metrics": metrics,
        "physics_only": metrics_physics,
        "parameters": parameters,
        "baselines": baselines,
        "verdict": verdict,
        "report": str(report_dir),
    }


# A fitted parameter this many prior widths from where it started (or, without a prior,
# this fraction of its nominal value) is one the data pulled hard: the model bends to a
# unit it does not describe.
_STRAINED_PRIOR_WIDTHS = 3.0
_STRAINED_FRACTION = 0.3


def calibration_verdict(metrics: dict, baselines: dict, parameters: list[dict], recipe: Recipe) -> dict:
    """Whether a calibrated unit is inside the model: its wrench R² on every axis against
    the cross-validated [`ridge_baseline`][] trained on the most frames, and the fitted
    parameters that moved far from their start.

    A pixel regression that reads an axis better than the calibrated physics says the
    physics misses something this unit does (its photometry, its mechanics, a load shape);
    `inside_model` is false then and `axes_behind_baseline` names each such axis with both
    R² values. The comparison favours the physics slightly (its R² is in-sample, the
    baseline's cross-validated), so a unit it flags is outside the model for certain.
    """
    behind = {}
    if baselines:
        ridge = baselines[max(baselines, key=int)]
        for axis, r2 in metrics["r2"].items():
            if not (r2 >= ridge[axis]):
                behind[axis] = {"calibrated": r2, "ridge_baseline": ridge[axis]}
    prior = dict(recipe.prior_sd)
    strained = []
    for row in parameters:
        name, nominal, fitted = row["parameter"], row["nominal"], row["fitted"]
        if name in prior:
            move = math.log(abs(fitted / nominal)) if name in recipe.log and nominal and fitted else fitted - nominal
            widths = abs(move) / prior[name]
            if widths > _STRAINED_PRIOR_WIDTHS:
                strained.append({"parameter": name, "nominal": nominal, "fitted": fitted, "prior_widths": widths})
        elif nominal and abs(fitted / nominal - 1.0) > _STRAINED_FRACTION:
            strained.append({"parameter": name, "nominal": nominal, "fitted": fitted})
    return {"inside_model": not behind, "axes_behind_baseline": behind, "strained_parameters": strained}


def eqx_replace_tilt(device, tilt: np.ndarray):
    import equinox as eqx

    return eqx.tree_at(lambda d: d.tilt, device, jnp.asarray(tilt, dtype=device.p1.dtype))


def evaluate(device_path: str | Path, data: str | Path, out_dir: str | Path, *, progress: bool = True) -> dict:
    """`moirejax evaluate`: invert a dataset with a (calibrated) device; metrics and plots.

    With a residual head, the metrics are of the corrected wrench and `physics_only`
    holds those of the physical model alone (also in `metrics.json`).
    """
    out_dir = check_output_folder(out_dir, argument="out_dir")
    device, head = load_calibrated(device_path)
    dataset = Dataset(data)
    reference = dataset_reference(dataset)
    idx = _select(dataset, None)
    inverter = Inverter(device, reference=reference)
    result = _Solutions.of(invert(inverter, dataset.frames(idx), progress=progress, desc="evaluate"))
    wrench, sigma = _apply_head(head, result)
    truth = dataset.wrenches[idx]
    metrics = wrench_metrics(truth, wrench, sigma)
    statuses = {Status(int(s)).name.lower(): int(np.sum(result.status == s)) for s in np.unique(result.status)}
    extra: dict = {"status_counts": statuses}
    if head is not None:
        extra["physics_only"] = wrench_metrics(truth, result.wrench, result.sigma)
    # Staged beside the outputs and moved in with metrics.json last: a rerun interrupted
    # part way leaves the previous report whole.
    with staging_folder(out_dir / "metrics.json") as staging:
        _write_report(
            staging / "report",
            metrics,
            truth,
            wrench,
            sigma,
            title=f"evaluation on {Path(data).name}",
            extra=extra,
        )
        names = ("parity.png", "residuals.png", "metrics.json")
        commit_staged(staging, [(staging / "report" / name, out_dir / name) for name in names])
    return {**metrics, **({"physics_only": extra["physics_only"]} if head is not None else {})}


def transfer(
    from_path: str | Path,
    data: str | Path,
    out: str | Path,
    *,
    max_frames: int = 20,
    recipe: Recipe | str | Path = "transfer",
    progress: bool = True,
) -> dict:
    """`moirejax transfer`: refit a new unit's physical parameters from a handful of frames,
    keeping the first unit's tilt matrix and, unless it makes the new unit's frames worse,
    its residual head; the recipe's priors centre on the first unit's fit.

    The frames are the `max_frames` that span the load space best ([`spanning_frames`][]).
    """
    from_path, out = Path(from_path), Path(out)
    _check_fit_outputs(out, report=False)
    recipe = load_recipe(recipe)
    device, head = load_calibrated(from_path)
    dataset = Dataset(data)
    reference = dataset_reference(dataset)
    idx = _select(dataset, max_frames)
    frames = dataset.frames(idx)
    wrenches = dataset.wrenches[idx]
    result = fit_physical_parameters(device, reference, frames, wrenches, recipe, progress=progress)
    head_check = None
    if head is not None:
        # The head learned what the physics left on the first unit; part of that is the
        # unit's own (its fabrication), so check it on the new unit's frames, which it
        # never saw. On a pair of simulated units it cost 0.01 R² on the shear axes.
        inverter = Inverter(result.device, reference=reference, match_reference=False)
        physical = _Solutions.of(invert(inverter, frames, progress=progress, desc="check residual head"))
        ok = np.all(np.isfinite(physical.wrench), axis=1) & (physical.status != Status.NO_CONTACT)
        without = float(np.mean(((physical.wrench[ok] - wrenches[ok]) / WRENCH_SCALE) ** 2))
        with_head = float(np.mean(((_apply_head(head, physical)[0][ok] - wrenches[ok]) / WRENCH_SCALE) ** 2))
        head_check = {
            "frames": int(ok.sum()),
            "scaled_mse_without_head": without,
            "scaled_mse_with_head": with_head,
            # Without a usable frame there is no evidence against the head.
            "kept": bool(not ok.any() or with_head <= without),
        }
        if not head_check["kept"]:
            head = None
    calibration = {
        "dataset": str(data),
        "recipe": recipe.name,
        "uncertainty": result.uncertainty,
        **({"residual_head_check": head_check} if head_check else {}),
    }
    _write_fit_set(out, result.device, calibration, head)
    return {"uncertainty": result.uncertainty, "frames": len(idx), "residual_head_check": head_check}


def _plot_parameters(path: Path, parameters: list[dict]) -> None:
    from .._plotting import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 0.5 + 0.45 * len(parameters)))
    names = [p["parameter"] for p in parameters]
    rel = [(p["fitted"] - p["nominal"]) / (abs(p["nominal"]) if p["nominal"] else 1.0) * 100 for p in parameters]
    err = [p["sd"] / (abs(p["nominal"]) if p["nominal"] else 1.0) * 100 * 1.96 for p in parameters]
    y = np.arange(len(names))
    ax.errorbar(rel, y, xerr=err, fmt="o", label="fitted (95%)")
    if all("true" in p for p in parameters):
        true = [(p["true"] - p["nominal"]) / (abs(p["nominal"]) if p["nominal"] else 1.0) * 100 for p in parameters]
        ax.plot(true, y, "rx", label="true unit")
    ax.axvline(0, color="k", lw=0.8)
    ax.set_yticks(y, names)
    ax.set_xlabel("deviation from nominal (% of nominal; absolute x100 for zero-nominal angles)")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)
