"""Moire observables: Fourier-transform demodulation against independent references.

Frames are synthesised here in numpy straight from `docs/conventions.md` (pixel (i, j) at
x = (j - (w-1)/2)/s, y = ((h-1)/2 - i)/s), never with the code under test. References:
the analytic fringe parameters, a zero-padded Hann-windowed numpy FFT with scikit-image's
peak finder, `skimage.restoration.unwrap_phase`, `cv2.moments`, and finite differences.
"""

import dataclasses
import math

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.feature import peak_local_max
from skimage.restoration import unwrap_phase

import moirejax as mj
from moirejax.observe._observables import (
    brightness_baseline,
    demodulate_numpy,
    Demodulator,
    frame_summary,
    fringe_observables,
    FringeFields,
    NumpyDemodulator,
    raised_cosine_window,
)

from .helpers import finite_difference_jvp


H = W = 512
PX_PER_MM = 16.0
X = (np.arange(W) - (W - 1) / 2) / PX_PER_MM
Y = ((H - 1) / 2 - np.arange(H)) / PX_PER_MM
XX, YY = np.meshgrid(X, Y)


def wavevector(period, degrees):
    theta = math.radians(degrees)
    return 2 * math.pi / period * np.array([math.cos(theta), math.sin(theta)])


def rotate(k, degrees):
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return np.array([c * k[0] - s * k[1], s * k[0] + c * k[1]])


# One family: period 4 mm at 17 degrees, deliberately between DFT bins.
K1 = wavevector(4.0, 17.0)
# A second, roughly orthogonal family for crossed grids.
K2 = wavevector(4.5, 107.0)
# The gratings themselves: periods of 5 and 5.5 px, far above the moire bands.
CARRIERS = 0.04 * np.cos(2 * math.pi * PX_PER_MM / 5.0 * XX) + 0.03 * np.cos(2 * math.pi * PX_PER_MM / 5.5 * YY)


def fringe(k, phase=0.0):
    return np.cos(k[0] * XX + k[1] * YY + phase)


def interior(field, border):
    return field[..., border:-border, border:-border]


def wrapped(angle):
    return np.angle(np.exp(1j * angle))


@pytest.fixture(scope="module")
def demodulator():
    return Demodulator((H, W), PX_PER_MM, K1[None])


@pytest.fixture(scope="module")
def crossed():
    return Demodulator((H, W), PX_PER_MM, np.stack([K1, K2]))


@pytest.fixture(scope="module")
def coarse(demodulator):
    return tuple(np.asarray(c) for c in demodulator.coarse_grid())


def spectral_peak_reference(frame, k_nominal, pad=4):
    """Fringe wavevector from a Hann-windowed, zero-padded FFT: skimage peak + log-parabola."""
    window = np.outer(np.hanning(H), np.hanning(W))
    magnitude = np.abs(np.fft.rfft2((frame - frame.mean()) * window, s=(pad * H, pad * W)))
    log_magnitude = np.log(magnitude + 1e-30)
    kx = 2 * math.pi * np.fft.rfftfreq(pad * W, 1 / PX_PER_MM)
    ky = -2 * math.pi * np.fft.fftfreq(pad * H, 1 / PX_PER_MM)
    near = np.hypot(kx[None, :] - k_nominal[0], ky[:, None] - k_nominal[1]) < 0.3 * np.hypot(*k_nominal)
    ((p, q),) = peak_local_max(np.where(near, log_magnitude, log_magnitude.min()), num_peaks=1)

    def vertex(a, b, c):
        return 0.5 * (a - c) / (a - 2 * b + c)

    dp = vertex(log_magnitude[p - 1, q], log_magnitude[p, q], log_magnitude[p + 1, q])
    dq = vertex(log_magnitude[p, q - 1], log_magnitude[p, q], log_magnitude[p, q + 1])
    row = p if p < pad * H // 2 else p - pad * H
    return np.array([(q + dq) * 2 * math.pi * PX_PER_MM / (pad * W), -(row + dp) * 2 * math.pi * PX_PER_MM / (pad * H)])


def period_and_orientation(k):
    return 2 * math.pi / np.hypot(k[0], k[1]), math.degrees(math.atan2(k[1], k[0]))


