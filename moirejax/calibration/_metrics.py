"""Accuracy metrics and evaluation plots of estimated wrenches against reference readings."""

from pathlib import Path

import numpy as np

from .._conventions import WRENCH_AXES, WRENCH_UNITS
from .._plotting import pyplot, save_figure


# Plots show torques in mN·m: tick labels in N·m (0.0025 steps) run into each other.
PLOT_SCALE = np.array([1.0, 1.0, 1.0, 1e3, 1e3, 1e3])
PLOT_UNITS = ("N", "N", "N", "mN·m", "mN·m", "mN·m")


def wrench_metrics(
    true: np.ndarray, estimate: np.ndarray, sigma: np.ndarray | None = None
) -> dict[str, dict[str, float]]:
    """Per-axis R², MAE, RMSE, max error and 95%-interval coverage.

    Rows where the estimate is not finite (failed frames) are left out and counted in
    `n_failed`. Returns a dict of metric name → {axis → value}, plus `n` and `n_failed`.
    """
    true = np.asarray(true, dtype=float)
    estimate = np.asarray(estimate, dtype=float)
    ok = np.all(np.isfinite(estimate), axis=1)
    t, e = true[ok], estimate[ok]
    err = e - t
    out: dict = {"r2": {}, "mae": {}, "rmse": {}, "max_error": {}, "coverage95": {}}
    for j, axis in enumerate(WRENCH_AXES):
        variance = np.sum((t[:, j] - t[:, j].mean()) ** 2)
        out["r2"][axis] = float(1 - np.sum(err[:, j] ** 2) / variance) if variance > 0 else float("nan")
        out["mae"][axis] = float(np.mean(np.abs(err[:, j]))) if len(t) else float("nan")
        out["rmse"][axis] = float(np.sqrt(np.mean(err[:, j] ** 2))) if len(t) else float("nan")
        out["max_error"][axis] = float(np.max(np.abs(err[:, j]))) if len(t) else float("nan")
        if sigma is not None:
            s = np.asarray(sigma, dtype=float)[ok][:, j]
            out["coverage95"][axis] = float(np.mean(np.abs(err[:, j]) <= 1.96 * s)) if len(t) else float("nan")
    if sigma is None:
        del out["coverage95"]
    out["n"] = int(ok.sum())
    out["n_failed"] = int((~ok).sum())
    return out


def format_metrics(metrics: dict, *, title: str = "") -> str:
    """A per-axis table of [`wrench_metrics`][]."""
    lines = [title] if title else []
    lines.append("axis   unit      R2        MAE        RMSE      max err   cov95")
    for j, axis in enumerate(WRENCH_AXES):
        cov = metrics.get("coverage95", {}).get(axis, float("nan"))
        lines.append(
            f"{axis:5s}  {WRENCH_UNITS[j]:5s} {metrics['r2'][axis]:8.4f}  {metrics['mae'][axis]:9.3g}  "
            f"{metrics['rmse'][axis]:9.3g}  {metrics['max_error'][axis]:9.3g}  {cov:6.3f}"
        )
    lines.append(f"frames: {metrics['n']} evaluated, {metrics['n_failed']} failed")
    return "\n".join(lines)


def plot_parity(
    path: str | Path, true: np.ndarray, estimate: np.ndarray, sigma: np.ndarray | None = None, *, title: str = ""
) -> None:
    """Parity plot per axis (estimate against reference) with 95% error bars."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(13, 8))
    ok = np.all(np.isfinite(estimate), axis=1)
    for j, ax in enumerate(axes.flat):
        t, e = true[ok, j] * PLOT_SCALE[j], estimate[ok, j] * PLOT_SCALE[j]
        if sigma is not None:
            ax.errorbar(t, e, yerr=1.96 * sigma[ok, j] * PLOT_SCALE[j], fmt="none", ecolor="0.7", lw=0.6, zorder=1)
        ax.scatter(t, e, s=6, zorder=2)
        lo, hi = float(np.min(t, initial=0)), float(np.max(t, initial=0))
        pad = 0.05 * (hi - lo + 1e-12)
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=0.8)
        r2 = 1 - np.sum((e - t) ** 2) / max(np.sum((t - t.mean()) ** 2), 1e-30)
        ax.set_title(f"{WRENCH_AXES[j]}  R² = {r2:.4f}")
        ax.set_xlabel(f"reference ({PLOT_UNITS[j]})")
        ax.set_ylabel(f"estimate ({PLOT_UNITS[j]})")
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path)


def plot_residuals(path: str | Path, true: np.ndarray, estimate: np.ndarray, *, title: str = "") -> None:
    """Histogram of the estimation error per axis."""
    plt = pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(13, 7))
    ok = np.all(np.isfinite(estimate), axis=1)
    for j, ax in enumerate(axes.flat):
        err = (estimate[ok, j] - true[ok, j]) * PLOT_SCALE[j]
        ax.hist(err, bins=40, color="C1")
        axis_title = f"{WRENCH_AXES[j]} error: mean {err.mean():.2g}, sd {err.std():.2g} {PLOT_UNITS[j]}"
        ax.set_title(axis_title if len(err) else WRENCH_AXES[j])
        ax.set_xlabel(f"estimate - reference ({PLOT_UNITS[j]})")
    fig.suptitle(title)
    fig.tight_layout()
    save_figure(fig, path)
