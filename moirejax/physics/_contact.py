r"""Contact loads: from a wrench and latent contact variables to surface traction fields.

A contact is a patch of radius $r$ centred at $(x_0, y_0)$ on the contact surface. Its
profile $H$ blends the two classical pressures of a rigid indenter on a soft half-space,
each normalised to a unit resultant: a sphere's (Hertz, $\sqrt{1 - \rho^2/r^2}$, zero at
the edge) and a flat punch's (Boussinesq, $1/\sqrt{1 - \rho^2/r^2}$, singular at the edge),
in the proportion $1 - f$ to $f$, where $f$ is the contact's flatness. A rounded
fingertip is $f = 0$; a flat face pressed square is $f = 1$. The patch may be elongated:
an ellipse of the same area, its semi-axes $r e^{\pm k}$, the profile of the round patch
stretched along one direction and squeezed across it, for an edge or a cylinder pressed
along its length. The sampled profile is
smoothed at the edge so that everything stays differentiable in $r$; shear and torsional
tractions use the same patch. Each field is a combination of three basis fields whose
coefficients are solved on the grid so that the discrete resultant about the origin
equals the requested wrench exactly, not just in the continuum limit:

- normal: $H$, $(X - x_0) H$, $(Y - y_0) H$ give $F_z$, $T_x = \sum Y p$, $T_y = -\sum X p$.
  A centre of pressure away from $(x_0, y_0)$ appears as a pressure tilt.
- in-plane: $(H, 0)$, $(0, H)$ and the torsional field $(-(Y - y_0) H, (X - x_0) H)$ give
  $F_x$, $F_y$ and $T_z = \sum (X t_y - Y t_x)$.

The elastomer is solved from [`traction_spectrum`][]: the exact Fourier transform of the
same fields with the hard Hertz edge, whose coefficients give the wrench as continuum
moments. The sampled fields of [`surface_tractions`][] (pressure maps, the contact's
glow) need the smoothed edge to stay differentiable in $r$; solving the layer from them
would spread the load past the edge and put the displacement 4-7 % (relative L2) off that
of the hard-edge contact under a 2.5-3 mm contact, whatever the grid.

Lengths are mm, tractions MPa (N/mm²); public torques are N·m.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from .._conventions import NMM_PER_NM
from ._fourier import wavenumber_grid


# Sharpness of the smoothed Hertz edge, in units of the normalised gap 1 - rho^2/r^2.
_EDGE_SHARPNESS = 20.0
# The sampled punch profile 1/sqrt(g) becomes sqrt(g)/(g + this), which peaks at
# 1/(2 sqrt(this)) = 2.9 at the edge instead of diverging.
_PUNCH_EDGE = 0.03
# Terms of the Hertz transform's series (see `_hertz_transform`).
_HERTZ_SERIES_TERMS = 10
# Below this squared log-stretch the patch's shape tensor is taken from its Taylor series.
_ROUND = 1e-4


class Contact(eqx.Module):
    r"""Latent contact variables of one frame.

    **Arguments:**

    - `x0`, `y0`: centre of the contact patch on the contact surface (mm, wrench frame).
    - `radius`: contact radius (mm).
    - `flatness`: the share of the load carried with a flat punch's pressure, the rest with
      a sphere's: 0 for a rounded indenter, 1 for a flat one (see the module's text).
    - `stretch_x`, `stretch_xy`: the patch's elongation, as the components $(k\cos 2\theta,
      k\sin 2\theta)$ of its log-stretch from a circle: an ellipse of the same area with
      semi-axes $r e^{k}$ along the direction $\theta$ from the x axis and $r e^{-k}$
      across it. Both 0 for a round patch. (Components rather than $k$ and $\theta$, so
      that the patch is smooth in them through the round one, where $\theta$ means
      nothing.) [`Contact.aspect_ratio`][] and [`Contact.long_axis_angle`][] read them.
    """

    x0: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    y0: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    radius: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=3.0)
    flatness: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    stretch_x: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)
    stretch_xy: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=0.0)

    @property
    def aspect_ratio(self) -> Float[Array, "*b"]:
        """The patch's long semi-axis over its short one, $e^{2k}$: 1 for a round patch."""
        return jnp.exp(2 * jnp.hypot(self.stretch_x, self.stretch_xy))

    @property
    def long_axis_angle(self) -> Float[Array, "*b"]:
        r"""The direction of the patch's long axis from the x axis (rad, in $(-\pi/2, \pi/2]$;
        0 for a round patch)."""
        return 0.5 * jnp.arctan2(self.stretch_xy, self.stretch_x)

    @classmethod
    def elongated(
        cls,
        x0: ArrayLike,
        y0: ArrayLike,
        radius: ArrayLike,
        aspect_ratio: ArrayLike,
        angle: ArrayLike,
        flatness: ArrayLike = 0.0,
    ) -> "Contact":
        """A patch of the area of a circle of `radius`, `aspect_ratio` times as long (along
        `angle`, rad from the x axis) as it is wide."""
        k = 0.5 * jnp.log(jnp.asarray(aspect_ratio))
        angle = jnp.asarray(angle)
        return cls(x0, y0, radius, flatness, k * jnp.cos(2 * angle), k * jnp.sin(2 * angle))

    def shape_tensor(self) -> tuple[Float[Array, "*b"], Float[Array, "*b"], Float[Array, "*b"]]:
        r"""$(P_{xx}, P_{xy}, P_{yy})$ of $P = S^2$, the square of the patch's stretch $S =
        \exp\begin{pmatrix} a & b \\ b & -a \end{pmatrix}$ ($a$, $b$ = `stretch_x`,
        `stretch_xy`): $P = \cosh 2k\, I + \frac{\sinh 2k}{k} \begin{pmatrix} a & b \\ b &
        -a\end{pmatrix}$ with $k^2 = a^2 + b^2$, $\det P = 1$. The patch's profile at $d$
        from its centre is the round one's at $\sqrt{d^\top P^{-1} d}$, its second moments
        are the round one's times $P$, and its transform at $q$ the round one's at
        $\sqrt{q^\top P q}$."""
        a, b = self.stretch_x, self.stretch_xy
        k2 = a * a + b * b
        small = k2 < _ROUND
        k = jnp.sqrt(jnp.where(small, 1.0, k2))
        # cosh 2k and sinh(2k)/k, by their series near the round patch (where k has no derivative).
        even = jnp.where(small, 1 + 2 * k2 + (2 / 3) * k2 * k2, jnp.cosh(2 * k))
        odd = jnp.where(small, 2 + (4 / 3) * k2 + (4 / 15) * k2 * k2, jnp.sinh(2 * k) / k)
        return even + odd * a, odd * b, even - odd * a


