"""The upper grating's own carriers: their demodulation, their band model, and what the
inversion takes from them.

The references are the renderer (`render_frame`, `render_deformed`), which draws the two
gratings pixel by pixel and never forms a band, and the parallax geometry written out by
hand: a uniform in-plane displacement u moves the upper grating's phase by -k1.u and the
moiré fringes by u Lambda/p1; a uniform compression w shrinks the far grating's apparent
wavenumber by the factor (Z + a - w)/(Z + a).
"""

import jax.numpy as jnp
import numpy as np
import pytest

import moirejax as mj


def _lines(duty=0.6, **optics):
    optics = {"glow_gain": 0.0, "rim_gain": 0.0, "phase1": (0.0,), "phase2": (0.0,), **optics}
    return mj.preset("mid", layout="lines", duty1=duty, duty2=duty, optics=mj.Optics(**optics))


def _demodulator(device):
    # The inversion's own: moiré families, then the carriers with the reference grating's
    # carrier cut out of their bands.
    return mj.Inverter(device, None).demodulator


def _inner(demodulator, family):
    envelope = np.asarray(demodulator.fringe_envelope[family])
    return envelope > 0.5 * envelope.max()


def test_carriers_are_resolved_on_the_paper_designs_and_not_on_a_coarse_camera():
    for name in ("dense", "mid", "sparse"):
        radius = mj.carrier_band_radius(mj.preset(name))
        # Several times the moiré band's radius (0.45 |K|, 0.67 rad/mm on Mid).
        assert radius is not None and radius > 2.0
    # At 4 px/mm the Mid design's upper grating (22 rad/mm) is beyond the Nyquist limit.
    coarse = mj.preset("mid", px_per_mm=4.0, height=128, width=128)
    assert mj.carrier_band_radius(coarse) is None
    with pytest.raises(ValueError, match="carriers=False"):
        mj.Inverter(coarse, None, carriers=True)


def test_baseband_pass_is_filter_baseband():
    device = _lines()
    demodulator = _demodulator(device)
    rng = np.random.default_rng(0)
    field = jnp.asarray(rng.normal(size=(2, 96, 96)) + 1j * rng.normal(size=(2, 96, 96)))
    reference = demodulator.wavevectors + 0.01
    expected = demodulator.filter_baseband(field, reference)
    got = demodulator.baseband_pass((96, 96), (0, 1), reference)(field)
    assert np.abs(np.asarray(got - expected)).max() < 1e-12 * np.abs(np.asarray(expected)).max()


def test_uniform_displacement_moves_carrier_and_fringes_as_parallax_says():
    # Duty 0.5: no even harmonics, so the carrier band holds the fundamental's term alone
    # (at other duties a moving term at k1' + K rides on it, which the band model has).
    device = _lines(duty=0.5)
    shape = (device.height, device.width)
    u0 = 0.01  # mm, along the upper grating's wavevector (x)
    rest = mj.render_deformed(device, jnp.zeros((3, *shape)), jnp.zeros(shape))
    moved = mj.render_deformed(device, jnp.zeros((3, *shape)).at[0].set(u0), jnp.zeros(shape))
    inverter = mj.Inverter(device, rest, match_reference=False)
    fields = inverter.observe(moved)
    k1 = 2 * np.pi / float(device.p1)
    for family in (0, 1):
        inner = _inner(inverter.demodulator, family)
        change = np.angle(np.asarray(fields.fringe[family] / inverter.reference.fringe[family]))[inner]
        # Both the moiré phase and the carrier's are the upper grating's phase: -k1 u.
        assert np.mean(change) == pytest.approx(-k1 * u0, abs=2e-3)
        assert np.std(change) < 2e-3
    # The fringes move by u Lambda/p1, along u because the far grating's apparent pitch is
    # the finer one on Mid (K parallel to k1).
    K = float(np.linalg.norm(np.asarray(device.moire_wavevectors())))
    inner = _inner(inverter.demodulator, 0)
    shift = -np.mean(np.angle(np.asarray(fields.fringe[0] / inverter.reference.fringe[0]))[inner]) / K
    assert shift == pytest.approx(u0 * (2 * np.pi / K) / float(device.p1), rel=2e-3)


def test_uniform_compression_changes_the_moire_period_through_parallax():
    device = _lines()
    shape = (device.height, device.width)
    w0 = 0.05  # mm into the sensor
    frame = mj.render_deformed(device, jnp.zeros((3, *shape)).at[2].set(w0), jnp.zeros(shape))
    Z, a = float(device.Z), float(device.a)
    k1_apparent = 2 * np.pi / float(device.p1) * (Z + a - w0) / Z
    expected = 2 * np.pi / abs(k1_apparent - 2 * np.pi / float(device.p2))
    # The moiré period of the compressed frame, from its spectral peak.
    measured = mj.measure_moire_wavevectors(np.asarray(frame), device)
    assert 2 * np.pi / np.linalg.norm(measured[0]) == pytest.approx(expected, rel=2e-3)
    at_rest = 2 * np.pi / np.linalg.norm(np.asarray(device.moire_wavevectors())[0])
    assert abs(expected - at_rest) > 20 * 2e-3 * at_rest  # the change is resolved


