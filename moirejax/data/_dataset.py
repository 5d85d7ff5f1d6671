"""The on-disk dataset format, its reader and writer, and import/export of lab recordings.

A dataset is a folder that ordinary tools can open:

- `frames/`: one grayscale PNG (8- or 16-bit) per frame, e.g. `000000.png`, or a colour
  (BGR) PNG per frame where the manifest says `channels: 3` (see-through frames);
- `wrench.csv`: header `frame,fx,fy,fz,tx,ty,tz[,t][,contact]`, one row per frame, `frame`
  being the image file name relative to `frames/`; forces in N, torques in N*m, in the
  convention [`WRENCH_CONVENTION`][];
- optionally a latent ground-truth CSV (simulated data), named by the manifest's `contacts`;
- optionally ground-truth images (simulated data), one 16-bit PNG per frame under a folder
  of each name the manifest's `images` lists, with the frame's file name;
- `manifest.json`, validated against `data_schema/dataset.schema.json`. It is written last,
  so a folder without it is recognisably incomplete.

Row numbers in error messages count the header as row 1, as a spreadsheet shows them.

Reader, writer, import and export are one module: they share the CSV and image helpers and
the constants that define the format.
"""

import csv
import dataclasses
import datetime
import io
import math
import os
import re
import shutil
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path, PurePosixPath
from typing import Any, Literal, NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
from jaxtyping import Bool, Float, Float32, Float64, Int64
from tqdm import tqdm

from .._conventions import WRENCH_AXES, WRENCH_CONVENTION
from .._fileio import (
    ARGUMENT,
    atomic_write_bytes,
    atomic_write_text,
    check_output_folder,
    DataError,
    DataWarning,
    read_json,
    staging_folder,
    validate_json,
    write_json,
)
from ._ft import _wrench_at, align_ft, fringe_change


FORMAT = "moirejax-dataset"
VERSION = 1
MANIFEST_NAME = "manifest.json"
FRAMES_DIR = "frames"
WRENCH_NAME = "wrench.csv"
CONTACTS_NAME = "contact.csv"

_OPTIONAL_COLUMNS = ("t", "contact")
# The names a force/torque log's time column may have (any case).
FT_TIME_COLUMNS = ("t", "time", "timestamp")
# The image files (by suffix, any case) that make up a folder of frames, wherever one is read.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm")
_MAXVAL = {8: 255, 16: 65535}
# Scalars as simulators hand them over (Python or NumPy).
_Real = float | int | np.floating | np.integer

# Float frames this far outside [0, 1] are rounding noise from the renderer, not a bug.
_FLOAT_RANGE_SLACK = 1e-6


# --------------------------------------------------------------------------- CSV reading


def _frame_name_problem(name: str) -> str | None:
    """Why `name` cannot be a frame file name relative to `frames/`, or `None` if it can."""
    if not name:
        return "is empty"
    if "\\" in name or any(ord(c) < 32 for c in name):
        return f"{name!r} contains a backslash or a control character"
    path = PurePosixPath(name)
    if path.is_absolute() or ".." in path.parts or not path.parts:
        return f"{name!r} is not a file name relative to the frames folder"
    return None


def _parse_number(text: str, where: str, field: str, *, require_finite: bool) -> float:
    text = text.strip()
    if not text:
        raise DataError(f"{where}: field '{field}': is empty")
    try:
        value = float(text)
    except ValueError:
        raise DataError(f"{where}: field '{field}': {text!r} is not a number") from None
    if require_finite and not math.isfinite(value):
        raise DataError(f"{where}: field '{field}': {text!r} is not finite")
    return value


def _read_header(reader: Any, path: Path, required: tuple[str, ...]) -> list[str]:
    try:
        header = [name.strip() for name in next(reader)]
    except StopIteration:
        raise DataError(f"{path}: file is empty (expected a header row)") from None
    duplicated = sorted({name for name in header if header.count(name) > 1})
    if duplicated:
        raise DataError(f"{path}: column(s) {', '.join(map(repr, duplicated))} appear twice")
    missing = [name for name in required if name not in header]
    if missing:
        raise DataError(
            f"{path}: missing column(s) {', '.join(map(repr, missing))} "
            f"(header is {','.join(header)!r}; expected {','.join(required)!r})"
        )
    return header


def _records(reader: Any, path: Path, header: list[str]) -> Iterator[tuple[int, dict[str, str]]]:
    """Yield `(row number, {column: text})` for every non-blank data row."""
    for record in reader:
        if not any(field.strip() for field in record):
            continue
        if len(record) != len(header):
            raise DataError(f"{path} row {reader.line_num}: expected {len(header)} fields, found {len(record)}")
        yield reader.line_num, dict(zip(header, record))


