"""The residual head: a linear correction that holds for load combinations it was not shown."""

import json

import numpy as np
import pytest

import moirejax as mj
from moirejax._conventions import WRENCH_SCALE
from moirejax.calibration._residual_head import (
    head_basis,
    head_features,
    load_head,
    N_BASIS,
    save_head,
    train_residual_head,
)


def _isolated_axes(rng, n):
    """Scaled wrenches of a calibration protocol: presses, shears and twists under preload,
    off-centre presses, each frame loading one axis besides Fz."""
    wrench = np.zeros((n, 6))
    x0, y0 = np.zeros(n), np.zeros(n)
    wrench[:, 2] = rng.uniform(0.1, 1.0, n)
    kind = np.arange(n) % 4
    axis = rng.integers(2, size=n)
    shear = kind == 1
    wrench[shear, axis[shear]] = rng.uniform(-1, 1, shear.sum())
    wrench[kind == 2, 5] = rng.uniform(-1, 1, (kind == 2).sum())
    off = kind == 3
    x0[off], y0[off] = rng.uniform(-8, 8, (2, off.sum()))
    wrench = wrench * WRENCH_SCALE
    # A press centred on its contact: Tx = y0 Fz, Ty = -x0 Fz (N*mm to N*m).
    wrench[off, 3], wrench[off, 4] = y0[off] * wrench[off, 2] / 1000, -x0[off] * wrench[off, 2] / 1000
    return wrench, x0, y0, rng.uniform(2.5, 4.5, n)


def _unit_error(wrench, x0, y0):
    """A unit's systematic error (scaled): Fz reads 6% high, plus 4% more per 10 mm to the
    right; Ty carries an offset proportional to Fz (a centre of pressure read 0.3 mm off);
    Fy picks up a tenth of Tx (a pressure tilt read as shear)."""
    scaled = wrench / WRENCH_SCALE
    error = np.zeros_like(scaled)
    error[:, 2] = scaled[:, 2] * (0.06 + 0.04 * x0 / 10.0)
    error[:, 4] = 0.3 * wrench[:, 2] / 1000 / WRENCH_SCALE[4]
    error[:, 1] = 0.1 * scaled[:, 3]
    return error


def test_a_correction_learned_on_isolated_axes_holds_for_combined_loads():
    rng = np.random.default_rng(0)
    wrench, x0, y0, radius = _isolated_axes(rng, 240)
    # The physics reads the true load plus the unit's error and a little noise; the head
    # learns the difference.
    read = wrench + (_unit_error(wrench, x0, y0) + 0.003 * rng.normal(size=wrench.shape)) * WRENCH_SCALE
    head, record = train_residual_head(head_features(read, x0, y0, radius), (wrench - read) / WRENCH_SCALE)
    assert {"fy", "fz", "ty"} <= set(record["axes_corrected"]), record
    # Combined loads: shear both ways, twist, a press anywhere at once, none of them like a
    # training frame (the tilts are a press's centred on its contact, as an indenter pressing
    # square makes them).
    n = 200
    combined = rng.uniform(-1, 1, (n, 6)) * WRENCH_SCALE
    combined[:, 2] = rng.uniform(0.1, 1.0, n) * WRENCH_SCALE[2]
    cx, cy, cr = rng.uniform(-8, 8, n), rng.uniform(-8, 8, n), rng.uniform(2.5, 4.5, n)
    combined[:, 3], combined[:, 4] = cy * combined[:, 2] / 1000, -cx * combined[:, 2] / 1000
    error = _unit_error(combined, cx, cy) * WRENCH_SCALE
    corrected = head.correct(combined + error, cx, cy, cr)
    left = np.abs(corrected - combined) / WRENCH_SCALE
    # Within the noise the head was trained on (0.003 of each range), where the error was
    # up to 0.08 of a range.
    assert np.max(np.abs(error) / WRENCH_SCALE) > 0.06
    assert np.max(left) < 0.012, np.max(left, axis=0)