@pytest.fixture(scope="module")
def loaded_lines():
    device = _lines(psf_sigma=0.6, defocus=0.02)
    demodulator = _demodulator(device)
    contact = mj.Contact(0.0, 0.0, 3.0)
    reference = demodulator(mj.render_frame(device, jnp.zeros(6), contact))
    model = mj.band_model(device, demodulator, (96, 96), reference.reference_wavevector)
    return device, demodulator, contact, reference, model


@pytest.mark.parametrize(
    "wrench, limit",
    [
        ([0.0, 0.0, 0.5, 0.0, 0.0, 0.0], 0.005),
        ([0.1, 0.0, 0.5, 0.0, 0.0, 0.0], 0.005),
        ([0.0, 0.1, 0.5, 0.0, 0.0, 0.0], 0.005),
        ([0.0, 0.0, 0.5, 0.0, 0.0, 0.003], 0.01),
    ],
)
def test_carrier_band_model_agrees_with_the_rendered_frame(loaded_lines, wrench, limit):
    device, demodulator, contact, reference, model = loaded_lines
    wrench = jnp.asarray(wrench)
    observed = demodulator(mj.render_frame(device, wrench, contact), reference.reference_wavevector)
    obs = np.asarray(observed.fringe[1])
    at_rest = np.asarray(reference.fringe[1])
    # The unit's fixed pattern, as the inversion corrects for it: the observed over the
    # model's carrier at rest.
    rest_model = np.asarray(model(jnp.zeros(6), contact).fringe[1])
    predicted = np.asarray(model(wrench, contact).fringe[1]) * at_rest / rest_model
    direction = predicted / np.abs(predicted)
    inner = _inner(demodulator, 1)
    residual = np.imag((obs - predicted) * np.conj(direction))[inner]
    signal = np.imag((obs - at_rest) * np.conj(at_rest / np.abs(at_rest)))[inner]
    # The phase part of the misfit is a small share of the phase signal: most of it comes
    # from the blur's dependence on the carrier's local wavenumber under a twist.
    assert np.std(residual) < limit * np.std(signal)
    assert np.std(signal) > 0.002


def test_carrier_phase_ignores_exposure_illumination_and_glow():
    # The frame at rest seen with another exposure, an illumination gradient and a contact's
    # glow (light that passes the reference grating alone): the carrier phase must not move.
    device = _lines(glow_gain=4.0)
    inverter = mj.Inverter(device, mj.render_frame(device, jnp.zeros(6), mj.Contact()))
    shape = (device.height, device.width)
    x, y = np.meshgrid(np.linspace(-1, 1, shape[1]), np.linspace(1, -1, shape[0]))
    # A glow 3 mm wide (sd) raising the brightness by a sixth at its peak.
    sd = 3.0 / (shape[1] / 2 / float(device.px_per_mm))
    light = 0.05 * np.exp(-((x - 0.1) ** 2 + (y + 0.2) ** 2) / (2 * sd**2))
    frame = mj.render_deformed(device, jnp.zeros((3, *shape)), jnp.asarray(light), exposure=1.2)
    # An illumination gradient scales the radiance, not the camera's offset.
    offset = float(device.optics.offset)
    frame = offset + (np.asarray(frame) - offset) * (1 + 0.1 * x)
    observed = inverter.observe(jnp.asarray(frame))
    sets = device.n_sets
    inner = _inner(inverter.demodulator, sets)
    change = np.angle(np.asarray(observed.fringe[sets] / inverter.reference.fringe[sets]))[inner]
    # Without the cut around the reference grating's carrier this is 0.02 rad; a glow
    # narrower than the cut's reach (1.6 mm) leaves 0.026 rad.
    assert np.max(np.abs(change)) < 0.01
    assert inverter.demodulator.num_families == 2 * sets


def test_inverter_uses_carriers_on_crossed_grids():
    device = mj.preset("mid")
    inverter = mj.Inverter(device, None)
    assert inverter.demodulator.num_families == 4
    assert mj.Inverter(device, None, carriers=False).demodulator.num_families == 2
    # The environment can leave them out of the default, never force an unknown setting.
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MOIREJAX_CARRIERS", "0")
        assert mj.Inverter(device, None).demodulator.num_families == 2
        assert mj.Inverter(device, None, carriers=True).demodulator.num_families == 4
        patch.setenv("MOIREJAX_CARRIERS", "yes")
        with pytest.raises(ValueError, match="MOIREJAX_CARRIERS"):
            mj.Inverter(device, None)
    # The model at rest reproduces its own reference (the carriers' fixed pattern included).
    fields = inverter.observe(mj.render_frame(device, jnp.zeros(6), mj.Contact()))
    ratio = np.asarray(fields.fringe / inverter.reference.fringe)
    for family in range(4):
        inner = _inner(inverter.demodulator, family)
        assert np.max(np.abs(np.angle(ratio[family][inner]))) < 0.02