def _open_csv(path: Path) -> io.TextIOWrapper:
    try:
        # utf-8-sig: spreadsheet programs often start CSV files with a byte-order mark.
        return open(path, newline="", encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None


@dataclasses.dataclass(frozen=True)
class _WrenchTable:
    frames: tuple[str, ...]
    rows: tuple[int, ...]
    wrenches: np.ndarray
    t: np.ndarray | None
    contact: np.ndarray | None
    ignored_columns: tuple[str, ...]


def _read_wrench_table(path: Path, *, strict: bool, frames_only: bool = False) -> _WrenchTable:
    """Parse a `frame,fx,fy,fz,tx,ty,tz[,t][,contact]` CSV.

    `strict` (a dataset's own `wrench.csv`) rejects unknown columns and non-finite wrenches;
    otherwise (a lab recording) unknown columns are ignored and non-finite wrench values are
    kept as NaN/inf for the caller to report per frame. `frames_only` (the frame list of a
    recording whose wrench comes from a force/torque log) reads `frame`, `t` and `contact`
    only, ignoring any wrench columns; the wrenches are NaN.
    """
    required = ("frame",) if frames_only else ("frame", *WRENCH_AXES)
    with _open_csv(path) as f:
        reader = csv.reader(f)
        header = _read_header(reader, path, required)
        extra = [name for name in header if name not in required + _OPTIONAL_COLUMNS]
        if strict and extra:
            raise DataError(
                f"{path}: unknown column(s) {', '.join(map(repr, extra))} "
                f"(allowed: {','.join(required + _OPTIONAL_COLUMNS)})"
            )
        has_t, has_contact = "t" in header, "contact" in header
        frames: list[str] = []
        rows: list[int] = []
        wrenches: list[list[float]] = []
        times: list[float] = []
        contacts: list[bool] = []
        first_row_of: dict[str, int] = {}
        for row, record in _records(reader, path, header):
            where = f"{path} row {row}"
            name = record["frame"].strip()
            problem = _frame_name_problem(name)
            if problem is not None:
                raise DataError(f"{where}: field 'frame': {problem}")
            name = str(PurePosixPath(name))
            if name in first_row_of:
                raise DataError(f"{where}: field 'frame': {name!r} already appears in row {first_row_of[name]}")
            first_row_of[name] = row
            frames.append(name)
            rows.append(row)
            if not frames_only:
                wrenches.append([_parse_number(record[c], where, c, require_finite=strict) for c in WRENCH_AXES])
            if has_t:
                times.append(_parse_number(record["t"], where, "t", require_finite=True))
            if has_contact:
                value = _parse_number(record["contact"], where, "contact", require_finite=True)
                if value not in (0.0, 1.0):
                    raise DataError(f"{where}: field 'contact': {record['contact'].strip()!r} is not 0 or 1")
                contacts.append(value == 1.0)
    return _WrenchTable(
        frames=tuple(frames),
        rows=tuple(rows),
        wrenches=np.full((len(frames), 6), np.nan)
        if frames_only
        else np.array(wrenches, dtype=np.float64).reshape(len(frames), 6),
        t=np.array(times, dtype=np.float64) if has_t else None,
        contact=np.array(contacts, dtype=bool) if has_contact else None,
        ignored_columns=tuple(extra),
    )


def _read_latents(path: Path, frames: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Read a latent ground-truth CSV whose `frame` column matches `frames` row by row."""
    with _open_csv(path) as f:
        reader = csv.reader(f)
        header = _read_header(reader, path, ("frame",))
        columns = [name for name in header if name != "frame"]
        values: list[list[float]] = []
        for row, record in _records(reader, path, header):
            where = f"{path} row {row}"
            i = len(values)
            name = record["frame"].strip()
            if i >= len(frames) or str(PurePosixPath(name)) != frames[i]:
                expected = repr(frames[i]) if i < len(frames) else "no more rows"
                raise DataError(f"{where}: field 'frame': {name!r} does not match {WRENCH_NAME} (expected {expected})")
            # NaN is allowed: a latent such as the contact centre is undefined without contact.
            values.append([_parse_number(record[c], where, c, require_finite=False) for c in columns])
    if len(values) != len(frames):
        raise DataError(f"{path}: {len(values)} rows, but {WRENCH_NAME} has {len(frames)}")
    table = np.array(values, dtype=np.float64).reshape(len(frames), len(columns))
    return {name: table[:, k] for k, name in enumerate(columns)}


def read_ft_log(path: str | os.PathLike) -> tuple[Float64[np.ndarray, " m"], Float64[np.ndarray, "m 6"]]:
    """Read a force/torque sensor's log: its sample times and wrenches.

    The CSV has a header row naming a time column (`t`, `time` or `timestamp`; seconds on
    the sensor's own clock, any origin) and `fx,fy,fz,tx,ty,tz` (N and N·m, in the
    convention [`WRENCH_CONVENTION`][moirejax.WRENCH_CONVENTION]); names match in any case
    and other columns are ignored. Times must increase from row to row and every value must
    be finite. [`import_recording`][] aligns such a log to the frames of a recording.

    **Arguments:**

    - `path`: the CSV file.

    **Returns:**

    `(times, wrenches)`: the sample times (s) and the wrench of each sample.

    **Raises:** [`DataError`][] naming the file, row and column of the first problem.
    """
    path = Path(path)
    with _open_csv(path) as f:
        reader = csv.reader(f)
        try:
            header = [name.strip().lower() for name in next(reader)]
        except StopIteration:
            raise DataError(f"{path}: file is empty (expected a header row)") from None
        time_columns = [name for name in FT_TIME_COLUMNS if name in header]
        if len(time_columns) != 1:
            found = "none" if not time_columns else " and ".join(map(repr, time_columns))
            raise DataError(
                f"{path}: needs exactly one time column ({', '.join(map(repr, FT_TIME_COLUMNS))}), found {found} "
                f"(header is {','.join(header)!r})"
            )
        _read_header(iter([header]), path, (time_columns[0], *WRENCH_AXES))
        time_column = time_columns[0]
        times: list[float] = []
        wrenches: list[list[float]] = []
        for row, record in _records(reader, path, header):
            where = f"{path} row {row}"
            t = _parse_number(record[time_column], where, time_column, require_finite=True)
            if times and not t > times[-1]:
                raise DataError(
                    f"{where}: field {time_column!r}: {t:g} s does not follow the previous row's "
                    f"{times[-1]:g} s (times must increase)"
                )
            times.append(t)
            wrenches.append([_parse_number(record[c], where, c, require_finite=True) for c in WRENCH_AXES])
    if len(times) < 2:
        raise DataError(f"{path}: {len(times)} data row(s); a force/torque log needs at least 2")
    return np.array(times, dtype=np.float64), np.array(wrenches, dtype=np.float64)


def _frame_list(frames_dir: Path) -> _WrenchTable:
    """The image files of a folder, in name order, as the frames of a recording."""
    names = sorted(p.name for p in frames_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not names:
        raise DataError(f"{frames_dir}: no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
    return _WrenchTable(
        frames=tuple(names),
        rows=(0,) * len(names),
        wrenches=np.full((len(names), 6), np.nan),
        t=None,
        contact=None,
        ignored_columns=(),
    )


def _format_csv(header: list[str], rows: list[list[Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


# --------------------------------------------------------------------------- images


def _load_gray(path: Path) -> np.ndarray:
    """Read an image file as a 2-D uint8 or uint16 grayscale array; colour is converted."""
    return _load_image(path, color=False)


def _load_image(path: Path, *, color: bool) -> np.ndarray:
    """Read an image file as uint8 or uint16: 2-D gray, or `(h, w, 3)` BGR with `color`
    (a gray file is then repeated in each channel)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except OSError as e:
        raise DataError(f"{path}: cannot be read ({e.strerror})") from None
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    if image is None:
        raise DataError(f"{path}: not a readable image (corrupt, truncated or unknown format)")
    if image.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: unsupported pixel type {image.dtype} (need 8 or 16 bits)")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        if color:
            return np.ascontiguousarray(image[:, :, :3])
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(image, code)
    if image.ndim != 2:
        raise DataError(f"{path}: unsupported image layout {image.shape}")
    return np.repeat(image[:, :, None], 3, axis=2) if color else image


def _quantise(frame: npt.ArrayLike, bit_depth: int) -> np.ndarray:
    """Convert a float frame in [0, 1], or a uint8/uint16 frame, to the PNG pixel type."""
    array = np.asarray(frame)
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    if not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 3)):
        raise ValueError(f"a frame must be a (height, width) or BGR (height, width, 3) array, got shape {array.shape}")
    if array.dtype == np.uint8:
        # 255 * 257 = 65535: full scale maps to full scale exactly.
        return array if bit_depth == 8 else array.astype(np.uint16) * np.uint16(257)
    if array.dtype == np.uint16:
        return array if bit_depth == 16 else np.round(array / 257.0).astype(np.uint8)
    if array.dtype.kind != "f":
        raise ValueError(f"frames must be float arrays in [0, 1] or uint8/uint16 arrays, got {array.dtype}")
    if not np.all(np.isfinite(array)):
        raise ValueError("frame contains NaN or inf")
    lo, hi = float(array.min()), float(array.max())
    if lo < -_FLOAT_RANGE_SLACK or hi > 1 + _FLOAT_RANGE_SLACK:
        raise ValueError(f"float frame values must lie in [0, 1] (clip first); got [{lo}, {hi}]")
    scaled = np.clip(array.astype(np.float64), 0.0, 1.0) * _MAXVAL[bit_depth]
    return np.round(scaled).astype(dtype)


