"""Two contacts at once: the bands superpose, and a frame one patch cannot explain is read
with two, on frames rendered through the simulator's own indenter mechanics."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import moirejax as mj
from moirejax import Contact, Indenter, invert, Inverter, LoadState, Status
from moirejax.inverse._invert_io import _rows, CSV_HEADER
from moirejax.inverse._second_contact import _pair_vector, both_press, pair_states


pytestmark = pytest.mark.xdist_group("second_contact")

SCALE = np.array([mj.PAPER_RANGES[axis] for axis in mj.WRENCH_AXES])


@pytest.fixture(scope="module")
def mid():
    return mj.preset("mid")


def test_contacts_superpose_in_the_bands(mid):
    # The layer is linear: two halves of a load at one place are the whole load (without the
    # rim light, which grows as the square root of each contact's own normal force); a
    # contact without load adds nothing, rim included; and the order of the contacts does
    # not matter.
    demodulator = mj.Demodulator((mid.height, mid.width), float(mid.px_per_mm), mid.moire_wavevectors())
    model = mj.band_model(mid, demodulator, (64, 64), mid.moire_wavevectors())
    wrench = jnp.array([0.1, -0.05, 0.8, 0.0, 0.0, 0.002])
    other = jnp.array([0.0, 0.04, 0.4, -0.001, 0.0016, 0.0])
    here, there = Contact(-3.0, 2.0, 2.5), Contact(4.0, -1.0, 3.0)
    stack = lambda *cs: jax.tree_util.tree_map(lambda *v: jnp.stack(v), *cs)  # noqa: E731
    close = lambda a, b: np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)  # noqa: E731

    one = model(wrench, here)
    alone = model.of_contacts(jnp.stack([wrench, jnp.zeros(6)]), stack(here, there))
    close(alone.fringe, one.fringe)
    close(alone.light, one.light)
    both = model.of_contacts(jnp.stack([wrench, other]), stack(here, there))
    swapped = model.of_contacts(jnp.stack([other, wrench]), stack(there, here))
    close(both.fringe, swapped.fringe)
    assert float(jnp.max(jnp.abs(both.fringe - one.fringe))) > 0.1
    no_rim = eqx.tree_at(lambda m: m.mechanics.device.optics.rim_gain, model, 0.0)
    halves = no_rim.of_contacts(jnp.stack([0.5 * wrench, 0.5 * wrench]), stack(here, here))
    close(halves.fringe, no_rim(wrench, here).fringe)
    close(halves.brightness, no_rim(wrench, here).brightness)


def test_a_patch_that_pulls_is_no_second_contact():
    # A push-pull pair can take most of a one-patch misfit away (an independent renderer's
    # aliasing, on a centred press, was "explained" by 1.1 N and -2.0 N), and its sum then
    # reads a press as a pull; contacts only push.
    def press(fz, x0):
        return LoadState.from_load(jnp.array([0.0, 0.0, fz, 0.0, -x0 * fz * 1e-3, 0.0]), Contact(x0, 0.0, 3.0))

    assert bool(both_press(_pair_vector(press(0.7, -4.0), press(0.35, 4.0))))
    assert not bool(both_press(_pair_vector(press(1.1, -1.0), press(-2.0, 1.0))))
    assert not bool(both_press(_pair_vector(press(-0.2, -4.0), press(0.9, 4.0))))
    first, second = pair_states(_pair_vector(press(0.7, -4.0), press(0.35, 4.0)))
    np.testing.assert_allclose(np.asarray(first.wrench[2]), 0.7, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(second.wrench[2]), 0.35, rtol=1e-6)


@pytest.fixture(scope="module")
def simulator(mid):
    return mj.Simulator(mid, fidelity="model")


@pytest.fixture(scope="module")
def inverter(mid, simulator):
    rest = simulator.deformed_frame(jax.random.PRNGKey(0), mj.indenter_deformation(mid, []))
    return Inverter(mid, reference=rest)


def _frame(simulator, mid, indenters):
    load = mj.indenter_deformation(mid, indenters)
    return simulator.deformed_frame(jax.random.PRNGKey(1), load), np.asarray(load.wrench)


def test_two_fingertips_are_read_with_two_patches(mid, simulator, inverter):
    # Two spherical fingertips 9 mm apart, one pressing harder and sheared, the other
    # twisted: one patch read such loads with Fz at R2 -0.9.
    fingertips = [
        Indenter("sphere", -4.0, 2.0, 3.0, force=(0.08, 0.0, 0.7)),
        Indenter("sphere", 4.0, -2.5, 3.0, force=(0.0, -0.05, 0.35), twist=0.002),
    ]
    frame, truth = _frame(simulator, mid, fingertips)
    estimate = invert(inverter, frame)
    assert Status(int(estimate.status)) in (Status.CONVERGED, Status.MAX_STEPS), Status(int(estimate.status))
    assert int(estimate.contacts) == 2
    # Within 8 % of each axis' range (the simulator's spherical fingertips are not the
    # inversion's patches; each alone reads within 1 %, the pair's shear split within 7 %).
    error = (np.asarray(estimate.wrench) - truth) / SCALE
    assert np.all(np.abs(error) < 0.08), error
    # The main patch is the harder-pressing fingertip; the second carries the other's load.
    assert np.hypot(float(estimate.contact.x0) + 4.0, float(estimate.contact.y0) - 2.0) < 0.5
    second = estimate.second_contact
    assert np.hypot(float(second.x0) - 4.0, float(second.y0) + 2.5) < 0.5
    assert abs(float(estimate.second_wrench[2]) - 0.35) < 0.05
    assert np.all(np.asarray(estimate.sigma) > 0)
    # The wrench CSV carries the second patch and its share of the wrench.
    row = dict(zip(CSV_HEADER, _rows(["f"], jax.tree.map(lambda x: x[None], estimate), [None])[0]))
    assert row["contacts"] == 2 and row["second_fz"] == pytest.approx(float(estimate.second_wrench[2]))
    assert row["second_flatness"] == pytest.approx(float(estimate.second_contact.flatness))
    # One fingertip alone is read with one patch.
    single, truth = _frame(simulator, mid, fingertips[:1])
    estimate = invert(inverter, single)
    assert int(estimate.contacts) == 1
    assert np.all(np.isnan(np.asarray(estimate.second_contact.x0)))
    row = dict(zip(CSV_HEADER, _rows(["f"], jax.tree.map(lambda x: x[None], estimate), [None])[0]))
    assert row["contacts"] == 1 and np.isnan(row["second_fz"])
    assert np.all(np.abs((np.asarray(estimate.wrench) - truth) / SCALE) < 0.02)
    # A round patch explains it: its elongation is never freed (only rounding in the
    # estimate's last step, which moves unknowns the data do not see towards their priors).
    assert float(estimate.contact.aspect_ratio) == pytest.approx(1.0, abs=1e-9)


def test_an_edge_is_read_with_one_elongated_patch(mid, simulator, inverter):
    # An edge 10 mm long and 1.6 mm wide, pressed and sheared, through the simulator's own
    # line mechanics (a stadium-shaped pressure, not the inversion's ellipse).
    edge = Indenter("line", 1.0, -1.0, 5.0, 0.8, angle=0.5, force=(0.05, -0.08, 0.8), twist=0.002)
    frame, truth = _frame(simulator, mid, [edge])
    estimate = invert(inverter, frame)
    assert Status(int(estimate.status)) in (Status.CONVERGED, Status.MAX_STEPS), Status(int(estimate.status))
    assert int(estimate.contacts) == 1
    contact = estimate.contact
    assert float(contact.aspect_ratio) > 3.0
    assert abs(float(contact.long_axis_angle) - 0.5) < np.radians(3.0)
    assert np.hypot(float(contact.x0) - 1.0, float(contact.y0) + 1.0) < 0.3
    # The normal force and the torques within 5 % of their ranges; the shear within 20 %: the
    # ellipse spreads it like its pressure, which is not the stadium's (read through one
    # round patch or two, edges read Fz at R2 0.08 on the contact-shape benchmark).
    error = np.abs(np.asarray(estimate.wrench) - truth) / SCALE
    assert np.all(error[2:] < 0.05) and np.all(error[:2] < 0.2), error
    row = dict(zip(CSV_HEADER, _rows(["f"], jax.tree.map(lambda x: x[None], estimate), [None])[0]))
    assert row["aspect_ratio"] == pytest.approx(float(contact.aspect_ratio))
    assert row["long_axis_angle"] == pytest.approx(float(contact.long_axis_angle))