def test_noise_is_not_learned():
    # Residuals that are noise alone: no axis is corrected, and the head is the identity.
    rng = np.random.default_rng(1)
    wrench, x0, y0, radius = _isolated_axes(rng, 120)
    head, record = train_residual_head(head_features(wrench, x0, y0, radius), 0.01 * rng.normal(size=(len(wrench), 6)))
    # An axis may pass the cross-validation by chance (at one standard error, about one in
    # six); its correction is then small.
    assert len(record["axes_corrected"]) <= 3, record
    change = (head.correct(wrench, x0, y0, radius) - wrench) / WRENCH_SCALE
    assert np.max(np.abs(change)) < 0.01, np.max(np.abs(change), axis=0)


def test_corrected_intervals_cover_the_error_the_model_does_not_describe():
    # A unit whose physics reads each load with a systematic error the head can learn, plus
    # an error of 0.02 of each range it cannot (what no term of its basis explains); the
    # solver's standard errors hold only the camera noise, 0.003 of a range.
    rng = np.random.default_rng(3)
    noise, unexplained = 0.003, 0.02

    def read(wrench, x0, y0):
        """The physical estimate and the contact centre it found (to 0.5 mm)."""
        error = _unit_error(wrench, x0, y0) + rng.normal(size=wrench.shape) * np.hypot(noise, unexplained)
        return wrench + error * WRENCH_SCALE, x0 + rng.normal(0, 0.5, len(x0)), y0 + rng.normal(0, 0.5, len(y0))

    wrench, x0, y0, radius = _isolated_axes(rng, 240)
    observed, ox, oy = read(wrench, x0, y0)
    head, _ = train_residual_head(head_features(observed, ox, oy, radius), (wrench - observed) / WRENCH_SCALE)
    # The forces' and the twist's unexplained error is all there is to see; the tilts' is
    # partly explained, by the contact centre the estimate found (a press's tilt is its centre
    # times its force).
    residual_sd = np.asarray(head.residual_sd)
    np.testing.assert_allclose(residual_sd[[0, 1, 2, 5]], np.hypot(noise, unexplained), rtol=0.2)
    assert np.all((residual_sd[3:5] > 2 * noise) & (residual_sd[3:5] < 1.2 * unexplained)), residual_sd
    held_out, hx, hy, hr = _isolated_axes(rng, 400)
    observed, ox, oy = read(held_out, hx, hy)
    error = head.correct(observed, ox, oy, hr) - held_out
    solver_sigma = np.full(held_out.shape, noise) * WRENCH_SCALE
    inside = lambda sigma: np.mean(np.abs(error) < 1.96 * sigma, axis=0)  # noqa: E731
    assert np.all(inside(solver_sigma) < 0.3), inside(solver_sigma)
    covered = inside(head.corrected_sigma(solver_sigma))
    assert np.all((covered > 0.9) & (covered < 0.99)), covered


def test_head_basis_is_the_features_and_the_normal_force_times_the_contact():
    features = np.arange(1.0, 10.0)[None]
    basis = np.asarray(head_basis(features))
    assert basis.shape == (1, N_BASIS)
    np.testing.assert_allclose(basis[0, :9], features[0])
    np.testing.assert_allclose(basis[0, 9:], features[0, 2] * features[0, 6:])


def test_a_head_round_trips_through_its_file_and_an_old_one_is_refused(tmp_path):
    rng = np.random.default_rng(2)
    wrench, x0, y0, radius = _isolated_axes(rng, 80)
    read = wrench + _unit_error(wrench, x0, y0) * WRENCH_SCALE
    head, _ = train_residual_head(head_features(read, x0, y0, radius), (wrench - read) / WRENCH_SCALE)
    save_head(tmp_path / "fit.head.eqx", head)
    again = load_head(tmp_path / "fit.head.eqx")
    np.testing.assert_array_equal(again.correct(read, x0, y0, radius), head.correct(read, x0, y0, radius))
    np.testing.assert_array_equal(np.asarray(again.residual_sd), np.asarray(head.residual_sd))
    (tmp_path / "fit.head.eqx.json").write_text(json.dumps({"width": 32, "depth": 2, "dtype": "float32"}))
    with pytest.raises(mj.DataError, match=r"fit\.head\.eqx: a residual head of another kind"):
        load_head(tmp_path / "fit.head.eqx")