@pytest.mark.parametrize("scale, turn", [(1.0, 0.0), (1.03, 1.5), (0.96, -2.0)])
def test_uniform_fringe(demodulator, coarse, scale, turn):
    """(a) Constant phase, period and orientation, at and off the nominal wavevector."""
    k_true = rotate(K1 * scale, turn)
    phase0 = 0.7
    frame = 0.5 * (1 + 0.6 * fringe(k_true, phase0)) + CARRIERS
    fields = demodulator(jnp.asarray(frame))
    observables = fringe_observables(demodulator, fields)
    summary = frame_summary(demodulator, jnp.asarray(frame))

    # Phase relative to the nominal K: psi = (k_true - K) . x + phase0.
    xc, yc = coarse
    expected = (k_true - K1)[0] * xc + (k_true - K1)[1] * yc + phase0
    assert np.abs(interior(wrapped(np.asarray(observables.phase[0]) - expected), 4)).max() < 2e-3
    assert np.abs(wrapped(float(summary.mean_phase[0]) - phase0)) < 2e-3
    np.testing.assert_allclose(summary.mean_phase_gradient[0], k_true - K1, atol=1e-4)

    period, orientation = period_and_orientation(k_true)
    reference_period, reference_orientation = period_and_orientation(spectral_peak_reference(frame, K1))
    for candidate_period, candidate_orientation in [
        (float(summary.period[0]), math.degrees(float(summary.orientation[0]))),
        (reference_period, reference_orientation),
    ]:
        assert abs(candidate_period / period - 1) < 5e-3
        assert abs(candidate_orientation - orientation) < 0.2
    assert abs(float(summary.period[0]) / reference_period - 1) < 1e-3
    assert abs(math.degrees(float(summary.orientation[0])) - reference_orientation) < 0.05

    # Local fields in the interior agree with the global values too.
    assert np.abs(interior(np.asarray(observables.period[0]), 4) / period - 1).max() < 5e-3
    assert np.abs(np.degrees(interior(np.asarray(observables.orientation[0]), 4)) - orientation).max() < 0.2
    # Brightness and contrast: the fringe's leakage into the DC band grows toward the border.
    np.testing.assert_allclose(interior(np.asarray(observables.contrast[0]), 6), 0.6, rtol=1e-2)
    np.testing.assert_allclose(interior(np.asarray(fields.brightness), 6), 0.5, rtol=1e-2)
    np.testing.assert_allclose(float(summary.contrast[0]), 0.6, rtol=1e-2)
    np.testing.assert_allclose(float(summary.mean_brightness), frame.mean(), rtol=1e-12)


def test_phase_bump(demodulator, coarse):
    """(b) A Gaussian phase bump of 1.5 rad: unwrapped phase and its gradient."""
    sigma, centre = 6.0, (2.0, -1.5)

    def bump(x, y):
        return 1.5 * np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * sigma**2))

    frame = 0.5 * (1 + 0.6 * fringe(K1, bump(XX, YY))) + CARRIERS
    observables = fringe_observables(demodulator, demodulator(jnp.asarray(frame)))
    xc, yc = coarse
    truth = bump(xc, yc)
    recovered = unwrap_phase(np.array(observables.phase[0]))
    error = interior(recovered - truth, 6)
    error = error - error.mean()
    assert np.abs(error).max() < 0.08
    assert np.sqrt(np.mean(error**2)) < 0.02

    gradient_truth = np.stack([-(xc - centre[0]) / sigma**2 * truth, -(yc - centre[1]) / sigma**2 * truth])
    gradient_error = np.hypot(*interior(np.asarray(observables.phase_gradient[0]) - gradient_truth, 6))
    assert gradient_error.max() < 0.05
    assert np.sqrt(np.mean(gradient_error**2)) < 0.015