def unit_frame(frame: npt.ArrayLike) -> Float[np.ndarray, "h w"]:
    """A frame in [0, 1], the range the inversion reads: uint8 frames are divided by 255 and
    uint16 frames by 65535 into float32 (as a camera or `cv2.imread` delivers them); float
    frames are returned as they are.

    **Raises:** `ValueError` for a frame that is not 2-D, or not of an unsigned 8/16-bit or
    float type.
    """
    array = np.asarray(frame)
    if array.ndim != 2:
        raise ValueError(f"a frame must be a 2-D (height, width) array, got shape {array.shape}")
    if array.dtype in (np.uint8, np.uint16):
        return array.astype(np.float32) / np.float32(_MAXVAL[8 * array.dtype.itemsize])
    if array.dtype.kind != "f":
        raise ValueError(f"frames must be float arrays in [0, 1] or uint8/uint16 arrays, got {array.dtype}")
    return array


def _encode_png(image: np.ndarray) -> bytes:
    ok, buffer = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("OpenCV failed to encode a PNG frame")
    return buffer.tobytes()


# --------------------------------------------------------------------------- writer


def _check_output_dir(path: Path, overwrite: bool) -> bool:
    """Whether `path` holds something to replace; raise if that is not allowed."""
    if path.exists() and not path.is_dir():
        raise DataError(f"{path}: exists and is not a folder")
    occupied = path.is_dir() and any(path.iterdir())
    if occupied and not overwrite:
        raise DataError(f"{path}: folder is not empty; pass {ARGUMENT} to replace it", argument="overwrite")
    return occupied


def _prepare_output_dir(path: Path, overwrite: bool, images: tuple[str, ...] = ()) -> None:
    if _check_output_dir(path, overwrite):
        # Remove the manifest first, so the folder stops claiming to be a complete dataset.
        for name in (MANIFEST_NAME, WRENCH_NAME, CONTACTS_NAME):
            (path / name).unlink(missing_ok=True)
        for folder in (FRAMES_DIR, *images):
            shutil.rmtree(path / folder, ignore_errors=True)
    for folder in (FRAMES_DIR, *images):
        (path / folder).mkdir(parents=True, exist_ok=True)


# The names of ground-truth image folders: plain lower-case words, not the frames' own.
_IMAGES_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


