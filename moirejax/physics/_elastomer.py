r"""Surface compliance of the sensor's elastomer: a linear elastic layer bonded to a rigid carrier.

The layer (thickness $h$, Young's modulus $E$, Poisson ratio $\nu$) occupies
$0 \le z \le h$ with $z$ pointing into the sensor. Its top $z = 0$ carries the traction
$(t_x, t_y, p)$ (MPa, $p > 0$ pressing in); its bottom $z = h$ is perfectly bonded to the
rigid carrier. For a traction $\propto e^{i q \cdot x}$ Navier's equation
$\mu \nabla^2 u + (\lambda + \mu) \nabla(\nabla \cdot u) = 0$ has the solutions
$e^{\pm |q| z}$, $z e^{\pm |q| z}$, and the surface displacement is
$\hat u(q) = C(q)\, \hat t(q)$ with a $3 \times 3$ Hermitian compliance $C(q)$.

In the frame of $q$ ($e_L = q/|q|$ longitudinal, $e_T$ in-plane transverse) $C$ splits into
the antiplane (SH) mode and the coupled longitudinal/normal (P-SV) mode. With
$s = |q| h$, $\kappa = 3 - 4\nu$, $\mu = E / (2(1+\nu))$:

$$C_{TT} = \frac{\tanh s}{\mu |q|},\qquad
C_{LL} = \frac{(1-\nu)(\kappa \sinh 2s + 2s)}{\mu |q| D},\qquad
C_{ww} = \frac{(1-\nu)(\kappa \sinh 2s - 2s)}{\mu |q| D},$$

$$C_{Lw} = -C_{wL} = i\,\frac{(1-2\nu)\kappa \sinh^2 s - s^2}{\mu |q| D},\qquad
D = \kappa \cosh 2s + \tfrac{1}{2}(1 + \kappa^2) + 2 s^2.$$

For $s \to \infty$ these become the half-space (Boussinesq/Cerruti) values
$C_{TT} = 1/(\mu|q|)$, $C_{LL} = C_{ww} = (1-\nu)/(\mu|q|)$, $C_{Lw} = i(1-2\nu)/(2\mu|q|)$.
At $q = 0$ they are simple shear $h/\mu$ and confined compression
$h/M$, $M = 2\mu(1-\nu)/(1-2\nu)$.

The sign of $C_{Lw}$ holds for the repository's Fourier convention
$f(x) = \int \hat f(q)\, e^{+i q\cdot x}$ (so $\partial_x \to i q_x$, see
`docs/conventions.md`). On a half-space it pulls the surface radially inward under a
pressure (Boussinesq, $\nu < 1/2$). In a thin bonded layer near incompressibility the
numerator turns negative and the pressed material is squeezed outward: the coupling that
lets a grating on the surface see the normal load.

Numerics: the closed forms are evaluated as $(h/\mu)\, b(s)$ with $b$ regular at $s = 0$,
using only $e^{-2s}$ (no overflow), `expm1`, and a series for $\sinh 2s - 2s$ (the whole
normal compliance as $\nu \to 1/2$). The exponentials saturate at $s = 30$, where the
layer is a half-space to float64 precision. $q = 0$ takes its exact limit behind a double
`where`, and the coupling is carried as $C_{Lw} / (i|q|)$ so that
$C_{xz} = i q_x\, C_{Lw}/(i|q|)$ is smooth through $q = 0$.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from ._fourier import wavenumber_grid


# Beyond s = |q| h = 30 every e^{-2s} term is below 1e-25 relative to the O(1) terms, so the
# layer equals the half-space to all float64 digits; clamping keeps s^2 e^{-2s} from forming
# inf * 0 in float32 at huge |q| h.
_HALF_SPACE_S = 30.0
# sinh(x) - x is summed as a Taylor series below x = 1 (9 terms reach float64 precision
# there) and taken directly above, where the cancellation costs less than a factor of 10.
_SINH_SERIES_X = 1.0
_SINH_SERIES_TERMS = 9


def _shear_modulus(E, nu):
    return E / (2 * (1 + nu))


def _exp_sinh_excess(s):
    r"""$g(s) = 1 - e^{-4s} - 4 s e^{-2s} = 2 e^{-2s}(\sinh 2s - 2s)$ without cancellation.

    This is the whole normal compliance of an incompressible layer, which is
    $O(s^3)$ at small $s$: the direct form would lose every digit there.
    """
    x = 2 * s
    # Double `where`: the unused branch gets a harmless argument so its gradient stays finite.
    x_small = jnp.minimum(x, _SINH_SERIES_X)
    x2 = x_small * x_small
    # Horner form of sum_{k>=1} x^{2k+1} / (2k+1)!, i.e. sinh(x) - x.
    series = jnp.zeros_like(x_small)
    for k in range(_SINH_SERIES_TERMS, 0, -1):
        series = (series + 1) * x2 / ((2 * k) * (2 * k + 1))
    series = series * x_small
    small = 2 * jnp.exp(-x_small) * series
    direct = -jnp.expm1(-2 * x) - 2 * x * jnp.exp(-x)
    return jnp.where(x < _SINH_SERIES_X, small, direct)


def _layer_modes(s, nu):
    r"""Dimensionless modal compliances of the bonded layer, as functions of $s = |q| h$ > 0.

    Returns `(b_T, b_L, b_w, b_Lw)` with $C_{TT} = (h/\mu)\, b_T$, $C_{LL} = (h/\mu)\, b_L$,
    $C_{ww} = (h/\mu)\, b_w$ and $C_{Lw} = i\, (h/\mu)\, s\, b_{Lw}$; each $b$ has a finite
    limit at $s = 0$. Numerator and denominator of the closed forms are multiplied by
    $2 e^{-2s}$, so only decaying exponentials appear (no overflow), and each difference of
    nearly equal terms is either `expm1` or the series in `_exp_sinh_excess`.
    """
    # Exponentials see the clamped s_c, divisions the true s.
    s_c = jnp.minimum(s, _HALF_SPACE_S)
    kappa = 3 - 4 * nu
    e = jnp.exp(-2 * s_c)
    # (1 - e^{-2s}) / s and (1 - e^{-4s}) / s, divided before any product so that nothing
    # underflows to 0/0 at tiny s in float32.
    one_minus_e_over_s = -jnp.expm1(-2 * s_c) / s
    one_minus_e2_over_s = -jnp.expm1(-4 * s_c) / s
    denominator = kappa * (1 + e * e) + (1 + kappa * kappa + 4 * s_c * s_c) * e
    b_T = jnp.tanh(s_c) / s
    b_L = (1 - nu) * (kappa * one_minus_e2_over_s + 4 * e) / denominator
    # kappa (1 - e^2) - 4 s e split as 2(1 - 2nu)(1 - e^2) + g(s): exact as nu -> 1/2.
    w_numerator = 2 * (1 - 2 * nu) * one_minus_e2_over_s + _exp_sinh_excess(s_c) / s
    b_w = (1 - nu) * w_numerator / denominator
    b_Lw = ((1 - 2 * nu) * kappa * one_minus_e_over_s**2 / 2 - 2 * e) / denominator
    return b_T, b_L, b_w, b_Lw


def _wavevector_polar(qx, qy, dtype):
    """`|q|` and direction cosines, safe at q = 0 (where the direction is taken along x)."""
    qx, qy = jnp.broadcast_arrays(jnp.asarray(qx, dtype), jnp.asarray(qy, dtype))
    q2 = qx * qx + qy * qy
    at_zero = q2 == 0
    # Double `where`: sqrt'(0) is infinite, so the q = 0 entries never see q = 0.
    q = jnp.sqrt(jnp.where(at_zero, 1, q2))
    cos = jnp.where(at_zero, 1, qx / q)
    sin = jnp.where(at_zero, 0, qy / q)
    return qx, qy, q, cos, sin, at_zero


def _layer_modal_compliance(q, at_zero, E, nu, thickness):
    """`(C_TT, C_LL, C_ww, Y)` in mm/MPa, with `C_Lw = i |q| Y`; exact at q = 0.

    The coupling is carried as $Y = C_{Lw} / (i |q|)$ because $C_{xz} = i q_x Y$ is then
    smooth through q = 0, derivatives included.
    """
    mu = _shear_modulus(E, nu)
    b_T, b_L, b_w, b_Lw = _layer_modes(q * thickness, nu)
    shear = thickness / mu
    confined = thickness * (1 - 2 * nu) / (2 * mu * (1 - nu))
    coupling_at_zero = ((1 - 2 * nu) * (3 - 4 * nu) - 1) / (8 * (1 - nu) ** 2)
    C_TT = jnp.where(at_zero, shear, shear * b_T)
    C_LL = jnp.where(at_zero, shear, shear * b_L)
    C_ww = jnp.where(at_zero, confined, shear * b_w)
    Y = thickness * shear * jnp.where(at_zero, coupling_at_zero, b_Lw)
    return C_TT, C_LL, C_ww, Y


def _half_space_modal_compliance(q, at_zero, E, nu):
    """Half-space `(C_TT, C_LL, C_ww, Y)`; the divergent q = 0 mode is set to zero."""
    inverse = jnp.where(at_zero, 0, 1 / (_shear_modulus(E, nu) * q))
    return inverse, (1 - nu) * inverse, (1 - nu) * inverse, (1 - 2 * nu) / 2 * inverse / q


def _assemble(qx, qy, cos, sin, C_TT, C_LL, C_ww, Y):
    """3x3 complex compliance in (x, y, z) from the modal values."""
    zero = jnp.zeros_like(C_TT)
    C_xy = (C_LL - C_TT) * cos * sin
    real = [
        [C_LL * cos * cos + C_TT * sin * sin, C_xy, zero],
        [C_xy, C_LL * sin * sin + C_TT * cos * cos, zero],
        [zero, zero, C_ww],
    ]
    # Hermitian: C_xz = i q_x Y = conj(C_zx), C_yz = i q_y Y = conj(C_zy).
    imag = [[zero, zero, qx * Y], [zero, zero, qy * Y], [-qx * Y, -qy * Y, zero]]
    stack = lambda rows: jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)
    return jax.lax.complex(stack(real), stack(imag))


def _inexact_dtype(*arrays):
    dtype = jnp.result_type(*arrays)
    return dtype if jnp.issubdtype(dtype, jnp.inexact) else jnp.result_type(float)


@jax.jit
def layer_compliance(
    qx: Float[ArrayLike, "*#q"],
    qy: Float[ArrayLike, "*#q"],
    E: Float[ArrayLike, ""],
    nu: Float[ArrayLike, ""],
    thickness: Float[ArrayLike, ""],
) -> Complex[Array, "*q 3 3"]:
    r"""Fourier-space surface compliance $C(q)$ of an elastic layer bonded to a rigid base.

    $\hat u(q) = C(q)\, \hat t(q)$ with $\hat u$ the transform of $(u_x, u_y, w)$ and
    $\hat t$ that of $(t_x, t_y, p)$. In terms of the modal values of the module docstring,
    with $c = q_x/|q|$, $\sigma = q_y/|q|$:

    $$C = \begin{pmatrix}
    C_{LL} c^2 + C_{TT} \sigma^2 & (C_{LL} - C_{TT}) c \sigma & C_{Lw} c \\
    (C_{LL} - C_{TT}) c \sigma & C_{LL} \sigma^2 + C_{TT} c^2 & C_{Lw} \sigma \\
    -C_{Lw} c & -C_{Lw} \sigma & C_{ww}
    \end{pmatrix}.$$

    At $q = 0$ it is $\operatorname{diag}(h/\mu, h/\mu, h/M)$ exactly, the limit of the
    formula, with finite gradients there. Stable in float32 for any $|q| h$; beyond
    $|q| h = 30$ it is the half-space compliance.

    **Arguments:**

    - `qx`, `qy`: wavevector components (rad/mm), broadcastable against each other.
    - `E`: Young's modulus (MPa).
    - `nu`: Poisson ratio, $0 \le \nu \le 1/2$ ($\nu = 1/2$ is incompressible).
    - `thickness`: layer thickness $h$ (mm), positive.

    **Returns:** the complex compliance (mm/MPa), shape `broadcast(qx, qy) + (3, 3)`.
    """
    dtype = _inexact_dtype(qx, qy)
    qx, qy, q, cos, sin, at_zero = _wavevector_polar(qx, qy, dtype)
    E, nu, thickness = (jnp.asarray(v, dtype) for v in (E, nu, thickness))
    modes = _layer_modal_compliance(q, at_zero, E, nu, thickness)
    return _assemble(qx, qy, cos, sin, *modes)


@jax.jit
def half_space_compliance(
    qx: Float[ArrayLike, "*#q"],
    qy: Float[ArrayLike, "*#q"],
    E: Float[ArrayLike, ""],
    nu: Float[ArrayLike, ""],
) -> Complex[Array, "*q 3 3"]:
    r"""Fourier-space surface compliance of an elastic half-space (Boussinesq and Cerruti).

    The thick-layer limit of `layer_compliance`: in the notation there,

    $$C_{TT} = \frac{1}{\mu |q|},\quad C_{LL} = C_{ww} = \frac{1-\nu}{\mu |q|},\quad
    C_{Lw} = i\,\frac{1 - 2\nu}{2 \mu |q|}.$$

    Its inverse transforms are $w = (1-\nu^2) P / (\pi E r)$ and
    $u_r = -(1-2\nu)(1+\nu) P / (2\pi E r)$ under a point force $P$ pressing in.
    A uniform traction moves a half-space without bound, so $C(0)$ is infinite; it is
    returned as zero, the usual gauge of FFT contact solvers (displacements are then
    defined up to a rigid translation).

    **Arguments:**

    - `qx`, `qy`: wavevector components (rad/mm), broadcastable against each other.
    - `E`: Young's modulus (MPa).
    - `nu`: Poisson ratio, $0 \le \nu \le 1/2$.

    **Returns:** the complex compliance (mm/MPa), shape `broadcast(qx, qy) + (3, 3)`.
    """
    dtype = _inexact_dtype(qx, qy)
    qx, qy, q, cos, sin, at_zero = _wavevector_polar(qx, qy, dtype)
    E, nu = jnp.asarray(E, dtype), jnp.asarray(nu, dtype)
    return _assemble(qx, qy, cos, sin, *_half_space_modal_compliance(q, at_zero, E, nu))


class LayerResponse(eqx.Module):
    """[`layer_compliance`][] on the `rfft2` bins of one grid, ready to apply.

    Everything [`surface_displacement`][] computes that does not depend on the traction: a
    unit's layer and grid are fixed, so an inversion builds this once
    ([`layer_response`][]) and pays only two FFTs and a few products per model evaluation.
    Call it on a `(3, h, w)` traction field for the displacement `(ux, uy, w)` (mm).
    """

    xx: Complex[Array, "h k"]
    yy: Complex[Array, "h k"]
    xy: Complex[Array, "h k"]
    ww: Complex[Array, "h k"]
    # i Y q_x and i Y q_y: the normal/tangential coupling is a quarter-period phase shift.
    coupling_x: Complex[Array, "h k"]
    coupling_y: Complex[Array, "h k"]
    shape: tuple[int, int] = eqx.field(static=True)

    def __call__(self, traction: Float[Array, "3 h w"]) -> Float[Array, "3 h w"]:
        if traction.shape != (3, *self.shape):
            raise ValueError(f"traction must have shape {(3, *self.shape)}, got {traction.shape}.")
        return self.displacement_of_spectrum(jnp.fft.rfft2(traction.astype(_real_dtype(self.xx.dtype))))

    def displacement_of_spectrum(self, spectrum: Complex[Array, "3 h k"]) -> Float[Array, "3 h w"]:
        """The displacement `(ux, uy, w)` (mm) under the traction field whose `rfft2` is `spectrum`."""
        tx, ty, p = spectrum.astype(self.xx.dtype)
        ux = self.xx * tx + self.xy * ty + self.coupling_x * p
        uy = self.xy * tx + self.yy * ty + self.coupling_y * p
        w = self.ww * p - self.coupling_x * tx - self.coupling_y * ty
        return jnp.fft.irfft2(jnp.stack([ux, uy, w]), s=self.shape)


def _real_dtype(complex_dtype):
    return jnp.zeros((), complex_dtype).real.dtype


def layer_response(
    shape: tuple[int, int],
    spacing: Float[ArrayLike, ""],
    E: Float[ArrayLike, ""],
    nu: Float[ArrayLike, ""],
    thickness: Float[ArrayLike, ""],
    dtype=None,
) -> LayerResponse:
    r"""The [`LayerResponse`][] of a bonded layer on an `h x w` grid of `spacing` (mm).

    The repository's Fourier convention ($k_x$ along columns, $k_y = -2\pi\,\mathrm{fftfreq}$
    along rows because $y$ points up). On even grids the Nyquist bins keep only the part of
    $C$ even in the aliased component, so the operator stays mirror-symmetric.
    Differentiable in `spacing`, `E`, `nu` and `thickness`; `dtype` is the real precision
    (default: that of the arguments).
    """
    n_rows, n_cols = (int(n) for n in shape)
    dtype = _inexact_dtype(spacing, E, nu, thickness) if dtype is None else dtype
    spacing, E, nu, thickness = (jnp.asarray(v, dtype) for v in (spacing, E, nu, thickness))
    kx, ky = wavenumber_grid((n_rows, n_cols), spacing, real=True, dtype=dtype)
    qx, qy, q, cos, sin, at_zero = _wavevector_polar(kx[None, :], ky[:, None], dtype)
    C_TT, C_LL, C_ww, Y = _layer_modal_compliance(q, at_zero, E, nu, thickness)
    # On an even grid the Nyquist frequency stands for +q and -q at once and can only carry
    # a cosine, so the parts of C odd in that component (C_xy, C_xz, C_yz) cancel there.
    # Dropping them keeps the operator mirror-symmetric as well as reciprocal.
    keep_x = ~((n_cols % 2 == 0) & (jnp.arange(kx.shape[0]) == n_cols // 2))[None, :]
    keep_y = ~((n_rows % 2 == 0) & (jnp.arange(ky.shape[0]) == n_rows // 2))[:, None]
    complex_dtype = jnp.complex64 if jnp.dtype(dtype) == jnp.float32 else jnp.complex128
    as_complex = lambda a: a.astype(complex_dtype)
    Y_x = jnp.where(keep_x, Y * qx, 0)
    Y_y = jnp.where(keep_y, Y * qy, 0)
    return LayerResponse(
        xx=as_complex(C_LL * cos * cos + C_TT * sin * sin),
        yy=as_complex(C_LL * sin * sin + C_TT * cos * cos),
        xy=as_complex(jnp.where(keep_x & keep_y, (C_LL - C_TT) * cos * sin, 0)),
        ww=as_complex(C_ww),
        coupling_x=jax.lax.complex(jnp.zeros_like(Y_x), Y_x),
        coupling_y=jax.lax.complex(jnp.zeros_like(Y_y), Y_y),
        shape=(n_rows, n_cols),
    )


@jax.jit
def surface_displacement(
    traction: Float[Array, "3 h w"],
    spacing: Float[ArrayLike, ""],
    E: Float[ArrayLike, ""],
    nu: Float[ArrayLike, ""],
    thickness: Float[ArrayLike, ""],
) -> Float[Array, "3 h w"]:
    r"""Surface displacement of the bonded layer under a periodic traction field, by FFT.

    Computes $u = \mathcal{F}^{-1}[C(q)\, \mathcal{F}[t]]$ on the grid, with $C$ from
    `layer_compliance`, using the repository's Fourier convention ($k_x$ along columns,
    $k_y = -2\pi\,\mathrm{fftfreq}$ along rows because $y$ points up). The field is
    periodic with the grid's period; pad the traction if the contact must not feel its
    periodic images. Exact for band-limited tractions. On even grids the Nyquist bins keep
    only the part of $C$ even in the aliased component, so the result stays mirror-symmetric.
    Uses `rfft2`/`irfft2`; differentiable in every argument. Many tractions on one layer
    and grid: build the [`layer_response`][] once.

    **Arguments:**

    - `traction`: $(t_x, t_y, p)$ in MPa on an `h x w` grid, `[row, col]` indexing,
      $p > 0$ pressing into the layer.
    - `spacing`: grid spacing (mm).
    - `E`: Young's modulus (MPa).
    - `nu`: Poisson ratio, $0 \le \nu \le 1/2$.
    - `thickness`: layer thickness (mm).

    **Returns:** $(u_x, u_y, w)$ in mm on the same grid, $w > 0$ into the layer.
    """
    if traction.ndim != 3 or traction.shape[0] != 3:
        raise ValueError(f"traction must have shape (3, h, w), got {traction.shape}.")
    dtype = _inexact_dtype(traction)
    response = layer_response(traction.shape[1:], spacing, E, nu, thickness, dtype)
    return response(jnp.asarray(traction, dtype))
