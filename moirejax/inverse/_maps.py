"""Where the load sits: the traction maps of inverted frames, and the file of a recording's.

The inversion reads a frame as one contact patch, or two, each with its share of the
wrench. The tractions those patches put on the contact surface ([`surface_tractions`][]:
shear `tx`, `ty` and pressure `p`) are the map of where the load sits and how it spreads,
and their moments are the frame's wrench (to the grid's sampling), so map and wrench never
disagree. The maps are drawn from the rows of the wrench CSV that `moirejax invert` writes,
so a recording inverted once, here or on a cluster, gives its maps without a second
inversion.

A recording's maps go in one HDF5 file (`moirejax invert --maps FILE.h5`), compressed
and chunked one frame to a chunk, so that a tool reads any frame without the rest; HDF5
opens in Python (h5py), MATLAB, Julia and C alike. Its layout:

| dataset | shape | what |
|---|---|---|
| `traction` | `(n, 3, h, w)` float32 | `tx`, `ty`, `p` in Pa on the grid below, row 0 at the top (+y) |
| `x_mm`, `y_mm` | `(w,)`, `(h,)` | the cell centres on the contact surface, in the wrench frame |
| `frame`, `status` | `(n,)` text | the CSV's frame name and status of each row |
| `wrench` | `(n, 6)` float64 | the CSV's wrench (N, N·m) |
| `centre_of_pressure_mm` | `(n, 2)` | `(x, y)` where the normal force acts ([`centre_of_pressure_mm`][moirejax.centre_of_pressure_mm]) |
| `contact_area_mm2` | `(n,)` | the patches' area |
| `contacts` | `(n,)` int8 | patches the frame was read with (0: none) |

A frame without contact has zero tractions; one without a wrench (a frame that could not be
read or solved) has NaN. The file's attributes give the wrench convention, the units and the
CSV it was drawn from.
"""

import csv
import math
import os
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._conventions import centre_of_pressure_mm, PA_PER_MPA, WRENCH_AXES, WRENCH_CONVENTION
from .._fileio import check_output_file, commit_staged, DataError, OutputError, staging_folder
from ..physics import Contact, Device, surface_grid, surface_tractions, SurfaceGrid


TRACTION_MAP_SHAPE = (64, 64)
"""The grid of the traction maps (about 0.6 mm cells over the paper's 40 mm pad)."""
# Columns of the wrench CSV that a map is drawn from; the shape and second-patch columns are
# optional (files written before them have round patches with a sphere's pressure).
WRENCH_CSV_COLUMNS = ("frame", *WRENCH_AXES, "x0", "y0", "radius", "status", "message")
# Statuses whose row carries the wrench of a load: converged, stopped at the step limit, or
# solved but not explained (its wrench kept, its status saying so).
_WITH_LOAD = frozenset({"converged", "max_steps", "unexplained"})
# Frames drawn at once: one compiled program for every chunk (the last is padded).
_CHUNK = 32