class DatasetWriter:
    """Stream frames and wrenches into a new dataset folder.

    Each frame is written as a PNG as soon as it is added; wrench rows are kept (small) and
    `wrench.csv`, the latent CSV and finally `manifest.json` are written atomically by
    [`DatasetWriter.close`][]. Used as a context manager, an exception (including
    `KeyboardInterrupt`) inside the block leaves a folder without a manifest, which
    [`open_dataset`][] reports as incomplete.

    **Arguments:**

    - `path`: the dataset folder; created if needed, and must be empty unless `overwrite`.
    - `device`: the nominal device JSON object, or a path to a device file relative to `path`.
    - `frame_shape`: `(height, width)`; by default taken from the first frame.
    - `bit_depth`: 8 or 16 bits per PNG pixel.
    - `source`: free text saying where the data came from.
    - `fps`, `protocol`, `fidelity`, `seed`, `true_device`, `metadata`, `ft_alignment`:
      optional manifest fields (see `data_schema/dataset.schema.json`).
    - `images`: names of ground-truth images that every frame comes with (a simulated
      see-through frame's `"grating_free"` view): each is written as a 16-bit PNG under a
      folder of its name, with the frame's file name, and read back by [`Dataset.image`][].
    - `overwrite`: replace the manifest, `wrench.csv`, latent CSV, `frames/` and the image
      folders of a non-empty `path` (other files there are left alone).

    Frames are gray `(h, w)` or colour, BGR `(h, w, 3)` in OpenCV's channel order; every
    frame of a dataset has the same kind, and the manifest records colour as `channels: 3`.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        device: dict | str,
        frame_shape: tuple[int, int] | None = None,
        bit_depth: int = 8,
        source: str = "",
        fps: _Real | None = None,
        protocol: str | None = None,
        fidelity: str | _Real | None = None,
        seed: int | None = None,
        true_device: dict | None = None,
        metadata: dict | None = None,
        ft_alignment: dict | None = None,
        images: tuple[str, ...] = (),
        overwrite: bool = False,
    ):
        images = tuple(images)
        if any(not _IMAGES_NAME.match(name) or name == FRAMES_DIR for name in images) or len(set(images)) < len(images):
            raise ValueError(
                f"images must be distinct lower-case names (letters, digits, _) other than {FRAMES_DIR!r}, got {images}"
            )
        if bit_depth not in _MAXVAL:
            raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth}")
        if frame_shape is not None and (len(frame_shape) != 2 or min(frame_shape) < 1):
            raise ValueError(f"frame_shape must be (height, width) >= 1, got {frame_shape}")
        self.path = Path(path)
        self.bit_depth = bit_depth
        self.frame_shape = None if frame_shape is None else tuple(map(int, frame_shape))
        optional = dict(
            fps=_plain(fps),
            true_device=true_device,
            protocol=protocol,
            fidelity=_plain(fidelity),
            seed=seed,
            metadata=metadata,
            ft_alignment=ft_alignment,
            images=list(images) or None,
        )
        self._manifest: dict[str, Any] = {
            "format": FORMAT,
            "version": VERSION,
            "n_frames": 0,
            "height": 1,
            "width": 1,
            "bit_depth": bit_depth,
            "wrench_convention": WRENCH_CONVENTION,
            "device": device,
            **{k: v for k, v in optional.items() if v is not None},
            "source": source,
            "created": "",
        }
        # Fail now on bad metadata rather than after writing thousands of frames.
        validate_json(dict(self._manifest, created=_now()), "dataset", source=str(self.path / MANIFEST_NAME))
        _prepare_output_dir(self.path, overwrite, images)
        self.images = images
        self._channels: int | None = None
        self._names: list[str] = []
        self._seen: set[str] = set()
        self._wrenches: list[np.ndarray] = []
        self._times: list[float] = []
        self._contacts: list[int] = []
        self._latents: list[list[float]] = []
        self._optional: tuple[bool, bool, tuple[str, ...] | None] | None = None
        self._state: Literal["open", "closed", "aborted"] = "open"

    def __len__(self) -> int:
        return len(self._names)

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> Literal[False]:
        if exc_type is None:
            self.close()
        else:
            self.abort()
        return False

    def add(
        self,
        frame: npt.ArrayLike,
        wrench: npt.ArrayLike,
        *,
        name: str | None = None,
        t: _Real | None = None,
        contact: bool | np.bool_ | int | None = None,
        latent: Mapping[str, _Real] | None = None,
        images: Mapping[str, npt.ArrayLike] | None = None,
    ) -> str:
        """Write one frame and record its wrench.

        **Arguments:**

        - `frame`: `(height, width)` gray or `(height, width, 3)` BGR float array in [0, 1],
          or a uint8/uint16 array.
        - `wrench`: `[fx, fy, fz, tx, ty, tz]` in N and N*m ([`WRENCH_CONVENTION`][]).
        - `name`: file name under `frames/` (ending `.png`); default `000000.png`, ...
        - `t`, `contact`, `latent`: optional time (s), in-contact flag and latent ground
          truth (e.g. `{"x0": ..., "y0": ..., "radius": ...}`); give them for every frame or
          for none.
        - `images`: the frame's ground-truth images, by the names given to the writer, each
          of the frame's size (gray or BGR), float in [0, 1] or uint8/uint16.

        **Returns:**

        The frame's file name.
        """
        if self._state != "open":
            raise RuntimeError(f"DatasetWriter for {self.path} is already {self._state}")
        name = f"{len(self._names):06d}.png" if name is None else name
        problem = _frame_name_problem(name)
        if problem is not None:
            raise ValueError(f"frame name {problem}")
        name = str(PurePosixPath(name))
        if not name.lower().endswith(".png"):
            raise ValueError(f"frame name {name!r} must end with .png")
        if name in self._seen:
            raise ValueError(f"frame name {name!r} is already used")
        wrench_row = np.asarray(wrench, dtype=np.float64)
        if wrench_row.shape != (6,):
            raise ValueError(f"frame {name!r}: wrench must have shape (6,), got {wrench_row.shape}")
        if not np.all(np.isfinite(wrench_row)):
            raise ValueError(f"frame {name!r}: wrench {wrench_row.tolist()} is not finite")
        if t is not None and not math.isfinite(t):
            raise ValueError(f"frame {name!r}: t={t} is not finite")
        if contact is not None and contact not in (0, 1):
            raise ValueError(f"frame {name!r}: contact must be 0/1 or a bool, got {contact!r}")
        latent_keys = None if latent is None else tuple(latent)
        if latent_keys is not None and any(not k or k == "frame" for k in latent_keys):
            raise ValueError(f"frame {name!r}: latent names must be non-empty and not 'frame'")
        optional = (t is not None, contact is not None, latent_keys)
        if self._optional is not None and optional != self._optional:
            raise ValueError(
                f"frame {name!r}: t, contact and latent (with the same keys) must be given for "
                f"every frame or for none; the first frame had "
                f"t={self._optional[0]}, contact={self._optional[1]}, latent={self._optional[2]}"
            )
        if set(images or {}) != set(self.images):
            raise ValueError(
                f"frame {name!r}: images {sorted(images or {})} differ from the writer's {sorted(self.images)}"
            )
        image = _quantise(frame, self.bit_depth)
        channels = 1 if image.ndim == 2 else 3
        if self.frame_shape is not None and image.shape[:2] != self.frame_shape:
            raise ValueError(f"frame {name!r}: shape {image.shape[:2]} differs from the dataset's {self.frame_shape}")
        if self._channels is not None and channels != self._channels:
            raise ValueError(f"frame {name!r}: {channels} channel(s), but the dataset's frames have {self._channels}")
        truths = {}
        for folder, truth in (images or {}).items():
            truths[folder] = _quantise(truth, 16)
            if truths[folder].shape[:2] != image.shape[:2]:
                raise ValueError(
                    f"frame {name!r}: image {folder!r} of shape {truths[folder].shape} differs from the frame's"
                )
        atomic_write_bytes(self.path / FRAMES_DIR / name, _encode_png(image))
        for folder, truth in truths.items():
            atomic_write_bytes(self.path / folder / name, _encode_png(truth))
        self.frame_shape = image.shape[:2]
        self._channels = channels
        self._optional = optional
        self._names.append(name)
        self._seen.add(name)
        self._wrenches.append(wrench_row)
        if t is not None:
            self._times.append(float(t))
        if contact is not None:
            self._contacts.append(int(contact))
        if latent is not None:
            self._latents.append([float(value) for value in latent.values()])
        return name

    def close(self) -> Path:
        """Write `wrench.csv`, the latent CSV and, last, `manifest.json`; return the folder."""
        if self._state == "closed":
            return self.path
        if self._state == "aborted":
            raise RuntimeError(f"DatasetWriter for {self.path} was aborted")
        if self.frame_shape is None:
            raise ValueError("no frames were added and frame_shape was not given")
        try:
            has_t, has_contact, latent_keys = self._optional or (False, False, None)
            header = ["frame", *WRENCH_AXES] + ["t"] * has_t + ["contact"] * has_contact
            rows = []
            for i, name in enumerate(self._names):
                row = [name, *map(repr, self._wrenches[i].tolist())]
                if has_t:
                    row.append(repr(self._times[i]))
                if has_contact:
                    row.append(self._contacts[i])
                rows.append(row)
            atomic_write_text(self.path / WRENCH_NAME, _format_csv(header, rows))
            manifest = dict(
                self._manifest,
                n_frames=len(self._names),
                height=self.frame_shape[0],
                width=self.frame_shape[1],
                created=_now(),
            )
            if self._channels == 3:
                manifest["channels"] = 3
            if latent_keys is not None:
                latent_rows = [[n, *map(repr, v)] for n, v in zip(self._names, self._latents)]
                latent_csv = _format_csv(["frame", *latent_keys], latent_rows)
                atomic_write_text(self.path / CONTACTS_NAME, latent_csv)
                manifest["contacts"] = CONTACTS_NAME
            write_json(self.path / MANIFEST_NAME, manifest, "dataset")
        except BaseException:
            self._state = "aborted"
            raise
        self._state = "closed"
        return self.path

    def abort(self) -> None:
        """Stop without writing a manifest; the frames written so far stay on disk."""
        if self._state == "open":
            self._state = "aborted"


def _plain(value: Any) -> Any:
    """A NumPy scalar as the Python number JSON can hold."""
    return value.item() if isinstance(value, np.generic) else value


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


# --------------------------------------------------------------------------- reader


class Batch(NamedTuple):
    """Consecutive frames from [`Dataset.iter_batches`][]."""

    indices: Int64[np.ndarray, " b"]
    frames: Float32[np.ndarray, "b h w"]
    wrenches: Float64[np.ndarray, "b 6"]


class Dataset:
    """A dataset folder opened for reading; frames are read from disk only on demand.

    Opening validates `manifest.json` against the schema and every row of `wrench.csv`
    (numeric, finite, frame file present), raising [`DataError`][] naming file, row and field.

    **Arguments:**

    - `path`: the dataset folder.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        manifest_path = self.path / MANIFEST_NAME
        if not manifest_path.is_file():
            if self.path.is_dir():
                raise DataError(
                    f"{manifest_path}: no such file; without a manifest the dataset is "
                    f"incomplete (was its writer interrupted?)"
                )
            raise DataError(f"{self.path}: no such dataset folder")
        self.manifest: dict[str, Any] = read_json(manifest_path, "dataset")
        table = _read_wrench_table(self.path / WRENCH_NAME, strict=True)
        if len(table.frames) != self.manifest["n_frames"]:
            raise DataError(
                f"{manifest_path}: field 'n_frames': {self.manifest['n_frames']}, but "
                f"{self.path / WRENCH_NAME} has {len(table.frames)} rows"
            )
        frames_dir = self.path / FRAMES_DIR
        for folder in (frames_dir, *(self.path / name for name in self.manifest.get("images", ()))):
            for name, row in zip(table.frames, table.rows):
                if not (folder / name).is_file():
                    raise DataError(
                        f"{self.path / WRENCH_NAME} row {row}: field 'frame': {folder / name} does not exist"
                    )
        self._table = table
        for array in (table.wrenches, table.t, table.contact):
            if array is not None:
                array.flags.writeable = False
        contacts = self.manifest.get("contacts")
        self._latents = None if contacts is None else _read_latents(self.path / contacts, table.frames)

    def __repr__(self) -> str:
        h, w = self.frame_shape
        return f"Dataset({str(self.path)!r}, n_frames={len(self)}, frame_shape=({h}, {w}))"

    def __len__(self) -> int:
        return len(self._table.frames)

    @property
    def frame_shape(self) -> tuple[int, int]:
        """`(height, width)` of every frame."""
        return self.manifest["height"], self.manifest["width"]

    @property
    def channels(self) -> int:
        """1 for gray frames, 3 for colour (BGR) frames."""
        return self.manifest.get("channels", 1)

    @property
    def image_names(self) -> tuple[str, ...]:
        """Names of the ground-truth images each frame comes with (e.g. `"grating_free"`)."""
        return tuple(self.manifest.get("images", ()))

    @property
    def bit_depth(self) -> int:
        """Bits per pixel of the PNG frames (8 or 16)."""
        return self.manifest["bit_depth"]

    @property
    def fps(self) -> float | None:
        """Nominal frame rate, if recorded."""
        return self.manifest.get("fps")

    @property
    def frame_names(self) -> tuple[str, ...]:
        """File names under `frames/`, in frame order."""
        return self._table.frames

    @property
    def wrenches(self) -> Float64[np.ndarray, "n 6"]:
        """`[fx, fy, fz, tx, ty, tz]` per frame in N and N*m (read-only)."""
        return self._table.wrenches

    @property
    def t(self) -> Float64[np.ndarray, " n"] | None:
        """Frame times in seconds, if the CSV has a `t` column."""
        return self._table.t

    @property
    def contact(self) -> Bool[np.ndarray, " n"] | None:
        """In-contact flags, if the CSV has a `contact` column."""
        return self._table.contact

    @property
    def latents(self) -> dict[str, Float64[np.ndarray, " n"]] | None:
        """Per-frame latent ground truth by column (e.g. `x0`, `y0`, `radius`), if any."""
        return self._latents

    @property
    def device(self) -> dict:
        """The nominal device JSON object (read from its file if the manifest names one)."""
        device = self.manifest["device"]
        if isinstance(device, str):
            device = read_json(self.path / device)
            if not isinstance(device, dict):
                raise DataError(f"{self.path / self.manifest['device']}: not a JSON object")
        return device

    @property
    def true_device(self) -> dict | None:
        """Simulated data: the true parameters of the unit, if recorded."""
        return self.manifest.get("true_device")

    def frame_path(self, i: int) -> Path:
        """Path of frame `i`'s image file."""
        return self.path / FRAMES_DIR / self._table.frames[self._index(i)]

    def frame(self, i: int) -> Float32[np.ndarray, "h w"]:
        """Read frame `i` from disk as float32 in [0, 1], gray (colour frames are converted);
        [`DataError`][] names a bad file."""
        return self._read(self.frame_path(i), color=False)

    def frames(self, indices: npt.ArrayLike | None = None) -> "FrameSequence":
        """Frames `indices` (all by default), in that order, as a [`FrameSequence`][]: a
        sequence that reads each frame from disk when it is indexed, so that a job over
        thousands of frames holds only the ones it is working on."""
        idx = np.arange(len(self)) if indices is None else np.asarray(indices, dtype=np.int64).reshape(-1)
        for i in idx:
            self._index(int(i))
        return FrameSequence(self, idx)

    def color_frame(self, i: int) -> Float32[np.ndarray, "h w 3"]:
        """Read frame `i` as a float32 BGR image in [0, 1] (a gray frame in every channel)."""
        return self._read(self.frame_path(i), color=True)

    def image(self, name: str, i: int) -> Float32[np.ndarray, "h w 3"]:
        """Read frame `i`'s ground-truth image `name` (one of [`image_names`][Dataset.image_names])
        as a float32 BGR image in [0, 1]."""
        if name not in self.image_names:
            raise DataError(
                f"{self.path / MANIFEST_NAME}: field 'images': no {name!r} (the dataset has {list(self.image_names)})"
            )
        return self._read(self.path / name / self._table.frames[self._index(i)], color=True)

    def _read(self, path: Path, *, color: bool) -> np.ndarray:
        image = _load_image(path, color=True) if color else _load_gray(path)
        if image.shape[:2] != self.frame_shape:
            raise DataError(
                f"{path}: image size {image.shape[0]}x{image.shape[1]} (rows x columns) "
                f"differs from the dataset's {self.frame_shape[0]}x{self.frame_shape[1]}"
            )
        return image.astype(np.float32) / np.float32(_MAXVAL[8 * image.dtype.itemsize])

    def __iter__(self) -> Iterator[Float32[np.ndarray, "h w"]]:
        for i in range(len(self)):
            yield self.frame(i)

    def iter_frames(
        self,
        start: int = 0,
        stop: int | None = None,
        *,
        on_error: Literal["raise", "status"] = "raise",
    ) -> Iterator[tuple[int, Float32[np.ndarray, "h w"] | None, str | None]]:
        """Yield `(index, frame, error)` for frames `start..stop-1`, reading one at a time.

        With `on_error="raise"` a bad frame raises [`DataError`][] (and `error` is always
        `None`); with `on_error="status"` it yields `(index, None, message)` and goes on, so a
        pipeline can emit a status row instead of crashing.
        """
        if on_error not in ("raise", "status"):
            raise ValueError(f"on_error must be 'raise' or 'status', got {on_error!r}")
        for i in range(*slice(start, stop).indices(len(self))):
            try:
                yield i, self.frame(i), None
            except DataError as e:
                if on_error == "raise":
                    raise
                yield i, None, str(e)

    def iter_batches(self, batch_size: int) -> Iterator[Batch]:
        """Yield [`Batch`][]es of `batch_size` consecutive frames (the last may be smaller)."""
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        for start in range(0, len(self), batch_size):
            indices = np.arange(start, min(start + batch_size, len(self)), dtype=np.int64)
            frames = np.empty((len(indices), *self.frame_shape), dtype=np.float32)
            for k, i in enumerate(indices):
                frames[k] = self.frame(int(i))
            yield Batch(indices, frames, self.wrenches[indices])

    def _index(self, i: int) -> int:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        return i % n


