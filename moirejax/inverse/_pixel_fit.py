r"""Pixel-domain refinement of a wrench inversion: the efficient estimator of a model frame.

The per-frame inversion ([`invert`][]) compares only the demodulated moiré bands
on a coarse grid. That is what a real unit needs, but it leaves out what the carriers,
their harmonics and the fine structure of the fringes say about the load, so its scatter
sits above the Cramér–Rao bound ([`cramer_rao`][]). [`refine_in_pixels`][] takes its
result and fits the full rendered frame to the observed one by weighted least squares,
each pixel whitened by its camera noise,
$$r_i = \frac{o_i - \mu_i(\theta)}{\sigma_i(\mu_i)},$$
over the inversion's own unknowns ([`LoadState`][]). With Gaussian pixel noise this
is the maximum-likelihood estimate, and its covariance, the inverse Fisher information
$(J^\top J)^{-1}$ at the solution, is the Cramér–Rao bound there: a scatter equal to
that covariance shows the estimator efficient.

**Only for frames the renderer describes exactly** (simulation, design studies, checks of
the bound). On a real unit the pixel model's mismatch (binary gratings and their
aliasing, grating phase errors, residual distortion, an elastomer that is not quite the
linear layer) is far above the camera noise across the whole frame and dominates the
fit; that is why the live inversion fits the demodulated bands, after a reference-frame
correction.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._conventions import WRENCH_SCALE
from ..physics import Contact, Device, HighFidelity, noise_as_arrays, pixel_noise_variance, render_frame
from ._state import Estimate, LoadState, N_UNKNOWNS, Status, WRENCH_COORDINATES


class PixelFit(eqx.Module):
    """The result of [`refine_in_pixels`][] (a batch has a leading axis on every field).

    - `wrench`: `[fx, fy, fz, tx, ty, tz]` in N and N·m.
    - `covariance`: 6x6 covariance of the wrench, the inverse Fisher information at the
      solution with the contact and the exposure estimated too; `sigma` its
      square-rooted diagonal.
    - `contact`: the fitted [`Contact`][]; `exposure`: the fitted exposure factor.
    - `state`: the fitted [`LoadState`][], as `Estimate.state`.
    - `chi2`: the whitened residual's sum of squares per degree of freedom; about 1 when
      the renderer and the noise model describe the frame, well above where they do not.
    - `status`: an integer [`Status`][] (`CONVERGED`, `MAX_STEPS` or `NONFINITE`);
      `steps`: Gauss–Newton steps taken.
    """

    wrench: Float[Array, "*b 6"]
    covariance: Float[Array, "*b 6 6"]
    sigma: Float[Array, "*b 6"]
    contact: Contact
    exposure: Float[Array, "*b"]
    state: LoadState
    chi2: Float[Array, "*b"]
    status: Int[Array, "*b"]
    steps: Int[Array, "*b"]

    @property
    def converged(self) -> Bool[Array, "*b"]:
        return self.status == Status.CONVERGED


def _residuals(y, args, mechanics_shape) -> tuple[Float[Array, " n"], Float[Array, ""]]:
    """Whitened pixel residuals, and how many pixels carry information."""
    frame, device, noise = args
    state = LoadState.from_vector(y)
    predicted = render_frame(
        device, state.wrench, state.contact, exposure=state.exposure, mechanics_shape=mechanics_shape
    )
    # A pixel the camera clips tells nothing about the load (as in the Fisher information).
    unclipped = (predicted > 0) & (predicted < 1)
    whiten = jnp.where(unclipped, jax.lax.rsqrt(pixel_noise_variance(predicted, noise)), 0.0)
    # The weights follow the prediction but are held fixed under differentiation (Fisher
    # scoring): the fixed point then solves sum w (o - mu) dmu = 0, which is zero on
    # average at the truth; differentiating sigma(mu) too would add a biased term.
    residuals = ((frame - predicted) * jax.lax.stop_gradient(whiten)).ravel()
    return residuals, jnp.sum(unclipped.astype(residuals.dtype))


def _linearise(y, args, mechanics_shape) -> tuple[Float[Array, " n"], Float[Array, "13 n"], Float[Array, ""]]:
    """Residuals, their transposed Jacobian (one linearisation, a tangent per unknown vmapped)
    and the number of informative pixels."""
    r, jvp, used = jax.linearize(lambda y_: _residuals(y_, args, mechanics_shape), y, has_aux=True)
    # Rows per unknown: contiguous in memory, and J^T J is one cheap product.
    return r, jax.vmap(jvp)(jnp.eye(N_UNKNOWNS, dtype=y.dtype)), used


def _inverse_information(jacobian_t: Float[Array, "13 n"]) -> Float[Array, "13 13"]:
    information = jacobian_t @ jacobian_t.T
    # Normalised to unit diagonal before inverting, so float32 loses nothing to the units.
    scale = jax.lax.rsqrt(jnp.diagonal(information))
    correlation = information * scale[:, None] * scale[None, :]
    return jnp.linalg.inv(correlation) * scale[:, None] * scale[None, :]


@eqx.filter_jit
def refine_in_pixels(
    device: Device,
    frame: Float[Array, "h w"],
    start: Estimate | LoadState,
    noise: HighFidelity | None = None,
    *,
    max_steps: int = 16,
    tolerance: float = 0.1,
    mechanics_shape: tuple[int, int] = (64, 64),
) -> PixelFit:
    r"""Refine an inversion by a maximum-likelihood fit of the whole frame (see the module docstring).

    Gauss–Newton (optimistix, normal equations) from `start`, on the whitened pixel
    residual of [`render_frame`][] with the camera noise of [`pixel_noise_variance`][];
    clipped pixels (predicted at or beyond 0 or 1) weigh nothing. The unknowns are those
    of the inversion: the wrench over the paper's ranges, the contact centre (mm), the log
    contact radius, the contact's flatness and elongation and the log exposure, without the inversion's
    priors. They are
    measured in standard errors at `start` (one Jacobian, which also takes the first
    step), so that the solve stops when a step moves every unknown by less than
    `tolerance` of its standard error; convergence is quadratic by then, and the answer
    within about 1e-3 of a standard error. Each step costs one linearisation of the
    renderer and thirteen vmapped tangents; from a band estimate the fit takes three steps, and
    one more linearisation for the covariance.

    This is the efficient estimator **for frames the renderer describes exactly**: on a
    real unit the model's mismatch dominates (see the module docstring) and `chi2` shows
    it. `start` must be near the solution (Gauss–Newton has no safeguard): a converged
    band inversion is.

    **Arguments:**

    - `device`: the [`Device`][] that rendered the frame.
    - `frame`: the observed frame, `(device.height, device.width)`, camera units.
    - `start`: an [`Estimate`][] of the band inversion, or a [`LoadState`][] (its `state`).
    - `noise`: the camera of a [`HighFidelity`][] model; `None` for its defaults. Its
      floats are compile-time constants: give arrays to vary it without recompiling.
    - `max_steps`: Gauss–Newton steps allowed.
    - `tolerance`: the largest last step, in standard errors of each unknown, that counts
      as converged.
    - `mechanics_shape`: grid of the elastomer solve; use the grid that rendered the frame
      (64 x 64 against [`render_frame`][]'s default 256 x 256 already changes pixels by a
      few percent of their noise, which a fit of every pixel sees).

    **Returns:** a [`PixelFit`][]; its covariance is the Cramér–Rao bound at the solution
    with the contact and the exposure estimated too. A frame without contact, whose
    contact latents nothing constrains, comes back `NONFINITE`.
    """
    state = start.state if isinstance(start, Estimate) else start
    if not isinstance(state, LoadState) or state.scaled_wrench.shape != (6,):
        raise ValueError("start must be one frame's Estimate or LoadState")
    if frame.shape != (device.height, device.width):
        raise ValueError(f"frame has shape {frame.shape}, device expects {(device.height, device.width)}")
    dtype = device.p1.dtype
    y0 = state.vector().astype(dtype)
    args = (frame.astype(dtype), device, noise_as_arrays(noise, dtype))

    r0, jacobian_t, _ = _linearise(y0, args, mechanics_shape)
    # Unknowns in standard errors (conditional on the others) at the start.
    scale = jax.lax.rsqrt(jnp.sum(jacobian_t**2, axis=1))
    scaled_t = jacobian_t * scale[:, None]
    # That Jacobian's Gauss–Newton step is the first step of the solve.
    z1 = -jnp.linalg.solve(scaled_t @ scaled_t.T, scaled_t @ r0)
    solver = optx.GaussNewton(rtol=0.0, atol=tolerance, linear_solver=lx.Normal(lx.Cholesky()))
    solution = optx.least_squares(
        lambda z, a: _residuals(y0 + scale * z, a, mechanics_shape),
        solver,
        z1,
        args=args,
        max_steps=max_steps - 1,
        has_aux=True,
        throw=False,
    )
    y = y0 + scale * solution.value

    r, jacobian_t, used = _linearise(y, args, mechanics_shape)
    covariance_y = _inverse_information(jacobian_t)
    wrench_scale = jnp.asarray(WRENCH_SCALE, dtype)
    covariance = covariance_y[WRENCH_COORDINATES, WRENCH_COORDINATES] * wrench_scale[:, None] * wrench_scale[None, :]
    fitted = LoadState.from_vector(y)
    finite = jnp.all(jnp.isfinite(y)) & jnp.all(jnp.isfinite(covariance))
    status = jnp.where(solution.result == optx.RESULTS.successful, Status.CONVERGED, Status.MAX_STEPS)
    return PixelFit(
        wrench=fitted.wrench,
        covariance=covariance,
        sigma=jnp.sqrt(jnp.clip(jnp.diagonal(covariance), 0.0, None)),
        contact=fitted.contact,
        exposure=fitted.exposure,
        state=fitted,
        chi2=jnp.sum(r**2) / jnp.maximum(used - N_UNKNOWNS, 1.0),
        status=jnp.where(finite, status, Status.NONFINITE).astype(jnp.int32),
        steps=jnp.asarray(solution.stats["num_steps"], jnp.int32) + 1,
    )
