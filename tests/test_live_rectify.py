"""Rectification from a synthetic cylinder-array image rendered through a known camera mapping."""

import json

import numpy as np
import pytest

from moirejax import DataError
from moirejax.live import (
    calibrate_rectification,
    detect_blobs,
    load_rectification,
    Rectification,
    save_rectification,
)


ROWS, COLS, SPACING = 5, 7, 5.0  # cylinder array, mm
RADIUS = 1.2  # cylinder imprint radius, mm
OUT_SIZE, OUT_PX_PER_MM = (400, 300), 10.0
# mm -> undistorted pixel: a tilted, slightly rotated view (y up in mm, rows down in px).
MM_TO_PX = np.array([[9.0, 1.2, 320.0], [0.6, -8.5, 240.0], [0.0008, 0.001, 1.0]])


def true_mapping(k1=0.0, k2=0.0):
    return Rectification(np.linalg.inv(MM_TO_PX), (640, 480), OUT_SIZE, OUT_PX_PER_MM, k1, k2)


def render(mapping, *, bright=True, noise=0.01, seed=0):
    """Camera image of the pressed array, evaluated analytically at every pixel.

    Each pixel is mapped to the contact plane through the true (distorted) mapping and
    shaded by its distance to the nearest cylinder centre, with a soft edge.
    """
    w, h = mapping.input_size
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    mm = mapping.pixel_to_mm(np.stack([cols, rows], axis=-1))
    c = np.clip(np.round(mm[..., 0] / SPACING + (COLS - 1) / 2), 0, COLS - 1)
    r = np.clip(np.round((ROWS - 1) / 2 - mm[..., 1] / SPACING), 0, ROWS - 1)
    dist = np.hypot(mm[..., 0] - (c - (COLS - 1) / 2) * SPACING, mm[..., 1] - ((ROWS - 1) / 2 - r) * SPACING)
    blob = 0.5 * (1 - np.tanh((dist - RADIUS) / 0.06))
    image = 0.35 + (0.45 if bright else -0.25) * blob
    image = image + np.random.default_rng(seed).normal(0.0, noise, image.shape)
    return np.clip(image * 255, 0, 255).astype(np.uint8)


def grid_mm():
    r, c = np.mgrid[0:ROWS, 0:COLS]
    return np.stack([(c - (COLS - 1) / 2) * SPACING, ((ROWS - 1) / 2 - r) * SPACING], axis=-1).reshape(-1, 2)


def max_pixel_error(estimate, truth):
    """Largest disagreement (input px) of where points across the array land in the camera image."""
    x, y = np.meshgrid(np.linspace(-15, 15, 31), np.linspace(-10, 10, 21))
    mm = np.stack([x, y], axis=-1)
    return float(np.max(np.linalg.norm(estimate.mm_to_pixel(mm) - truth.mm_to_pixel(mm), axis=-1)))


@pytest.mark.parametrize("bright", [True, False], ids=["bright", "dark"])
def test_recovers_known_homography(bright):
    truth = true_mapping()
    estimate = calibrate_rectification(render(truth, bright=bright), (ROWS, COLS), SPACING, OUT_SIZE, OUT_PX_PER_MM)
    assert max_pixel_error(estimate, truth) < 0.5
    assert estimate.rms_residual_px < 0.2
    assert estimate.input_size == (640, 480) and estimate.output_size == OUT_SIZE


def test_recovers_radial_distortion():
    truth = true_mapping(k1=-0.15, k2=0.02)
    image = render(truth)
    estimate = calibrate_rectification(image, (ROWS, COLS), SPACING, OUT_SIZE, OUT_PX_PER_MM, distortion="k1k2")
    assert max_pixel_error(estimate, truth) < 0.5
    # Ignoring the distortion is visibly worse: the joint fit is doing the work.
    plain = calibrate_rectification(image, (ROWS, COLS), SPACING, OUT_SIZE, OUT_PX_PER_MM)
    assert max_pixel_error(plain, truth) > 1.0 and plain.rms_residual_px > 2 * estimate.rms_residual_px
    assert estimate.k1 == pytest.approx(-0.15, abs=0.03)


def test_rectified_image_puts_cylinders_on_the_grid():
    truth = true_mapping()
    rect = calibrate_rectification(render(truth), (ROWS, COLS), SPACING, OUT_SIZE, OUT_PX_PER_MM)
    rectified = rect.apply(render(truth))
    assert rectified.shape == (OUT_SIZE[1], OUT_SIZE[0]) and rectified.dtype == np.uint8
    centres, _ = detect_blobs(rectified, "bright")
    w, h = OUT_SIZE
    expected = np.stack(
        [grid_mm()[:, 0] * OUT_PX_PER_MM + (w - 1) / 2, (h - 1) / 2 - grid_mm()[:, 1] * OUT_PX_PER_MM], axis=-1
    )
    assert len(centres) == len(expected)
    nearest = np.min(np.linalg.norm(centres[:, None, :] - expected[None, :, :], axis=-1), axis=0)
    assert nearest.max() < 0.5
    # Colour frames go through the same maps.
    colour = rect.apply(np.repeat(render(truth)[..., None], 3, axis=-1))
    np.testing.assert_array_equal(colour[..., 1], rectified)


def test_mapping_round_trip_and_size_check():
    rect = true_mapping(k1=-0.05, k2=0.01)
    points = np.array([[12.5, -3.0], [-20.0, 11.0], [0.0, 0.0]])
    np.testing.assert_allclose(rect.pixel_to_mm(rect.mm_to_pixel(points)), points, atol=1e-9)
    with pytest.raises(ValueError, match="expects"):
        rect.apply(np.zeros((100, 100), np.uint8))


def test_save_load_round_trip(tmp_path):
    rect = calibrate_rectification(render(true_mapping()), (ROWS, COLS), SPACING, OUT_SIZE, OUT_PX_PER_MM)
    path = tmp_path / "rect.json"
    save_rectification(path, rect)
    loaded = load_rectification(path)
    np.testing.assert_allclose(loaded.homography, rect.homography, rtol=1e-15)
    assert (loaded.input_size, loaded.output_size, loaded.px_per_mm) == (rect.input_size, rect.output_size, 10.0)
    assert loaded.grid_shape == (ROWS, COLS) and loaded.spacing_mm == SPACING
    frame = render(true_mapping())
    np.testing.assert_array_equal(loaded.apply(frame), rect.apply(frame))
    assert not list(tmp_path.glob(".*.tmp"))


def test_load_rejects_bad_files(tmp_path):
    good = true_mapping().to_json()
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({**good, "px_per_mm": -1}))
    with pytest.raises(DataError, match="px_per_mm"):
        load_rectification(path)
    path.write_text(json.dumps({**good, "homography": [[1, 0, 0], [0, 1, 0], [0, 0]]}))
    with pytest.raises(DataError, match="homography"):
        load_rectification(path)
    path.write_text(json.dumps({**good, "homography": [[1, 2, 0], [2, 4, 0], [0, 0, 1]]}))
    with pytest.raises(DataError, match="homography"):
        load_rectification(path)


def test_calibration_failures_are_value_errors():
    image = render(true_mapping())
    with pytest.raises(ValueError, match="need 48"):
        calibrate_rectification(image, (6, 8), SPACING, OUT_SIZE, OUT_PX_PER_MM, polarity="bright")
    with pytest.raises(ValueError, match="calibration failed"):
        calibrate_rectification(np.full((480, 640), 90, np.uint8), (ROWS, COLS), SPACING, OUT_SIZE, OUT_PX_PER_MM)