def open_dataset(path: str | os.PathLike) -> Dataset:
    """Open and validate the dataset folder at `path` (see [`Dataset`][])."""
    return Dataset(path)


# --------------------------------------------------------------------------- import / export


@dataclasses.dataclass(frozen=True)
class ImportReport:
    """What [`import_recording`][] did.

    - `out_dir`: the new dataset folder.
    - `n_frames`: frames written; `n_rows`: frames the recording lists (data rows of its
      CSV, or image files in its folder).
    - `skipped`: `(frame name, reason)` for every frame left out (only with `skip_bad`).
    - `ignored_columns`: CSV columns that are not part of the dataset format.
    - `ft_alignment`: with a force/torque log, how it was put on the frames' clock, as
      recorded in the manifest: the log's file name, `offset_s` (its clock minus the
      frames'), whether the offset was `estimated`, the correlation `peak` if it was, and
      the number of frames outside its span (`frames_outside`, dropped).
    """

    out_dir: Path
    n_frames: int
    n_rows: int
    frame_shape: tuple[int, int]
    bit_depth: int
    skipped: tuple[tuple[str, str], ...]
    ignored_columns: tuple[str, ...]
    ft_alignment: dict[str, Any] | None = None

    def __str__(self) -> str:
        lines = [
            f"imported {self.n_frames} of {self.n_rows} frames "
            f"({self.frame_shape[0]}x{self.frame_shape[1]}, {self.bit_depth}-bit) "
            f"into {self.out_dir}"
        ]
        if self.ft_alignment is not None:
            ft = self.ft_alignment
            how = f"estimated, correlation peak {ft['peak']:.3f}" if ft["estimated"] else "not estimated"
            lines.append(
                f"force/torque log {ft['ft_log']}: clock offset {ft['offset_s']:+.4f} s ({how}); "
                f"{ft['frames_outside']} frames outside its span dropped"
            )
        if self.ignored_columns:
            lines.append(f"ignored columns: {', '.join(self.ignored_columns)}")
        lines += [f"skipped {name}: {reason}" for name, reason in self.skipped]
        return "\n".join(lines)


