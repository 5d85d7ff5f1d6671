import equinox as eqx
import jax.numpy as jnp
import jax.random as jr
import jaxtyping
import numpy as np
import pytest

import moirejax as mj
from moirejax.design._observability import fisher_information
from moirejax.inverse._pixel_fit import refine_in_pixels
from moirejax.physics._contact import Contact
from moirejax.physics._render import HighFidelity, pixel_noise_variance, render_frame

from .helpers import camera_variance, finite_difference_jacobian


# A coarse frame and mechanics grid: only the numerics of the fit are under test here.
SHAPE = (32, 32)
NOISE = HighFidelity(full_well=3000.0, read_noise=5.0)
WRENCH = np.array([0.03, -0.02, 0.6, 0.001, -0.0005, 0.002])
X0, Y0, RADIUS, EXPOSURE = 0.4, -0.3, 3.5, 1.05


# Every fit of this module goes through one compiled program: a new frame, start or
# load must never recompile the per-frame solve.
_refine = eqx.filter_jit(eqx.debug.assert_max_traces(refine_in_pixels, max_traces=1))


def _device():
    return mj.preset("mid", height=48, width=48, px_per_mm=6.0)


def _truth():
    return mj.LoadState.from_load(jnp.asarray(WRENCH), Contact(x0=X0, y0=Y0, radius=RADIUS), EXPOSURE)


def _frame(device):
    contact = Contact(x0=X0, y0=Y0, radius=RADIUS)
    return render_frame(device, jnp.asarray(WRENCH), contact, exposure=EXPOSURE, mechanics_shape=SHAPE)


def test_noise_free_frame_recovers_the_load_from_a_perturbed_start():
    device = _device()
    truth = _truth()
    # Off in every unknown, the wrench by about 2% of its range.
    offset = jnp.asarray([0.02, -0.02, 0.01, 0.02, -0.02, 0.02, 0.05, -0.05, 0.03, 0.05, 0.04, -0.03, 0.01])
    start = mj.LoadState.from_vector(truth.vector() + offset)
    fit = _refine(device, _frame(device), start, NOISE, mechanics_shape=SHAPE)
    assert int(fit.status) == int(mj.Status.CONVERGED) and bool(fit.converged)
    assert 2 <= int(fit.steps) <= 6
    assert np.all(np.abs(np.asarray(fit.wrench) - WRENCH) < 1e-3 * np.asarray(fit.sigma))
    np.testing.assert_allclose(fit.state.vector(), truth.vector(), atol=1e-8)
    assert float(fit.contact.radius) == pytest.approx(RADIUS, rel=1e-8)
    assert float(fit.exposure) == pytest.approx(EXPOSURE, rel=1e-8)
    assert float(fit.chi2) < 1e-12


def test_covariance_is_the_inverse_fisher_information():
    device = _device()
    frame = _frame(device)
    fit = _refine(device, frame, _truth(), NOISE, mechanics_shape=SHAPE)

    # A second route: central differences of the frame in (wrench, x0, y0, radius,
    # flatness, elongation, exposure), the camera noise by hand (the pixel fit has no
    # priors). The fit's log radius and log exposure change the nuisance parameterisation
    # only, which leaves the wrench block unchanged.
    theta = np.concatenate([WRENCH, [X0, Y0, RADIUS, 0.0, 0.0, 0.0, EXPOSURE]])

    def render(t):
        contact = Contact(x0=t[6], y0=t[7], radius=t[8], flatness=t[9], stretch_x=t[10], stretch_xy=t[11])
        return np.asarray(render_frame(device, jnp.asarray(t[:6]), contact, exposure=t[12], mechanics_shape=SHAPE))

    J = finite_difference_jacobian(render, theta, [1e-5] * 3 + [1e-7] * 3 + [1e-5] * 7)
    variance = camera_variance(frame, full_well=3000.0, read_noise=5.0).ravel()
    information = (J / variance) @ J.T
    covariance = np.linalg.inv(information)[:6, :6]
    scale = np.sqrt(np.outer(np.diag(covariance), np.diag(covariance)))
    assert np.max(np.abs(np.asarray(fit.covariance) - covariance) / scale) < 1e-5
    np.testing.assert_allclose(fit.sigma, np.sqrt(np.diag(covariance)), rtol=1e-5)

    # `fisher_information` is the same information with the exposure known: its 9x9
    # block agrees, and its bound is nowhere wider than the fit's.
    F9 = np.asarray(
        fisher_information(
            device,
            jnp.asarray(WRENCH),
            Contact(x0=X0, y0=Y0, radius=RADIUS),
            NOISE,
            exposure=EXPOSURE,
            mechanics_shape=SHAPE,
        )
    )
    np.testing.assert_allclose(F9, information[:9, :9], rtol=1e-5, atol=1e-6 * np.max(np.abs(F9)))
    known_exposure = np.sqrt(np.diag(np.linalg.inv(F9))[:6])
    assert np.all(known_exposure <= np.asarray(fit.sigma) * (1 + 1e-9))


def test_noisy_frames_fit_to_their_noise(getkey):
    device = _device()
    frame = _frame(device)
    std = jnp.sqrt(pixel_noise_variance(frame, NOISE))
    for _ in range(2):
        noisy = frame + std * jr.normal(getkey(), frame.shape)
        fit = _refine(device, noisy, _truth(), NOISE, mechanics_shape=SHAPE)
        assert bool(fit.converged)
        # The noise the weights assume: chi2 per degree of freedom is 1 (its std is 0.03 here).
        assert float(fit.chi2) == pytest.approx(1.0, abs=0.15)


def test_wrong_shapes_are_refused():
    device = _device()
    with pytest.raises(ValueError, match="frame has shape"):
        refine_in_pixels(device, jnp.zeros((40, 48)), _truth())
    with pytest.raises((ValueError, jaxtyping.TypeCheckError)):
        refine_in_pixels(device, jnp.zeros((48, 48)), jnp.zeros(9))