def read_wrench_csv(path: str | os.PathLike) -> list[dict[str, str]]:
    """The rows of a wrench CSV of `moirejax invert`, as text.

    **Raises:** [`DataError`][moirejax.DataError] naming the file when it cannot be read, is
    not text, or lacks a column a wrench CSV has."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            missing = [c for c in WRENCH_CSV_COLUMNS if c not in (reader.fieldnames or ())]
            if missing:
                raise DataError(f"{path}: no column {', '.join(missing)}; not a wrench CSV of `moirejax invert`")
            return list(reader)
    except UnicodeDecodeError as e:
        raise DataError(f"{path}: not a text CSV ({e.reason})") from None
    except OSError as e:
        raise DataError(f"{path}: cannot be read ({e.strerror or e})") from None


def row_number(row: dict[str, str], column: str, path: str | os.PathLike, line: int) -> float:
    """The number in `column` of a CSV row (NaN for `nan`); a [`DataError`][moirejax.DataError]
    naming the file, line and field otherwise."""
    try:
        return float(row[column])
    except (TypeError, ValueError):
        raise DataError(f"{path} row {line}: field {column!r}: {row[column]!r} is not a number") from None


def _row_patch(row: dict[str, str], prefix: str, path, line: int) -> Contact:
    centre = [row_number(row, f"{prefix}{c}", path, line) for c in ("x0", "y0", "radius")]
    flatness, aspect, angle = (
        row_number(row, f"{prefix}{c}", path, line) if row.get(f"{prefix}{c}") not in (None, "", "nan") else default
        for c, default in (("flatness", 0.0), ("aspect_ratio", 1.0), ("long_axis_angle", 0.0))
    )
    return Contact.elongated(*centre, aspect, angle, flatness)


def row_patches(row: dict[str, str], path: str | os.PathLike, line: int) -> list[tuple[np.ndarray, Contact]]:
    """The contact patches of a wrench CSV row, each `(wrench, contact)`: none for a row
    without the wrench of a load, one, or two when the row was read with two and carries
    the second patch's share of the wrench (the first carries the rest). Files written
    before that share was a column draw their two contacts as one."""
    wrench = np.array([row_number(row, axis, path, line) for axis in WRENCH_AXES])
    if row.get("status") not in _WITH_LOAD or not np.all(np.isfinite(wrench)):
        return []
    first = _row_patch(row, "", path, line)
    columns = [f"second_{axis}" for axis in WRENCH_AXES]
    if row.get("contacts") != "2" or any(row.get(c) in (None, "", "nan") for c in columns):
        return [(wrench, first)]
    second = np.array([row_number(row, c, path, line) for c in columns])
    return [(wrench - second, first), (second, _row_patch(row, "second_", path, line))]


def patch_tractions(wrenches: Float[Array, "patches 6"], contacts: Contact, grid: SurfaceGrid) -> Float[Array, "3 h w"]:
    """The tractions `(tx, ty, p)` in MPa on `grid` of patches that press at once: patch `i`
    of `contacts` (fields with a leading axis) carries `wrenches[i]` (N, N·m, about the
    origin). The layer is linear, so the patches' tractions add."""
    return jnp.sum(jax.vmap(surface_tractions, in_axes=(0, 0, None))(wrenches, contacts, grid), axis=0)


def patches_area_mm2(patches: list[tuple[np.ndarray, Contact]]) -> float:
    """The contact area (mm²) of patches of [`row_patches`][]: each
    patch has the area of a circle of its radius, elongated or not; NaN for none."""
    return sum(math.pi * float(c.radius) ** 2 for _, c in patches) if patches else math.nan


def stack_patches(patches: list[tuple[np.ndarray, Contact]], dtype) -> tuple[np.ndarray, Contact]:
    """Patches of [`row_patches`][] as the arguments of
    [`patch_tractions`][]: always two (a second without load where there is one, no load
    at all for none), so that one compiled program draws any frame."""
    if not patches:
        patches = [(np.zeros(6), Contact())]
    if len(patches) == 1:
        patches = [patches[0], (np.zeros(6), patches[0][1])]
    wrenches = np.stack([w for w, _ in patches]).astype(dtype)
    contacts = jax.tree_util.tree_map(lambda *v: np.stack([np.asarray(x, dtype) for x in v]), *(c for _, c in patches))
    return wrenches, contacts


class TractionMaps(NamedTuple):
    """A recording's traction maps as read back by [`read_traction_maps`][] (see the module
    text for each field)."""

    traction: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    frame: list[str]
    status: list[str]
    wrench: np.ndarray
    centre_of_pressure_mm: np.ndarray
    contact_area_mm2: np.ndarray
    contacts: np.ndarray


def map_grid(device: Device, shape: tuple[int, int] = TRACTION_MAP_SHAPE) -> SurfaceGrid:
    """The [`SurfaceGrid`][] of `shape` cells over `device`'s field that maps are drawn on.

    **Raises:** `ValueError` when the grid's aspect ratio is not the image's."""
    return surface_grid(shape, device.px_per_mm, (device.height, device.width), device.a, device.Z)


def write_traction_maps(
    out: str | os.PathLike,
    device: Device,
    wrench_csv: str | os.PathLike,
    *,
    shape: tuple[int, int] = TRACTION_MAP_SHAPE,
) -> int:
    """Draw the traction map of every row of `wrench_csv` on `device`'s contact surface
    and write them to the HDF5 file `out`, atomically (readers see the old file or the
    whole new one). Returns the number of frames.

    **Raises:** [`DataError`][moirejax.DataError] for a CSV that cannot be read or is not a
    wrench CSV (nothing is written); [`OutputError`][moirejax.OutputError] when `out` cannot be
    written; `ValueError` for a `shape` whose aspect ratio is not the image's."""
    out = check_output_file(out, argument="maps")
    grid = map_grid(device, shape)
    rows = read_wrench_csv(wrench_csv)
    dtype = np.dtype(device.p1.dtype)
    patches = [row_patches(row, wrench_csv, line) for line, row in enumerate(rows, start=2)]
    wrench = np.array([[row_number(row, a, wrench_csv, line) for a in WRENCH_AXES] for line, row in enumerate(rows, 2)])
    draw = eqx.filter_jit(jax.vmap(patch_tractions, in_axes=(0, 0, None)))
    with staging_folder(out) as staging:
        staged = staging / out.name
        _write_h5(staged, rows, patches, wrench, grid, draw, dtype, shape, Path(wrench_csv))
        commit_staged(staging, [(staged, out)])
    return len(rows)


