"""Plots of an inverted recording (`moirejax invert --plot DIR`): the wrench over the
recording with its uncertainty and statuses, and, for the frames worth a look, the frame
with its pressure and shear, and where the reading explains the fringes and where not."""

import os
from pathlib import Path

import equinox as eqx
import numpy as np

from .._conventions import centre_of_pressure_mm, PA_PER_MPA, WRENCH_AXES, WRENCH_UNITS
from .._plotting import pyplot, save_figure
from ._inversion import Inverter
from ._invert_io import iter_source_frames
from ._maps import map_grid, patch_tractions, read_wrench_csv, row_number, row_patches, stack_patches


# The length (mm) of a shear arrow whose traction equals the frame's peak pressure.
_SHEAR_ARROW = 4.0
# Status colours of the timeline (converged frames are the line itself).
_STATUS_COLOURS = {
    "max_steps": "tab:orange",
    "unexplained": "tab:red",
    "no_contact": "0.7",
    "bad_frame": "tab:purple",
    "nonfinite": "black",
    "unreadable": "black",
    "wrong_size": "black",
}


def frames_worth_a_look(rows: list[dict[str, str]], count: int) -> list[int]:
    """Up to `count` rows to draw: first those solved but not explained or not converged
    (a user's first question), then the hardest presses (largest normal force)."""
    flagged = [i for i, row in enumerate(rows) if row["status"] in ("unexplained", "max_steps")]
    fz = [(float(row["fz"]), i) for i, row in enumerate(rows) if row["status"] == "converged"]
    pressed = [i for f, i in sorted(fz, reverse=True) if f > 0]
    return sorted((flagged + pressed)[:count])


