r"""Moire observables from a camera frame: Fourier-transform demodulation and its summaries.

A rectified frame is, to a good approximation,

$$I(\mathbf{x}) = B(\mathbf{x})\Big[1 + \sum_f m_f(\mathbf{x})
\cos\big(\mathbf{K}_f\cdot\mathbf{x} + \psi_f(\mathbf{x})\big)\Big] + \text{carriers},$$

with one moire fringe family per grating direction (one for line gratings, two for crossed
grids), a nominal moire wavevector $\mathbf{K}_f$ fixed by the design, a slowly varying
phase $\psi_f$ that carries the deformation, and the grating carriers at far higher spatial
frequency. Everything here works on the complex baseband field of each family,

$$z_f(\mathbf{x}) \approx \tfrac12 B m_f\, e^{i\psi_f(\mathbf{x})},$$

with $\mathbf{x}$ measured from the image centre (a frame $\cos(\mathbf{K}_f\cdot\mathbf{x} +
\psi_0)$ gives $\arg z_f = \psi_0$ everywhere), and on the low-passed brightness $B$.

**Why the Fourier-transform method (Takeda).** One real FFT of the frame gives every band
at once. The baseband field is band-limited to a disc of radius $R_f$ around $\mathbf{K}_f$,
so inverse-transforming only a small $m\times n$ window of the spectrum around that disc
yields $z_f$ directly on a coarse grid covering the whole field of view: demodulation,
low-pass and decimation cost one small inverse FFT. A windowed Fourier transform (many
windows and frequency candidates) or quadrature (Gabor/Riesz) filters (a full-size complex
filter per family) cost several full-size transforms for the same band. The band is a known
array, a raised-cosine disc with compact support, so the DC band, the other families, their
cross terms at $\mathbf{K}_a\pm\mathbf{K}_b$ and the carriers are excluded exactly, and the
trade-off between spatial resolution and crosstalk is one number, `band_fraction`. Because
the method is linear, a forward model can push its predicted baseband field through the
same operator ([`moirejax.Demodulator.filter_baseband`][]) and compare with the
measurement after identical filtering, finite-field effects included.

**Finite field of view.** With only a few fringes across the frame its border matters. A
fringe whose wavevector is not a DFT bin jumps across the periodic boundary, and a narrow
band spreads that jump as ringing all the way to the image centre (about 0.05 rad for
eight fringes across). So

1. the fringe bands are taken from the frame times a separable Hann apodization
   $\cos^2(\pi x/L_x)\cos^2(\pi y/L_y)$, applied exactly as a three-tap convolution of the
   spectrum window (no second FFT), which makes the field smooth across the boundary;
2. the apodized band-passed field is divided by the same pipeline's response to a unit
   fringe at a *reference wavevector*: the spectral peak of the frame (Jacobsen's
   three-bin interpolation on the raw DFT), clipped to half the band radius around
   $\mathbf{K}_f$. The response has a closed form (a product of Dirichlet kernels), so this
   costs one more $m\times n$ inverse FFT.

A fringe at any wavevector in the band is then demodulated exactly up to the leakage of
its conjugate term: ~1e-4 rad in the interior for 4 mm fringes on a 32 mm field, up to a
few 1e-2 rad in the outermost coarse samples, where the apodization leaves little signal.
The reference response's magnitude ([`moirejax.Demodulator.fringe_envelope`][]) is the
natural reliability weight, and the per-frame summaries use it. The brightness band is
apodized the same way and divided by the band-passed apodization (normalised convolution),
so a uniform brightness is exact.

**Resolution.** The band limit is the price of one FFT: phase features narrower than about
$1/R_f$ are smoothed. With 4 mm fringes and the defaults, a 1.5 rad Gaussian phase bump of
6 mm standard deviation comes back within 0.06 rad (0.015 rad rms) and its gradient within
0.035 rad/mm over the central 20 mm; narrower features lose height. A forward model
compared through [`moirejax.Demodulator.filter_baseband`][] sees the same smoothing.

Conventions follow `docs/conventions.md`: x right, y up, origin at the image centre,
$k_y = -2\pi\,\mathrm{fftfreq}$ along rows; wavevectors are rows `[kx, ky]` in rad/mm.

It is one module because the JAX `Demodulator` and its numpy twin share every band-window
and crop helper (written once for either array module), and the observables and summaries
read the demodulator's plan.
"""

import cmath
import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Complex, Float

from ..physics import wavenumber_grid


# Band radius over |K| and taper of every band's window, unless a Demodulator is told
# otherwise. Below 0.5 the fringe bands stay clear of the brightness band.
BAND_FRACTION = 0.45
BAND_ROLLOFF = 0.3


# The smallest brightness envelope, relative to its peak, a coarse sample is given.
_ENVELOPE_FLOOR = 1e-6


def _raised_cosine(xp, distance, radius, rolloff):
    """Raised-cosine disc profile: 1 inside `radius*(1-rolloff)`, cosine taper to 0 at `radius`."""
    flat = radius * (1 - rolloff)
    t = xp.clip((distance - flat) / (radius - flat), 0.0, 1.0)
    return 0.5 * (1 + xp.cos(math.pi * t))


def raised_cosine_window(
    distance: Float[ArrayLike, "*k"], radius: Float[ArrayLike, ""], rolloff: float
) -> Float[Array, "*k"]:
    r"""The band window used for every band: a raised-cosine disc.

    $W(r) = 1$ for $r \le (1-\beta)R$, $\tfrac12\{1+\cos[\pi(r-(1-\beta)R)/(\beta R)]\}$ up to
    $R$, and $0$ beyond; continuous with a continuous first derivative.

    **Arguments:**

    - `distance`: distance $r$ from the band centre in wavevector space (rad/mm).
    - `radius`: support radius $R$ (rad/mm).
    - `rolloff`: taper fraction $\beta \in (0, 1]$; $1$ is a Hann disc.

    **Returns:**

    The window values, shaped like `distance`.
    """
    return _raised_cosine(jnp, jnp.asarray(distance), jnp.asarray(radius), rolloff)


def _cast(xp, array, dtype):
    return xp.asarray(array, dtype=dtype)


def _expi(xp, phase):
    """`exp(i phase)` in the matching complex precision (no implicit promotion)."""
    complex_dtype = np.complex64 if phase.dtype == np.float32 else np.complex128
    return xp.exp(_cast(xp, phase, complex_dtype) * 1j)


def _real_dtype(xp, complex_dtype):
    return xp.real(xp.zeros((), dtype=complex_dtype)).dtype


def _wrapped(xp, x, start, count, axis):
    """Indices `start ... start + count - 1` of `x` along `axis`, modulo its length (static)."""
    size = x.shape[axis]
    start %= size

    def take(lo, hi):
        index = [slice(None)] * x.ndim
        index[axis] = slice(lo, hi)
        return x[tuple(index)]

    if start + count <= size:
        return take(start, start + count)
    return xp.concatenate([take(start, size), take(0, start + count - size)], axis=axis)


def _crop(xp, spectrum, row_start, col_start, rows, cols):
    """A `rows x cols` window of the full 2-D DFT of a real frame, read from its half spectrum.

    `spectrum[p, q]` holds bins `q = 0, 1, ...` (rfft layout, all rows). The window covers
    signed bins `p = row_start ... row_start + rows - 1` (wrapped) and
    `q = col_start ... col_start + cols - 1`; bins with `q < 0` come from Hermitian
    symmetry, `X[p, q] = conj(X[-p, -q])`. All indices are static: slicing only.
    """
    parts = []
    if col_start < 0:
        negative = min(-col_start, cols)
        # Rows -p for p = row_start ... row_start + rows - 1: a reversed contiguous block.
        mirrored = _wrapped(xp, spectrum, -(row_start + rows - 1), rows, 0)[::-1]
        parts.append(xp.conj(mirrored[:, -col_start - negative + 1 : -col_start + 1][:, ::-1]))
    if col_start + cols > 0:
        direct = _wrapped(xp, spectrum, row_start, rows, 0)
        parts.append(direct[:, max(col_start, 0) : col_start + cols])
    return parts[0] if len(parts) == 1 else xp.concatenate(parts, axis=1)


def _apodize(xp, windows, h, w):
    r"""Spectrum windows of the Hann-apodized frame, from windows one bin wider on every side.

    Along rows the apodization $\sin^2(\pi(i + 1/2)/h) = \tfrac12 - \tfrac14(e^{i\pi/h}
    e^{2\pi i i/h} + \mathrm{c.c.})$ shifts the spectrum one bin either way:
    `out[p] = X[p]/2 - e^{i pi/h} X[p-1]/4 - e^{-i pi/h} X[p+1]/4`. Same along columns.
    """
    up, down = 0.25 * cmath.exp(1j * math.pi / h), 0.25 * cmath.exp(-1j * math.pi / h)
    windows = 0.5 * windows[..., 1:-1, :] - up * windows[..., :-2, :] - down * windows[..., 2:, :]
    up, down = 0.25 * cmath.exp(1j * math.pi / w), 0.25 * cmath.exp(-1j * math.pi / w)
    return 0.5 * windows[..., 1:-1] - up * windows[..., :-2] - down * windows[..., 2:]


def _band_pass(xp, windows, transfer, apodize, h, w):
    """`ifft2(transfer * window)` from spectrum windows one bin wider on every side."""
    windows = _apodize(xp, windows, h, w) if apodize else windows[..., 1:-1, 1:-1]
    return xp.fft.ifft2(transfer * windows)


