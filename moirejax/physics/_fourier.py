r"""The angular-wavenumber grid of a discrete Fourier transform, in the repository's convention.

A field sampled with columns along $+x$ and rows along $-y$ (`docs/conventions.md`: x right,
y up) has, on the `fft2` grid, $k_x = 2\pi\,\mathrm{fftfreq}/\Delta$ along columns and
$k_y = -2\pi\,\mathrm{fftfreq}/\Delta$ along rows, for sample spacing $\Delta$. Every
Fourier-space computation in moirejax (the elastomer's compliance, blurs, band windows,
spectral derivatives and peak finding) reads its wavenumbers from here.
"""

from types import ModuleType

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike


def wavenumber_grid(
    shape: tuple[int, int],
    spacing: ArrayLike | tuple[ArrayLike, ArrayLike] = 1.0,
    *,
    real: bool = False,
    dtype=None,
    xp: ModuleType = jnp,
):
    r"""Angular wavenumbers $(k_x, k_y)$ of the DFT bins of an `h x w` field.

    **Arguments:**

    - `shape`: `(h, w)` of the field.
    - `spacing`: sample spacing $\Delta$ (mm for rad/mm; 1 for rad/px), or a pair
        `(row spacing, column spacing)` for a grid whose cells are not square.
    - `real`: the `rfft2` grid (columns `0..w//2`) instead of the full `fft2` grid.
    - `dtype`: real precision of the frequencies (default: the array module's).
    - `xp`: `jax.numpy` (traceable, differentiable in `spacing`) or `numpy`.

    **Returns:** `kx` of shape `(w,)` (`(w//2 + 1,)` with `real`) and `ky` of shape `(h,)`;
    broadcast them as `kx[None, :]` and `ky[:, None]`.
    """
    h, w = shape
    spacing_y, spacing_x = spacing if isinstance(spacing, tuple) else (spacing, spacing)
    if xp is np:
        freq_x = np.fft.rfftfreq(w) if real else np.fft.fftfreq(w)
        freq_y = np.fft.fftfreq(h)
        if dtype is not None:
            freq_x, freq_y = freq_x.astype(dtype), freq_y.astype(dtype)
    else:
        freq_x = jnp.fft.rfftfreq(w, dtype=dtype) if real else jnp.fft.fftfreq(w, dtype=dtype)
        freq_y = jnp.fft.fftfreq(h, dtype=dtype)
    return 2 * xp.pi * freq_x / spacing_x, -2 * xp.pi * freq_y / spacing_y
