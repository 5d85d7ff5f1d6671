"""The inversion's Levenberg–Marquardt: it stops where the data can no longer tell points
apart, measured against the exact optimum of problems whose answer is known independently."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from scipy.optimize import least_squares

from moirejax.inverse._estimate import reweighing_step
from moirejax.inverse._solvers import _covariance_shape, Marquardt


NOISE = 0.02
TIMES = np.linspace(0.0, 4.0, 2000)


def _decay(p, t):
    return p[0] * jnp.exp(-p[1] * t) + p[2] * jnp.sin(p[3] * t)


def _data(seed, misfit=0.0):
    rng = np.random.default_rng(seed)
    truth = np.array([1.5, 0.8, 0.3, 2.0])
    clean = np.asarray(_decay(truth, TIMES))
    # `misfit`: a component the model does not contain, many times the noise.
    return clean + misfit * np.cos(7.0 * TIMES) ** 3 + NOISE * rng.standard_normal(TIMES.size)


def _residuals(p, data):
    return _decay(p, TIMES) - data


def _exact(data, start):
    """The optimum and the standard errors of its unknowns, from scipy in float64."""
    fit = least_squares(
        lambda p: np.asarray(_residuals(jnp.asarray(p), data)), start, xtol=1e-15, ftol=1e-15, gtol=1e-15
    )
    jacobian = np.asarray(jax.jacfwd(_residuals)(jnp.asarray(fit.x), data))
    sigma = NOISE * np.sqrt(np.diag(np.linalg.inv(jacobian.T @ jacobian)))
    return fit.x, sigma


@pytest.mark.parametrize("misfit", [0.0, 0.2], ids=["model-describes-data", "unmodelled-component"])
def test_stops_within_its_tolerance_of_the_optimum(misfit):
    data = _data(0, misfit)
    start = np.array([1.0, 0.5, 0.5, 1.8])
    optimum, sigma = _exact(data, start)
    tolerance = 0.05
    solver = Marquardt(noise=jnp.asarray(NOISE), tolerance=tolerance)
    sol = optx.least_squares(_residuals, solver, jnp.asarray(start), args=jnp.asarray(data), max_steps=100)
    assert sol.result == optx.RESULTS.successful
    # The stopping rule is a Gauss-Newton step shorter than the tolerance; near the optimum
    # that step is the distance to it, to first order.
    assert np.all(np.abs(np.asarray(sol.value) - optimum) / sigma < 2 * tolerance)
    # A looser tolerance stops earlier, and still inside its own distance.
    loose = optx.least_squares(
        _residuals, Marquardt(noise=jnp.asarray(NOISE), tolerance=0.5), jnp.asarray(start), args=jnp.asarray(data)
    )
    assert int(loose.stats["num_steps"]) <= int(sol.stats["num_steps"])
    assert np.all(np.abs(np.asarray(loose.value) - optimum) / sigma < 1.0)


def test_takes_no_step_from_the_optimum_and_composes_with_jit_and_vmap():
    data = np.stack([_data(seed) for seed in range(3)])
    start = np.array([1.0, 0.5, 0.5, 1.8])
    solver = Marquardt(noise=jnp.asarray(NOISE), tolerance=0.05)

    @jax.jit
    def solve(y0, d):
        sol = optx.least_squares(_residuals, solver, y0, args=d, max_steps=100, throw=False)
        return sol.value, sol.stats["num_steps"], sol.result

    values, steps, _ = jax.vmap(solve, in_axes=(None, 0))(jnp.asarray(start), jnp.asarray(data))
    for d, value in zip(data, values):
        optimum, sigma = _exact(d, start)
        assert np.all(np.abs(np.asarray(value) - optimum) / sigma < 0.1)
        one, _, _ = solve(jnp.asarray(start), jnp.asarray(d))
        np.testing.assert_allclose(np.asarray(one), np.asarray(value), rtol=1e-9, atol=1e-12)
    assert np.all(np.asarray(steps) > 0)
    optimum, _ = _exact(data[0], start)
    _, steps_from_optimum, result = solve(jnp.asarray(optimum), jnp.asarray(data[0]))
    assert int(steps_from_optimum) == 0 and result == optx.RESULTS.successful


def test_a_start_it_cannot_improve_ends_without_running_to_max_steps():
    # A cost whose minimum is a kink: no smooth model describes it, and the solver must
    # still stop once no step as long as its tolerance lowers the cost.
    def kinked(p, _):
        return jnp.concatenate([jnp.abs(p) * 1e3, jnp.zeros(10)])

    solver = Marquardt(noise=jnp.asarray(1.0), tolerance=0.05)
    sol = optx.least_squares(kinked, solver, jnp.array([0.3, -0.2]), max_steps=200, throw=False)
    assert sol.result == optx.RESULTS.successful
    assert int(sol.stats["num_steps"]) < 200
    assert np.all(np.abs(np.asarray(sol.value)) < 1e-2)


def test_held_coordinates_keep_their_start_and_leave_the_others_solve_unchanged():
    # A fifth unknown, an offset the data do contain: held at a value, the solve must be the
    # exact optimum of the other four with the offset fixed there.
    data = _data(1) + 0.1
    held_value = 0.08

    def with_offset(p, d):
        return _decay(p[:4], TIMES) + p[4] - d

    start = np.array([1.0, 0.5, 0.5, 1.8, held_value])
    optimum, sigma = _exact(data - held_value, start[:4])
    solver = Marquardt(noise=jnp.asarray(NOISE), tolerance=0.05, held=(4,))
    sol = optx.least_squares(with_offset, solver, jnp.asarray(start), args=jnp.asarray(data), max_steps=100)
    assert float(sol.value[4]) == held_value
    assert np.all(np.abs(np.asarray(sol.value[:4]) - optimum) / sigma < 0.1)
    # Freed, the offset is fitted and moves towards the data's.
    free = optx.least_squares(
        with_offset, Marquardt(noise=jnp.asarray(NOISE), tolerance=0.05), jnp.asarray(start), args=jnp.asarray(data)
    )
    assert abs(float(free.value[4]) - 0.1) < 0.01


def _weakly_seen_system():
    """A Jacobian whose columns are informed from 1e-3 to 1e3, the two weakest strongly
    correlated, and a residual it does not explain."""
    rng = np.random.default_rng(3)
    basis = rng.standard_normal((500, 6))
    basis[:, 1] = basis[:, 0] + 0.3 * basis[:, 1]
    return basis * np.array([1e-3, 1e-3, 1.0, 10.0, 1e2, 1e3]), rng.standard_normal(500)


def test_covariance_of_unknowns_on_very_different_scales_in_single_precision():
    """A frame's unknowns are informed over many decades (a contact centre in mm against a
    shear the gratings barely see). In single precision the normal matrix's inverse must
    keep the weakly seen direction's variance, not drop it as rounding: a dropped direction
    reads as an axis known almost exactly."""
    jacobian, _ = _weakly_seen_system()
    jtj = jacobian.T @ jacobian
    exact = np.diag(np.linalg.inv(jtj))
    single = np.diag(np.asarray(_covariance_shape(jnp.asarray(jtj, jnp.float32)), np.float64))
    np.testing.assert_allclose(single, exact, rtol=1e-2)
    # The plain pseudo-inverse in single precision loses the weak directions: what the
    # scaling is for.
    plain = np.diag(np.asarray(jnp.linalg.pinv(jnp.asarray(jtj, jnp.float32), hermitian=True), np.float64))
    assert np.min(plain[:2] / exact[:2]) < 0.1


def test_the_reweighing_step_stays_off_directions_single_precision_cannot_resolve():
    """The reweighed priors' step at the end of a solve is the opposite choice from the
    covariance's: along the weakly seen pair of the system above, a residual the model
    does not explain would pull the exact Gauss-Newton step far out of the region where the
    linearisation holds. In single precision the step must leave that pair nearly where it
    is, and still take the well-seen unknowns' step."""
    jacobian, misfit = _weakly_seen_system()
    jtj, gradient = jacobian.T @ jacobian, jacobian.T @ misfit
    exact = -np.linalg.solve(jtj, gradient)
    step = np.asarray(reweighing_step(jnp.asarray(jtj, jnp.float32), jnp.asarray(gradient, jnp.float32)), np.float64)
    assert np.max(np.abs(step[:2] / exact[:2])) < 0.1
    # The three best-seen unknowns take the exact step, to what the dropped directions they
    # correlate with shift it.
    np.testing.assert_allclose(step[3:], exact[3:], rtol=0.2)
    # The unit-diagonal inverse, right for the covariance, takes the whole weak step.
    scaled = np.asarray(-_covariance_shape(jnp.asarray(jtj, jnp.float32)) @ jnp.asarray(gradient, jnp.float32))
    assert np.min(np.abs(scaled[:2] / exact[:2])) > 0.5
