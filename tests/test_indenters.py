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


def test_uniform_shear_traction_shears_the_layer_by_thickness_over_modulus():
    # A bonded layer under a uniform tangential traction tau shears simply: u = tau h / mu.
    device = mj.preset("mid")
    tau = 0.004
    field = np.zeros((3, 64, 64))
    field[0] = tau
    frame = mj.traction_deformation(device, field)
    e = device.elastomer
    mu = float(e.E) / (2 * (1 + float(e.nu)))
    np.testing.assert_allclose(np.asarray(frame.displacement[0]), tau * float(e.thickness) / mu, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(frame.displacement[1:]), 0.0, atol=1e-9)
    area = (64 * float(frame.grid.spacing)) ** 2
    np.testing.assert_allclose(np.asarray(frame.wrench)[:3], [tau * area, 0.0, 0.0], rtol=1e-5)


def test_traction_deformation_is_the_indenters_deformation_of_their_field():
    device = mj.preset("mid")
    indenters = [mj.Indenter("ring", x0=-1.0, y0=2.0, size=3.0, width=0.7, force=(0.05, 0.1, 0.8), twist=0.002)]
    by_indenters = mj.indenter_deformation(device, indenters, shape=(96, 96))
    by_field = mj.traction_deformation(device, by_indenters.tractions)
    np.testing.assert_allclose(np.asarray(by_field.displacement), np.asarray(by_indenters.displacement), atol=1e-9)
    np.testing.assert_allclose(np.asarray(by_field.light), np.asarray(by_indenters.light), atol=1e-7)
    # Refused by the signature's checker under the tests, by the function itself otherwise.
    with pytest.raises((ValueError, TypeError)):
        mj.traction_deformation(device, np.zeros((2, 8, 8)))


def test_contact_summary_places_and_sizes_a_sphere():
    device = mj.preset("mid")
    frame = mj.indenter_deformation(device, [mj.Indenter("sphere", x0=2.0, y0=-3.0, size=3.0)], shape=(160, 160))
    summary = mj.contact_summary(frame)
    assert abs(summary["x0"] - 2.0) < 0.02 and abs(summary["y0"] + 3.0) < 0.02
    # The pressed cells of a 3 mm disc on 0.25 mm cells.
    assert abs(summary["area"] / (np.pi * 9.0) - 1) < 0.08
    assert abs(summary["radius"] - 3.0) < 0.12
    assert np.isnan(mj.contact_summary(mj.indenter_deformation(device, [], shape=(32, 32)))["x0"])


def test_grasp_loads_scale_from_the_paper_range_to_the_cap_removal():
    assert mj.grasp_limits(1.2) == pytest.approx((0.2, 0.006))
    assert mj.grasp_limits(0.5) == pytest.approx((0.2, 0.006))
    shear, twist = mj.grasp_limits(10.0)
    assert 0.9 < shear < 1.1 and 0.033 < twist < 0.037
    rng = np.random.default_rng(3)
    for family in mj.CONTACT_FAMILIES:
        for _ in range(4):
            indenters = mj.random_indenters(rng, family, max_force=10.0)
            assert 0 < sum(i.force[2] for i in indenters) <= 10.0 + 1e-9
            assert np.hypot(*np.sum([i.force[:2] for i in indenters], axis=0)) <= np.sqrt(2) * shear + 1e-9


def test_shape_schedule_mixes_every_family_after_an_unloaded_start():
    schedule = mj.shape_schedule(100, seed=2, max_force=4.0)
    assert schedule[0] is None and schedule[1] is None and schedule[2] is not None
    families = [c[0] for c in schedule if c is not None]
    assert set(families) == set(mj.CONTACT_FAMILIES)
    assert max(sum(i.force[2] for i in c[1]) for c in schedule if c is not None) <= 4.0
    assert mj.shape_schedule(100, seed=2, max_force=4.0)[40] == schedule[40]
    with pytest.raises(ValueError, match="contact families"):
        mj.shape_schedule(10, families=("blob",))
    with pytest.raises(ValueError, match="max_force"):
        mj.shape_schedule(10, max_force=0.0)


def test_shapes_dataset_records_each_frames_resultant_and_contact(tmp_path):
    from moirejax.cli._main import main

    out = tmp_path / "shapes"
    assert main(["simulate", "--protocol", "shapes", "--n", "9", "--fidelity", "model", "--out", str(out),
                 "--max-force", "6", "--seed", "4"]) == 0  # fmt: skip
    dataset = mj.open_dataset(out)
    schedule = mj.shape_schedule(9, seed=4, max_force=6.0)
    device = mj.preset("mid")
    for i, contact in enumerate(schedule):
        if contact is None:
            assert not dataset.contact[i] and np.all(dataset.wrenches[i] == 0)
            assert np.isnan(dataset.latents["family"][i])
            continue
        # The unit deviates from its design (model fidelity: it is the design itself).
        expected = mj.indenter_deformation(device, contact[1])
        np.testing.assert_allclose(dataset.wrenches[i], np.asarray(expected.wrench), rtol=1e-5, atol=1e-7)
        assert mj.CONTACT_FAMILIES[int(dataset.latents["family"][i])] == contact[0]
        assert dataset.latents["area"][i] > 0
    frames = np.stack([dataset.frame(i) for i in range(len(schedule))])
    assert frames.min() >= 0 and frames.max() <= 1 and not np.allclose(frames[2], frames[0])
    # --max-force belongs to the shapes protocol only: a usage error before anything is written.
    assert main(["simulate", "--protocol", "mixed", "--n", "4", "--max-force", "3", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()
