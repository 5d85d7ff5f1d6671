"""Aligning a force/torque sensor's log to the frames of a recording.

A lab calibrates a unit by pressing it while a commercial force/torque sensor logs the
reference wrench on its own clock and at its own rate (often 1 kHz), and the camera records
frames with their capture times. The two clocks differ by an unknown offset. The frames say
when the sensor was loaded: their fringes change when it is pressed. So the offset is the
shift that best lines up the log's load with a statistic of how much each frame changed,
found by cross-correlation with the force magnitude $|F|$ and refined by fitting that
statistic with the wrench, and the log's wrench is then interpolated to each frame's time.

Pure NumPy: an import aligns thousands of frames in well under a second.
"""

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from jaxtyping import Bool, Float, Float64


# The coarse search pairs frames and log on a grid of one frame period; the fine search
# then steps this fraction of a period through +-1.5 periods around the coarse peak.
_FINE_STEPS_PER_PERIOD = 50
_FINE_HALF_WIDTH = 3.0
# The fine score fits 24 coefficients; fewer frames than this would fit noise.
_MIN_FIT_FRAMES = 48
_FLAT = (
    "cannot align: the frames' activity or the log's force magnitude does not change where "
    "they overlap (press and release the sensor during the recording)"
)


class FtAlignment(NamedTuple):
    """A force/torque log aligned to the frames of a recording, from [`align_ft`][].

    - `offset_s`: the log's clock minus the frames' clock (s): frame time `t` is log time
      `t + offset_s`.
    - `peak`: at that offset, the correlation of the frames' squared activity with its
      least-squares fit in the log's wrench (1 is a perfect match; below about 0.5 the
      offset is doubtful).
    - `wrench`: `[fx, fy, fz, tx, ty, tz]` at each frame, linearly interpolated from the
      log; rows of frames outside the log's span are NaN.
    - `kept`: which frames lie inside the log's span.
    """

    offset_s: float
    peak: float
    wrench: Float64[np.ndarray, "n 6"]
    kept: Bool[np.ndarray, " n"]


def fringe_change(frame: npt.ArrayLike, reference: npt.ArrayLike) -> float:
    """How much a frame's fringes changed from a no-contact reference frame: the root mean
    square of `frame - reference` after removing its mean.

    Removing the mean leaves out a change of overall brightness (the camera's exposure, the
    light), which says nothing about contact. For small loads the fringes shift in
    proportion to the load, so this grows about linearly with it; it saturates once they
    move by a period. It is the frame activity that [`import_recording`][] hands to
    [`align_ft`][], from the recording's first frame as the reference.

    **Arguments:**

    - `frame`, `reference`: `(height, width)` frames of the same size and scale (both
      `[0, 1]` floats, or both of one integer type).

    **Returns:**

    The change, in the frames' brightness units.
    """
    frame, reference = np.asarray(frame), np.asarray(reference)
    if frame.ndim != 2 or frame.shape != reference.shape:
        raise ValueError(f"frame {frame.shape} and reference {reference.shape} must be 2-D arrays of one size")
    change = frame.astype(np.float64) - reference.astype(np.float64)
    change -= change.mean()
    return float(np.sqrt(np.mean(change * change)))


def _check_times(name: str, times: np.ndarray) -> None:
    if times.ndim != 1 or len(times) < 2:
        raise ValueError(f"{name} must be a 1-D array of at least 2 times, got shape {times.shape}")
    if not np.all(np.isfinite(times)):
        raise ValueError(f"{name} contains NaN or inf")
    step = np.diff(times)
    if not np.all(step > 0):
        i = int(np.argmin(step > 0))
        raise ValueError(f"{name} must increase: element {i + 1} ({times[i + 1]}) follows {times[i]}")


def _wrench_at(
    frame_times: np.ndarray, ft_times: np.ndarray, ft_wrench: np.ndarray, offset: float
) -> tuple[np.ndarray, np.ndarray]:
    """The log's wrench interpolated at each frame time plus `offset`, NaN outside its span."""
    at = frame_times + offset
    kept = (at >= ft_times[0]) & (at <= ft_times[-1])
    wrench = np.full((len(frame_times), 6), np.nan)
    for axis in range(6):
        wrench[kept, axis] = np.interp(at[kept], ft_times, ft_wrench[:, axis])
    return wrench, kept


def _pearson(x: np.ndarray, y: np.ndarray) -> float:
    """Pearson correlation, or -inf where either signal is (numerically) constant."""
    x, y = x - x.mean(), y - y.mean()
    scale = np.sqrt(np.sum(x * x) * np.sum(y * y))
    return float(np.sum(x * y) / scale) if scale > 0 else -np.inf


