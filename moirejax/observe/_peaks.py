"""Where an image's fringes are: the peaks of its Hann-windowed power spectrum (numpy).

The one spectral peak finder for frames outside the traced pipeline: the reference
geometry's moiré wavevectors (`match_reference_geometry`) and the live gate's and vision
mode's peaks (`moirejax.live`) are read with it. The Hann window keeps the leakage of
the strong brightness and shading terms away from the peaks, and makes the log power
near a peak close to a parabola, whose vertex gives the sub-bin position.
"""

import numpy as np
from jaxtyping import ArrayLike

from ..physics import wavenumber_grid


def windowed_power_spectrum(image: ArrayLike) -> np.ndarray:
    """`|fft2((image - mean) * hann)|^2` of an `(h, w)` image, on the unshifted `fft2` grid."""
    g = np.asarray(image, dtype=np.float64)
    if g.ndim != 2:
        raise ValueError(f"expected a 2D image, got shape {g.shape}")
    h, w = g.shape
    window = np.outer(np.hanning(h), np.hanning(w))
    return np.abs(np.fft.fft2((g - g.mean()) * window)) ** 2


def _vertex(minus: float, centre: float, plus: float) -> float:
    """Offset of the vertex of the parabola through three samples; 0 unless it is a maximum."""
    denominator = minus - 2 * centre + plus
    return 0.5 * (minus - plus) / denominator if denominator < 0 else 0.0


def spectral_peak(power: np.ndarray, allowed: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    r"""The strongest allowed bin of a power spectrum, as a wavevector refined to sub-bin.

    Along each axis a parabola through the log power of the bin and its two neighbours
    (the spectrum is periodic, so neighbours wrap) moves the peak to the parabola's vertex.

    **Arguments:**

    - `power`: `(h, w)` power spectrum on the `fft2` grid, e.g. `windowed_power_spectrum`.
    - `allowed`: boolean mask broadcastable to `(h, w)`: the bins to search.
    - `spacing`: sample spacing of the image (mm for rad/mm, 1 for rad/px).

    **Returns:** `(2,)` wavevector `(kx, ky)` in the x-right, y-up convention
    (`physics.wavenumber_grid`).

    **Raises:** `ValueError` when no allowed bin has any power.
    """
    h, w = power.shape
    candidates = np.where(allowed, power, -1.0)
    r, c = np.unravel_index(np.argmax(candidates), power.shape)
    if candidates[r, c] <= 0:
        raise ValueError("no spectral peak among the allowed frequencies")

    def log_power(i, j):
        return float(np.log(power[i % h, j % w] + 1e-30))

    centre = log_power(r, c)
    dr = _vertex(log_power(r - 1, c), centre, log_power(r + 1, c))
    dc = _vertex(log_power(r, c - 1), centre, log_power(r, c + 1))
    kx, ky = wavenumber_grid((h, w), spacing, xp=np)
    # One bin is 2 pi / (n spacing); rows run towards -y.
    return np.array([kx[c] + dc * 2 * np.pi / (w * spacing), ky[r] - dr * 2 * np.pi / (h * spacing)])