# Below this correlation peak an estimated clock offset is doubtful (see FtAlignment.peak).
_WEAK_PEAK = 0.5


def _frame_activity(frames_dir: Path, names: tuple[str, ...], progress: bool) -> tuple[np.ndarray, np.ndarray]:
    """[`fringe_change`][] of every readable frame from the first readable one, and which
    frames those are (unreadable or wrong-size frames are left to the import to report)."""
    activity = np.zeros(len(names))
    readable = np.zeros(len(names), dtype=bool)
    reference = None
    for i, name in enumerate(tqdm(names, disable=not progress, unit="frame", desc="align")):
        try:
            image = unit_frame(_load_gray(frames_dir / name))
        except DataError:
            continue
        if reference is None:
            reference = image
        if image.shape == reference.shape:
            activity[i], readable[i] = fringe_change(image, reference), True
    return activity, readable


def _put_on_frame_clock(
    table: _WrenchTable,
    frames_dir: Path,
    listing: Path,
    ft_csv: Path,
    *,
    fps: _Real | None,
    align: bool,
    max_offset: float | None,
    progress: bool,
) -> tuple[_WrenchTable, np.ndarray, dict[str, Any]]:
    """Replace the table's wrenches by a force/torque log's, interpolated to the frames'
    times (the table's `t`, else `index / fps`), with the clock offset estimated if `align`.

    Returns the table of the frames inside the log's span, which of the old table's frames
    those are, and the manifest's `ft_alignment` record.
    """
    ft_times, ft_wrench = read_ft_log(ft_csv)
    if table.t is not None:
        times = table.t
    elif fps is not None:
        times = np.arange(len(table.frames)) / float(fps)
    else:
        raise DataError(
            f"{listing}: the frames have no capture times (no 't' column); give the frame rate with {ARGUMENT}",
            argument="fps",
            python="fps=FRAMES_PER_SECOND",
        )
    record: dict[str, Any] = {"ft_log": ft_csv.name}
    if align:
        activity, readable = _frame_activity(frames_dir, table.frames, progress)
        try:
            alignment = align_ft(times[readable], activity[readable], ft_times, ft_wrench, max_offset=max_offset)
        except ValueError as e:
            raise DataError(f"{ft_csv}: {e}") from None
        offset = alignment.offset_s
        record.update(offset_s=offset, estimated=True, peak=alignment.peak)
        if alignment.peak < _WEAK_PEAK:
            warnings.warn(
                f"{ft_csv}: the clock offset {offset:+.4f} s is doubtful (correlation peak "
                f"{alignment.peak:.2f}, below {_WEAK_PEAK}); check the imported wrenches",
                DataWarning,
                stacklevel=3,
            )
    else:
        offset = 0.0
        record.update(offset_s=offset, estimated=False)
    wrench, kept = _wrench_at(times, ft_times, ft_wrench, offset)
    if not np.any(kept):
        # Only without `align`: an estimated offset always overlaps some frames.
        raise DataError(
            f"{ft_csv}: no frame lies inside the log's span ({ft_times[0]:g} to {ft_times[-1]:g} s "
            f"on its clock, frames at {times[0]:g} to {times[-1]:g} s); pass {ARGUMENT} to "
            f"estimate the clock offset",
            argument="align",
        )
    record["frames_outside"] = int(np.sum(~kept))
    table = dataclasses.replace(
        table,
        frames=tuple(name for name, inside in zip(table.frames, kept) if inside),
        rows=tuple(row for row, inside in zip(table.rows, kept) if inside),
        wrenches=wrench[kept],
        t=times[kept],
        contact=None if table.contact is None else table.contact[kept],
    )
    return table, kept, record