def test_translation_shifts_phase(demodulator):
    """(c) Translating the pattern by u shifts the phase by -K.u everywhere."""
    u = np.array([0.3, -0.2])
    before = demodulator(jnp.asarray(0.5 * (1 + 0.6 * fringe(K1, 0.4)) + CARRIERS))
    shifted = np.cos(K1[0] * (XX - u[0]) + K1[1] * (YY - u[1]) + 0.4)
    after = demodulator(jnp.asarray(0.5 * (1 + 0.6 * shifted) + CARRIERS))
    shift = np.angle(np.asarray(after.fringe[0]) * np.conj(np.asarray(before.fringe[0])))
    np.testing.assert_allclose(interior(shift, 4), -K1 @ u, atol=1e-4)
    np.testing.assert_allclose(interior(shift, 2), -K1 @ u, atol=2e-3)


def test_crossed_families_are_separated(crossed):
    """(d) Each family of a crossed grid demodulates as if the other were absent."""
    psi1 = 1.2 * np.exp(-((XX + 3) ** 2 + (YY - 2) ** 2) / (2 * 7.0**2))
    psi2 = 0.5 + 0.03 * XX
    cross_terms = 0.05 * fringe(K1 + K2, psi1 + psi2) + 0.05 * fringe(K1 - K2, psi1 - psi2)
    both = 0.5 * (1 + 0.5 * fringe(K1, psi1) + 0.4 * fringe(K2, psi2) + cross_terms) + CARRIERS
    only1 = 0.5 * (1 + 0.5 * fringe(K1, psi1)) + CARRIERS
    only2 = 0.5 * (1 + 0.4 * fringe(K2, psi2)) + CARRIERS
    z_both = np.asarray(crossed(jnp.asarray(both)).fringe)
    z_only = [np.asarray(crossed(jnp.asarray(f)).fringe[i]) for i, f in enumerate([only1, only2])]
    for family in range(2):
        difference = wrapped(np.angle(z_both[family]) - np.angle(z_only[family]))
        assert np.abs(interior(difference, 6)).max() < 2e-3
        assert np.abs(interior(difference, 4)).max() < 1e-2
    summary = frame_summary(crossed, jnp.asarray(both))
    for family, alone in enumerate([only1, only2]):
        reference = frame_summary(crossed, jnp.asarray(alone))
        np.testing.assert_allclose(summary.wavevector[family], reference.wavevector[family], atol=5e-4)
        np.testing.assert_allclose(
            summary.mean_phase_gradient[family], reference.mean_phase_gradient[family], atol=2e-4
        )
    # Family 2 alone is uniform, with an extra 0.03 rad/mm along x.
    period, orientation = period_and_orientation(K2 + np.array([0.03, 0.0]))
    assert abs(float(summary.period[1]) / period - 1) < 5e-3
    assert abs(math.degrees(float(summary.orientation[1])) - orientation) < 0.2


def test_overlapping_bands_are_refused():
    with pytest.raises(ValueError, match="overlap"):
        Demodulator((H, W), PX_PER_MM, np.stack([K1, rotate(K1, 20.0)]))
    with pytest.raises(ValueError, match="does not fit"):
        Demodulator((H, W), PX_PER_MM, K1[None], crop_shape=(8, 8))
    with pytest.raises(ValueError, match="even"):
        Demodulator((H, W + 1), PX_PER_MM, K1[None])


def test_frame_shape_is_checked(demodulator):
    with pytest.raises(ValueError, match="shape"):
        demodulator(jnp.zeros((H, W - 2)))


def test_brightness_centroid(demodulator):
    """(e) Centroid of an off-centre Gaussian blob: analytic, cv2.moments, and under fringes."""
    centre = np.array([4.3, -2.7])
    blob = 0.8 * np.exp(-((XX - centre[0]) ** 2 + (YY - centre[1]) ** 2) / (2 * 2.0**2))
    moments = cv2.moments(blob)
    opencv = np.array(
        [
            (moments["m10"] / moments["m00"] - (W - 1) / 2) / PX_PER_MM,
            ((H - 1) / 2 - moments["m01"] / moments["m00"]) / PX_PER_MM,
        ]
    )
    np.testing.assert_allclose(opencv, centre, atol=1e-6)
    centroid = np.asarray(frame_summary(demodulator, jnp.asarray(blob)).brightness_centroid)
    np.testing.assert_allclose(centroid, opencv, atol=0.02)

    # A contact on vignetted fringes: the blob brightens them and shifts them locally.
    vignetting = 0.5 + 0.1 * np.exp(-(XX**2 + YY**2) / (2 * 15.0**2))
    shift = 0.7 * np.exp(-((XX - centre[0]) ** 2 + (YY - centre[1]) ** 2) / (2 * 3.0**2))
    no_contact = vignetting * (1 + 0.6 * fringe(K1)) + CARRIERS
    contact = (vignetting + blob / 4) * (1 + 0.6 * fringe(K1, shift)) + CARRIERS
    baseline = brightness_baseline(demodulator, jnp.asarray(no_contact))
    centroid = np.asarray(frame_summary(demodulator, jnp.asarray(contact), baseline).brightness_centroid)
    np.testing.assert_allclose(centroid, centre, atol=0.05)