def _dirichlet(xp, offset, size):
    """`sum_j exp(2 pi i offset j / size)` over `j < size`, without its phase: sin(pi u)/sin(pi u/size)."""
    at_bin = offset == 0
    safe = xp.where(at_bin, 1.0, offset)
    return xp.where(at_bin, float(size), xp.sin(math.pi * safe) / xp.sin(math.pi * safe / size))


def _tone_windows(xp, wavevectors, crop_starts, frame_shape, crop_shape, pixel, dtype):
    r"""DFT of the unit fringes $e^{i\mathbf{K}\cdot\mathbf{x}}$ over each window, one bin wider.

    Separable: along rows $\sum_i e^{iK_y y_i} e^{-2\pi i p i/h} = e^{-i\pi p(h-1)/h}
    D_h(p_K - p)$ with $p_K = -K_y h\,\Delta x/2\pi$ the fractional bin of $K_y$ and $D$ the
    Dirichlet kernel; the same along columns with $q_K = K_x w\,\Delta x/2\pi$.
    """
    h, w = frame_shape
    m, n = crop_shape
    real_dtype = _real_dtype(xp, dtype)
    tones = []
    for family, (row_start, col_start) in enumerate(crop_starts):
        p = row_start - 1 + np.arange(m + 2)
        q = col_start - 1 + np.arange(n + 2)
        p_bin = -wavevectors[family, 1] * pixel * (h / (2 * math.pi))
        q_bin = wavevectors[family, 0] * pixel * (w / (2 * math.pi))
        rows = _cast(xp, np.exp(-1j * math.pi * p * (h - 1) / h), dtype) * _cast(
            xp, _dirichlet(xp, p_bin - _cast(xp, p, real_dtype), h), dtype
        )
        cols = _cast(xp, np.exp(-1j * math.pi * q * (w - 1) / w), dtype) * _cast(
            xp, _dirichlet(xp, q_bin - _cast(xp, q, real_dtype), w), dtype
        )
        tones.append(rows[:, None] * cols[None, :])
    return xp.stack(tones)


def _peak_offset(xp, left, centre, right, size):
    """Sub-bin offset of a DFT peak from three complex bins (Jacobsen, with Candan's correction).

    Unbiased for a single tone under the rectangular window of a plain DFT, unlike a
    parabola through the (log) magnitude, which is biased by up to ~0.1 bin there.
    """
    numerator = left - right
    denominator = 2 * centre - left - right
    degenerate = xp.abs(denominator) == 0
    ratio = xp.real(numerator / xp.where(degenerate, 1, denominator))
    offset = xp.where(degenerate, 0, ratio) * (math.tan(math.pi / size) / (math.pi / size))
    return xp.clip(offset, -1, 1)


def _peak_wavevectors(xp, windows, support, crop_starts, frame_shape, pixel):
    """Spectral peak of every family inside its band support, refined to sub-bin (rad/mm).

    Not `observe.spectral_peak`: this one runs inside the traced demodulation
    (numpy or JAX), on the complex bins of the unwindowed DFT that the demodulator already
    holds, where Jacobsen's three-bin estimate is unbiased and a parabola through the
    Hann-windowed log power would need a second, windowed FFT of the frame.
    """
    h, w = frame_shape
    families, rows, cols = windows.shape
    m, n = rows - 2, cols - 2
    real_dtype = pixel.dtype
    power = xp.where(support, xp.abs(windows[:, 1:-1, 1:-1]) ** 2, 0)
    flat = xp.argmax(xp.reshape(power, (families, m * n)), axis=1)
    row, col = flat // n, flat % n
    centre = (row + 1) * cols + col + 1
    neighbours = xp.stack([centre - cols, centre, centre + cols, centre - 1, centre + 1], axis=1)
    up, mid, down, left, right = xp.moveaxis(
        xp.take_along_axis(xp.reshape(windows, (families, rows * cols)), neighbours, axis=1), 1, 0
    )
    starts = _cast(xp, np.asarray(crop_starts, dtype=float), real_dtype)
    row_bin = starts[:, 0] + _cast(xp, row, real_dtype) + _peak_offset(xp, up, mid, down, h)
    col_bin = starts[:, 1] + _cast(xp, col, real_dtype) + _peak_offset(xp, left, mid, right, w)
    return xp.stack([col_bin * (2 * math.pi / w), -row_bin * (2 * math.pi / h)], axis=1) / pixel


def _reference_wavevectors(xp, peaks, nominal, max_offset):
    """Peaks pulled back to within `max_offset` of the nominal wavevectors."""
    offset = peaks - nominal
    squared = xp.sum(offset**2, axis=1)
    scale = xp.sqrt(max_offset**2 / xp.maximum(squared, max_offset**2))
    return nominal + offset * scale[:, None]


def _ramp(xp, offset, coarse_x, coarse_y):
    """`exp(i offset . x)` on the coarse grid, one row per family."""
    phase = offset[:, 0, None, None] * coarse_x[None, None, :] + offset[:, 1, None, None] * coarse_y[None, :, None]
    return _expi(xp, phase)


class _Demodulated(NamedTuple):
    fringe: Any  # normalised fringe fields, `raw / reference * ramp`
    brightness: Any
    peaks: Any  # refined spectral peaks
    reference_k: Any  # reference wavevectors
    raw: Any  # band-passed fringe fields before normalisation
    reference: Any  # band-passed unit fringes at the reference wavevectors


