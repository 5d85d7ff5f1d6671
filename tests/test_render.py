import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import moirejax as mj
from moirejax.physics._contact import Contact
from moirejax.physics._optics import image_coordinates
from moirejax.physics._render import deformation, render_deformed, render_frame, render_frame_high, upper_grating_phase

from .helpers import check_grad_against_fd, spectral_peak, wrap


def _lines(**kwargs):
    return mj.preset("mid", layout="lines", **kwargs)


def _render_displaced(device, ux=0.0, uy=0.0, w=0.0):
    shape = (device.height, device.width)
    displacement = jnp.stack([jnp.full(shape, ux), jnp.full(shape, uy), jnp.full(shape, w)])
    return render_deformed(device, displacement, jnp.zeros(shape))


def _peak(device, frame):
    K = np.asarray(device.moire_wavevectors()[0])
    return spectral_peak(frame, float(device.px_per_mm), K, 0.4 * np.linalg.norm(K))


def test_rendered_period_matches_exact_parallax():
    device = _lines(alpha1=math.radians(1.0))
    K, _ = _peak(device, _render_displaced(device))
    expected = float(mj.moire_period_exact(device.p1, device.p2, device.alpha1 - device.alpha2, device.a, device.Z))
    assert abs(2 * math.pi / np.linalg.norm(K) - expected) / expected < 0.01


def test_rigid_rotation_of_upper_grating_rotates_fringes_as_eq2():
    base = _lines()
    for dalpha_deg in (0.3, 0.8, -0.5):
        device = dataclasses.replace(base, alpha1=jnp.asarray(math.radians(dalpha_deg)))
        K, _ = _peak(device, _render_displaced(device))
        measured = math.atan2(K[1], K[0])
        expected = float(mj.moire_orientation(device.moire_wavevectors()[0]))
        assert abs(measured - expected) < math.radians(0.5)
        # Strong amplification of rotation: theta moves far more than the grating did.
        assert abs(expected) > 5 * abs(math.radians(dalpha_deg))


def test_uniform_shift_of_upper_grating_shifts_phase_by_k1_u():
    device = _lines()
    _, psi0 = _peak(device, _render_displaced(device))
    k1 = np.asarray(device.upper_wavevectors()[0])
    for u in (0.01, 0.03):
        _, psi = _peak(device, _render_displaced(device, ux=u))
        # Phase moves by -k1.u: the fringes move by u * Lambda / p1, the shear amplification.
        assert abs(wrap(psi - psi0 + k1[0] * u)) < 0.02


def test_translation_of_both_gratings_shifts_phase_by_K_u():
    device = _lines()
    _, psi0 = _peak(device, _render_displaced(device))
    t = np.array([0.05, 0.0])  # image-plane translation (mm)
    k1 = np.asarray(device.upper_wavevectors()[0])
    k2 = np.asarray(device.reference_wavevectors()[0])
    magnification = float((device.Z + device.a) / device.Z)
    moved = eqx.tree_at(
        lambda d: (d.optics.phase1, d.optics.phase2),
        device,
        (device.optics.phase1 - k1 @ t * magnification, device.optics.phase2 - k2 @ t),
    )
    _, psi = _peak(moved, _render_displaced(moved))
    K = np.asarray(device.moire_wavevectors()[0])
    assert abs(wrap(psi - psi0 + K @ t)) < 0.02


@pytest.mark.parametrize("p1, grows", [(0.35, True), (0.45, False)])
def test_compression_moves_period_as_eq7_predicts(p1, grows):
    # Mid has delta_obj < a/Z: compression makes fringes sparser; p1 = 0.45 has delta_obj > a/Z.
    device = _lines(p1=p1)
    assert (float(mj.object_mismatch(device.p1, device.p2)) < float(device.a / device.Z)) == grows
    K0, _ = _peak(device, _render_displaced(device))
    K1, _ = _peak(device, _render_displaced(device, w=0.05))
    assert (np.linalg.norm(K1) < np.linalg.norm(K0)) == grows


def test_press_changes_local_period_in_predicted_direction():
    # A real contact: the bonded layer squeezes outward and the surface moves closer;
    # both make the local apparent upper pitch grow, so Mid fringes get sparser at the contact.
    device = _lines()
    state = deformation(device, jnp.array([0.0, 0, 1.2, 0, 0, 0]), Contact(0.0, 0.0, 4.0), (128, 128))
    ux, uy, w = state.displacement
    centre = (64, 64)
    assert float(w[centre]) > 0
    strain = (ux[64, 66] - ux[64, 62]) / (4 * float(state.grid.spacing))
    assert float(strain) > 0


def test_gradients_wrt_wrench_and_device_match_finite_differences():
    device = mj.preset("mid", height=64, width=64, px_per_mm=4.0)
    wrench = jnp.array([0.1, -0.05, 0.8, 0.002, -0.003, 0.004])
    contact = Contact(1.0, -0.5, 3.0)

    def frame_of_wrench(w):
        return render_frame(device, w, contact, mechanics_shape=(32, 32))

    check_grad_against_fd(frame_of_wrench, wrench, rtol=1e-4, atol=1e-6)

    def frame_of_device(d):
        return render_frame(d, wrench, contact, mechanics_shape=(32, 32))

    check_grad_against_fd(frame_of_device, device, eps=1e-6, rtol=1e-4, atol=1e-6)