def test_bands_of_a_sampled_traction_field_match_the_analytic_contact():
    # `BandModel.of_deformation` takes any displacement: the layer's response to a Hertz
    # press sampled on the model grid must give the bands of the analytic transform that
    # the inversion uses, to the sampling error of the field (about 1% of the phase change),
    # and leaving out the contact's glow must leave a misfit of the size of that glow.
    device = _lines(duty=0.5, glow_gain=4.0)
    inverter = mj.Inverter(device, None)
    model = inverter.model
    grid, response = model.mechanics.grid, model.mechanics.response
    wrench = jnp.asarray([0.0, 0.0, 0.8, 0.0, 0.0, 0.0])
    contact = mj.Contact(x0=jnp.asarray(1.0), y0=jnp.asarray(-2.0), radius=jnp.asarray(2.5))
    analytic = model(wrench, contact)
    state = model.mechanics(wrench, contact)
    sampled = model.of_deformation(response(mj.surface_tractions(wrench, contact, grid)), state.light)
    unlit = model.of_deformation(state.displacement)
    families, m, n = inverter.fringe_weight.shape
    phase = slice(families * m * n, 2 * families * m * n)

    def misfit(predicted):
        return float(np.linalg.norm(inverter.band_residual(analytic, predicted)[phase]))

    change = misfit(inverter.model_reference)
    assert misfit(model.of_deformation(state.displacement, state.light)) < 1e-4 * change
    assert misfit(sampled) < 0.03 * change
    assert misfit(unlit) > 0.1 * change


def _phase_only_fy_covariance(inverter, frame, state, variance):
    # Covariance of one least-squares step of the inverter's phase residual at `state`
    # under white pixel noise: the gradient of that step with respect to every pixel,
    # exactly, one vector-Jacobian product per unknown (wrench, x0, y0, log radius).
    import jax

    y = state.vector()
    jacobian = np.asarray(inverter._data_jacobian(y, inverter.observe(frame)), np.float64)[:, :9]
    step = jnp.asarray(np.linalg.pinv(jacobian.T @ jacobian) @ jacobian.T, frame.dtype)
    _, vjp = jax.vjp(lambda f: step @ inverter._data_residuals(y, inverter.observe(f)), frame)
    gradients = np.stack([np.asarray(vjp(row)[0], np.float64).ravel() for row in jnp.eye(9, dtype=frame.dtype)])
    return gradients @ gradients.T * variance


def test_carriers_hold_the_shear_along_line_gratings():
    """Line gratings see only the displacement across their lines; the shear along them
    reaches it through the quadrupole of in-plane motion across the lines that it makes
    around the contact (Cerruti's u_x ~ xy/r^3) and through the parallax of the compression
    it causes, patterns the size of the contact, which the carriers resolve. At camera noise
    the inversion's Fy from its phase observables is within 2.5x of the whole-frame
    Cramér–Rao bound (on the full Mid frame 1.9% of the range against 1.1%,
    `benchmarks/fy_information.py`): the information for Fy reaches the inversion. Its
    estimate of Fy is tied to Tx (a pressure tilted along the lines) and the contact's y0."""
    from moirejax.design._observability import _scaled_information_jit
    from moirejax.inverse._state import LoadState
    from moirejax.physics import Contact, HighFidelity, noise_as_arrays, pixel_noise_variance, render_frame

    device = mj.preset("mid", layout="lines", duty1=0.5, duty2=0.5, height=192, width=192)
    shape = (48, 48)
    dtype = device.p1.dtype
    wrench = jnp.asarray([0.0, 0.0, 0.6, 0.0, 0.0, 0.0], dtype)
    contact = Contact(x0=jnp.asarray(0.0, dtype), y0=jnp.asarray(0.0, dtype), radius=jnp.asarray(3.0, dtype))
    frame = render_frame(device, wrench, contact, mechanics_shape=shape)
    reference = render_frame(device, jnp.zeros(6, dtype), contact, mechanics_shape=shape)
    variance = float(jnp.mean(pixel_noise_variance(frame, HighFidelity())))
    scaled = _scaled_information_jit(device, wrench, contact, noise_as_arrays(None, dtype), 1.0, shape, 9, "pixels")
    pixel_bound = np.sqrt(np.diag(np.linalg.inv(np.asarray(scaled, np.float64))))[1]
    inverter = mj.Inverter(device, np.asarray(reference), crop_shape=(16, 16), model_shape=shape, carriers=True)
    covariance = _phase_only_fy_covariance(
        inverter.phase_only(1.0), frame, LoadState.from_load(wrench, contact), variance
    )
    sd = np.sqrt(np.diag(covariance))
    correlation = covariance[1] / (sd[1] * sd)
    assert sd[1] < 2.5 * pixel_bound
    assert correlation[3] < -0.5 and correlation[7] < -0.2
