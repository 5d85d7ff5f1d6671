"""Inverting recordings: datasets, videos and folders of frames into a wrench CSV."""

import csv
import io
import math
import warnings
from collections.abc import Iterator
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .._conventions import WRENCH_AXES
from .._fileio import atomic_write_text, check_output_file, DataError, DataWarning
from ..data import IMAGE_SUFFIXES
from ._inversion import Inverter
from ._invert import _invert_chunk, frame_tracker, with_second_contact
from ._state import Estimate, Status


CSV_HEADER = (
    "frame",
    *WRENCH_AXES,
    *(f"sigma_{c}" for c in WRENCH_AXES),
    "x0",
    "y0",
    "radius",
    "flatness",
    "aspect_ratio",
    "long_axis_angle",
    "contacts",
    "second_x0",
    "second_y0",
    "second_radius",
    "second_flatness",
    "second_aspect_ratio",
    "second_long_axis_angle",
    *(f"second_{c}" for c in WRENCH_AXES),
    "status",
    "message",
)


def check_source(source: str | Path) -> str:
    """Check that `source` can be read, before anything is compiled; returns its kind:
    `"dataset"`, `"folder"` (of images) or `"video"`.

    Raises [`DataError`][] naming the path: no such path, a dataset folder whose manifest is
    missing (an interrupted writer) or invalid, a folder without images, a file that is not
    a video.
    """
    import cv2

    from ..data import Dataset

    path = Path(source)
    if (path / "manifest.json").exists():
        Dataset(path)  # validates the manifest and every row of wrench.csv
        return "dataset"
    if path.is_dir():
        if (path / "frames").is_dir() or (path / "wrench.csv").exists():
            raise DataError(
                f"{path / 'manifest.json'}: no such file; the folder has a dataset's frames/ or wrench.csv but no "
                "manifest, so the dataset is incomplete (was its writer interrupted?)"
            )
        if not any(p.suffix.lower() in IMAGE_SUFFIXES for p in path.iterdir()):
            raise DataError(f"{path}: no image files ({', '.join(sorted(IMAGE_SUFFIXES))}) and no dataset manifest")
        return "folder"
    if not path.exists():
        raise DataError(f"{path}: no such dataset, folder or video")
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise DataError(f"{path}: cannot open as a video")
    finally:
        capture.release()
    return "video"


def count_source_frames(source: str | Path) -> int:
    """The number of frames of a dataset or a folder of images (a video's count is what its
    container declares, which a truncated file does not hold: it is not counted here)."""
    from ..data import Dataset

    kind = check_source(source)
    if kind == "dataset":
        return len(Dataset(Path(source)))
    if kind == "folder":
        return len(_folder_images(Path(source)))
    raise DataError(f"{source}: a video has no reliable frame count; import it into a dataset first (moirejax import)")


def _folder_images(path: Path) -> list[Path]:
    return sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


def iter_source_frames(
    source: str | Path, shape: tuple[int, int], start: int = 0, stop: int | None = None
) -> Iterator[tuple[str, np.ndarray | None, str | None]]:
    """Yield `(name, frame or None, error or None)` from a dataset, a video file or a folder
    of images: its frames `start` to `stop - 1` (default: all).

    A frame that cannot be read, or has the wrong size, comes back as `None` with a
    message; the iteration goes on. A video that ends before the number of frames its
    container declares (truncated, or corrupt part way) is read as far as it goes, with
    a [`DataWarning`][moirejax.DataWarning] giving both counts.
    """
    import cv2

    from ..data import Dataset

    kind = check_source(source)
    path = Path(source)
    if kind == "dataset":
        dataset = Dataset(path)
        for i, frame, error in dataset.iter_frames(start, stop, on_error="status"):
            yield dataset.frame_names[i], frame, error
        return
    if kind == "folder":
        for p in _folder_images(path)[start:stop]:
            image = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if image is None:
                yield p.name, None, f"{p.name}: unreadable image"
                continue
            yield p.name, _to_gray(image), None
        return
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise DataError(f"{path}: cannot open as a video")
    declared = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    index = 0
    try:
        while stop is None or index < stop:
            ok, image = capture.read()
            if not ok:
                break
            if index >= start:
                yield f"{index:06d}", _to_gray(image), None
            index += 1
    finally:
        capture.release()
    if stop is not None:
        return
    if declared > index:
        warnings.warn(
            f"{path}: read {index} of the {declared} frames the video declares; it is truncated or corrupt "
            f"after frame {index}",
            DataWarning,
            stacklevel=2,
        )


def _to_gray(image: np.ndarray) -> np.ndarray:
    import cv2

    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    scale = 65535.0 if image.dtype == np.uint16 else 255.0
    return image.astype(np.float32) / scale


