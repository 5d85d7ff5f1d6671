"""See-through scenes in the simulator, restoration against the grating-free render, and objects located before contact."""

import jax.random as jr
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio

import moirejax as mj
from moirejax.live import locate, make_colour_probe, restore, SeeThrough


def frame_of(vision_device, scene, seed=0):
    return np.asarray(mj.render_scene(jr.PRNGKey(seed), vision_device, scene).frame)


def test_grating_free_view_of_a_uniform_scene_is_uniform_and_carries_the_mean_transmission(vision_device):
    flat = mj.Device(**{**vision_device.__dict__, "optics": mj.Optics(vignetting=0.0)})
    rendered = mj.render_scene(jr.PRNGKey(0), flat, None, backdrop=(0.5, 0.5, 0.5))
    truth = np.asarray(rendered.grating_free)
    # Each crossed grating passes duty^2 of the light on average.
    o = flat.optics
    expected = float(o.offset + o.gain * o.background * 0.5 * (flat.duty1 * flat.duty2) ** 2)
    np.testing.assert_allclose(truth, expected, rtol=1e-6)
    # The frame is modulated by the gratings, and its mean is that of the grating-free view.
    frame = np.asarray(rendered.frame)
    assert frame.std() > 10 * 1 / 255
    assert abs(frame.mean() - expected) < 0.05 * expected


def test_scene_defocus_follows_the_thin_lens_law(vision_device):
    # At the surface the object is as blurred as the upper grating; it grows with height
    # towards the far-field limit defocus (Z + a) / a.
    d0 = float(mj.scene_defocus(vision_device, 0.0))
    np.testing.assert_allclose(d0, float(vision_device.optics.defocus), rtol=1e-12)
    blurs = [float(mj.scene_defocus(vision_device, h)) for h in (0.0, 10.0, 30.0, 1e6)]
    assert np.all(np.diff(blurs) > 0)
    np.testing.assert_allclose(blurs[-1], d0 * float((vision_device.Z + vision_device.a) / vision_device.a), rtol=1e-4)


@pytest.mark.parametrize("height", [0.0, 15.0, 30.0])
def test_a_disc_is_located_at_its_pose_at_any_height(vision_device, see_through, height):
    scene = mj.scene_disc(1.5, -2.0, 8.0 * (12 + height) / 12, height=height, rgb=(0.1, 0.7, 0.2))
    sighting = locate(
        frame_of(vision_device, scene, seed=int(height)), vision_device, see_through=see_through, height=height
    )
    assert sighting.status == "ok" and len(sighting.objects) == 1
    (seen,) = sighting.objects
    assert np.hypot(seen.x_mm - 1.5, seen.y_mm + 2.0) < 0.15
    assert abs(seen.size_mm - float(scene.length)) < 0.05 * float(scene.length)
    assert seen.yaw_deg is None and seen.colour == "green" and seen.confidence > 0.5


def test_height_corrects_the_scale(vision_device, see_through):
    # Seen without its height, an object 20 mm up is placed on the surface: positions and
    # size shrink by (Z + a) / (Z + a + h), the ratio of the two magnifications.
    scene = mj.scene_ring(4.0, 3.0, 20.0, 11.0, height=20.0, rgb=(0.9, 0.5, 0.1))
    frame = frame_of(vision_device, scene, seed=3)
    known = locate(frame, vision_device, see_through=see_through, height=20.0).objects[0]
    assumed = locate(frame, vision_device, see_through=see_through).objects[0]
    ratio = float(mj.scene_magnification(vision_device, 0.0) / mj.scene_magnification(vision_device, 20.0))
    np.testing.assert_allclose(
        [assumed.x_mm, assumed.y_mm, assumed.size_mm],
        np.multiply([known.x_mm, known.y_mm, known.size_mm], ratio),
        rtol=1e-9,
    )
    assert np.hypot(known.x_mm - 4.0, known.y_mm - 3.0) < 0.2


def test_a_rectangle_yaw_is_located(vision_device, see_through):
    scene = mj.scene_rectangle(-1.0, 1.0, 14.0, 5.0, yaw_deg=35.0, height=8.0, rgb=(0.2, 0.3, 0.9))
    (seen,) = locate(frame_of(vision_device, scene, seed=4), vision_device, see_through=see_through, height=8.0).objects
    assert seen.yaw_deg is not None and abs(seen.yaw_deg - 35.0) < 1.0
    assert abs(seen.size_mm - 14.0) < 0.5


def test_restore_beats_the_notch_filter(vision_device, see_through):
    rendered = mj.render_scene(jr.PRNGKey(5), vision_device, mj.scene_texture("astronaut", 60.0, height=5.0))
    frame, truth = np.asarray(rendered.frame, np.float32), np.asarray(rendered.grating_free)
    restored = see_through(frame)
    notch = make_colour_probe(vision_device).notch
    assert notch is not None
    notched = notch(frame)
    scene_range = float(truth.max() - truth.min())
    ours = peak_signal_noise_ratio(truth, restored, data_range=scene_range)
    baseline = peak_signal_noise_ratio(truth, notched, data_range=scene_range)
    assert ours > 25.0 and ours > baseline + 10.0
    # uint8 frames restore the same, and restore() is the one-shot form of SeeThrough.
    frame8 = np.round(frame * 255).astype(np.uint8)
    reference = see_through.envelope + np.float32(see_through.black_level)
    assert restore(frame8, reference, black_level=see_through.black_level).dtype == np.uint8


def test_empty_dark_and_saturated_frames_give_no_objects(vision_device, see_through):
    empty = locate(frame_of(vision_device, None, seed=6), vision_device, see_through=see_through)
    assert empty.objects == [] and empty.status == "empty"
    shape = (vision_device.height, vision_device.width, 3)
    dark = locate(np.zeros(shape, np.uint8), vision_device, see_through=see_through)
    saturated = locate(np.full(shape, 255, np.uint8), vision_device, see_through=see_through)
    assert (dark.objects, dark.status) == ([], "dark")
    assert (saturated.objects, saturated.status) == ([], "saturated")


def test_bad_input_raises_a_clear_error(vision_device, see_through):
    with pytest.raises(ValueError, match="height must be >= 0"):
        mj.scene_disc(0.0, 0.0, 5.0, height=-1.0)
    with pytest.raises(ValueError, match="unknown scene texture"):
        mj.scene_texture("lena", 50.0)
    with pytest.raises(ValueError, match="ring width"):
        mj.scene_ring(0.0, 0.0, 5.0, 6.0)
    with pytest.raises(ValueError, match="rgb must lie"):
        mj.scene_disc(0.0, 0.0, 5.0, rgb=(0.0, 2.0, 0.0))
    with pytest.raises(ValueError, match="reference is dark"):
        SeeThrough(np.zeros((32, 32, 3)), black_level=0.05)
    with pytest.raises(ValueError, match="differs from the reference"):
        see_through(np.zeros((32, 32, 3)))
    with pytest.raises(ValueError, match=r"BGR image \(h, w, 3\)"):
        locate(np.zeros((vision_device.height, vision_device.width)), vision_device)
    with pytest.raises(ValueError, match="height must be >= 0"):
        locate(np.zeros((vision_device.height, vision_device.width, 3)), vision_device, height=-2.0)