def test_rim_energy_grows_with_ring(demodulator):
    """(f) A brighter contact rim gives more rim energy (quadratically); uniform light none."""
    radius = np.hypot(XX - 2.0, YY + 1.0)
    ring = np.exp(-((radius - 5.0) ** 2) / (2 * 0.6**2))
    no_contact = 0.5 * (1 + 0.6 * fringe(K1)) + CARRIERS
    baseline = brightness_baseline(demodulator, jnp.asarray(no_contact))

    def rim_energy(frame):
        return float(frame_summary(demodulator, jnp.asarray(frame), baseline).rim_energy)

    energies = [rim_energy(no_contact + a * ring * (1 + 0.6 * fringe(K1))) for a in [0.0, 0.05, 0.1, 0.2]]
    assert energies[0] < 1e-20
    assert all(later > earlier for earlier, later in zip(energies, energies[1:]))
    np.testing.assert_allclose(energies[3] / energies[2], 4.0, rtol=1e-6)
    assert rim_energy(no_contact + 0.1) < 1e-8 * energies[2]
    # Moving fringes (shear) are not a rim.
    assert rim_energy(0.5 * (1 + 0.6 * fringe(K1, 0.7)) + CARRIERS) < 0.02 * energies[2]


@pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-10), (np.float32, 1e-5)])
def test_numpy_floor_agrees(crossed, dtype, rtol):
    """(g) The numpy/OpenCV floor computes the same fields as JAX."""
    frame = (0.5 * (1 + 0.5 * fringe(K1, 0.3) + 0.4 * fringe(K2, -1.0)) + CARRIERS).astype(dtype)
    fields = crossed(jnp.asarray(frame))
    assert fields.fringe.dtype == np.result_type(dtype, np.complex64)
    fringe_np, brightness_np, reference_np = NumpyDemodulator(crossed, dtype)(frame)
    assert fringe_np.dtype == fields.fringe.dtype
    # Compare where the fields are meaningful: the envelope drops to ~0 at the border.
    weight = np.asarray(crossed.fringe_envelope)
    scale = np.abs(np.asarray(fields.fringe)).max()
    assert np.max(weight * np.abs(fringe_np - np.asarray(fields.fringe))) < rtol * scale
    brightness_weight = np.asarray(crossed.brightness_envelope)
    assert np.max(brightness_weight * np.abs(brightness_np - np.asarray(fields.brightness))) < rtol
    np.testing.assert_allclose(reference_np, fields.reference_wavevector, rtol=rtol)
    fringe_once, _, _ = demodulate_numpy(crossed, frame)
    np.testing.assert_array_equal(fringe_once, fringe_np)


def test_float32_accuracy(demodulator):
    frame = (0.5 * (1 + 0.6 * fringe(K1, 0.7)) + CARRIERS).astype(np.float32)
    summary = frame_summary(demodulator, jnp.asarray(frame))
    fields = demodulator(jnp.asarray(frame))
    assert fields.brightness.dtype == jnp.float32 and summary.period.dtype == jnp.float32
    assert np.abs(interior(wrapped(np.angle(np.asarray(fields.fringe[0])) - 0.7), 4)).max() < 1e-3
    assert abs(float(summary.period[0]) / 4.0 - 1) < 1e-4