def find_reference(source: str | Path, shape: tuple[int, int]) -> tuple[np.ndarray | None, str]:
    """A no-contact reference frame for `source`: the mean of up to 8 frames flagged
    `contact = 0` in a dataset. Returns `(frame or None, description)`.

    A contact-free frame that cannot be read (truncated, corrupt) is skipped with a
    [`DataWarning`][moirejax.DataWarning] and the next one used; it still gets its
    own status row when the recording is inverted.
    """
    from ..data import Dataset

    path = Path(source)
    if not (path / "manifest.json").exists():
        return None, "no reference: none given and the source is not a dataset with contact flags"
    dataset = Dataset(path)
    if dataset.contact is None:
        return None, f"no reference: {path} has no contact column"
    free = np.flatnonzero(~dataset.contact)
    if len(free) == 0:
        return None, f"no reference: {path} has no contact-free frame"
    if dataset.frame_shape != shape:
        return None, "no reference: frame size differs from the device"
    frames, skipped = [], []
    for i in free:
        try:
            frames.append(dataset.frame(int(i)))
        except DataError as e:
            skipped.append(str(e))
            continue
        if len(frames) == 8:
            break
    for message in skipped:
        warnings.warn(f"reference frame skipped: {message}", DataWarning, stacklevel=2)
    if not frames:
        return None, f"no reference: none of the {len(free)} contact-free frames of {path} can be read"
    return np.mean(frames, axis=0), f"reference: mean of {len(frames)} contact-free frames of {path}"


def load_reference_image(path: str | Path) -> np.ndarray:
    """Read a reference (no-contact) frame from an image file."""
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataError(f"{path}: cannot read the reference image")
    return _to_gray(image)


def _patch_columns(c) -> list[np.ndarray]:
    """A patch's columns: centre, radius, flatness, aspect ratio and long axis' direction."""
    return [np.asarray(v) for v in (c.x0, c.y0, c.radius, c.flatness, c.aspect_ratio, c.long_axis_angle)]


def _rows(names: list[str], estimate: Estimate, messages: list[str | None], head=None) -> list[list]:
    wrench, sigma = np.asarray(estimate.wrench), np.asarray(estimate.sigma)
    if head is not None:
        ok = np.all(np.isfinite(wrench), axis=1) & (np.asarray(estimate.status) != Status.NO_CONTACT)
        if np.any(ok):
            wrench, sigma = wrench.copy(), sigma.copy()
            c = estimate.contact
            wrench[ok] = head.correct(wrench[ok], np.asarray(c.x0)[ok], np.asarray(c.y0)[ok], np.asarray(c.radius)[ok])
            sigma[ok] = head.corrected_sigma(sigma[ok])
    status = np.asarray(estimate.status)
    c = estimate.contact
    second = estimate.second_contact
    contacts = np.asarray(estimate.contacts)
    patch = [*_patch_columns(c), contacts, *_patch_columns(second)]
    # The second patch's share of the wrench; NaN for a frame read with one patch.
    second_wrench = np.where(contacts[:, None] == 2, np.asarray(estimate.second_wrench), np.nan)
    rows = []
    for i, name in enumerate(names):
        code = Status(int(status[i]))
        message = messages[i] or code.message
        rows.append(
            [name, *wrench[i], *sigma[i], *(v[i] for v in patch), *second_wrench[i], code.name.lower(), message]
        )
    return rows


def _failed_row(name: str, code: Status, message: str) -> list:
    # Every number unknown (NaN) but the count of contacts, laid out by the header itself.
    row = dict.fromkeys(CSV_HEADER, float("nan")) | {
        "frame": name,
        "contacts": 0,
        "status": code.name.lower(),
        "message": message,
    }
    return [row[column] for column in CSV_HEADER]


