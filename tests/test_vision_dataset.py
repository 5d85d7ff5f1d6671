"""The `vision` protocol: colour see-through frames written as a dataset with their ground
truth, read back, and an object located against it; scenes through the live simulated sensor."""

import json

import numpy as np
import pytest

import moirejax as mj
from moirejax.cli._main import main
from moirejax.live import locate, SeeThrough, SimulatedSensor


@pytest.fixture(scope="module")
def small_device():
    """A Mid unit with a 128² camera (an 8 mm field): a vision dataset in a few seconds."""
    return mj.preset("mid", height=128, width=128)


@pytest.fixture(scope="module")
def vision_dataset(small_device, tmp_path_factory):
    folder = tmp_path_factory.mktemp("vision")
    mj.save_device(folder / "device.json", small_device)
    out = folder / "dataset"
    argv = ["simulate", "--protocol", "vision", "--device", str(folder / "device.json"), "--n", "6"]
    assert main([*argv, "--seed", "3", "--out", str(out)]) == 0
    return mj.open_dataset(out)


def test_vision_dataset_holds_colour_frames_and_their_ground_truth(vision_dataset):
    ds = vision_dataset
    assert ds.channels == 3 and ds.image_names == ("grating_free",)
    assert ds.manifest["protocol"] == "vision" and not np.any(ds.contact)
    np.testing.assert_array_equal(ds.wrenches, 0.0)
    kinds = ds.manifest["metadata"]["scene_kinds"]
    assert kinds == list(mj.SCENE_KINDS)
    latents = ds.latents
    assert latents is not None
    # Two empty views first (the restoration's reference), then a disc, a ring, a
    # rectangle and a picture, 0-30 mm above the pad.
    labels = ["empty" if np.isnan(k) else kinds[int(k)] for k in latents["kind"]]
    assert labels == ["empty", "empty", "disc", "ring", "rectangle", mj.SCENE_TEXTURES[0]]
    heights = latents["height"][2:]
    assert np.all((heights >= 0) & (heights <= 30))
    frame = ds.color_frame(2)
    assert frame.shape == (*ds.frame_shape, 3) and frame.dtype == np.float32
    # The gray frame the tactile tools read is the colour frame's luma (OpenCV's weights).
    np.testing.assert_allclose(ds.frame(2), frame @ np.float32([0.114, 0.587, 0.299]), atol=1 / 255)


def test_grating_free_view_shows_the_object_of_the_csv(vision_dataset, small_device):
    # At the disc's centre (from the CSV, through the magnification at its height) the
    # grating-free view over that of the empty view is the disc's colour over the backdrop.
    ds, device = vision_dataset, small_device
    latents = ds.latents
    assert latents is not None
    disc = 2
    m = float(mj.scene_magnification(device, latents["height"][disc]))
    col = round((device.width - 1) / 2 + latents["x"][disc] / m * float(device.px_per_mm))
    row = round((device.height - 1) / 2 - latents["y"][disc] / m * float(device.px_per_mm))
    black = float(device.optics.offset)
    seen = ds.image("grating_free", disc)[row, col] - black
    empty = ds.image("grating_free", 0)[row, col] - black
    rgb = np.array([latents[c][disc] for c in "rgb"])
    np.testing.assert_allclose(seen / empty, rgb[::-1] / np.array(mj.simulate.BACKDROP_RGB), rtol=0.05)
    # The empty view without the gratings is smooth: no fringe left in it.
    truth = ds.image("grating_free", 0)
    assert np.abs(np.diff(truth, axis=1)).max() < 2e-3 < np.abs(np.diff(ds.color_frame(0), axis=1)).max()


def test_located_objects_match_the_ground_truth(vision_dataset, small_device):
    ds = vision_dataset
    latents = ds.latents
    assert latents is not None
    # The unit restores with its own empty views, the session's first frames.
    reference = np.stack([ds.color_frame(0), ds.color_frame(1)])
    see_through = SeeThrough(reference, black_level=float(small_device.optics.offset))
    for i in (2, 3, 4):
        (seen,) = locate(ds.color_frame(i), small_device, see_through=see_through, height=latents["height"][i]).objects
        assert np.hypot(seen.x_mm - latents["x"][i], seen.y_mm - latents["y"][i]) < 0.3
        assert abs(seen.size_mm - latents["length"][i]) < 0.1 * latents["length"][i]
    assert locate(ds.color_frame(1), small_device, see_through=see_through).status == "empty"
    (rectangle,) = locate(ds.color_frame(4), small_device, see_through=see_through, height=latents["height"][4]).objects
    assert rectangle.yaw_deg is not None and abs((rectangle.yaw_deg - latents["yaw_deg"][4] + 90) % 180 - 90) < 3.0


def test_a_colour_writer_refuses_mixed_frames_and_missing_truth(tmp_path):
    writer = mj.DatasetWriter(tmp_path / "d", device={"name": "x"}, images=("grating_free",))
    colour = np.full((4, 5, 3), 0.5)
    with pytest.raises(ValueError, match="images"):
        writer.add(colour, np.zeros(6))
    writer.add(colour, np.zeros(6), images={"grating_free": colour})
    with pytest.raises(ValueError, match="channel"):
        writer.add(colour[..., 0], np.zeros(6), images={"grating_free": colour})
    writer.close()
    manifest = json.loads((tmp_path / "d" / "manifest.json").read_text())
    assert manifest["channels"] == 3 and manifest["images"] == ["grating_free"]
    with pytest.raises(ValueError, match="lower-case"):
        mj.DatasetWriter(tmp_path / "e", device={"name": "x"}, images=("frames",))
    ds = mj.open_dataset(tmp_path / "d")
    with pytest.raises(mj.DataError, match="'images'"):
        ds.image("depth", 0)
    (tmp_path / "d" / "grating_free" / "000000.png").unlink()
    with pytest.raises(mj.DataError, match="grating_free/000000.png does not exist"):
        mj.open_dataset(tmp_path / "d")


def test_the_simulated_live_sensor_shows_a_scene(small_device):
    # No contact, a disc 10 mm up on frames 1 and 2: colour frames whose gray is the
    # tactile frame's where the view is empty, and whose object is located at its pose.
    disc = mj.scene_disc(1.0, -1.5, 8.0, height=10.0, rgb=(0.1, 0.7, 0.2))
    still = mj.LoadSchedule(
        wrench=np.zeros((3, 6)), x0=np.zeros(3), y0=np.zeros(3), radius=np.full(3, 3.0), contact=np.zeros(3, bool)
    )
    sensor = SimulatedSensor(small_device, still, scene=lambda i: None if i == 0 else disc)
    empty = sensor.frame(0)
    assert empty is not None and empty.shape == (small_device.height, small_device.width, 3)
    np.testing.assert_allclose(empty[..., 1], sensor.reference_frame(), atol=1e-6)
    see_through = SeeThrough(empty, black_level=float(small_device.optics.offset))
    with sensor.source() as source:
        frames = [item for item in source if isinstance(item, mj.live.Frame)]
    assert [f.index for f in frames] == [0, 1, 2] and all(f.color is not None for f in frames)
    color = frames[1].color
    assert color is not None
    (seen,) = locate(color, small_device, see_through=see_through, height=10.0).objects
    assert np.hypot(seen.x_mm - 1.0, seen.y_mm + 1.5) < 0.2 and seen.colour == "green"