def test_filter_baseband_reproduces_measurement(demodulator):
    """A predicted baseband field through `filter_baseband` equals the demodulated frame."""
    psi = 1.2 * np.exp(-((XX - 3) ** 2 + (YY + 2) ** 2) / (2 * 4.0**2)) + 0.02 * YY
    brightness = 0.5 + 0.05 * np.exp(-((XX + 4) ** 2 + YY**2) / (2 * 6.0**2))
    visibility = 0.6 - 0.2 * np.exp(-((XX - 3) ** 2 + (YY + 2) ** 2) / (2 * 3.0**2))
    baseband = 0.5 * brightness * visibility * np.exp(1j * psi)
    frame = brightness + 2 * np.real(baseband * np.exp(1j * (K1[0] * XX + K1[1] * YY))) + CARRIERS
    fields = demodulator(jnp.asarray(frame))
    weight = np.asarray(demodulator.fringe_envelope[0])
    scale = np.abs(np.asarray(fields.fringe)).max()
    # Exact on the frame grid, up to the leakage of the conjugate fringe term.
    predicted = demodulator.filter_baseband(jnp.asarray(baseband[None]), fields.reference_wavevector)
    assert np.max(weight * np.abs(np.asarray(predicted - fields.fringe)[0])) < 1e-4 * scale
    # A model may predict on a coarser grid: 128 x 128 cell centres.
    xs = (np.arange(128) - 63.5) * (W / 128) / PX_PER_MM
    ys = (63.5 - np.arange(128)) * (H / 128) / PX_PER_MM
    gx, gy = np.meshgrid(xs, ys)
    psi_c = 1.2 * np.exp(-((gx - 3) ** 2 + (gy + 2) ** 2) / (2 * 4.0**2)) + 0.02 * gy
    brightness_c = 0.5 + 0.05 * np.exp(-((gx + 4) ** 2 + gy**2) / (2 * 6.0**2))
    visibility_c = 0.6 - 0.2 * np.exp(-((gx - 3) ** 2 + (gy + 2) ** 2) / (2 * 3.0**2))
    baseband_c = 0.5 * brightness_c * visibility_c * np.exp(1j * psi_c)
    predicted_c = demodulator.filter_baseband(jnp.asarray(baseband_c[None]), fields.reference_wavevector)
    assert np.max(weight * np.abs(np.asarray(predicted_c - fields.fringe)[0])) < 1e-4 * scale
    # Brightness: the same operator exactly on the frame itself.
    np.testing.assert_allclose(demodulator.filter_brightness(jnp.asarray(frame)), fields.brightness, rtol=0, atol=1e-10)
    # The observables of the predicted field are those of the measurement.
    predicted_fields = FringeFields(
        fringe=predicted,
        brightness=demodulator.filter_brightness(jnp.asarray(frame)),
        reference_wavevector=fields.reference_wavevector,
    )
    measured = fringe_observables(demodulator, fields)
    modelled = fringe_observables(demodulator, predicted_fields)
    np.testing.assert_allclose(interior(modelled.phase_gradient, 4), interior(measured.phase_gradient, 4), atol=2e-3)


