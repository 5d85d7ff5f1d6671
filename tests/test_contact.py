import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest

from moirejax.physics._contact import Contact, surface_grid, surface_tractions, traction_resultant

from .helpers import check_grad_against_fd


GRID = surface_grid((96, 96), 16.0, (512, 512), 3.0, 12.0)


@pytest.mark.parametrize(
    "wrench, contact",
    [
        ([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], Contact(0.0, 0.0, 3.0)),
        ([0.1, -0.2, 0.8, 0.004, -0.006, 0.007], Contact(2.3, -1.7, 3.5)),
        ([-0.2, 0.15, 1.2, -0.012, 0.011, -0.008], Contact(-6.1, 4.4, 2.2)),
        ([0.0, 0.0, 0.0, 0.0, 0.0, 0.003], Contact(0.0, 0.0, 4.0)),
    ],
)
def test_resultant_equals_requested_wrench(wrench, contact):
    wrench = jnp.asarray(wrench)
    tractions = surface_tractions(wrench, contact, GRID)
    assert jnp.allclose(traction_resultant(tractions, GRID), wrench, rtol=0, atol=1e-9)


def test_centred_press_is_a_hertz_like_pressure():
    tractions = surface_tractions(jnp.array([0.0, 0, 1.0, 0, 0, 0]), Contact(0.0, 0.0, 3.0), GRID)
    tx, ty, p = tractions
    assert jnp.allclose(tx, 0) and jnp.allclose(ty, 0)
    # Peak at the centre, positive inside, tiny outside the patch, mean pressure = F / (pi r^2).
    rho = jnp.hypot(GRID.X, GRID.Y)
    assert p.max() == p[rho == rho.min()].max()
    assert jnp.all(p[rho < 2.5] > 0) and jnp.all(jnp.abs(p[rho > 4.0]) < 1e-3 * p.max())
    hertz_peak = 1.5 * 1.0 / (jnp.pi * 3.0**2)
    assert abs(float(p.max()) / float(hertz_peak) - 1) < 0.1


def test_off_centre_press_moments_follow_convention():
    # Pressing at +x gives Ty = -x Fz (z into the sensor); at +y gives Tx = +y Fz.
    contact = Contact(5.0, 2.0, 3.0)
    fz = 1.0
    wrench = jnp.array([0.0, 0.0, fz, 2.0 * fz / 1000, -5.0 * fz / 1000, 0.0])
    p = surface_tractions(wrench, contact, GRID)[2]
    # A pressure centred on the contact: no tilt needed, profile symmetric about it.
    symmetric = surface_tractions(jnp.array([0.0, 0, fz, 0, 0, 0]), Contact(0.0, 0.0, 3.0), GRID)[2]
    assert float(p.max()) == pytest.approx(float(symmetric.max()), rel=0.05)


def test_gradients_with_respect_to_wrench_and_contact():
    def f(args):
        wrench, contact = args
        return surface_tractions(wrench, contact, GRID)

    args = (jnp.array([0.1, -0.05, 0.9, 0.003, -0.002, 0.004]), Contact(1.0, -0.5, 3.0))
    check_grad_against_fd(f, args)
    jac = jax.jacfwd(lambda w: surface_tractions(w, args[1], GRID))(args[0])
    assert jac.shape == (3, 96, 96, 6)


def test_bad_wrench_shape_is_a_trace_time_error():
    # Under pytest jaxtyping's runtime check fires first; without it, our ValueError.
    with pytest.raises((ValueError, jaxtyping.TypeCheckError)):
        surface_tractions(jnp.zeros(5), Contact(), GRID)


def test_resultant_under_vmap():
    wrenches = jnp.asarray(np.random.default_rng(0).normal(size=(4, 6)) * np.array([0.1, 0.1, 1, 0.005, 0.005, 0.004]))
    tractions = jax.vmap(lambda w: surface_tractions(w, Contact(1.0, 2.0, 3.0), GRID))(wrenches)
    resultants = jax.vmap(lambda t: traction_resultant(t, GRID))(tractions)
    assert jnp.allclose(resultants, wrenches, atol=1e-9)