def import_recording(
    frames_dir: str | os.PathLike,
    wrench_csv: str | os.PathLike | None,
    device: dict | str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    skip_bad: bool = False,
    progress: bool = True,
    bit_depth: int | None = None,
    fps: _Real | None = None,
    protocol: str | None = None,
    source: str | None = None,
    overwrite: bool = False,
    ft_csv: str | os.PathLike | None = None,
    align: bool = False,
    max_offset: float | None = None,
) -> ImportReport:
    """Convert a lab recording (image files plus a force/torque CSV) into a dataset.

    The CSV has columns `frame,fx,fy,fz,tx,ty,tz` and optionally `t` and `contact`; `frame`
    is the image file name relative to `frames_dir`; other columns are ignored. Images of
    any format OpenCV reads are converted to grayscale PNG named like the source with a
    `.png` suffix, and must all have the size of the first one.

    With `ft_csv`, the wrenches come instead from a force/torque sensor's log on its own
    clock and at its own rate ([`read_ft_log`][] describes the file): `wrench_csv`, if
    given, only lists the frames (`frame`) with their capture times (`t`) and in-contact
    flags (`contact`), and any wrench columns in it are ignored; without it the frames are
    the image files of `frames_dir` in name order. Frames without a `t` are at
    `index / fps`. The log's wrench is interpolated linearly to each frame's time, and
    frames outside the log's span are dropped and counted. Without `align` the log is
    taken to run on the frames' clock; with `align` the offset between the clocks is
    estimated from the data by [`align_ft`][], from the [`fringe_change`][] of each frame
    from the first (so the recording should start without contact), reading every frame
    twice. The manifest records the offset, its correlation peak and the dropped count
    (`ft_alignment`), and `wrench.csv` the frames' times; a peak below 0.5 warns
    ([`DataWarning`][]).

    Every missing, unreadable or wrong-size frame and every non-finite wrench is collected;
    then either the import fails with one [`DataError`][] listing them all (leaving `out_dir`
    without a manifest), or with `skip_bad=True` those frames are left out and reported.

    **Arguments:**

    - `frames_dir`, `wrench_csv`: the recording (`wrench_csv` may be `None` with `ft_csv`).
    - `device`: the nominal device JSON object, or a path to a device JSON file (embedded).
    - `out_dir`: the new dataset folder (empty, or replaced with `overwrite=True`).
    - `bit_depth`: 8 or 16; by default that of the first readable image.
    - `fps`, `protocol`, `source`: manifest fields (`source` defaults to the input paths);
      `fps` also times frames that have no `t`, with `ft_csv`.
    - `progress`: show a tqdm progress bar.
    - `ft_csv`: a force/torque log to take the wrenches from.
    - `align`: estimate the log's clock offset from the data.
    - `max_offset`: with `align`, the largest clock offset considered (s); by default any
      at which the log and the frames overlap.

    **Returns:**

    An [`ImportReport`][].
    """
    frames_dir, out_dir = Path(frames_dir), Path(out_dir)
    wrench_csv = None if wrench_csv is None else Path(wrench_csv)
    ft_csv = None if ft_csv is None else Path(ft_csv)
    if wrench_csv is None and ft_csv is None:
        raise ValueError("a recording needs wrench_csv, or ft_csv to take its wrenches from")
    if ft_csv is None and (align or max_offset is not None):
        raise ValueError("align and max_offset apply to a force/torque log (ft_csv) only")
    if bit_depth not in (None, *_MAXVAL):
        raise ValueError(f"bit_depth must be 8, 16 or None, got {bit_depth}")
    for source_path in (frames_dir, wrench_csv, ft_csv):
        if source_path is not None and source_path.resolve().is_relative_to(out_dir.resolve()):
            raise DataError(f"{source_path}: the recording must not lie inside out_dir {out_dir}")
    if not frames_dir.is_dir():
        raise DataError(f"{frames_dir}: no such folder")
    check_output_folder(out_dir, argument="out_dir")
    _check_output_dir(out_dir, overwrite)
    if wrench_csv is None:
        table = _frame_list(frames_dir)
    else:
        table = _read_wrench_table(wrench_csv, strict=False, frames_only=ft_csv is not None)
        if not table.frames:
            raise DataError(f"{wrench_csv}: no data rows")
    # What names the frames in messages: the CSV (with its rows) or the folder.
    listing = frames_dir if wrench_csv is None else wrench_csv
    if not isinstance(device, dict):
        device_path = device
        device = read_json(device_path)
        if not isinstance(device, dict):
            raise DataError(f"{device_path}: not a JSON object")
    out_names = [str(PurePosixPath(name).with_suffix(".png")) for name in table.frames]
    first_of: dict[str, str] = {}
    for name, out_name, row in zip(table.frames, out_names, table.rows):
        if out_name in first_of:
            where = f"{listing} row {row}: field 'frame'" if row else str(listing)
            raise DataError(f"{where}: {name!r} would be stored as {out_name!r}, like {first_of[out_name]!r}")
        first_of[out_name] = name
    if source is None:
        source = f"imported from {ft_csv or wrench_csv} and {frames_dir}"
    n_rows = len(table.frames)
    ft_alignment = None
    if ft_csv is not None:
        table, kept, ft_alignment = _put_on_frame_clock(
            table, frames_dir, listing, ft_csv, fps=fps, align=align, max_offset=max_offset, progress=progress
        )
        out_names = [out_name for out_name, inside in zip(out_names, kept) if inside]

    problems: list[tuple[int, str, str]] = []
    writer: DatasetWriter | None = None
    first_shape: tuple[int, int] | None = None
    n_written = 0
    progress_bar = tqdm(total=len(table.frames), disable=not progress, unit="frame", desc="import")
    # The dataset is written in a folder beside out_dir and moved into place once complete:
    # a failed or interrupted import leaves nothing behind, and out_dir as it was.
    with staging_folder(out_dir) as staging:
        try:
            for i in range(len(table.frames)):
                progress_bar.update(1)
                name, row = table.frames[i], table.rows[i]
                try:
                    image = _load_gray(frames_dir / name)
                except DataError as e:
                    problems.append((row, name, str(e)))
                    continue
                if first_shape is None:
                    first_shape = image.shape
                if image.shape != first_shape:
                    problems.append(
                        (
                            row,
                            name,
                            f"{frames_dir / name}: image size {image.shape[0]}x{image.shape[1]} "
                            f"differs from the first frame's {first_shape[0]}x{first_shape[1]}",
                        )
                    )
                    continue
                if not np.all(np.isfinite(table.wrenches[i])):
                    problems.append(
                        (row, name, f"{listing} row {row}: wrench {table.wrenches[i].tolist()} is not finite")
                    )
                    continue
                if problems and not skip_bad:
                    # The import will fail; keep checking so that every bad frame is reported.
                    continue
                if writer is None:
                    writer = DatasetWriter(
                        staging / "dataset",
                        device=device,
                        frame_shape=first_shape,
                        bit_depth=bit_depth or 8 * image.dtype.itemsize,
                        source=source,
                        fps=fps,
                        protocol=protocol,
                        ft_alignment=ft_alignment,
                    )
                writer.add(
                    image,
                    table.wrenches[i],
                    name=out_names[i],
                    t=None if table.t is None else float(table.t[i]),
                    contact=None if table.contact is None else bool(table.contact[i]),
                )
                n_written += 1
            if problems and (not skip_bad or writer is None):
                lines = "\n".join(f"  row {row}: {message}" if row else f"  {message}" for row, _, message in problems)
                hint = "" if skip_bad else f" (pass {ARGUMENT} to skip them)"
                raise DataError(
                    f"{len(problems)} of {len(table.frames)} frames in {listing} could not be imported{hint}:\n{lines}",
                    argument=None if skip_bad else "skip_bad",
                )
            assert writer is not None and first_shape is not None
            writer.close()
            _move_dataset_into_place(staging / "dataset", out_dir, staging)
        except BaseException:
            if writer is not None:
                writer.abort()
            raise
        finally:
            progress_bar.close()
    return ImportReport(
        out_dir=out_dir,
        n_frames=n_written,
        n_rows=n_rows,
        frame_shape=first_shape,
        bit_depth=writer.bit_depth,
        skipped=tuple((name, message) for _, name, message in problems),
        ignored_columns=table.ignored_columns,
        ft_alignment=ft_alignment,
    )