def invert_segment(
    inverter: Inverter,
    source: str | Path,
    start: int = 0,
    stop: int | None = None,
    *,
    batch: int = 1,
    head=None,
    progress=None,
) -> list[list]:
    """The CSV rows of frames `start` to `stop - 1` of `source`, inverted as one stream that
    starts cold at `start` (see [`invert_recording`][]). `progress`, if given, is called
    with each frame's row count as it is done."""
    shape = (inverter.device.height, inverter.device.width)
    rows: list[list] = []
    track = inverter.cold_track()
    step = frame_tracker(inverter)
    pending: list[tuple[str, np.ndarray]] = []

    def flush():
        nonlocal track
        if not pending:
            return
        estimates, track = _invert_chunk(inverter, [f for _, f in pending], track, batch)
        estimates = [with_second_contact(inverter, jnp.asarray(frame), e) for (_, frame), e in zip(pending, estimates)]
        stacked = jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v) for v in x]), *estimates)
        rows.extend(_rows([name for name, _ in pending], stacked, [None] * len(pending), head))
        if progress is not None:
            progress(len(pending))
        pending.clear()

    def failed(row):
        flush()
        rows.append(row)
        if progress is not None:
            progress(1)

    for name, frame, error in iter_source_frames(source, shape, start, stop):
        if frame is None:
            failed(_failed_row(name, Status.UNREADABLE, error or "unreadable"))
            continue
        if frame.shape != shape:
            message = f"{name}: frame is {frame.shape[0]}x{frame.shape[1]}, device expects {shape[0]}x{shape[1]}"
            failed(_failed_row(name, Status.WRONG_SIZE, message))
            continue
        if batch > 1:
            pending.append((name, frame))
            if len(pending) == batch:
                flush()
            continue
        estimate, track = step(frame, track)
        estimate = with_second_contact(inverter, jnp.asarray(frame), estimate)
        rows.extend(_rows([name], _expand(estimate), [None], head))
        if progress is not None:
            progress(1)
    flush()
    return rows


def segments(n_frames: int, restart_every: int | None) -> list[tuple[int, int]]:
    """`(start, stop)` of each stream of a recording of `n_frames` that restarts cold every
    `restart_every` frames (one stream when None)."""
    if restart_every is None:
        return [(0, n_frames)]
    return [(k, min(k + restart_every, n_frames)) for k in range(0, n_frames, restart_every)]


def _check_count(batch, name: str = "batch") -> None:
    if isinstance(batch, bool) or not isinstance(batch, int | np.integer) or batch < 1:
        raise ValueError(f"{name} must be a whole number >= 1, got {batch!r}")


def _csv_text(rows: list[list]) -> str:
    """The lines of the wrench CSV for rows of [`invert_segment`][], without the header."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    for row in rows:
        writer.writerow([row[0], *(_fmt(v) for v in row[1:-2]), row[-2], row[-1]])
    return buffer.getvalue()


def write_wrench_csv(out_csv: str | Path, rows: list[list]) -> dict[str, int]:
    """Write the rows of [`invert_segment`][] as the wrench CSV (atomically); returns the
    count of each status."""
    counts: dict[str, int] = {}
    for row in rows:
        counts[row[-2]] = counts.get(row[-2], 0) + 1
    atomic_write_text(out_csv, ",".join(CSV_HEADER) + "\n" + _csv_text(rows))
    return counts


def invert_recording(
    inverter: Inverter,
    source: str | Path,
    out_csv: str | Path,
    *,
    batch: int = 1,
    restart_every: int | None = None,
    progress: bool = True,
    head=None,
) -> dict[str, int]:
    """Invert every frame of `source` and write `out_csv` (atomically, at the end).

    Frames are inverted as a stream ([`frame_tracker`][]: each continues from the last
    good one), or, with `batch > 1`, in chunks of `batch` consecutive frames vectorised
    from the previous chunk's solution (as [`invert`][] with `sequence=True`; higher
    throughput, the same estimates to about one standard error). With `restart_every`,
    the stream starts cold again every that many frames: each such segment depends on no
    other, which is what lets [`invert_distributed`][] hand segments to separate workers
    and still write the same numbers as this function. Bad frames give status rows, never
    an exception. Returns the count of each status.

    **Raises:** `ValueError` for `batch < 1` or `restart_every < 1`; [`DataError`][] for a
    source that cannot be read (or a video with `restart_every`, which needs a frame
    count); [`OutputError`][moirejax.OutputError] when `out_csv` cannot be written
    (checked before the first frame).
    """
    from tqdm.auto import tqdm

    _check_count(batch)
    if restart_every is not None:
        _check_count(restart_every, "restart_every")
    check_source(source)
    check_output_file(out_csv, argument="out_csv")
    n_frames = count_source_frames(source) if restart_every is not None else None
    bar = tqdm(total=n_frames, desc="invert", unit="frame", disable=not progress)
    rows: list[list] = []
    try:
        if n_frames is None:
            rows = invert_segment(inverter, source, batch=batch, head=head, progress=bar.update)
        else:
            for start, stop in segments(n_frames, restart_every):
                rows += invert_segment(inverter, source, start, stop, batch=batch, head=head, progress=bar.update)
    finally:
        bar.close()
    return write_wrench_csv(out_csv, rows)


def _fmt(value) -> str:
    value = float(value)
    return "nan" if math.isnan(value) else f"{value:.9g}"


def _expand(estimate: Estimate) -> Estimate:
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[None], estimate)