class SurfaceGrid(eqx.Module):
    """Cell-centred grid on the contact surface on which tractions and displacements live.

    It covers the same field as the rectified image, magnified by $(Z + a)/Z$ because the
    contact surface is farther from the camera than the reference plane.
    """

    X: Float[Array, "h w"]
    Y: Float[Array, "h w"]
    spacing: Float[Array, ""]


def grid_shape(image_shape: tuple[int, int], cells: int) -> tuple[int, int]:
    """The smallest grid with at least `cells` cells along the image's longer side whose cells
    are square in the image (the aspect ratio [`surface_grid`][] needs): `(cells, cells)`
    for a square image, `(96, 128)` for 128 cells over a 480 x 640 one. An image whose sides
    share no common factor needs a grid of its own size."""
    h, w = (int(v) for v in image_shape)
    if h < 1 or w < 1 or cells < 1:
        raise ValueError(f"grid_shape needs positive sizes, got image {image_shape} and {cells} cells")
    common = math.gcd(h, w)
    unit_h, unit_w = h // common, w // common
    k = -(-int(cells) // max(unit_h, unit_w))
    return (unit_h * k, unit_w * k)


def surface_grid(
    shape: tuple[int, int], px_per_mm: ArrayLike, image_shape: tuple[int, int], a: ArrayLike, Z: ArrayLike
) -> SurfaceGrid:
    """The [`SurfaceGrid`][] of `shape` cells covering an image of `image_shape` pixels.

    The image must be square in mm per cell: `image_shape[0] / shape[0] == image_shape[1] / shape[1]`.
    """
    h, w = shape
    H, W = image_shape
    if H * w != W * h:
        raise ValueError(
            f"grid {shape} and image {image_shape} must have the same aspect ratio "
            f"(e.g. {grid_shape(image_shape, max(h, w))}, see grid_shape)"
        )
    Z = jnp.asarray(Z)
    spacing = (W / w) / jnp.asarray(px_per_mm) * (Z + jnp.asarray(a)) / Z
    cols = (jnp.arange(w, dtype=float) - (w - 1) / 2) * spacing
    rows = ((h - 1) / 2 - jnp.arange(h, dtype=float)) * spacing
    X, Y = jnp.meshgrid(cols, rows, indexing="xy")
    return SurfaceGrid(X=X, Y=Y, spacing=spacing)


def contact_profile(contact: Contact, grid: SurfaceGrid) -> Float[Array, "h w"]:
    r"""The contact's pressure profile with a smooth edge, each part over its resultant:
    $(1 - f)\,\frac{3}{2\pi r^2}\sqrt{g} + f\,\frac{1}{2\pi r^2}\frac{\sqrt{g}}{g + \epsilon}$,
    with $g$ the smoothed gap $\max(1 - \rho^2/r^2, 0)$ and $f$ the flatness; $\epsilon$ caps
    the punch's edge (at about nine times its centre pressure on the sampled grid). On an
    elongated patch $\rho^2 = d^\top P^{-1} d$ ([`Contact.shape_tensor`][])."""
    dX, dY = grid.X - contact.x0, grid.Y - contact.y0
    pxx, pxy, pyy = contact.shape_tensor()
    # P^-1 of a unit-determinant symmetric P swaps its diagonal and negates the off-diagonal.
    rho2 = pyy * dX * dX - 2 * pxy * dX * dY + pxx * dY * dY
    gap = jax.nn.softplus(_EDGE_SHARPNESS * (1 - rho2 / contact.radius**2)) / _EDGE_SHARPNESS
    # The tiny floor keeps the square root differentiable where softplus underflows.
    hertz = jnp.sqrt(gap + 1e-20)
    punch = hertz / (gap + _PUNCH_EDGE)
    area = 2 * jnp.pi * contact.radius**2
    return (1 - contact.flatness) * 3 * hertz / area + contact.flatness * punch / area


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


def _hertz_transform(x2: Float[Array, "*q"]) -> tuple[Float[Array, "*q"], Float[Array, "*q"]]:
    r"""$g(x) = (\sin x - x\cos x)/x^3$ and $g'(x)/x$ of $x^2$ = `x2`, each by its Taylor
    series below $x = 1$ (taking $x^2$ keeps the derivatives finite at $x = 0$).

    $2\pi r^2 g(qr)$ is the Fourier transform of the unit Hertz profile
    $\sqrt{1 - \rho^2/r^2}$ of radius $r$; $g'$ gives the transforms of its first moments.
    The closed forms cancel near zero; the series
    $g = \sum_k (-1)^k \frac{2k + 2}{(2k + 3)!} x^{2k}$ (and its derivative) reach float64
    precision at $x = 1$ with eleven terms.
    """
    small = x2 < 1.0
    safe = jnp.sqrt(jnp.where(small, 1.0, x2))
    s, c = jnp.sin(safe), jnp.cos(safe)
    g = (s - safe * c) / safe**3
    dg_over_x = ((safe * safe - 3) * s + 3 * safe * c) / safe**5
    x2 = jnp.where(small, x2, 0.0)
    g_series, dg_series = jnp.zeros_like(x2), jnp.zeros_like(x2)
    for k in range(_HERTZ_SERIES_TERMS, -1, -1):
        coefficient = (-1) ** k * (2 * k + 2) / math.factorial(2 * k + 3)
        g_series = g_series * x2 + coefficient
        if k > 0:
            dg_series = dg_series * x2 + 2 * k * coefficient
    return jnp.where(small, g_series, g), jnp.where(small, dg_series, dg_over_x)


def _punch_transform(
    x2: Float[Array, "*q"], hertz: Float[Array, "*q"]
) -> tuple[Float[Array, "*q"], Float[Array, "*q"]]:
    r"""$\sin x / x$ and its $\frac{d}{dx}(\sin x/x)/x = -g(x)$ of $x^2$ = `x2`, given the
    Hertz transform $g$ of [`_hertz_transform`][] of the same argument.

    $2\pi r^2 \sin(qr)/(qr)$ is the Fourier transform of the unit flat-punch profile
    $1/\sqrt{1 - \rho^2/r^2}$ of radius $r$. Below $x = 1$ its Taylor series
    $\sum_k (-1)^k x^{2k}/(2k + 1)!$ replaces the quotient, which loses its derivative at 0.
    """
    small = x2 < 1.0
    safe = jnp.sqrt(jnp.where(small, 1.0, x2))
    series = jnp.zeros_like(x2)
    z = jnp.where(small, x2, 0.0)
    for k in range(_HERTZ_SERIES_TERMS, -1, -1):
        series = series * z + (-1) ** k / math.factorial(2 * k + 1)
    return jnp.where(small, series, jnp.sin(safe) / safe), -hertz


def traction_spectrum(wrench: Float[Array, "6"], contact: Contact, grid: SurfaceGrid) -> Complex[Array, "3 h k"]:
    r"""The `rfft2` of the traction fields `(tx, ty, p)` (MPa) of [`surface_tractions`][],
    from their exact continuum transform with the hard Hertz edge.

    The basis fields of [`surface_tractions`][] about the contact centre are the profile
    $H$ and its first moments $\Delta X H$, $\Delta Y H$, whose transforms are
    $i\,\partial\hat H/\partial q_{x,y}$. The sphere's part of $H$, $\sqrt{1 - \rho^2/r^2}$,
    has the transform $2\pi r^2 g(qr)$ with $g(x) = (\sin x - x\cos x)/x^3$, resultant
    $2\pi r^2/3$ and second moment $\int \Delta X^2 H = 2\pi r^4/15$; the punch's,
    $1/\sqrt{1 - \rho^2/r^2}$, has $2\pi r^2 \sin(qr)/(qr)$, $2\pi r^2$ and $2\pi r^4/3$. The
    coefficients come from those continuum moments, so the field's resultant is `wrench`. Dividing by the cell area and shifting to the grid's first
    cell gives the DFT of the band-limited field, in the repository's Fourier convention
    ($k_y$ negative along rows, because $y$ points up); the Nyquist bins are dropped. The
    result is smooth in the wrench and in the contact's centre and radius.
    """
    if wrench.shape != (6,):
        raise ValueError(f"wrench must have shape (6,), got {wrench.shape}")
    rows, cols = grid.X.shape
    dtype = grid.X.dtype
    kx, ky = wavenumber_grid((rows, cols), grid.spacing, real=True, dtype=dtype)
    kx, ky = kx[None, :], ky[:, None]
    r, x0, y0, f = contact.radius, contact.x0, contact.y0, contact.flatness
    pxx, pxy, pyy = contact.shape_tensor()
    # The elongated patch's transform is the round one's at |S q| (P = S^2, det S = 1).
    pqx, pqy = pxx * kx + pxy * ky, pxy * kx + pyy * ky
    q2r2 = (kx * pqx + ky * pqy) * r * r
    g, dg = _hertz_transform(q2r2)
    sinc, dsinc = _punch_transform(q2r2, g)
    # The unit-resultant profile's transform and its second moment (the int of dX^2 over
    # it): 3 g(qr) and r^2/5 for the sphere's part, sin(qr)/(qr) and r^2/3 for the punch's;
    # the elongated patch's second moments are m2 P.
    profile = (1 - f) * 3 * g + f * sinc
    m0, m2 = 1.0, r**2 * ((1 - f) / 5 + f / 3)
    # i dH/dq_x and i dH/dq_y, without the factor i (applied below).
    radial = r**2 * ((1 - f) * 3 * dg + f * dsinc)
    moment_x, moment_y = radial * pqx, radial * pqy
    fx, fy, fz = wrench[0], wrench[1], wrench[2]
    tx, ty, tz = wrench[3] * NMM_PER_NM, wrench[4] * NMM_PER_NM, wrench[5] * NMM_PER_NM
    # Resultants about the origin of the basis fields centred at (x0, y0): see
    # surface_tractions. The pressure's tilt (cx, cy) solves m2 P (cx, cy) = (-(ty + x0 fz),
    # tx - y0 fz), with P^-1 as in `contact_profile`.
    bx, by = -(ty + x0 * fz) / m2, (tx - y0 * fz) / m2
    c0, cx, cy = fz / m0, pyy * bx - pxy * by, pxx * by - pxy * bx
    s0, s1, twist = fx / m0, fy / m0, (tz - x0 * fy + y0 * fx) / (m2 * (pxx + pyy))
    real = jnp.stack([s0 * profile, s1 * profile, c0 * profile])
    imaginary = jnp.stack([-twist * moment_y, twist * moment_x, cx * moment_x + cy * moment_y])
    shift = kx * (grid.X[0, 0] - x0) + ky * (grid.Y[0, 0] - y0)
    area = grid.spacing**2
    phasor = jax.lax.complex(jnp.cos(shift) / area, jnp.sin(shift) / area)
    keep = (
        ~((jnp.arange(cols // 2 + 1) == cols // 2) & (cols % 2 == 0))[None, :]
        & ~((jnp.arange(rows) == rows // 2) & (rows % 2 == 0))[:, None]
    )
    return jnp.where(keep[None], jax.lax.complex(real, imaginary) * phasor[None], 0)