def _demodulate(xp, plan, spectrum, reference_k=None):
    """The whole demodulation, for `xp` = numpy or jax.numpy; `plan` holds the geometry.

    `reference_k` fixes the normalisation wavevectors instead of measuring them.
    """
    h, w = plan.frame_shape
    m, n = plan.crop_shape
    dtype = spectrum.dtype
    real_dtype = _real_dtype(xp, dtype)
    pixel = 1 / _cast(xp, plan.px_per_mm, real_dtype)
    nominal = _cast(xp, plan.wavevectors, real_dtype)
    transfer = _cast(xp, plan.fringe_transfer, dtype)
    windows = xp.stack([_crop(xp, spectrum, p - 1, q - 1, m + 2, n + 2) for p, q in plan.crop_starts])
    if reference_k is None:
        peaks = _peak_wavevectors(xp, windows, plan.peak_support, plan.crop_starts, plan.frame_shape, pixel)
        reference_k = _reference_wavevectors(xp, peaks, nominal, 0.5 * _cast(xp, plan.peak_radius, real_dtype))
    else:
        reference_k = _cast(xp, reference_k, real_dtype)
        peaks = reference_k
    tones = _tone_windows(xp, reference_k, plan.crop_starts, plan.frame_shape, plan.crop_shape, pixel, dtype)
    raw = _band_pass(xp, windows, transfer, plan.apodize, h, w)
    reference = _band_pass(xp, tones, transfer, plan.apodize, h, w)
    ramp = _ramp(xp, reference_k - nominal, _cast(xp, plan.coarse_x, real_dtype), _cast(xp, plan.coarse_y, real_dtype))
    fringe = raw / reference * ramp
    dc = _crop(xp, spectrum, -(m // 2) - 1, -(n // 2) - 1, m + 2, n + 2)
    dc = _band_pass(xp, dc, _cast(xp, plan.brightness_transfer, dtype), plan.apodize, h, w)
    brightness = xp.real(dc) * _cast(xp, plan.brightness_normalisation, real_dtype)
    return _Demodulated(fringe, brightness, peaks, reference_k, raw, reference)


def _check_shape(name, actual, expected):
    if tuple(actual) != tuple(expected):
        raise ValueError(f"{name} has shape {tuple(actual)}, expected {tuple(expected)}.")


def _check_bands(k_nominal, radius, dc_radius):
    """Refuse overlapping band windows: DC, other families and their conjugates."""
    for a, (k_a, r_a) in enumerate(zip(k_nominal, radius)):
        if np.hypot(*k_a) <= r_a + dc_radius:
            raise ValueError(f"The band of wavevector {k_a} overlaps the brightness band.")
        for k_b, r_b in zip(k_nominal[a + 1 :], radius[a + 1 :]):
            if min(np.hypot(*(k_a - k_b)), np.hypot(*(k_a + k_b))) <= r_a + r_b:
                raise ValueError(f"The bands of wavevectors {k_a} and {k_b} overlap.")


def _tukey(size, taper):
    """Weights 1 in the middle and a cos^2 taper to 0 over `taper * size` samples at each end."""
    t = (np.arange(size) + 0.5) / size
    edge = np.minimum(t, 1 - t) / taper
    return np.where(edge >= 1, 1.0, np.sin(0.5 * math.pi * np.minimum(edge, 1)) ** 2)


class FringeFields(eqx.Module):
    r"""Demodulated frame on the coarse grid of a [`moirejax.Demodulator`][].

    **Fields:**

    - `fringe`: complex baseband field $z_f \approx \tfrac12 B m_f e^{i\psi_f}$ per family.
    - `brightness`: low-passed brightness $B$ (frame units).
    - `reference_wavevector`: the wavevector whose unit fringe `fringe` is normalised by
      (the frame's spectral peak, clipped to the band), rows `[kx, ky]` (rad/mm).
    - `light`: in a prediction ([`BandModel`][moirejax.BandModel]), the part of `fringe`
      that the elastomer's own light puts there; `None` for a measured frame. That light
      passes the reference grating alone, so a unit's fringe contrast (its defocus, its
      duty) does not scale it as it scales the rest.
    """

    fringe: Complex[Array, "families m n"]
    brightness: Float[Array, "m n"]
    reference_wavevector: Float[Array, "families 2"]
    light: Complex[Array, "families m n"] | None = None


class DemodulationWindowTooSmall(ValueError):
    """A band of the frame does not fit the windows of the coarse demodulation grid: a wider
    `crop_shape` (or a narrower `band_fraction`) holds it. A design of fine fringes has
    bands wide in wavenumber and needs the wider grid."""


class Demodulator(eqx.Module):
    r"""Fourier-transform demodulator for one camera geometry, built once per device.

    The frame is transformed once (`rfft2`). For each fringe family an $m\times n$ window of
    the apodized spectrum centred on the bin nearest $\mathbf{K}_f$ is multiplied by the band
    window $W(|\mathbf{k}-\mathbf{K}_f|)$ of radius $R_f$ = `band_fraction`
    $|\mathbf{K}_f|$, inverse-transformed, and divided by the response to a unit fringe at
    the reference wavevector; phases are referred to $\mathbf{K}_f$ and the image centre. The
    brightness is the same with a disc of radius `band_fraction` $\min_f|\mathbf{K}_f|$
    around DC, divided by the band-passed apodization. Outputs live on a cell-centred coarse
    grid: sample `(r, s)` is the centre of the cell in row `r` of `m` and column `s` of `n`
    equal cells tiling the frame, at (`coarse_x[s]`, `coarse_y[r]`) mm.

    Window positions are static (set by the nominal wavevectors); the transfer arrays are
    data. A different nominal wavevector needs a new `Demodulator`.

    **Fields:**

    - `frame_shape`, `crop_shape`: static `(h, w)` and `(m, n)`.
    - `crop_starts`: static signed first bin `(p, q)` of each family's window.
    - `apodize`: static; whether the bands use the Hann apodization.
    - `px_per_mm`: rectified resolution.
    - `wavevectors`: nominal $\mathbf{K}_f$ (rad/mm); `bin_wavevectors`: the bin each
      window is centred on.
    - `band_radius`: $R_f$ per family; `brightness_band_radius`: radius of the DC band.
    - `peak_radius`: per family, the disc around $\mathbf K_f$ searched for the frame's peak.
    - `notches`, `notch_radius`: per family, wavevectors cut out of its band (static), and the
      radius of the cuts.
    - `rolloff`: taper fraction of the raised-cosine windows.
    - `coarse_x`, `coarse_y`: coarse-grid coordinates (mm); `coarse_y` decreases with row.
    - `fringe_envelope`: magnitude of the band-passed unit nominal fringe, about 1 in the
      middle and small at the border: how much signal each coarse sample rests on.
    - `fringe_transfer`: per-bin factor on each family's window in natural bin order (band
      window, phase reference moved from pixel (0, 0) to coarse sample (0, 0), normalisation).
    - `brightness_transfer`: the same for the DC band (window centred on DC).
    - `brightness_envelope`: the band-passed apodization, about 1 in the middle and small at
      the border (floored at `_ENVELOPE_FLOOR` of its peak); the brightness is divided by it.
    - `brightness_normalisation`: `(-1)^(r+s) / brightness_envelope`.
    - `peak_support`: bins where each family's band window is non-zero, within `peak_radius`.
    - `centroid_weights`: separable Tukey weights `(rows, columns)` of the brightness
      centroid on the frame grid.
    """

    frame_shape: tuple[int, int] = eqx.field(static=True)
    crop_shape: tuple[int, int] = eqx.field(static=True)
    crop_starts: tuple[tuple[int, int], ...] = eqx.field(static=True)
    apodize: bool = eqx.field(static=True)
    px_per_mm: Float[Array, ""]
    wavevectors: Float[Array, "families 2"]
    bin_wavevectors: Float[Array, "families 2"]
    band_radius: Float[Array, " families"]
    peak_radius: Float[Array, " families"]
    notches: tuple[tuple[tuple[float, float], ...], ...] = eqx.field(static=True)
    notch_radius: Float[Array, " families"]
    brightness_band_radius: Float[Array, ""]
    rolloff: Float[Array, ""]
    coarse_x: Float[Array, " n"]
    coarse_y: Float[Array, " m"]
    fringe_envelope: Float[Array, "families m n"]
    fringe_transfer: Complex[Array, "families m n"]
    brightness_envelope: Float[Array, "m n"]
    brightness_transfer: Complex[Array, "m n"]
    brightness_normalisation: Float[Array, "m n"]
    peak_support: Bool[Array, "families m n"]
    centroid_weights: tuple[Float[Array, " h"], Float[Array, " w"]]

    def __init__(
        self,
        frame_shape: tuple[int, int],
        px_per_mm: float,
        wavevectors: Float[ArrayLike, "families 2"],
        crop_shape: tuple[int, int] = (32, 32),
        band_fraction: float = BAND_FRACTION,
        rolloff: float = BAND_ROLLOFF,
        apodize: bool = True,
        centroid_taper: float = 0.25,
        band_radius: ArrayLike | Sequence[float] | None = None,
        peak_radius: ArrayLike | Sequence[float] | None = None,
        notches: Sequence[Any] | None = None,
        notch_radius: ArrayLike | Sequence[float] | None = None,
    ):
        r"""**Arguments:**

        - `frame_shape`: `(h, w)` of the rectified frames, both even.
        - `px_per_mm`: rectified resolution (px/mm).
        - `wavevectors`: nominal moire wavevectors $\mathbf{K}_f$, rows `[kx, ky]` in rad/mm
          (repo convention, y up). Must be concrete.
        - `crop_shape`: `(m, n)` spectrum window, also the coarse output grid; both even.
        - `band_fraction`: band radius as a fraction of $|\mathbf{K}_f|$; below 0.5 keeps the
          fringe bands clear of the brightness band.
        - `rolloff`: taper fraction of the raised-cosine windows, in $(0, 1]$. Smaller is a
          wider flat pass band (sharper phase features) with longer ringing from the border.
        - `apodize`: apodize the fringe and brightness bands (see the module notes).
        - `centroid_taper`: fraction of the width and height, on each side, over which the
          brightness centroid's weight tapers to zero (see [`moirejax.frame_summary`][]).
        - `band_radius`: band radius (rad/mm) per family, overriding `band_fraction`
          $|\mathbf K_f|$ where it is not NaN: the bands of the upper grating's own carriers
          are wider than the moiré bands (see [`moirejax.carrier_band_radius`][]). The
          brightness band keeps `band_fraction` of the smallest $|\mathbf K_f|$.
        - `peak_radius`: per family (NaN for the band radius), how far from $\mathbf K_f$ the
          frame's spectral peak is sought, and half of it how far the reference wavevector may
          move: a carrier's band also holds the reference grating's static carrier, which
          must not be taken for its peak.
        - `notches`: per family, wavevectors (rad/mm) cut out of its band by raised-cosine
          discs of `notch_radius` (per family): the reference grating's carrier and its
          sidebands inside a carrier band, which do not move under load but follow the
          illumination and an elastomer's glow.
        """
        h, w = (int(s) for s in frame_shape)
        m, n = (int(s) for s in crop_shape)
        if h % 2 or w % 2 or m % 2 or n % 2:
            raise ValueError(f"frame_shape {frame_shape} and crop_shape {crop_shape} must be even.")
        if m + 2 > h or n + 2 > w:
            raise ValueError(f"crop_shape {crop_shape} too large for frame_shape {frame_shape}.")
        if not 0 < rolloff <= 1:
            raise ValueError(f"rolloff must be in (0, 1], got {rolloff}.")
        if not 0 < band_fraction < 1:
            raise ValueError(f"band_fraction must be in (0, 1), got {band_fraction}.")
        if not 0 < centroid_taper <= 0.5:
            raise ValueError(f"centroid_taper must be in (0, 0.5], got {centroid_taper}.")
        try:
            k_nominal = np.asarray(wavevectors, dtype=np.float64)
            pixel = 1.0 / float(px_per_mm)
        except jax.errors.ConcretizationTypeError as e:
            raise ValueError("Demodulator needs concrete wavevectors and px_per_mm.") from e
        if k_nominal.ndim != 2 or k_nominal.shape[1] != 2 or k_nominal.shape[0] < 1:
            raise ValueError(f"wavevectors must have shape (families, 2), got {k_nominal.shape}.")
        k_norm = np.hypot(k_nominal[:, 0], k_nominal[:, 1])
        radius = band_fraction * k_norm
        dc_radius = band_fraction * k_norm.min()
        if band_radius is not None:
            given = np.broadcast_to(np.asarray(band_radius, dtype=np.float64), radius.shape)
            radius = np.where(np.isnan(given), radius, given)
            if not np.all(radius > 0):
                raise ValueError(f"band_radius must be positive, got {band_radius}.")
        notch_radius = (
            np.zeros_like(radius)
            if notch_radius is None
            else np.broadcast_to(np.asarray(notch_radius, float), radius.shape)
        )
        notches = [[] for _ in radius] if notches is None else [np.asarray(c, float).reshape(-1, 2) for c in notches]
        if len(notches) != len(radius):
            raise ValueError(f"notches needs one list of wavevectors per family, got {len(notches)} for {len(radius)}.")
        peak = radius.copy()
        if peak_radius is not None:
            given = np.broadcast_to(np.asarray(peak_radius, dtype=np.float64), radius.shape)
            peak = np.where(np.isnan(given), radius, np.minimum(given, radius))
        _check_bands(k_nominal, radius, dc_radius)

        dk_col = 2 * math.pi / (w * pixel)  # kx per column bin (rad/mm)
        dk_row = 2 * math.pi / (h * pixel)  # -ky per row bin
        pixel0 = np.array([-(w - 1) / 2 * pixel, (h - 1) / 2 * pixel])  # pixel (0, 0), mm
        coarse_x = (np.arange(n) - (n - 1) / 2) * (w * pixel / n)
        coarse_y = ((m - 1) / 2 - np.arange(m)) * (h * pixel / m)
        coarse0 = np.array([coarse_x[0], coarse_y[0]])
        normalisation = m * n / (h * w)
        dkx = np.broadcast_to((np.arange(n)[None, :] - n // 2) * dk_col, (m, n))
        dky = np.broadcast_to(-(np.arange(m)[:, None] - m // 2) * dk_row, (m, n))

        crop_starts, bin_k, transfer, support = [], [], [], []
        for k_f, radius_f, peak_f, notches_f, notch_f in zip(k_nominal, radius, peak, notches, notch_radius):
            p0 = int(round(-k_f[1] / dk_row))
            q0 = int(round(k_f[0] / dk_col))
            row_start, col_start = p0 - m // 2, q0 - n // 2
            if max(abs(col_start - 1), abs(col_start + n)) > w // 2:
                raise ValueError(f"Wavevector {k_f} is too close to the Nyquist frequency.")
            k0 = np.array([q0 * dk_col, -p0 * dk_row])
            window = _raised_cosine(np, np.hypot(k0[0] + dkx - k_f[0], k0[1] + dky - k_f[1]), radius_f, rolloff)
            for centre in notches_f:
                window = window * (
                    1 - _raised_cosine(np, np.hypot(k0[0] + dkx - centre[0], k0[1] + dky - centre[1]), notch_f, rolloff)
                )
            # The support must stay clear of the window's border: no aliasing on the coarse
            # grid, and an exactly zero Nyquist row and column for spectral derivatives.
            if window[[0, -1]].any() or window[:, [0, -1]].any():
                raise DemodulationWindowTooSmall(
                    f"The band of wavevector {k_f} does not fit in crop_shape {crop_shape}; "
                    "increase crop_shape or decrease band_fraction."
                )
            # DFT phases refer to pixel (0, 0); refer them to the image centre, then shift
            # the inverse FFT's origin to coarse sample (0, 0).
            phase = -((k0[0] + dkx) * pixel0[0] + (k0[1] + dky) * pixel0[1]) + dkx * coarse0[0] + dky * coarse0[1]
            crop_starts.append((row_start, col_start))
            bin_k.append(k0)
            transfer.append(window * np.exp(1j * phase) * normalisation)
            support.append((window > 0) & (np.hypot(k0[0] + dkx - k_f[0], k0[1] + dky - k_f[1]) < peak_f))
        transfer = np.stack(transfer)
        tones = _tone_windows(np, k_nominal, crop_starts, (h, w), (m, n), np.float64(pixel), np.complex128)
        envelope = np.abs(_band_pass(np, tones, transfer, apodize, h, w))
        if envelope.min() < 1e-6 * envelope.max():
            raise DemodulationWindowTooSmall(f"The fringe envelope vanishes; increase crop_shape {crop_shape}.")

        # The brightness band: the same construction around DC.
        dc_window = _raised_cosine(np, np.hypot(dkx, dky), dc_radius, rolloff)
        if dc_window[[0, -1]].any() or dc_window[:, [0, -1]].any():
            raise DemodulationWindowTooSmall(f"The brightness band does not fit in crop_shape {crop_shape}.")
        dc_transfer = dc_window * np.exp(1j * (dkx * (coarse0[0] - pixel0[0]) + dky * (coarse0[1] - pixel0[1])))
        dc_transfer = dc_transfer * normalisation
        dc_starts = [(-(m // 2), -(n // 2))]
        dc_tone = _tone_windows(np, np.zeros((1, 2)), dc_starts, (h, w), (m, n), np.float64(pixel), np.complex128)
        # Natural bin order makes the inverse FFT carry a (-1)^(r+s) sign pattern.
        parity = (-1.0) ** (np.arange(m)[:, None] + np.arange(n)[None, :])
        dc_envelope = parity * np.real(_band_pass(np, dc_tone[0], dc_transfer, apodize, h, w))
        # A long moiré period (a unit whose pitches came out closer than drawn) narrows the
        # brightness band to a few bins, and its band-passed apodization then rings below
        # zero at the border. The brightness is a nuisance there: floor the envelope so that
        # those samples carry next to no weight instead of a division by zero or a sign flip.
        dc_envelope = np.maximum(dc_envelope, _ENVELOPE_FLOOR * dc_envelope.max())

        self.frame_shape = (h, w)
        self.crop_shape = (m, n)
        self.crop_starts = tuple(crop_starts)
        self.apodize = bool(apodize)
        self.px_per_mm = jnp.asarray(1.0 / pixel, dtype=float)
        self.wavevectors = jnp.asarray(k_nominal, dtype=float)
        self.bin_wavevectors = jnp.asarray(np.stack(bin_k), dtype=float)
        self.band_radius = jnp.asarray(radius, dtype=float)
        self.peak_radius = jnp.asarray(peak, dtype=float)
        self.notches = tuple(tuple(tuple(float(v) for v in c) for c in n) for n in notches)
        self.notch_radius = jnp.asarray(notch_radius, dtype=float)
        self.brightness_band_radius = jnp.asarray(dc_radius, dtype=float)
        self.rolloff = jnp.asarray(rolloff, dtype=float)
        self.coarse_x = jnp.asarray(coarse_x, dtype=float)
        self.coarse_y = jnp.asarray(coarse_y, dtype=float)
        self.fringe_envelope = jnp.asarray(envelope, dtype=float)
        self.fringe_transfer = jnp.asarray(transfer, dtype=complex)
        self.brightness_envelope = jnp.asarray(dc_envelope, dtype=float)
        self.brightness_transfer = jnp.asarray(dc_transfer, dtype=complex)
        self.brightness_normalisation = jnp.asarray(parity / dc_envelope, dtype=float)
        self.centroid_weights = (
            jnp.asarray(_tukey(h, centroid_taper), dtype=float),
            jnp.asarray(_tukey(w, centroid_taper), dtype=float),
        )
        self.peak_support = jnp.asarray(np.stack(support))

    @property
    def num_families(self) -> int:
        """Number of fringe families."""
        return len(self.crop_starts)

    def coarse_grid(self) -> tuple[Float[Array, "m n"], Float[Array, "m n"]]:
        """Coordinates `(x, y)` (mm) of every coarse sample, each of shape `(m, n)`."""
        m, n = self.crop_shape
        return (
            jnp.broadcast_to(self.coarse_x[None, :], (m, n)),
            jnp.broadcast_to(self.coarse_y[:, None], (m, n)),
        )

    def transfer_function(self, kx: Float[ArrayLike, "*k"], ky: Float[ArrayLike, "*k"]) -> Float[Array, "families ..."]:
        r"""Band window $W(|\mathbf{k}-\mathbf{K}_f|)$ of every family at wavevectors `(kx, ky)`.

        **Arguments:**

        - `kx`, `ky`: wavevector components (rad/mm), same shape.

        **Returns:**

        The window values, one leading row per family.
        """
        kx, ky = jnp.asarray(kx), jnp.asarray(ky)
        extra = (None,) * kx.ndim
        distance = jnp.hypot(
            kx[None] - self.wavevectors[(slice(None), 0, *extra)],
            ky[None] - self.wavevectors[(slice(None), 1, *extra)],
        )
        window = _raised_cosine(jnp, distance, self.band_radius[(slice(None), *extra)], self.rolloff)
        cuts = []
        for family, centres in enumerate(self.notches):
            cut = jnp.ones_like(kx)
            for centre in centres:
                cut = cut * (
                    1
                    - _raised_cosine(
                        jnp, jnp.hypot(kx - centre[0], ky - centre[1]), self.notch_radius[family], self.rolloff
                    )
                )
            cuts.append(cut)
        return window * jnp.stack(cuts)

    def brightness_transfer_function(
        self, kx: Float[ArrayLike, "*k"], ky: Float[ArrayLike, "*k"]
    ) -> Float[Array, "*k"]:
        """Low-pass window of the brightness band at wavevectors `(kx, ky)` (rad/mm)."""
        distance = jnp.hypot(jnp.asarray(kx), jnp.asarray(ky))
        return _raised_cosine(jnp, distance, self.brightness_band_radius, self.rolloff)

    def apodization(self, rows: int, cols: int) -> Float[Array, "rows cols"]:
        """The bands' apodization on a cell-centred `rows x cols` grid over the frame (ones if off)."""
        if not self.apodize:
            return jnp.ones((rows, cols))
        row = jnp.sin(math.pi * jnp.arange(0.5, rows) / rows) ** 2
        col = jnp.sin(math.pi * jnp.arange(0.5, cols) / cols) ** 2
        return row[:, None] * col[None, :]

    def _demodulate(self, frame, reference_wavevector=None):
        _check_shape("frame", frame.shape, self.frame_shape)
        return _demodulate(jnp, self, jnp.fft.rfft2(frame), reference_wavevector)

    @eqx.filter_jit
    def __call__(
        self, frame: Float[Array, "h w"], reference_wavevector: Float[Array, "families 2"] | None = None
    ) -> FringeFields:
        """Demodulate one frame.

        **Arguments:**

        - `frame`: rectified grayscale frame of shape `frame_shape`, float32 or float64.
        - `reference_wavevector`: normalise to unit fringes at these wavevectors instead of
          the frame's own spectral peaks. A unit's stream demodulated against its reference
          frame's wavevectors goes through one fixed linear operator, so differences of
          fields are differences of frames.

        **Returns:**

        A [`moirejax.FringeFields`][] on the coarse grid, in the frame's precision.
        """
        out = self._demodulate(frame, reference_wavevector)
        return FringeFields(fringe=out.fringe, brightness=out.brightness, reference_wavevector=out.reference_k)

    def _reference_response(self, reference_k, dtype):
        """The band-passed unit fringe at `reference_k`, before normalisation."""
        real_dtype = _real_dtype(jnp, dtype)
        pixel = 1 / self.px_per_mm.astype(real_dtype)
        tones = _tone_windows(jnp, reference_k, self.crop_starts, self.frame_shape, self.crop_shape, pixel, dtype)
        h, w = self.frame_shape
        return _band_pass(jnp, tones, self.fringe_transfer.astype(dtype), self.apodize, h, w)

    def _grid_origin(self, rows, cols, dtype):
        """Position (mm) of sample (0, 0) of a cell-centred `rows x cols` grid over the frame."""
        h, w = self.frame_shape
        pixel = 1 / self.px_per_mm.astype(dtype)
        return -(cols - 1) / 2 * (w / cols) * pixel, (rows - 1) / 2 * (h / rows) * pixel

    def _grid_axes(self, rows, cols, dtype):
        """The x (columns) and y (rows) positions, mm, of a cell-centred `rows x cols` grid."""
        h, w = self.frame_shape
        grid_x0, grid_y0 = self._grid_origin(rows, cols, dtype)
        pixel = 1 / self.px_per_mm.astype(dtype)
        grid_x = grid_x0 + jnp.arange(cols, dtype=dtype) * (w / cols) * pixel
        grid_y = grid_y0 - jnp.arange(rows, dtype=dtype) * (h / rows) * pixel
        return grid_x, grid_y

    def _reference_ramp(self, reference_wavevector, dtype):
        """The nominal wavevectors, the reference ones (the nominal for `None`), and the phase
        ramp on the coarse grid that refers a band from the first to the second."""
        nominal = self.wavevectors.astype(dtype)
        reference_k = nominal if reference_wavevector is None else reference_wavevector.astype(dtype)
        ramp = _ramp(jnp, reference_k - nominal, self.coarse_x.astype(dtype), self.coarse_y.astype(dtype))
        return nominal, reference_k, ramp

    def _window_offsets(self, dtype):
        """Wavevector offsets of the window bins from the centre bin, natural order (rad/mm)."""
        h, w = self.frame_shape
        m, n = self.crop_shape
        pixel = 1 / self.px_per_mm.astype(dtype)
        dkx = (jnp.arange(n, dtype=dtype) - n // 2) * (2 * math.pi / w) / pixel
        dky = -(jnp.arange(m, dtype=dtype) - m // 2) * (2 * math.pi / h) / pixel
        return dkx, dky

    def _grid_band_pass(self, field, bin_wavevectors, transfer):
        """`ifft2(transfer * window)` for fields on any cell-centred grid over the frame.

        The same as the measurement's path (with the apodization applied in space), with the
        DFT phases and normalisation of `transfer` (made for frame pixel (0, 0) and h*w
        samples) referred to this grid's sample (0, 0) and sample count.
        """
        _, rows, cols = field.shape
        m, n = self.crop_shape
        if rows < m or cols < n:
            raise ValueError(f"field shape {field.shape} has fewer samples than crop_shape {self.crop_shape}.")
        h, w = self.frame_shape
        dtype = field.dtype
        real_dtype = _real_dtype(jnp, dtype)
        spectrum = jnp.fft.fft2(field * self.apodization(rows, cols).astype(dtype)[None])
        windows = _wrapped(jnp, _wrapped(jnp, spectrum, -(m // 2), m, 1), -(n // 2), n, 2)
        regrid = self._regrid(bin_wavevectors, rows, cols, real_dtype)
        return jnp.fft.ifft2(transfer.astype(dtype) * regrid * windows)

    def _regrid(self, bin_wavevectors, rows, cols, real_dtype):
        """The DFT phases and normalisation that refer a band made for frame pixel (0, 0) and
        h*w samples to sample (0, 0) and the sample count of a `rows x cols` grid."""
        h, w = self.frame_shape
        frame_x0, frame_y0 = self._grid_origin(h, w, real_dtype)
        grid_x0, grid_y0 = self._grid_origin(rows, cols, real_dtype)
        dkx, dky = self._window_offsets(real_dtype)
        k_bin = bin_wavevectors.astype(real_dtype)
        return _expi(
            jnp,
            (k_bin[:, 0] * frame_x0 + k_bin[:, 1] * frame_y0)[:, None, None]
            + (dkx * (frame_x0 - grid_x0))[None, None, :]
            + (dky * (frame_y0 - grid_y0))[None, :, None],
        ) * (h * w / (rows * cols))

    def filter_baseband(
        self,
        field: Complex[Array, "families rows cols"],
        reference_wavevector: Float[Array, "families 2"] | None = None,
    ) -> Complex[Array, "families m n"]:
        r"""Apply the measurement's fringe band-pass to a predicted baseband field.

        For a frame whose family-$f$ component is
        $\mathrm{Re}[2 a_f(\mathbf{x}) e^{i\mathbf{K}_f\cdot\mathbf{x}}]$, `self(frame).fringe[f]`
        equals `filter_baseband(a, self(frame).reference_wavevector)[f]` up to the leakage of
        the conjugate term: the same linear operator (apodization, band window, normalisation)
        on the same finite field of view. Use it to compare a model's predicted
        $a_f = \tfrac12 B m_f e^{i\psi_f}$ with a measurement.

        **Arguments:**

        - `field`: baseband field per family on a cell-centred grid covering the frame:
          `frame_shape` itself (exact), or any grid with at least `crop_shape` samples that
          resolves the band and the apodization (128 x 128 for a 512 x 512 frame agrees
          to ~1e-6 of the fringe amplitude).
        - `reference_wavevector`: the measurement's `reference_wavevector`; the nominal
          wavevectors if omitted.

        **Returns:**

        The filtered field on the coarse grid.
        """
        families, rows, cols = field.shape
        if families != self.num_families:
            raise ValueError(f"field shape {field.shape} needs {self.num_families} families.")
        real_dtype = _real_dtype(jnp, field.dtype)
        nominal, reference_k, ramp = self._reference_ramp(reference_wavevector, real_dtype)
        grid_x, grid_y = self._grid_axes(rows, cols, real_dtype)
        # The sub-bin offset K - k_bin turns this grid's DFT bins into the window's offsets.
        carrier = _ramp(jnp, nominal - self.bin_wavevectors.astype(real_dtype), grid_x, grid_y)
        raw = self._grid_band_pass(field * carrier.astype(field.dtype), self.bin_wavevectors, self.fringe_transfer)
        return raw / self._reference_response(reference_k, field.dtype) * ramp

    def smallest_band_grid(self, families: tuple[int, ...] | None = None) -> int:
        r"""The smallest square grid (a multiple of 16) whose spectrum holds every band window
        away from its Nyquist bins: the coarsest grid [`real_band_pass`][moirejax.Demodulator.real_band_pass]
        accepts (a band of wavevector $\mathbf K$ needs about $|\mathbf K|/\Delta k$ + `crop_shape`/2
        bins each side)."""
        m, n = self.crop_shape
        families = tuple(range(self.num_families)) if families is None else families
        half = max(
            max(row_start + m, 1 - row_start, col_start + n, 1 - col_start)
            for row_start, col_start in (*(self.crop_starts[f] for f in families), (-(m // 2), -(n // 2)))
        )
        return 16 * math.ceil(2 * half / 16)

    def real_band_pass(
        self,
        shape: tuple[int, int],
        reference_wavevector: Float[Array, "families 2"] | None = None,
        dtype=None,
        families: tuple[int, ...] | None = None,
    ) -> "RealBandPass":
        r"""[`filter_baseband`][moirejax.Demodulator.filter_baseband] and
        [`filter_brightness`][moirejax.Demodulator.filter_brightness] at once, for a real field
        on a `shape` cell-centred grid over the frame, with everything but the field precomputed.

        A real field $F$ holds its family-$f$ band as $a_f e^{i\mathbf K_f\cdot\mathbf x}$ +
        c.c.; `filter_baseband(F e^{-i K.x})` moves it to baseband with a full-size complex
        multiply and FFT per family. Here one `rfft2` of $F$ serves every band: the bin
        $\mathbf K_f$ lies on is a whole bin of this grid too (it covers the same field), so the
        shift is a window offset and a constant phase. A forward model that evaluates many
        fields on one grid (an inversion's model evaluations) builds this once.

        **Arguments:**

        - `shape`: `(rows, cols)` of the field's grid; at least `crop_shape`, and fine enough
          that every band lies inside its Nyquist limits.
        - `reference_wavevector`: the measurement's `reference_wavevector`; the nominal
          wavevectors if omitted.
        - `dtype`: real precision of the fields (default: JAX's default float).
        - `families`: the fringe families to pass (default all); the upper grating's carriers
          lie far above any model grid's Nyquist limit and reach a model through
          [`baseband_pass`][moirejax.Demodulator.baseband_pass] instead.

        **Returns:** a [`RealBandPass`][moirejax.observe._observables.RealBandPass]; call it with the
        field for `(fringe, brightness)` on the coarse grid.
        """
        families = tuple(range(self.num_families)) if families is None else tuple(families)
        rows, cols = (int(n) for n in shape)
        m, n = self.crop_shape
        h, w = self.frame_shape
        if rows < m or cols < n:
            raise ValueError(f"grid {shape} has fewer samples than crop_shape {self.crop_shape}.")
        # The DC band last; every window must stay clear of this grid's Nyquist bins.
        starts = (*(self.crop_starts[f] for f in families), (-(m // 2), -(n // 2)))
        for row_start, col_start in starts:
            inside_rows = -(rows // 2) < row_start and row_start + m <= rows // 2
            inside_cols = -(cols // 2) < col_start and col_start + n <= cols // 2
            if not (inside_rows and inside_cols):
                raise ValueError(f"grid {shape} is too coarse for the bands of this demodulator; refine it.")
        real_dtype = jnp.dtype(jnp.result_type(float) if dtype is None else dtype)
        complex_dtype = np.complex64 if real_dtype == np.float32 else np.complex128
        select = np.asarray(families, dtype=int)
        _, reference_k, ramp = self._reference_ramp(reference_wavevector, real_dtype)
        frame_x0, frame_y0 = self._grid_origin(h, w, real_dtype)
        grid_x0, grid_y0 = self._grid_origin(rows, cols, real_dtype)
        dkx, dky = self._window_offsets(real_dtype)
        k_bin = jnp.concatenate([self.bin_wavevectors.astype(real_dtype)[select], jnp.zeros((1, 2), real_dtype)])
        # As `_grid_band_pass`: DFT phases referred from this grid's sample (0, 0) to the
        # frame's pixel (0, 0) and sample counts to the frame's; and the shift to bin k_bin,
        # exp(-i k_bin.x) in space, is exp(-i k_bin.x_00) times a window offset.
        phase = (k_bin[:, 0] * (frame_x0 - grid_x0) + k_bin[:, 1] * (frame_y0 - grid_y0))[:, None, None]
        phase = phase + (dkx * (frame_x0 - grid_x0))[None, None, :] + (dky * (frame_y0 - grid_y0))[None, :, None]
        transfer = jnp.concatenate([self.fringe_transfer[select], self.brightness_transfer[None]]).astype(complex_dtype)
        spectral = transfer * _expi(jnp, phase) * (h * w / (rows * cols))
        return RealBandPass(
            shape=(rows, cols),
            crop_shape=(m, n),
            window_starts=tuple(starts),
            apodization=self.apodization(rows, cols).astype(real_dtype),
            spectral=spectral,
            spatial=(ramp / self._reference_response(reference_k, complex_dtype))[select],
            brightness_normalisation=self.brightness_normalisation.astype(real_dtype),
        )

    def baseband_pass(
        self,
        shape: tuple[int, int],
        families: tuple[int, ...],
        reference_wavevector: Float[Array, "families 2"] | None = None,
        dtype=None,
        blur: Callable[[Array], Array] | None = None,
    ) -> "BasebandPass":
        """[`filter_baseband`][moirejax.Demodulator.filter_baseband] for the `families` given, on
        one `shape` cell-centred grid over the frame, with everything but the field precomputed.

        A forward model that predicts the complex baseband of a band whose centre lies above
        its grid's Nyquist limit (the upper grating's carrier) builds this once and calls it
        with a `(len(families), rows, cols)` field for the filtered field on the coarse grid.
        `blur`, a function of the absolute wavenumber (rad/mm), is a transfer the frame went
        through before demodulation (a lens PSF), applied at each bin's own wavenumber.
        """
        rows, cols = (int(n) for n in shape)
        families = tuple(int(f) for f in families)
        select = np.asarray(families, dtype=int)
        m, n = self.crop_shape
        if rows < m or cols < n:
            raise ValueError(f"grid {shape} has fewer samples than crop_shape {self.crop_shape}.")
        real_dtype = jnp.dtype(jnp.result_type(float) if dtype is None else dtype)
        complex_dtype = np.complex64 if real_dtype == np.float32 else np.complex128
        nominal, reference_k, ramp = self._reference_ramp(reference_wavevector, real_dtype)
        grid_x, grid_y = self._grid_axes(rows, cols, real_dtype)
        regrid = self._regrid(self.bin_wavevectors[select], rows, cols, real_dtype)
        spectral = self.fringe_transfer[select].astype(complex_dtype) * regrid
        if blur is not None:
            k_bin = self.bin_wavevectors.astype(real_dtype)[select]
            dkx, dky = self._window_offsets(real_dtype)
            wavenumber = jnp.hypot(
                k_bin[:, 0, None, None] + dkx[None, None, :], k_bin[:, 1, None, None] + dky[None, :, None]
            )
            spectral = spectral * blur(wavenumber).astype(complex_dtype)
        return BasebandPass(
            shape=(rows, cols),
            crop_shape=(m, n),
            carrier=_ramp(jnp, (nominal - self.bin_wavevectors.astype(real_dtype))[select], grid_x, grid_y),
            apodization=self.apodization(rows, cols).astype(real_dtype),
            spectral=spectral,
            spatial=(ramp / self._reference_response(reference_k, complex_dtype))[select],
        )

    def filter_brightness(self, field: Float[Array, "rows cols"]) -> Float[Array, "m n"]:
        """Apply the measurement's brightness low-pass to a predicted brightness field.

        **Arguments:**

        - `field`: brightness on a cell-centred grid covering the frame: `frame_shape`
          itself (exact), or any grid with at least `crop_shape` samples that resolves the
          band and the apodization.

        **Returns:**

        The filtered brightness on the coarse grid; equal to `self(frame).brightness` when
        `field` is the frame.
        """
        complex_dtype = np.complex64 if field.dtype == np.float32 else np.complex128
        band = self._grid_band_pass(
            field.astype(complex_dtype)[None], jnp.zeros((1, 2)), self.brightness_transfer[None]
        )
        return jnp.real(band[0]) * self.brightness_normalisation.astype(field.dtype)


class RealBandPass(eqx.Module):
    """A [`Demodulator`][moirejax.Demodulator]'s band-passes for real fields on one grid
    (see [`Demodulator.real_band_pass`][moirejax.Demodulator.real_band_pass]): call it
    with a `(rows, cols)` field for its `(fringe, brightness)` on the coarse grid."""

    shape: tuple[int, int] = eqx.field(static=True)
    crop_shape: tuple[int, int] = eqx.field(static=True)
    window_starts: tuple[tuple[int, int], ...] = eqx.field(static=True)
    apodization: Float[Array, "rows cols"]
    spectral: Complex[Array, "bands m n"]
    spatial: Complex[Array, "families m n"]
    brightness_normalisation: Float[Array, "m n"]

    def __call__(self, field: Float[Array, "rows cols"]) -> tuple[Complex[Array, "families m n"], Float[Array, "m n"]]:
        _check_shape("field", field.shape, self.shape)
        m, n = self.crop_shape
        spectrum = jnp.fft.rfft2(field * self.apodization)
        windows = jnp.stack([_crop(jnp, spectrum, p, q, m, n) for p, q in self.window_starts])
        bands = jnp.fft.ifft2(self.spectral * windows)
        return bands[:-1] * self.spatial, jnp.real(bands[-1]) * self.brightness_normalisation


class BasebandPass(eqx.Module):
    """A [`Demodulator`][moirejax.Demodulator]'s fringe band-pass for complex baseband fields of
    some of its families on one grid (see
    [`Demodulator.baseband_pass`][moirejax.Demodulator.baseband_pass]): call it with a
    `(families, rows, cols)` field for the filtered fields on the coarse grid."""

    shape: tuple[int, int] = eqx.field(static=True)
    crop_shape: tuple[int, int] = eqx.field(static=True)
    carrier: Complex[Array, "families rows cols"]
    apodization: Float[Array, "rows cols"]
    spectral: Complex[Array, "families m n"]
    spatial: Complex[Array, "families m n"]

    def __call__(self, field: Complex[Array, "families rows cols"]) -> Complex[Array, "families m n"]:
        _check_shape("field", field.shape[1:], self.shape)
        m, n = self.crop_shape
        taper = self.carrier * self.apodization.astype(self.carrier.dtype)[None]
        spectrum = jnp.fft.fft2(field * taper.astype(field.dtype))
        windows = _wrapped(jnp, _wrapped(jnp, spectrum, -(m // 2), m, 1), -(n // 2), n, 2)
        return jnp.fft.ifft2(self.spectral.astype(field.dtype) * windows) * self.spatial.astype(field.dtype)


class FringeObservables(eqx.Module):
    r"""Local moire observables on the coarse grid, one leading row per family.

    **Fields:**

    - `phase`: wrapped phase $\psi_f = \arg z_f$ (rad), relative to $\mathbf{K}_f\cdot\mathbf{x}$.
    - `phase_gradient`: $\nabla\psi_f$, components `[d/dx, d/dy]` (rad/mm).
    - `wavevector`: local moire wavevector $\mathbf{K}_f + \nabla\psi_f$, `[kx, ky]` (rad/mm).
    - `orientation`: local $\theta = \mathrm{atan2}(k_y, k_x)$ (rad).
    - `period`: local $\Lambda = 2\pi/|\mathbf{K}_f + \nabla\psi_f|$ (mm).
    - `contrast`: fringe visibility $m_f = 2|z_f|/B$.
    """

    phase: Float[Array, "families m n"]
    phase_gradient: Float[Array, "families 2 m n"]
    wavevector: Float[Array, "families 2 m n"]
    orientation: Float[Array, "families m n"]
    period: Float[Array, "families m n"]
    contrast: Float[Array, "families m n"]


def _trig_gradient(v, dkx, dky):
    r"""`Im(conj(v) grad v)` (shape `families 2 m n`) and `|v|^2` for `v = ifft2(window)`.

    `v` samples $(-1)^{r+s} u(\mathbf{x})$ with $u$ the trigonometric polynomial over the
    window bins (offsets `dkx`, `dky` from the centre bin), so the gradient is exact in
    Fourier space, and the sign pattern cancels in `conj(v) grad v`.
    """
    coefficients = jnp.fft.fft2(v)
    dkx, dky = dkx.astype(coefficients.dtype), dky.astype(coefficients.dtype)
    grad_x = jnp.fft.ifft2(1j * dkx[None, None, :] * coefficients)
    grad_y = jnp.fft.ifft2(1j * dky[None, :, None] * coefficients)
    cross = jnp.stack([jnp.imag(jnp.conj(v) * grad_x), jnp.imag(jnp.conj(v) * grad_y)], axis=1)
    return cross, jnp.abs(v) ** 2


def _phase_gradient_terms(demodulator, raw, reference, reference_k):
    r"""Terms of $\nabla\psi = \mathrm{Im}(\bar v\nabla v)/|v|^2 - \nabla\arg v_\mathrm{ref} +
    (\mathbf{K}_\mathrm{ref} - \mathbf{K})$, from `fringe = raw / reference * ramp`.

    Returns `Im(conj(v) grad v)`, `|v|^2`, the reference's phase gradient (all per coarse
    sample) and the ramp's constant gradient (per family).
    """
    real_dtype = _real_dtype(jnp, raw.dtype)
    dkx, dky = demodulator._window_offsets(real_dtype)
    cross, power = _trig_gradient(raw, dkx, dky)
    reference_cross, reference_power = _trig_gradient(reference, dkx, dky)
    ramp_gradient = reference_k - demodulator.wavevectors.astype(real_dtype)
    return cross, power, reference_cross / reference_power[:, None], ramp_gradient


def _unnormalise(demodulator, fields):
    """`(raw, reference)` with `fields.fringe = raw / reference * ramp`."""
    dtype = fields.fringe.dtype
    real_dtype = _real_dtype(jnp, dtype)
    reference_k = fields.reference_wavevector.astype(real_dtype)
    reference = demodulator._reference_response(reference_k, dtype)
    offset = reference_k - demodulator.wavevectors.astype(real_dtype)
    ramp = _ramp(jnp, offset, demodulator.coarse_x.astype(real_dtype), demodulator.coarse_y.astype(real_dtype))
    return fields.fringe * reference * jnp.conj(ramp), reference


@eqx.filter_jit
def fringe_observables(demodulator: Demodulator, fields: FringeFields) -> FringeObservables:
    r"""Local phase, phase gradient, orientation, period and contrast of every family.

    The phase gradient comes from $z$ without unwrapping,
    $\nabla\psi = \mathrm{Im}(\bar z\nabla z)/|z|^2$, with $\nabla z$ taken in Fourier space
    (exact for the band-limited coarse field). It is meaningless where the fringes vanish.

    **Arguments:**

    - `demodulator`: the [`moirejax.Demodulator`][] that produced `fields`.
    - `fields`: its output.

    **Returns:**

    A [`moirejax.FringeObservables`][].
    """
    fringe = fields.fringe
    real_dtype = _real_dtype(jnp, fringe.dtype)
    tiny = jnp.finfo(real_dtype).tiny
    raw, reference = _unnormalise(demodulator, fields)
    cross, power, reference_gradient, ramp_gradient = _phase_gradient_terms(
        demodulator, raw, reference, fields.reference_wavevector.astype(real_dtype)
    )
    gradient = cross / (power[:, None] + tiny) - reference_gradient + ramp_gradient[:, :, None, None]
    wavevector = demodulator.wavevectors.astype(real_dtype)[:, :, None, None] + gradient
    return FringeObservables(
        phase=jnp.angle(fringe),
        phase_gradient=gradient,
        wavevector=wavevector,
        orientation=jnp.arctan2(wavevector[:, 1], wavevector[:, 0]),
        period=2 * math.pi / jnp.hypot(wavevector[:, 0], wavevector[:, 1]),
        contrast=2 * jnp.abs(fringe) / jnp.maximum(fields.brightness, tiny)[None],
    )


class FrameSummary(eqx.Module):
    r"""Per-frame observables (Table I of the MoireTac paper), per family where relevant.

    **Fields:**

    - `mean_phase`: circular mean of $\psi_f$ weighted by the envelope (rad).
    - `mean_phase_gradient`: mean of $\nabla\psi_f$ weighted by the band-passed fringe power,
      `[d/dx, d/dy]` (rad/mm).
    - `wavevector`: spectral peak $\mathbf{K}$ of each family, refined to sub-bin (rad/mm).
    - `orientation`: $\theta = \mathrm{atan2}(K_y, K_x)$ of the peak (rad).
    - `period`: $\Lambda = 2\pi/|\mathbf{K}|$ of the peak (mm).
    - `contrast`: envelope-weighted mean fringe visibility $2|z_f|/B$.
    - `mean_brightness`: mean frame brightness $I$.
    - `brightness_centroid`: $\mathbf{c} = [x, y]$ (mm) of the brightness above the baseline.
    - `rim_energy`: envelope-weighted mean squared gradient of the low-passed brightness
      above the baseline (squared frame units per mm^2).
    """

    mean_phase: Float[Array, " families"]
    mean_phase_gradient: Float[Array, "families 2"]
    wavevector: Float[Array, "families 2"]
    orientation: Float[Array, " families"]
    period: Float[Array, " families"]
    contrast: Float[Array, " families"]
    mean_brightness: Float[Array, ""]
    brightness_centroid: Float[Array, "2"]
    rim_energy: Float[Array, ""]


def _coarse_gradient(demodulator, field):
    """Spectral `[d/dx, d/dy]` of a real band-limited field on the coarse grid (per mm)."""
    h, w = demodulator.frame_shape
    m, n = demodulator.crop_shape
    dtype = field.dtype
    pixel = 1 / demodulator.px_per_mm.astype(dtype)
    # The coarse grid samples the frame's field at h/m and w/n pixels.
    kx, ky = wavenumber_grid((m, n), (h / m * pixel, w / n * pixel), real=True, dtype=dtype)
    coefficients = jnp.fft.rfft2(field)
    kx, ky = kx.astype(coefficients.dtype), ky.astype(coefficients.dtype)
    return (
        jnp.fft.irfft2(1j * kx[None, :] * coefficients, s=(m, n)),
        jnp.fft.irfft2(1j * ky[:, None] * coefficients, s=(m, n)),
    )


def _rim_energy(demodulator, change):
    r"""$\langle e^2|\nabla c|^2\rangle$ for a brightness change $c$ with envelope $e$, exactly.

    $c\,e$ (the band-passed apodized change) and $e$ are band-limited, so
    $e\nabla c = \nabla(c e) - c\nabla e$ is exact with spectral gradients; a uniform change
    gives zero.
    """
    envelope = demodulator.brightness_envelope.astype(change.dtype)
    raw_x, raw_y = _coarse_gradient(demodulator, change * envelope)
    envelope_x, envelope_y = _coarse_gradient(demodulator, envelope)
    return jnp.mean((raw_x - change * envelope_x) ** 2 + (raw_y - change * envelope_y) ** 2)


def _brightness_moments(demodulator, frame):
    """`[sum(w I), sum(x w I), sum(y w I)]` over the frame pixels with the centroid weights."""
    h, w = demodulator.frame_shape
    dtype = frame.dtype
    pixel = 1 / demodulator.px_per_mm.astype(dtype)
    x = (jnp.arange(w, dtype=dtype) - (w - 1) / 2) * pixel
    y = ((h - 1) / 2 - jnp.arange(h, dtype=dtype)) * pixel
    weight_rows, weight_cols = (weights.astype(dtype) for weights in demodulator.centroid_weights)
    column_sums = weight_rows @ frame
    row_sums = frame @ weight_cols
    return jnp.stack([column_sums @ weight_cols, column_sums @ (x * weight_cols), row_sums @ (y * weight_rows)])


class BrightnessBaseline(eqx.Module):
    """What [`moirejax.frame_summary`][] subtracts: the brightness of a no-contact frame.

    **Fields:**

    - `brightness`: its low-passed brightness on the coarse grid.
    - `moments`: its weighted brightness moments `[sum(w I), sum(x w I), sum(y w I)]`.
    """

    brightness: Float[Array, "m n"]
    moments: Float[Array, "3"]


@eqx.filter_jit
def brightness_baseline(demodulator: Demodulator, frame: Float[Array, "h w"]) -> BrightnessBaseline:
    """The [`moirejax.BrightnessBaseline`][] of a no-contact frame.

    **Arguments:**

    - `demodulator`: the device's [`moirejax.Demodulator`][].
    - `frame`: a frame without contact (an average of several is better).

    **Returns:**

    A [`moirejax.BrightnessBaseline`][].
    """
    return BrightnessBaseline(brightness=demodulator(frame).brightness, moments=_brightness_moments(demodulator, frame))


@eqx.filter_jit
def frame_summary(
    demodulator: Demodulator,
    frame: Float[Array, "h w"],
    baseline: BrightnessBaseline | None = None,
) -> FrameSummary:
    r"""Per-frame observables from one FFT of the frame.

    - Phase: circular mean of $z_f$ weighted by the envelope $|v_\mathrm{ref}|$; mean phase
      gradient weighted by the band-passed fringe power, so the border and regions without
      fringes count little.
    - Orientation and period: the spectral peak inside the family band of the raw DFT,
      refined to sub-bin precision with Jacobsen's three-bin estimator along each axis.
    - Brightness centroid $\mathbf{c} = \sum \mathbf{x}\,w\,(I - I_0) / \sum w\,(I - I_0)$
      over the frame pixels, with $I_0$ the baseline frame ($0$ without one) and $w$ the
      demodulator's separable Tukey weight (1 in the middle, tapering to 0 over
      `centroid_taper` of the width at each border); the image centre when the weighted
      brightness change is not positive. Moments of the full-resolution frame, not of the
      low-passed brightness: a contact feature narrower than a few fringe periods overlaps
      the fringe band in wavevector, so any band split misplaces it, while the smooth
      weight's first moments see only wavevectors near zero, where fringes modulated by a
      local contact contribute little (~0.03 mm for a 2 mm blob under 4 mm fringes). A
      change of the whole fringe field (a global phase or period change) does leak in, in
      proportion to the weight's Fourier transform at $\mathbf{K}_f$; a wider taper
      suppresses it more but biases off-centre features toward the centre.
    - Rim energy: $\langle e^2|\nabla(B - B_0)|^2\rangle$ over the coarse grid, weighted by
      the squared `brightness_envelope` $e$ so the noisy border counts little ($B_0 = 0$
      without a baseline), with exact spectral gradients of the band-passed brightness. The
      waveguided LED rim is a bright ring, i.e. strong brightness edges: the energy grows
      with the square of the ring's brightness and with its length, and a uniform
      brightness change adds nothing.

    **Arguments:**

    - `demodulator`: the device's [`moirejax.Demodulator`][].
    - `frame`: rectified frame of shape `frame_shape`.
    - `baseline`: from [`moirejax.brightness_baseline`][] of a no-contact frame.

    **Returns:**

    A [`moirejax.FrameSummary`][].
    """
    fringe, brightness, peaks, reference_k, raw, reference = demodulator._demodulate(frame)
    dtype = frame.dtype
    tiny = jnp.finfo(dtype).tiny

    cross, power, reference_gradient, ramp_gradient = _phase_gradient_terms(demodulator, raw, reference, reference_k)
    mean_gradient = jnp.sum(cross - power[:, None] * reference_gradient, axis=(2, 3)) / (
        jnp.sum(power, axis=(1, 2))[:, None] + tiny
    )
    envelope = jnp.abs(reference)

    moments = _brightness_moments(demodulator, frame)
    above = brightness
    if baseline is not None:
        moments = moments - baseline.moments.astype(dtype)
        above = brightness - baseline.brightness.astype(dtype)
    positive = moments[0] > 0
    centroid = jnp.where(positive, moments[1:] / jnp.where(positive, moments[0], 1), 0)

    return FrameSummary(
        mean_phase=jnp.angle(jnp.sum(envelope.astype(fringe.dtype) * fringe, axis=(1, 2))),
        mean_phase_gradient=mean_gradient + ramp_gradient,
        wavevector=peaks,
        orientation=jnp.arctan2(peaks[:, 1], peaks[:, 0]),
        period=2 * math.pi / jnp.hypot(peaks[:, 0], peaks[:, 1]),
        contrast=2
        * jnp.sum(envelope * jnp.abs(fringe), axis=(1, 2))
        / (jnp.sum(envelope * brightness[None], axis=(1, 2)) + tiny),
        mean_brightness=jnp.mean(frame),
        brightness_centroid=centroid,
        rim_energy=_rim_energy(demodulator, above),
    )


def white_noise_variance(frame: Float[Array, "h w"]) -> Float[Array, ""]:
    r"""Variance of the white part of a frame's pixel noise, estimated from the frame alone.

    Camera noise (shot, read, quantisation) spreads evenly over the frame's spectrum, while
    the gratings, their moiré and the brightness occupy a few lines and points of it. So
    the median power over the spectrum of the Hann-tapered frame (every third bin each way)
    is the noise's: for white noise of variance $\sigma^2$ each bin's power is exponential
    with mean $\sigma^2 \sum_x h(x)^2$, whose median is $\ln 2$ of that. The taper keeps the
    leakage of the strong lines to a few bins. Where shot noise varies across the frame this
    is the taper-weighted mean variance, which favours the brighter centre.
    """
    h, w = frame.shape
    dtype = frame.dtype
    taper = jnp.outer(jnp.hanning(h), jnp.hanning(w)).astype(dtype)
    spectrum = jnp.fft.rfft2((frame - jnp.mean(frame)) * taper)[::3, ::3]
    power = spectrum.real**2 + spectrum.imag**2
    return jnp.median(power) / (math.log(2) * jnp.sum(taper**2))


def white_noise_map(frame: Float[Array, "h w"], block: int = 32) -> Float[Array, "rows cols"]:
    r"""The variance of a frame's white pixel noise in each `block` × `block` square of it, by
    the estimator of [`white_noise_variance`][] (the median power of every third bin each
    way) applied to each square on its own; pixels beyond the last whole square are left out.

    Camera noise varies over a frame only as its brightness does, by a few times; a part of
    the frame whose pixels are corrupt (a transmission fault, a foreign patch pasted in)
    carries pixel-scale noise tens to hundreds of times the rest's. A single defective pixel
    counts as white noise too, but in one square only.

    In a square this small the fringes' spectral lines leak into a share of its bins, so the
    median can sit among them: an upper estimate, up to about twice the noise where strong
    fringes meet faint noise, the same for every square of like fringes.

    **Raises:** `ValueError` (trace time) for a frame smaller than one square.
    """
    h, w = frame.shape
    rows, cols = h // block, w // block
    if rows < 1 or cols < 1:
        raise ValueError(f"frame of shape {frame.shape} is smaller than one {block}x{block} square")
    dtype = frame.dtype
    squares = frame[: rows * block, : cols * block].reshape(rows, block, cols, block).transpose(0, 2, 1, 3)
    squares = squares - jnp.mean(squares, axis=(2, 3), keepdims=True)
    taper = jnp.outer(jnp.hanning(block), jnp.hanning(block)).astype(dtype)
    spectrum = jnp.fft.rfft2(squares * taper[None, None])[:, :, ::3, ::3]
    power = (spectrum.real**2 + spectrum.imag**2).reshape(rows, cols, -1)
    return jnp.median(power, axis=-1) / (math.log(2) * jnp.sum(taper**2))


class NumpyDemodulator:
    """Plain numpy/OpenCV implementation of [`moirejax.Demodulator`][]: the latency floor.

    The same algorithm (shared code, `xp = numpy`) and the same transfer arrays; the spectrum
    comes from OpenCV's row DFTs followed by column FFTs of only the columns the windows
    need.
    """

    def __init__(self, demodulator: Demodulator, dtype=np.float32):
        """**Arguments:**

        - `demodulator`: the JAX demodulator whose geometry and windows to copy.
        - `dtype`: `numpy.float32` or `numpy.float64`, the precision of the frames.
        """
        self.dtype = np.dtype(dtype)
        complex_dtype = np.result_type(self.dtype, np.complex64)
        self.frame_shape = demodulator.frame_shape
        self.crop_shape = demodulator.crop_shape
        self.crop_starts = demodulator.crop_starts
        self.apodize = demodulator.apodize
        self.px_per_mm = np.asarray(demodulator.px_per_mm, dtype=self.dtype)
        self.wavevectors = np.asarray(demodulator.wavevectors, dtype=self.dtype)
        self.band_radius = np.asarray(demodulator.band_radius, dtype=self.dtype)
        self.peak_radius = np.asarray(demodulator.peak_radius, dtype=self.dtype)
        self.coarse_x = np.asarray(demodulator.coarse_x, dtype=self.dtype)
        self.coarse_y = np.asarray(demodulator.coarse_y, dtype=self.dtype)
        self.fringe_transfer = np.asarray(demodulator.fringe_transfer).astype(complex_dtype)
        self.brightness_transfer = np.asarray(demodulator.brightness_transfer).astype(complex_dtype)
        self.brightness_normalisation = np.asarray(demodulator.brightness_normalisation, dtype=self.dtype)
        self.peak_support = np.asarray(demodulator.peak_support)
        m, n = self.crop_shape
        widest = max(max(abs(q - 1), abs(q + n)) for _, q in self.crop_starts)
        self.columns = max(widest, n // 2) + 1

    def __call__(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Demodulate one frame.

        **Arguments:**

        - `frame`: `(h, w)` frame.

        **Returns:**

        `(fringe, brightness, reference_wavevector)`, as the fields of
        [`moirejax.FringeFields`][].
        """
        _check_shape("frame", frame.shape, self.frame_shape)
        h, w = self.frame_shape
        frame = np.asarray(frame, dtype=self.dtype)
        # Row DFTs in OpenCV's packed layout: Re0, Re1, Im1, ..., Re(w/2).
        packed = cv2.dft(frame, flags=cv2.DFT_ROWS)
        complex_dtype = self.fringe_transfer.dtype
        columns = np.empty((self.columns, h), dtype=complex_dtype)
        columns[0] = packed[:, 0]
        inner = min(self.columns - 1, w // 2 - 1)
        columns[1 : inner + 1] = packed[:, 1 : 2 * inner + 1].view(complex_dtype).T
        if self.columns - 1 == w // 2:
            columns[-1] = packed[:, -1]
        spectrum = np.fft.fft(columns, axis=1).T
        out = _demodulate(np, self, spectrum)
        return out.fringe, out.brightness, out.reference_k


def demodulate_numpy(demodulator: Demodulator, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-off numpy/OpenCV demodulation; build a [`moirejax.NumpyDemodulator`][] for streams.

    **Arguments:**

    - `demodulator`: the JAX demodulator whose geometry to use.
    - `frame`: `(h, w)` float32 or float64 frame.

    **Returns:**

    `(fringe, brightness, reference_wavevector)` as from [`moirejax.NumpyDemodulator`][].
    """
    return NumpyDemodulator(demodulator, np.asarray(frame).dtype)(frame)
