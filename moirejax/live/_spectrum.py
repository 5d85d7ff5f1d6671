"""Spectral peak finding and wavevector unit conversions shared by the gate and vision mode.

Internally wavevectors are in rad per pixel along image indices, `(k_col, k_row)`, so a
fringe is `cos(k_col * j + k_row * i)`. Public wavevectors follow `docs/conventions.md`:
`(kx, ky)` in rad/mm with y up, so `k_col = kx / px_per_mm` and `k_row = -ky / px_per_mm`.
"""

import numpy as np

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
    `k_row > 0`), refined to sub-bin precision by a parabola through the log power.

    **Arguments:**

    - `gray`: `(h, w)` image.
    - `n_peaks`: how many peaks.
    - `min_cycles`: ignore frequencies below this many cycles per image (DC and shading).
    - `max_cycles_per_px`: ignore frequencies above this (0.5 is Nyquist).

    **Returns:** `(n_peaks, 2)` wavevectors `(k_col, k_row)` in rad/px, strongest first.
    """
    g = np.asarray(gray, dtype=np.float64)
    h, w = g.shape
    window = np.outer(np.hanning(h), np.hanning(w))
    power = np.abs(np.fft.fft2((g - g.mean()) * window)) ** 2
    f_row, f_col = np.meshgrid(np.fft.fftfreq(h), np.fft.fftfreq(w), indexing="ij")
    cycles = np.hypot(f_row * h, f_col * w)
    radius = np.hypot(f_row, f_col)
    half_plane = (f_col > 0) | ((f_col == 0) & (f_row > 0))
    allowed = half_plane & (cycles >= min_cycles) & (radius <= max_cycles_per_px)
    log_power = np.log(power + 1e-30)
    peaks = []
    for _ in range(n_peaks):
        candidates = np.where(allowed, power, -1.0)
        r, c = np.unravel_index(np.argmax(candidates), power.shape)
        if candidates[r, c] <= 0:
            raise ValueError(f"found only {len(peaks)} spectral peaks, asked for {n_peaks}")

        def vertex(m, z, p):
            denominator = m - 2 * z + p
            return 0.5 * (m - p) / denominator if denominator < 0 else 0.0

        dr = vertex(log_power[(r - 1) % h, c], log_power[r, c], log_power[(r + 1) % h, c])
        dc = vertex(log_power[r, (c - 1) % w], log_power[r, c], log_power[r, (c + 1) % w])
        fr, fc = f_row[r, c] + dr / h, f_col[r, c] + dc / w
        peaks.append((2 * np.pi * fc, 2 * np.pi * fr))
        # Suppress the peak's neighbourhood (its window leakage) and its mirror image.
        for sr, sc in ((fr, fc), (-fr, -fc)):
            near = np.hypot((f_row - sr) * h, (f_col - sc) * w) < 3.0
            allowed &= ~near
    return np.asarray(peaks, dtype=np.float64).reshape(-1, 2)
