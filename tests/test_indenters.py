"""The simulator's indenters: their traction fields carry exactly the load each indenter states."""

import numpy as np
import pytest

import moirejax as mj


@pytest.mark.parametrize("shape", mj.CONTACT_SHAPES)
def test_traction_field_carries_the_indenters_wrench(shape):
    device = mj.preset("mid")
    indenter = mj.Indenter(
        shape, x0=1.5, y0=-2.0, size=2.5, width=0.8, angle=0.4, force=(0.12, -0.07, 0.9), twist=0.004
    )
    frame = mj.indenter_deformation(device, [indenter], shape=(128, 128))
    tractions = np.asarray(frame.tractions)
    X, Y = np.asarray(frame.grid.X), np.asarray(frame.grid.Y)
    dA = float(frame.grid.spacing) ** 2
    # Centre of pressure, from the field itself.
    cx, cy = (np.sum(tractions[2] * X), np.sum(tractions[2] * Y)) / np.sum(tractions[2])
    fx, fy, fz = indenter.force
    # The convention's moments: Tx = sum(y p), Ty = -sum(x p), Tz = sum(x ty - y tx), in N·m.
    expected = [fx, fy, fz, cy * fz / 1e3, -cx * fz / 1e3, indenter.twist + (cx * fy - cy * fx) / 1e3]
    # Forces exactly; moments to what averaging over a cell (0.2 mm here) leaves of them:
    # a thousandth of the twist range.
    np.testing.assert_allclose(np.asarray(frame.wrench)[:3], expected[:3], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(frame.wrench)[3:], expected[3:], rtol=0, atol=1e-5)
    np.testing.assert_allclose(tractions.sum(axis=(1, 2)) * dA, [fx, fy, fz], rtol=1e-6)
    # Every shape is symmetric about its centre: it presses where it is centred.
    assert abs(cx - 1.5) < 0.05 and abs(cy + 2.0) < 0.05, (cx, cy)
    # The pressure is nowhere negative and the normal displacement presses inward under it.
    assert tractions[2].min() >= 0
    w = np.asarray(frame.displacement[2])
    assert w[np.unravel_index(np.argmax(tractions[2]), w.shape)] > 0


def test_bad_indenters_are_refused():
    with pytest.raises(ValueError, match="unknown indenter shape"):
        mj.Indenter("cone")
    with pytest.raises(ValueError, match="must not be negative"):
        mj.Indenter("sphere", force=(0.0, 0.0, -1.0))
    with pytest.raises(ValueError, match="outside the field"):
        mj.indenter_deformation(mj.preset("mid"), [mj.Indenter("sphere", x0=80.0)], shape=(64, 64))
    with pytest.raises(ValueError, match="unknown contact family"):
        mj.random_indenters(np.random.default_rng(0), "blob")


def test_random_indenters_stay_inside_the_paper_ranges():
    rng = np.random.default_rng(1)
    for family in (*mj.CONTACT_SHAPES, "two"):
        for _ in range(5):
            indenters = mj.random_indenters(rng, family)
            assert len(indenters) == (2 if family == "two" else 1)
            assert 0 < sum(i.force[2] for i in indenters) <= 1.2 + 1e-9