@pytest.mark.parametrize("shape", [(96, 96), (128, 128)])
def test_real_band_pass_is_filter_baseband_of_the_shifted_field(crossed, shape):
    # One rfft2 of a real field on a model grid against the per-family path: shift each
    # family to baseband by e^{-i K.x} and filter it, and filter the brightness.
    demodulator = crossed
    rows, cols = shape
    xs = (np.arange(cols) - (cols - 1) / 2) * (W / cols) / PX_PER_MM
    ys = ((rows - 1) / 2 - np.arange(rows)) * (H / rows) / PX_PER_MM
    gx, gy = np.meshgrid(xs, ys)
    bump = np.exp(-((gx - 3) ** 2 + (gy + 2) ** 2) / (2 * 4.0**2))
    field = 0.5 + 0.1 * bump + 0.2 * sum(np.cos(k[0] * gx + k[1] * gy + 1.5 * bump) for k in (K1, K2))
    reference_k = jnp.asarray(np.stack([K1, K2]) + 0.01)
    fringe, brightness = demodulator.real_band_pass(shape, reference_k)(jnp.asarray(field))
    K = np.asarray(demodulator.wavevectors)
    shifted = np.stack([field * np.exp(-1j * (k[0] * gx + k[1] * gy)) for k in K])
    expected = demodulator.filter_baseband(jnp.asarray(shifted), reference_k)
    scale = np.abs(np.asarray(expected)).max()
    np.testing.assert_allclose(np.asarray(fringe), np.asarray(expected), rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(
        np.asarray(brightness), np.asarray(demodulator.filter_brightness(jnp.asarray(field))), rtol=0, atol=1e-9
    )
    with pytest.raises(ValueError, match="too coarse"):
        demodulator.real_band_pass((32, 32))


def test_transfer_function(demodulator):
    k_norm = np.hypot(*K1)
    at = demodulator.transfer_function(jnp.asarray([K1[0], K1[0] + 0.2 * k_norm]), jnp.asarray([K1[1], K1[1]]))
    np.testing.assert_allclose(at[0], [1.0, 1.0])
    edge = demodulator.transfer_function(K1[0] + 0.45 * k_norm, K1[1])
    np.testing.assert_allclose(edge, [0.0], atol=1e-12)
    np.testing.assert_allclose(raised_cosine_window(0.5, 1.0, 1.0), 0.5)
    np.testing.assert_allclose(demodulator.brightness_transfer_function(0.0, 0.0), 1.0)


def test_jit_vmap_no_retrace(demodulator):
    """(h) jit + vmap over a batch equals per-frame calls; a new frame does not retrace."""
    frames = np.stack([0.5 * (1 + 0.6 * fringe(K1, phase)) + CARRIERS for phase in (0.0, 1.0, 2.5)])
    batched = jax.jit(jax.vmap(lambda f: frame_summary(demodulator, f)))(jnp.asarray(frames))
    for index, frame in enumerate(frames):
        single = frame_summary(demodulator, jnp.asarray(frame))
        np.testing.assert_allclose(batched.mean_phase[index], single.mean_phase, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched.period[index], single.period, rtol=1e-10)
    fields = jax.vmap(demodulator)(jnp.asarray(frames))
    assert fields.fringe.shape == (3, 1, 32, 32)
    np.testing.assert_allclose(np.angle(np.asarray(fields.fringe[:, 0, 16, 16])), [0.0, 1.0, 2.5], atol=1e-3)

    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def observe(frame):
        return fringe_observables(demodulator, demodulator(frame))

    for frame in frames:
        observe(jnp.asarray(frame))


def test_gradient_through_demodulation(demodulator):
    """(h) d(observable)/d(frame parameter) matches finite differences (and -K for a shift)."""
    xx, yy = jnp.asarray(XX), jnp.asarray(YY)
    k = jnp.asarray(K1)

    def frame(shift):
        return 0.5 * (1 + 0.6 * jnp.cos(k[0] * (xx - shift[0]) + k[1] * (yy - shift[1]) + 0.4))

    def mean_phase(shift):
        return frame_summary(demodulator, frame(shift)).mean_phase[0]

    def field_statistic(shift):
        observables = fringe_observables(demodulator, demodulator(frame(shift)))
        return jnp.sum(jnp.cos(observables.phase[0, 8:-8, 8:-8])) + jnp.sum(observables.period[0, 8:-8, 8:-8])

    shift = jnp.asarray([0.1, -0.05])
    tangent = jnp.asarray([0.6, 0.8])
    for fn in (mean_phase, field_statistic):
        gradient = jax.jit(jax.grad(fn))(shift)
        _, fd = finite_difference_jvp(jax.jit(fn), (shift,), (tangent,), eps=1e-5)
        np.testing.assert_allclose(gradient @ tangent, fd, rtol=1e-6, atol=1e-9)
        if fn is mean_phase:
            np.testing.assert_allclose(gradient, -K1, rtol=1e-4)


def test_unapodized_option(coarse):
    """Without apodization a fringe at any in-band wavevector is still exact away from the border."""
    plain = Demodulator((H, W), PX_PER_MM, K1[None], apodize=False)
    k_true = rotate(K1 * 1.02, 1.0)
    frame = 0.5 * (1 + 0.6 * fringe(k_true, -0.4)) + CARRIERS
    fields = plain(jnp.asarray(frame))
    xc, yc = coarse
    expected = (k_true - K1)[0] * xc + (k_true - K1)[1] * yc - 0.4
    assert np.abs(interior(wrapped(np.angle(np.asarray(fields.fringe[0])) - expected), 4)).max() < 1e-2
    fringe_np, _, _ = NumpyDemodulator(plain, np.float64)(frame)
    np.testing.assert_allclose(fringe_np, fields.fringe, rtol=1e-9, atol=1e-12)


def test_white_noise_variance_reads_the_camera_noise_under_the_gratings():
    # Two gratings with their first harmonics, multiplied (carriers, moire and mixed beats:
    # strong spectral lines), under vignetting, plus white noise of known variance: the
    # estimate sees the noise, not the pattern.
    import moirejax as mj

    rng = np.random.default_rng(5)
    h = w = 256
    y, x = np.mgrid[0:h, 0:w] / 16.0

    def grating(u):
        return 0.5 + 0.4 * np.cos(2 * np.pi * u) - 0.13 * np.cos(6 * np.pi * u)

    pattern = grating(x / 0.3) * grating((x + y) / 0.35) * (1 - 0.3 * ((x - 8) ** 2 + (y - 8) ** 2) / 64)
    for sigma in (0.003, 0.02):
        frame = jnp.asarray(pattern + rng.normal(0, sigma, pattern.shape))
        assert abs(float(mj.white_noise_variance(frame)) / sigma**2 - 1) < 0.15
    # Without noise, what is left is leakage of the pattern: far below any camera's noise.
    assert float(mj.white_noise_variance(jnp.asarray(pattern))) < 1e-7


def test_white_noise_map_reads_each_square_noise_under_the_gratings():
    # Two gratings; the left half carries white noise ten times the right half's: each
    # 32 x 32 square reads its own half's variance (no square straddles the two).
    import moirejax as mj

    rng = np.random.default_rng(6)
    h, w = 128, 256
    y, x = np.mgrid[0:h, 0:w] / 16.0
    pattern = (0.5 + 0.4 * np.cos(2 * np.pi * x / 0.3)) * (0.5 + 0.4 * np.cos(2 * np.pi * (x + y) / 0.35))
    sigma = np.where(x < w / 32.0, 0.02, 0.002)
    noise_map = np.asarray(mj.white_noise_map(jnp.asarray(pattern + rng.normal(size=pattern.shape) * sigma), 32))
    assert noise_map.shape == (4, 8)
    # An upper estimate: in a square this small the gratings' lines leak into a share of the
    # bins, and under the quiet half's noise the median sits among them (about twice).
    assert np.all((noise_map[:, :4] / 0.02**2 > 0.8) & (noise_map[:, :4] / 0.02**2 < 2.5))
    assert np.all((noise_map[:, 4:] / 0.002**2 > 0.8) & (noise_map[:, 4:] / 0.002**2 < 2.5))
    assert 40 < np.median(noise_map[:, :4]) / np.median(noise_map[:, 4:]) < 120
    with pytest.raises(ValueError, match="smaller than one"):
        mj.white_noise_map(jnp.zeros((16, 64)), 32)


def test_long_moire_period_keeps_a_positive_brightness_envelope():
    # A Mid unit whose reference pitch came out 3 % finer than drawn (inside what
    # `perturb_device` draws for the two pitches together) has a moiré period of 7.4 mm
    # instead of 4.2: its brightness band is a few bins wide and the band-passed
    # apodization rings below zero at the border, which used to refuse the unit outright.
    device = mj.preset("mid")
    unit = dataclasses.replace(device, p2=0.291)
    moire = np.asarray(unit.moire_wavevectors(), np.float64)
    assert np.linalg.norm(moire, axis=-1).max() < 0.6 * np.linalg.norm(np.asarray(device.moire_wavevectors())[0])
    demodulator = Demodulator((unit.height, unit.width), float(unit.px_per_mm), moire)
    envelope = np.asarray(demodulator.brightness_envelope)
    assert envelope.min() > 0 and np.isfinite(np.asarray(demodulator.brightness_normalisation)).all()
    # The middle of a uniform frame still reads its brightness.
    fields = demodulator(jnp.full((unit.height, unit.width), 0.4))
    m, n = np.asarray(fields.brightness).shape
    np.testing.assert_allclose(np.asarray(fields.brightness)[m // 4 : -m // 4, n // 4 : -n // 4], 0.4, rtol=2e-3)