def test_jit_vmap_grad_compose():
    device = mj.preset("mid", height=64, width=64, px_per_mm=4.0)
    contact = Contact(0.0, 0.0, 3.0)
    wrenches = jnp.array([[0.0, 0, 0.5, 0, 0, 0], [0.1, 0, 1.0, 0, 0, 0.002]])

    def loss(w):
        return jnp.sum(render_frame(device, w, contact, mechanics_shape=(32, 32)) ** 2)

    grads = jax.jit(jax.vmap(jax.grad(loss)))(wrenches)
    assert grads.shape == (2, 6) and jnp.all(jnp.isfinite(grads))
    total = jax.grad(lambda ws: jnp.sum(jax.vmap(loss)(ws)))(wrenches)
    assert jnp.allclose(total, grads, rtol=1e-8)


def test_high_fidelity_frame_is_quantised_noisy_and_close_to_model():
    device = mj.preset("mid", height=128, width=128, px_per_mm=8.0)
    wrench = jnp.array([0.0, 0, 0.8, 0, 0, 0])
    contact = Contact(0.0, 0.0, 3.0)
    model = np.asarray(render_frame(device, wrench, contact, mechanics_shape=(64, 64)))
    high = np.asarray(render_frame_high(jax.random.PRNGKey(0), device, wrench, contact, mechanics_shape=(64, 64)))
    assert high.min() >= 0 and high.max() <= 1
    assert np.allclose(high * 255, np.round(high * 255))
    # Same moire: the mean brightness agrees within the binary-vs-truncated-harmonics gap.
    assert abs(high.mean() - model.mean()) < 0.1 * model.mean()


def test_band_model_predicts_what_the_demodulator_reads_from_a_rendered_frame():
    # The inversion's forward model skips the render: the low-frequency part of the frame on
    # a 96 x 96 grid through the demodulator's band-passes. Against the full render (512 x 512,
    # elastomer on 256 x 256, every modelled harmonic, lens PSF) demodulated for real:
    device = mj.preset("mid")
    demodulator = mj.Demodulator((device.height, device.width), 16.0, np.asarray(device.moire_wavevectors()))
    wrench, contact = jnp.asarray([0.05, -0.03, 0.6, 0.002, -0.001, 0.003]), Contact(1.0, -0.5, 3.5)
    K = demodulator.wavevectors
    measured = demodulator(render_frame(device, wrench, contact), K)
    unloaded = demodulator(render_frame(device, jnp.zeros(6), Contact()), K)
    model = mj.band_model(device, demodulator, (96, 96), K)
    predicted = model(wrench, contact)
    # Weighted by the envelope: the demodulator divides by it, which blows up the border.
    envelope = np.asarray(demodulator.fringe_envelope)
    scale = np.max(envelope * np.abs(np.asarray(unloaded.fringe)))
    error = np.max(envelope * np.abs(np.asarray(predicted.fringe - measured.fringe))) / scale
    change = np.max(envelope * np.abs(np.asarray(measured.fringe - unloaded.fringe))) / scale
    assert change > 0.1 and error < 2e-3 * change  # the model follows the load to 0.1% (0.06% of the amplitude)
    weight = np.asarray(demodulator.brightness_envelope)
    brightness_scale = np.max(weight * np.abs(np.asarray(measured.brightness)))
    assert np.max(weight * np.abs(np.asarray(predicted.brightness - measured.brightness))) < 1e-4 * brightness_scale
    # The model built once is `predicted_bands` evaluated afresh.
    again = mj.predicted_bands(device, demodulator, wrench, contact, model_shape=(96, 96), reference_wavevector=K)
    np.testing.assert_allclose(np.asarray(predicted.fringe), np.asarray(again.fringe), rtol=0, atol=1e-12 * scale)


def test_upper_grating_is_read_at_its_material_point():
    # The grating moves with the material: under an affine displacement u = G X of the
    # surface (a twist of 0.1 rad plus a 3% stretch, far beyond the linear regime's
    # X0 = Xs - u(Xs)), the ray meeting the surface at Xs sees the grating's material point
    # X0 = (I + G)^-1 Xs exactly.
    device = mj.preset("mid", height=64, width=64)
    x, y = image_coordinates(device)
    magnification = (device.Z + device.a) / device.Z
    G = np.array([[0.03, -0.1], [0.1, 0.03]])
    X, Y = x * magnification, y * magnification
    displacement = jnp.stack([G[0, 0] * X + G[0, 1] * Y, G[1, 0] * X + G[1, 1] * Y, jnp.zeros_like(X)])
    phase = upper_grating_phase(device, x, y, displacement)
    inverse = np.linalg.inv(np.eye(2) + G)
    X0 = inverse[0, 0] * X + inverse[0, 1] * Y
    Y0 = inverse[1, 0] * X + inverse[1, 1] * Y
    k1 = np.asarray(device.upper_wavevectors())
    expected = (
        k1[:, 0, None, None] * X0[None]
        + k1[:, 1, None, None] * Y0[None]
        + np.asarray(device.optics.phase1)[:, None, None]
    )
    np.testing.assert_allclose(np.asarray(phase), np.asarray(expected), atol=1e-9)
    # The first-order reading X0 = Xs - u(Xs) would be off by k1 |G^2 X|: radians at the edge.
    first_order = k1[0, 0] * (X - displacement[0]) + k1[0, 1] * (Y - displacement[1])
    assert np.max(np.abs(np.asarray(first_order) - np.asarray(expected[0]))) > 0.5
