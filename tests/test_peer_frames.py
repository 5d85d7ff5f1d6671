"""Frames the inversion did not render: a committed set from an independent ray-casting renderer.

The contact gate must hold on them (no loaded frame reported as no contact, no unloaded frame
reported in contact). The accuracy test records the open gap: the inversion does not yet
reach the accuracy it has on its own frames (see `benchmarks/peer_frames.py`).
"""

import csv
from pathlib import Path

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import moirejax as mj


# One worker inverts the frames once for every test here.
pytestmark = pytest.mark.xdist_group("peer")

DATA = Path(__file__).parent / "data" / "peer"
AXES = mj.WRENCH_AXES


@pytest.fixture(scope="module")
def peer():
    rows = list(csv.DictReader(open(DATA / "wrench.csv")))
    frames = np.stack([cv2.imread(str(DATA / "frames" / r["frame"]), cv2.IMREAD_UNCHANGED) / 255.0 for r in rows])
    wrench = np.array([[float(r[a]) for a in AXES] for r in rows])
    loaded = np.array([int(r["contact"]) for r in rows], dtype=bool)
    device = mj.preset("mid", layout="lines", duty1=0.5, duty2=0.5)
    inverter = mj.Inverter(device, frames[~loaded].mean(axis=0))
    return frames.astype(np.float32), wrench, loaded, inverter


@pytest.fixture(scope="module")
def estimates(peer):
    frames, _, _, inverter = peer
    stacked = mj.invert(inverter, frames)
    return [jax.tree_util.tree_map(lambda x, i=i: x[i], stacked) for i in range(len(frames))]


def test_committed_frames_match_their_design():
    design = __import__("json").loads((DATA / "design.json").read_text())
    device = mj.preset("mid", layout="lines", duty1=0.5, duty2=0.5)
    assert design["layout"] == "lines" and design["size"] == device.height == device.width
    assert np.isclose(design["p1"], float(device.p1)) and np.isclose(design["px_per_mm"], float(device.px_per_mm))


def test_contact_is_decided_from_the_fringe_phase(peer, estimates):
    _, _, loaded, inverter = peer
    status = np.array([int(e.status) for e in estimates])
    assert np.all(status[~loaded] == mj.Status.NO_CONTACT), status
    # Nor is a loaded frame refused as not showing the unit's fringes.
    solved = (mj.Status.CONVERGED, mj.Status.MAX_STEPS, mj.Status.UNEXPLAINED)
    assert np.all(np.isin(status[loaded], solved)), status
    # The gate's statistic is near one without load and far above the threshold with it.
    phase_change = eqx.filter_jit(lambda inv, frame: inv.phase_change(frame))
    frames = peer[0]
    unloaded = [float(phase_change(inverter, jnp.asarray(f))) for f in frames[~loaded]]
    lightest = float(phase_change(inverter, jnp.asarray(frames[loaded][np.argmin(peer[1][loaded, 2])])))
    assert max(unloaded) < inverter.contact_threshold < lightest, (unloaded, lightest)


def test_unloaded_frames_get_a_zero_wrench_with_an_interval(estimates, peer):
    _, _, loaded, _ = peer
    for e in np.array(estimates, dtype=object)[~loaded]:
        assert np.all(np.asarray(e.wrench) == 0)
        assert np.all(np.isfinite(np.asarray(e.sigma)))


def test_reported_intervals_hold_the_truth_on_independent_frames(peer, estimates):
    """The covariance is honest on frames of a renderer the inversion does not share: every
    loaded frame's error stays within four reported standard deviations on every axis
    (the model's own misfit is part of the reported uncertainty, not only the pixel noise)."""
    _, wrench, loaded, _ = peer
    estimate = np.stack([np.asarray(e.wrench) for e in estimates])[loaded]
    sigma = np.stack([np.asarray(e.sigma) for e in estimates])[loaded]
    z = np.abs(estimate - wrench[loaded]) / sigma
    assert np.all(z < 4.0), z


@pytest.mark.xfail(strict=True, reason="open: the inversion's model does not yet match this renderer's frames")
def test_wrench_on_independent_frames_is_accurate(peer, estimates):
    _, wrench, loaded, _ = peer
    estimate = np.nan_to_num(np.stack([np.asarray(e.wrench) for e in estimates]))[loaded]
    truth = wrench[loaded]
    scale = np.array([0.2, 0.2, 1.2, 0.012, 0.012, 0.008])
    # Every axis within a fifth of its range on every loaded frame.
    assert np.all(np.abs(estimate - truth) / scale < 0.2), (estimate - truth) / scale
