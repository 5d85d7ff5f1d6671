"""Spectral peak finding and wavevector unit conversions shared by the gate and vision mode.

Internally wavevectors are in rad per pixel along image indices, `(k_col, k_row)`, so a
fringe is `cos(k_col * j + k_row * i)`. Public wavevectors follow `docs/conventions.md`:
`(kx, ky)` in rad/mm with y up, so `k_col = kx / px_per_mm` and `k_row = -ky / px_per_mm`.
"""

import numpy as np

from ..observe import spectral_peak, windowed_power_spectrum
from ..physics import wavenumber_grid
from ._types import Real


def to_index_wavevectors(wavevectors_mm: np.ndarray, px_per_mm: Real) -> np.ndarray:
    """`(n, 2)` `(kx, ky)` rad/mm (y up) -> `(n, 2)` `(k_col, k_row)` rad/px."""
    k = np.asarray(wavevectors_mm, dtype=np.float64).reshape(-1, 2)
    return np.stack([k[:, 0] / px_per_mm, -k[:, 1] / px_per_mm], axis=-1)


def to_physical_wavevectors(wavevectors_px: np.ndarray, px_per_mm: Real) -> np.ndarray:
    """Inverse of [`to_index_wavevectors`][]."""
    k = np.asarray(wavevectors_px, dtype=np.float64).reshape(-1, 2)
    return np.stack([k[:, 0] * px_per_mm, -k[:, 1] * px_per_mm], axis=-1)


def spectral_peaks(
    gray: np.ndarray, n_peaks: int, *, min_cycles: Real = 3.0, max_cycles_per_px: Real = 0.5
) -> np.ndarray:
    """The `n_peaks` strongest non-DC peaks of a Hann-windowed power spectrum.

    Each peak is reported once (the half-plane with `k_col > 0`, or `k_col == 0` and
    `k_row > 0`), refined to sub-bin precision by `observe.spectral_peak`; after each, its
    neighbourhood (the window's leakage) and its mirror image are left out of the search.

    **Arguments:**

    - `gray`: `(h, w)` image.
    - `n_peaks`: how many peaks.
    - `min_cycles`: ignore frequencies below this many cycles per image (DC and shading).
    - `max_cycles_per_px`: ignore frequencies above this (0.5 is Nyquist).

    **Returns:** `(n_peaks, 2)` wavevectors `(k_col, k_row)` in rad/px, strongest first.
    """
    power = windowed_power_spectrum(gray)
    h, w = power.shape
    kx, ky = wavenumber_grid((h, w), xp=np)
    KX, KY = kx[None, :], ky[:, None]
    cycles = np.hypot(KY * h, KX * w) / (2 * np.pi)
    radius = np.hypot(KY, KX) / (2 * np.pi)
    # k_row = -ky: rows run towards -y.
    half_plane = (KX > 0) | ((KX == 0) & (KY < 0))
    allowed = half_plane & (cycles >= min_cycles) & (radius <= max_cycles_per_px)
    peaks = []
    for _ in range(n_peaks):
        try:
            peak = spectral_peak(power, allowed)
        except ValueError:
            raise ValueError(f"found only {len(peaks)} spectral peaks, asked for {n_peaks}") from None
        peaks.append(peak)
        for sign in (1, -1):
            near = np.hypot((KY - sign * peak[1]) * h, (KX - sign * peak[0]) * w) < 3.0 * 2 * np.pi
            allowed = allowed & ~near
    return to_index_wavevectors(np.asarray(peaks).reshape(-1, 2), 1.0)