# What a dataset folder holds; a folder with nothing else is replaced whole.
_DATASET_ENTRIES = frozenset({MANIFEST_NAME, WRENCH_NAME, CONTACTS_NAME, FRAMES_DIR})


def _move_dataset_into_place(new: Path, out_dir: Path, staging: Path) -> None:
    """Move the complete dataset folder `new` to `out_dir` by renames.

    An absent or empty `out_dir` is replaced by one rename; a dataset folder holding
    nothing else by two (the old one goes into `staging`, removed with it). Otherwise the
    other files stay: the old manifest is removed first, so that the folder never claims a
    mix of old and new, then `frames/` and the CSVs are moved in and the manifest last.
    """
    if out_dir.is_dir() and not any(out_dir.iterdir()):
        out_dir.rmdir()
    if not out_dir.exists():
        os.replace(new, out_dir)
        return
    if {p.name for p in out_dir.iterdir()} <= _DATASET_ENTRIES:
        os.replace(out_dir, staging / "old")
        os.replace(new, out_dir)
        return
    (out_dir / MANIFEST_NAME).unlink(missing_ok=True)
    for name in (FRAMES_DIR, WRENCH_NAME, CONTACTS_NAME):
        if (out_dir / name).exists():
            os.replace(out_dir / name, staging / f"old-{name}")
        if (new / name).exists():
            os.replace(new / name, out_dir / name)
    os.replace(new / MANIFEST_NAME, out_dir / MANIFEST_NAME)


def export_recording(
    dataset: Dataset | str | os.PathLike,
    frames_dir: str | os.PathLike,
    wrench_csv: str | os.PathLike,
) -> None:
    """Write a dataset back out as a lab recording: image files plus a wrench CSV.

    The inverse of [`import_recording`][]: the PNG files are copied byte for byte into
    `frames_dir` under their dataset names, and `wrench_csv` gets the columns
    `frame,fx,fy,fz,tx,ty,tz` plus `t` and `contact` where the dataset has them.
    """
    if not isinstance(dataset, Dataset):
        dataset = Dataset(dataset)
    frames_dir = Path(frames_dir)
    frames_dir.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(dataset.frame_names):
        atomic_write_bytes(frames_dir / name, dataset.frame_path(i).read_bytes())
    t, contact = dataset.t, dataset.contact
    header = ["frame", *WRENCH_AXES] + ["t"] * (t is not None) + ["contact"] * (contact is not None)
    rows = []
    for i, name in enumerate(dataset.frame_names):
        row = [name, *map(repr, dataset.wrenches[i].tolist())]
        if t is not None:
            row.append(repr(float(t[i])))
        if contact is not None:
            row.append(int(contact[i]))
        rows.append(row)
    atomic_write_text(wrench_csv, _format_csv(header, rows))


class FrameSequence(Sequence):
    """Frames of a [`Dataset`][], read from disk when indexed (see [`Dataset.frames`][moirejax.Dataset.frames]).

    `frames[i]` is one `(h, w)` float32 frame in [0, 1]; a slice or an array of positions
    gives those frames stacked into `(k, h, w)`. `np.asarray(frames)` reads them all.
    """

    def __init__(self, dataset: Dataset, indices: np.ndarray):
        self.dataset = dataset
        self.indices = indices

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, item: Any) -> Any:
        if isinstance(item, int | np.integer):
            return self.dataset.frame(int(self.indices[item]))
        chosen = self.indices[item]
        h, w = self.dataset.frame_shape
        if len(chosen) == 0:
            return np.zeros((0, h, w), np.float32)
        return np.stack([self.dataset.frame(int(i)) for i in chosen])

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        frames = self[:]
        return frames if dtype is None else frames.astype(dtype)

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self), *self.dataset.frame_shape)
