r"""Contact loads: from a wrench and latent contact variables to surface traction fields.

A contact is a patch of radius $r$ centred at $(x_0, y_0)$ on the contact surface. The
normal pressure has a Hertz-like profile $H \propto \sqrt{1 - \rho^2/r^2}$ (smoothed at the
edge so that everything stays differentiable in $r$); shear and torsional tractions
use the same patch. Each field is a combination of three basis fields whose
coefficients are solved on the grid so that the discrete resultant about the origin
equals the requested wrench exactly, not just in the continuum limit:

- normal: $H$, $(X - x_0) H$, $(Y - y_0) H$ give $F_z$, $T_x = \sum Y p$, $T_y = -\sum X p$.
  A centre of pressure away from $(x_0, y_0)$ appears as a pressure tilt.
- in-plane: $(H, 0)$, $(0, H)$ and the torsional field $(-(Y - y_0) H, (X - x_0) H)$ give
  $F_x$, $F_y$ and $T_z = \sum (X t_y - Y t_x)$.

Lengths are mm, tractions MPa (N/mm²); public torques are N·m.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._conventions import NMM_PER_NM


# Sharpness of the smoothed Hertz edge, in units of the normalised gap 1 - rho^2/r^2.
_EDGE_SHARPNESS = 20.0


class Contact(eqx.Module):
    """Latent contact variables of one frame.

    **Arguments:**

    - `x0`, `y0`: centre of the contact patch on the contact surface (mm, wrench frame).
    - `radius`: contact radius (mm).
    """

    x0: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    y0: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    radius: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=3.0)


class SurfaceGrid(eqx.Module):
    """Cell-centred grid on the contact surface on which tractions and displacements live.

    It covers the same field as the rectified image, magnified by $(Z + a)/Z$ because the
    contact surface is farther from the camera than the reference plane.
    """

    X: Float[Array, "h w"]
    Y: Float[Array, "h w"]
    spacing: Float[Array, ""]


def surface_grid(
    shape: tuple[int, int], px_per_mm: ArrayLike, image_shape: tuple[int, int], a: ArrayLike, Z: ArrayLike
) -> SurfaceGrid:
    """The [`SurfaceGrid`][] of `shape` cells covering an image of `image_shape` pixels.

    The image must be square in mm per cell: `image_shape[0] / shape[0] == image_shape[1] / shape[1]`.
    """
    h, w = shape
    H, W = image_shape
    if H * w != W * h:
        raise ValueError(f"grid {shape} and image {image_shape} must have the same aspect ratio")
    Z = jnp.asarray(Z)
    spacing = (W / w) / jnp.asarray(px_per_mm) * (Z + jnp.asarray(a)) / Z
    cols = (jnp.arange(w, dtype=float) - (w - 1) / 2) * spacing
    rows = ((h - 1) / 2 - jnp.arange(h, dtype=float)) * spacing
    X, Y = jnp.meshgrid(cols, rows, indexing="xy")
    return SurfaceGrid(X=X, Y=Y, spacing=spacing)


def contact_profile(contact: Contact, grid: SurfaceGrid) -> Float[Array, "h w"]:
    r"""Unnormalised Hertz-like profile $\sqrt{\max(1 - \rho^2/r^2, 0)}$ with a smooth edge."""
    rho2 = (grid.X - contact.x0) ** 2 + (grid.Y - contact.y0) ** 2
    gap = 1 - rho2 / contact.radius**2
    # The tiny floor keeps the square root differentiable where softplus underflows.
    return jnp.sqrt(jax.nn.softplus(_EDGE_SHARPNESS * gap) / _EDGE_SHARPNESS + 1e-20)


def surface_tractions(wrench: Float[Array, "6"], contact: Contact, grid: SurfaceGrid) -> Float[Array, "3 h w"]:
    """Traction fields `(tx, ty, p)` (MPa) whose resultant about the origin is `wrench`.

    **Arguments:**

    - `wrench`: `[fx, fy, fz, tx, ty, tz]` in N and N·m, in the moirejax wrench convention.
    - `contact`: the [`Contact`][] patch.
    - `grid`: the [`SurfaceGrid`][].

    **Returns:** shear tractions `tx`, `ty` and the normal pressure `p` (positive pressing
    into the sensor), stacked on the first axis.
    """
    if wrench.shape != (6,):
        raise ValueError(f"wrench must have shape (6,), got {wrench.shape}")
    X, Y, area = grid.X, grid.Y, grid.spacing**2
    H = contact_profile(contact, grid)
    dX, dY = X - contact.x0, Y - contact.y0
    fx, fy, fz = wrench[0], wrench[1], wrench[2]
    tx, ty, tz = wrench[3] * NMM_PER_NM, wrench[4] * NMM_PER_NM, wrench[5] * NMM_PER_NM
    # Every resultant of every basis field is a moment of H about the contact centre up to
    # second order: six sums over the grid instead of eighteen.
    m0, mx, my = jnp.sum(H) * area, jnp.sum(dX * H) * area, jnp.sum(dY * H) * area
    mxx, myy, mxy = jnp.sum(dX * dX * H) * area, jnp.sum(dY * dY * H) * area, jnp.sum(dX * dY * H) * area
    x0, y0 = contact.x0, contact.y0

    # Normal basis H, dX H, dY H; rows Fz = sum p, Tx = sum Y p, Ty = -sum X p (Y = y0 + dY).
    normal_moments = jnp.stack(
        [
            jnp.stack([m0, mx, my]),
            jnp.stack([y0 * m0 + my, y0 * mx + mxy, y0 * my + myy]),
            -jnp.stack([x0 * m0 + mx, x0 * mx + mxx, x0 * my + mxy]),
        ]
    )
    c = jnp.linalg.solve(normal_moments, jnp.stack([fz, tx, ty]))
    pressure = H * (c[0] + c[1] * dX + c[2] * dY)

    # In-plane basis (H, 0), (0, H), (-dY H, dX H); rows Fx, Fy, Tz = sum (X t_y - Y t_x).
    zero = jnp.zeros_like(m0)
    torsion = x0 * mx + mxx + y0 * my + myy
    shear_moments = jnp.stack(
        [
            jnp.stack([m0, zero, -my]),
            jnp.stack([zero, m0, mx]),
            jnp.stack([-(y0 * m0 + my), x0 * m0 + mx, torsion]),
        ]
    )
    s = jnp.linalg.solve(shear_moments, jnp.stack([fx, fy, tz]))
    return jnp.stack([H * (s[0] - s[2] * dY), H * (s[1] + s[2] * dX), pressure])


def traction_resultant(tractions: Float[Array, "3 h w"], grid: SurfaceGrid) -> Float[Array, "6"]:
    """The wrench `[fx, fy, fz, tx, ty, tz]` (N, N·m) of traction fields about the origin."""
    t_x, t_y, p = tractions
    area = grid.spacing**2
    X, Y = grid.X, grid.Y
    return jnp.stack(
        [
            jnp.sum(t_x) * area,
            jnp.sum(t_y) * area,
            jnp.sum(p) * area,
            jnp.sum(Y * p) * area / NMM_PER_NM,
            -jnp.sum(X * p) * area / NMM_PER_NM,
            jnp.sum(X * t_y - Y * t_x) * area / NMM_PER_NM,
        ]
    )