def plot_inversion(
    folder: str | os.PathLike,
    inverter: Inverter,
    source: str | os.PathLike,
    wrench_csv: str | os.PathLike,
    *,
    frames: int = 6,
) -> list[Path]:
    """Draw an inverted recording into `folder`: `timeline.png` (each axis of the wrench
    over the frames, with its 95 % interval and the frames that did not converge marked),
    and `frame-NAME.png` for up to `frames` frames (first those `unexplained` or stopped at
    the step limit, then the hardest presses): the frame
    with the pressure's contours, the shear's arrows and the centre of pressure; the
    pressure map; the fringe phase's change from the reference and what the reading leaves
    of it ([`Inverter.misfit_map`][]), in units of the pixel noise. Returns the files.

    `inverter` is the one the recording was inverted with, `source` the recording and
    `wrench_csv` the CSV `moirejax invert` wrote for it. The maps are those of the CSV's
    wrench: for a unit whose calibration has a residual head, the corrected one, so what the
    misfit map shows left includes the head's correction."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rows = read_wrench_csv(wrench_csv)
    written = [folder / "timeline.png"]
    _plot_timeline(written[0], rows, wrench_csv)
    chosen = frames_worth_a_look(rows, frames)
    if not chosen:
        return written
    device = inverter.device
    grid = map_grid(device)
    dtype = np.dtype(device.p1.dtype)
    draw = eqx.filter_jit(patch_tractions)
    misfit = eqx.filter_jit(lambda i, frame, w, c: i.misfit_map(frame, w, c))
    x_coarse, y_coarse = (np.asarray(v) for v in inverter.demodulator.coarse_grid())
    shape = (device.height, device.width)
    for i in chosen:
        name, frame, _ = next(iter_source_frames(source, shape, i, i + 1), (None, None, None))
        if frame is None or frame.shape != shape:
            continue
        patches = row_patches(rows[i], wrench_csv, i + 2)
        wrenches, contacts = stack_patches(patches, dtype)
        traction = np.asarray(draw(wrenches, contacts, grid)) * PA_PER_MPA
        energies = np.asarray(misfit(inverter, frame.astype(dtype), wrenches, contacts))
        path = folder / f"frame-{Path(str(name)).stem}.png"
        _plot_frame(path, rows[i], frame, traction, grid, energies, (x_coarse, y_coarse))
        written.append(path)
    return written


def _plot_timeline(path: Path, rows, wrench_csv) -> None:
    plt = pyplot()
    index = np.arange(len(rows))
    fig, axes = plt.subplots(6, 1, figsize=(9, 10), sharex=True)
    statuses = np.array([row["status"] for row in rows])
    for axis, unit, ax in zip(WRENCH_AXES, WRENCH_UNITS, axes):
        value = np.array([row_number(row, axis, wrench_csv, j + 2) for j, row in enumerate(rows)])
        sigma = np.array([row_number(row, f"sigma_{axis}", wrench_csv, j + 2) for j, row in enumerate(rows)])
        ax.plot(index, value, color="tab:blue", lw=1.0)
        ax.fill_between(index, value - 1.96 * sigma, value + 1.96 * sigma, color="tab:blue", alpha=0.25, lw=0)
        for status, colour in _STATUS_COLOURS.items():
            marked = statuses == status
            if np.any(marked):
                shown = np.where(np.isfinite(value[marked]), value[marked], 0.0)
                ax.scatter(index[marked], shown, s=12, color=colour, label=status, zorder=3)
        ax.set_ylabel(f"{axis} ({unit})")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    for ax in axes[1:]:
        for h, label in zip(*ax.get_legend_handles_labels()):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    if labels:
        fig.legend(handles, labels, loc="upper right", fontsize=8)
    axes[-1].set_xlabel("frame (row of the CSV)")
    fig.suptitle("wrench with its 95 % interval; frames not converged marked by status")
    fig.tight_layout()
    save_figure(fig, path)


def _plot_frame(path: Path, row, frame, traction, grid, energies, coarse) -> None:
    plt = pyplot()
    X, Y = np.asarray(grid.X), np.asarray(grid.Y)
    half = 0.5 * float(grid.spacing)
    extent = (X.min() - half, X.max() + half, Y.min() - half, Y.max() + half)
    pressure_kpa = traction[2] / 1e3
    fig, axes = plt.subplots(2, 2, figsize=(10, 9))
    ax = axes[0, 0]
    ax.imshow(frame, cmap="gray", extent=extent, origin="upper")
    if np.all(np.isfinite(pressure_kpa)) and pressure_kpa.max() > 0:
        levels = pressure_kpa.max() * np.array([0.1, 0.3, 0.5, 0.7, 0.9])
        ax.contour(X, Y, pressure_kpa, levels=levels, cmap="autumn", linewidths=1.0)
        step = max(1, X.shape[0] // 16)
        loaded = pressure_kpa[::step, ::step] > 0.05 * pressure_kpa.max()
        # Drawn to scale: a shear as large as the peak pressure is an arrow of `_SHEAR_ARROW` mm.
        ax.quiver(
            X[::step, ::step][loaded],
            Y[::step, ::step][loaded],
            traction[0][::step, ::step][loaded] / 1e3,
            traction[1][::step, ::step][loaded] / 1e3,
            color="cyan",
            width=0.004,
            angles="xy",
            scale_units="xy",
            scale=pressure_kpa.max() / _SHEAR_ARROW,
        )
        cop = centre_of_pressure_mm(np.array([float(row[a]) for a in WRENCH_AXES]))
        if np.all(np.isfinite(cop)):
            ax.plot(*cop, "+", color="lime", ms=14, mew=2)
    ax.set_title("pressure contours, shear (to scale), centre of pressure", fontsize=9)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax = axes[0, 1]
    im = ax.imshow(pressure_kpa, cmap="magma", extent=extent, origin="upper")
    fig.colorbar(im, ax=ax, label="pressure (kPa)")
    ax.set_title("pressure", fontsize=9)
    x, y = coarse
    dx, dy = abs(x[0, 1] - x[0, 0]), abs(y[1, 0] - y[0, 0])
    coarse_extent = (x.min() - dx / 2, x.max() + dx / 2, y.min() - dy / 2, y.max() + dy / 2)
    top = max(float(np.nanmax(energies)), 10.0)
    norm = _log_norm(1.0, top)
    for ax, energy, title in zip(
        axes[1], energies, ("fringe phase change from the reference", "left after the reading")
    ):
        im = ax.imshow(np.maximum(energy, 1.0), cmap="viridis", norm=norm, extent=coarse_extent, origin="upper")
        fig.colorbar(im, ax=ax, label="phase energy / pixel-noise floor")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x (mm)")
    wrench = ", ".join(f"{a} {float(row[a]):.4g}" for a in WRENCH_AXES)
    fig.suptitle(f"frame {row['frame']}: {row['status']} ({row.get('message', '')})\n{wrench} (N, N·m)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def _log_norm(low: float, high: float):
    from matplotlib.colors import LogNorm

    return LogNorm(vmin=low, vmax=high)