def _running_integral(times: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The trapezoidal integral of `values` (along the first axis) from the first time."""
    steps = 0.5 * (values[1:] + values[:-1]) * np.diff(times).reshape(-1, *([1] * (values.ndim - 1)))
    return np.concatenate([np.zeros((1, *values.shape[1:])), np.cumsum(steps, axis=0)])


def _mean_over_period(at: np.ndarray, ft_times: np.ndarray, integral: np.ndarray, period: float) -> np.ndarray:
    """The mean of a logged signal over one frame period centred on each time in `at`, from
    its running integral (trapezoidal) at the log's sample times."""
    upper = np.interp(at + 0.5 * period, ft_times, integral)
    lower = np.interp(at - 0.5 * period, ft_times, integral)
    return (upper - lower) / period


def _energy_fit_correlation(energy: np.ndarray, wrench: np.ndarray, axis_scale: np.ndarray, max_force: float) -> float:
    """The correlation of the frames' fringe-change energy with its least-squares fit by a
    quadratic form in the wrench plus the cube and fourth power of $|F|$.

    For small loads the fringes shift linearly in the wrench, so the mean squared change of
    a frame is a quadratic form in its six components; the powers of $|F|$ take up the
    saturation of a hard press. Each axis is scaled by `axis_scale` and $|F|$ by
    `max_force`, so that the basis is well conditioned.
    """
    if len(energy) < _MIN_FIT_FRAMES:
        return -np.inf
    scaled = wrench / axis_scale
    force = np.linalg.norm(wrench[:, :3], axis=1)[:, None] / max_force
    upper = np.triu_indices(6)
    basis = np.concatenate(
        [np.ones_like(force), (scaled[:, :, None] * scaled[:, None, :])[:, upper[0], upper[1]], force**3, force**4],
        axis=1,
    )
    # Normal equations: a 24 x 24 solve per offset instead of an SVD of the whole basis; the
    # cutoff drops the directions of axes that never move, or move together.
    coefficients = np.linalg.lstsq(basis.T @ basis, basis.T @ energy, rcond=1e-12)[0]
    return _pearson(energy, basis @ coefficients)


def _correlate(u: np.ndarray, v: np.ndarray, length: int) -> np.ndarray:
    """`c[m] = sum_k u[k] v[k + m]` for every lag `m`, as `c[m % length]` (by FFT)."""
    return np.fft.irfft(np.conj(np.fft.rfft(u, length)) * np.fft.rfft(v, length), length)


def _coarse_offsets(
    frame_times: np.ndarray, activity: np.ndarray, ft_times: np.ndarray, integral: np.ndarray, period: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every offset on a grid of one frame period at which frames and log overlap, with the
    correlation there and the number of frames paired.

    Frames go into bins of one period (summed, with their count); $|F|$ is sampled on the
    same step through the log's span. Masked cross-correlation by FFT (sums, sums of
    squares and counts over the overlap at every lag) gives the Pearson correlation over
    exactly the overlapping frames at every lag at once, so no window of offsets need be
    guessed: a log on an unrelated clock (seconds since its driver started) aligns too.
    """
    activity = activity - activity.mean()
    bins = np.round((frame_times - frame_times[0]) / period).astype(np.int64)
    count = np.bincount(bins).astype(np.float64)
    s1 = np.bincount(bins, weights=activity)
    s2 = np.bincount(bins, weights=activity * activity)
    grid = ft_times[0] + period * np.arange(int(np.floor((ft_times[-1] - ft_times[0]) / period)) + 1)
    y = _mean_over_period(grid, ft_times, integral, period)
    y -= y.mean()
    inside = np.ones_like(y)
    length = len(count) + len(y)
    pairs = _correlate(count, inside, length)
    sx, sxx = _correlate(s1, inside, length), _correlate(s2, inside, length)
    sy, syy = _correlate(count, y, length), _correlate(count, y * y, length)
    sxy = _correlate(s1, y, length)
    lags = np.arange(-(len(count) - 1), len(y))
    offsets = ft_times[0] - frame_times[0] + period * lags
    pairs, sx, sxx, sy, syy, sxy = (c[lags % length] for c in (pairs, sx, sxx, sy, syy, sxy))
    pairs = np.round(pairs)
    with np.errstate(divide="ignore", invalid="ignore"):
        covariance = sxy - sx * sy / pairs
        variance = (sxx - sx * sx / pairs) * (syy - sy * sy / pairs)
        correlation = np.where(variance > 0, covariance / np.sqrt(np.maximum(variance, 0)), -np.inf)
    return offsets, correlation, pairs


def align_ft(
    frame_times: Float[np.ndarray, " n"],
    frame_activity: Float[np.ndarray, " n"],
    ft_times: Float[np.ndarray, " m"],
    ft_wrench: Float[np.ndarray, "m 6"],
    *,
    max_offset: float | None = None,
) -> FtAlignment:
    r"""Estimate the clock offset between a force/torque log and the frames of a recording
    from the data, and interpolate the log's wrench to every frame.

    A coarse search on a grid of one frame period scores every offset at which at least
    half as many frames overlap the log as at best by the Pearson correlation of the
    activity with the force magnitude $|F| = \sqrt{f_x^2 + f_y^2 + f_z^2}$ of the log at the
    frame's time on the log's clock, all at once by FFT, so a log on an unrelated clock
    aligns too. A fine search then steps a fiftieth of a period through three periods
    either side of the coarse peak, scoring each offset by how well the squared activity
    (the fringe-change energy) is fitted by least squares with a quadratic form in the
    log's wrench plus the cube and fourth power of $|F|$: for small loads the fringes shift
    linearly in the wrench, so their mean squared change is such a quadratic form, and a
    twist or a shear that changes the fringes at a constant $|F|$ is fitted too. A parabola
    through the best three scores places the peak between them. The log is averaged over
    one frame period centred on each frame's time, as an exposure integrates the load,
    which also averages away its noise; the wrench returned is interpolated linearly.

    Only the timing of the activity matters, not its scale. The recording must load and
    unload the sensor at least once inside the log's span, over at least 48 frames.

    **Arguments:**

    - `frame_times`: each frame's capture time (s, the frames' clock), increasing.
    - `frame_activity`: each frame's activity, finite.
    - `ft_times`: the log's sample times (s, its own clock), increasing; any rate.
    - `ft_wrench`: the log's `[fx, fy, fz, tx, ty, tz]` per sample, N and N·m, in the
      convention [`WRENCH_CONVENTION`][moirejax.WRENCH_CONVENTION].
    - `max_offset`: if given, the largest `|offset_s|` considered (s); by default any
      offset at which the two overlap.

    **Returns:**

    An [`FtAlignment`][]: the offset (log clock minus frame clock), the correlation peak,
    the wrench at each frame and which frames lie inside the log's span.

    **Raises:** `ValueError` for inputs of the wrong shape, non-finite or non-increasing
    times, no overlap within `max_offset`, or activity or force that never changes.
    """
    frame_times = np.asarray(frame_times, dtype=np.float64)
    activity = np.asarray(frame_activity, dtype=np.float64)
    ft_times = np.asarray(ft_times, dtype=np.float64)
    ft_wrench = np.asarray(ft_wrench, dtype=np.float64)
    _check_times("frame_times", frame_times)
    _check_times("ft_times", ft_times)
    if activity.shape != frame_times.shape or not np.all(np.isfinite(activity)):
        raise ValueError(f"frame_activity must be {len(frame_times)} finite numbers, one per frame")
    if ft_wrench.shape != (len(ft_times), 6) or not np.all(np.isfinite(ft_wrench)):
        raise ValueError(f"ft_wrench must be a finite ({len(ft_times)}, 6) array, got shape {ft_wrench.shape}")
    if max_offset is not None and not (np.isfinite(max_offset) and max_offset >= 0):
        raise ValueError(f"max_offset must be a number >= 0, got {max_offset}")
    force = np.linalg.norm(ft_wrench[:, :3], axis=1)
    integral = _running_integral(ft_times, force)
    period = float(np.median(np.diff(frame_times)))

    offsets, correlation, pairs = _coarse_offsets(frame_times, activity, ft_times, integral, period)
    allowed = np.ones(len(offsets), dtype=bool) if max_offset is None else np.abs(offsets) <= max_offset
    if not np.any(allowed & (pairs >= 2)):
        within = "" if max_offset is None else f" within ±{max_offset:g} s"
        raise ValueError(
            f"the force/torque log ({ft_times[0]:g} to {ft_times[-1]:g} s) and the frames "
            f"({frame_times[0]:g} to {frame_times[-1]:g} s) overlap at no clock offset{within}"
        )
    candidate = allowed & (pairs >= max(3.0, 0.5 * pairs[allowed].max()))
    if not np.any(np.isfinite(correlation[candidate])):
        raise ValueError(_FLAT)
    coarse = float(offsets[candidate][np.argmax(correlation[candidate])])

    fine = coarse + period * np.linspace(
        -_FINE_HALF_WIDTH, _FINE_HALF_WIDTH, int(2 * _FINE_HALF_WIDTH * _FINE_STEPS_PER_PERIOD) + 1
    )
    if max_offset is not None:
        fine = fine[np.abs(fine) <= max_offset]
    wrench_integral = _running_integral(ft_times, ft_wrench)
    axis_scale = np.where(np.abs(ft_wrench).max(axis=0) > 0, np.abs(ft_wrench).max(axis=0), 1.0)
    max_force = max(float(force.max()), np.finfo(np.float64).tiny)
    energy = activity * activity
    scores = np.empty(len(fine))
    for i, offset in enumerate(fine):
        at = frame_times + offset
        inside = (at >= ft_times[0]) & (at <= ft_times[-1])
        wrench = np.stack(
            [_mean_over_period(at[inside], ft_times, wrench_integral[:, k], period) for k in range(6)], axis=1
        )
        scores[i] = _energy_fit_correlation(energy[inside], wrench, axis_scale, max_force)
    best = int(np.argmax(scores))
    offset, peak = float(fine[best]), float(scores[best])
    if not np.isfinite(peak):
        raise ValueError(_FLAT)
    if 0 < best < len(fine) - 1 and np.all(np.isfinite(scores[best - 1 : best + 2])):
        left, right = scores[best - 1], scores[best + 1]
        curvature = left - 2 * peak + right
        if curvature < 0:
            offset += 0.5 * (left - right) / curvature * (fine[1] - fine[0])
    wrench, kept = _wrench_at(frame_times, ft_times, ft_wrench, offset)
    return FtAlignment(offset_s=offset, peak=peak, wrench=wrench, kept=kept)