def _write_h5(path: Path, rows, patches, wrench, grid: SurfaceGrid, draw, dtype, shape, source: Path) -> None:
    import importlib.metadata

    import h5py

    n = len(rows)
    h, w = shape
    cell_area_m2 = float(grid.spacing) ** 2 * 1e-6
    try:
        with h5py.File(path, "w") as f:
            f.attrs["convention"] = WRENCH_CONVENTION
            f.attrs["traction_components"] = "tx, ty, p (Pa): shear along x and y, pressure into the surface"
            f.attrs["cell_area_m2"] = cell_area_m2
            f.attrs["source"] = str(source)
            f.attrs["moirejax_version"] = importlib.metadata.version("moirejax")
            traction = f.create_dataset(
                "traction",
                (n, 3, h, w),
                dtype="f4",
                chunks=(1, 3, h, w) if n else None,
                compression="gzip",
                compression_opts=4,
                shuffle=True,
            )
            for start in range(0, n, _CHUNK):
                chunk = patches[start : start + _CHUNK]
                stacked = [stack_patches(p, dtype) for p in chunk]
                stacked += [stacked[-1]] * (_CHUNK - len(stacked))  # one program for every chunk
                wrenches = np.stack([s[0] for s in stacked])
                contacts = jax.tree_util.tree_map(lambda *v: np.stack(v), *(s[1] for s in stacked))
                maps = np.asarray(draw(wrenches, contacts, grid), np.float32)[: len(chunk)] * np.float32(PA_PER_MPA)
                for k, p in enumerate(chunk):
                    if not p and rows[start + k]["status"] != "no_contact":
                        maps[k] = np.nan  # no wrench: no map either
                traction[start : start + len(chunk)] = maps
            f["x_mm"] = np.asarray(grid.X[0], np.float64)
            f["y_mm"] = np.asarray(grid.Y[:, 0], np.float64)
            f["frame"] = np.array([row["frame"] for row in rows], dtype=h5py.string_dtype())
            f["status"] = np.array([row["status"] for row in rows], dtype=h5py.string_dtype())
            f["wrench"] = wrench.reshape(n, 6)
            f["centre_of_pressure_mm"] = centre_of_pressure_mm(wrench.reshape(n, 6))
            f["contact_area_mm2"] = np.array([patches_area_mm2(p) for p in patches], np.float64)
            f["contacts"] = np.array([len(p) for p in patches], np.int8)
    except OSError as e:
        raise OutputError(f"{path.name}: cannot be written ({e})", argument="maps") from e


def read_traction_maps(path: str | os.PathLike, frames: slice | np.ndarray | None = None) -> TractionMaps:
    """A traction-map file of [`write_traction_maps`][], its maps of `frames` only when
    given (a slice, or increasing indices: the other frames' chunks are not read).

    **Raises:** [`DataError`][moirejax.DataError] naming the file when it is not one."""
    import h5py

    path = Path(path)
    select = slice(None) if frames is None else frames
    try:
        with h5py.File(path, "r") as f:

            def text(name: str) -> list[str]:
                values = np.asarray(f[name][select])
                return [v.decode() if isinstance(v, bytes) else str(v) for v in values]

            return TractionMaps(
                traction=f["traction"][select],
                x_mm=f["x_mm"][:],
                y_mm=f["y_mm"][:],
                frame=text("frame"),
                status=text("status"),
                wrench=f["wrench"][select],
                centre_of_pressure_mm=f["centre_of_pressure_mm"][select],
                contact_area_mm2=f["contact_area_mm2"][select],
                contacts=f["contacts"][select],
            )
    except (OSError, KeyError) as e:
        raise DataError(f"{path}: not a traction-map file of `moirejax invert --maps` ({e})") from None
