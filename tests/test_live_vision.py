"""Vision mode: notch filters remove the moire and keep colour; hue identification of the six colour classes."""

import cv2
import numpy as np
import pytest

from moirejax.live import (
    classify_patch,
    ColourProbe,
    find_spectral_peaks,
    Frame,
    HUE_CLASSES,
    hue_histogram,
    identify_colour,
    MoireNotch,
    suppress_moire,
)


H = W = 160
PX_PER_MM = 20.0
ROWS, COLS = np.mgrid[0:H, 0:W].astype(np.float64)
# Apparent carrier wavevectors (col, row) in rad/px and their moire beat.
K1 = 2 * np.pi / 3.0 * np.array([np.cos(0.05), np.sin(0.05)])
K2 = 2 * np.pi / 3.5 * np.array([1.0, 0.0])
MOIRE = K1 - K2
# The sum frequency lies beyond Nyquist; the camera sees its alias.
SUM_ALIAS = K1 + K2 - np.array([2 * np.pi, 0.0])
# BGR colours whose OpenCV hues are near the six class centres.
COLOURS = {
    "red": (40, 40, 220),
    "orange": (20, 120, 240),
    "yellow": (30, 220, 230),
    "green": (40, 200, 40),
    "cyan": (220, 210, 40),
    "purple": (170, 40, 140),
}
PATCH = np.s_[50:110, 50:110]


def physical(k_px):
    """(col, row) rad/px -> (kx, ky) rad/mm with y up."""
    return np.array([k_px[0] * PX_PER_MM, -k_px[1] * PX_PER_MM])


def scene_through_sensor(bgr, seed=0):
    """A coloured square on a gray card, seen through the two gratings (float BGR in [0, 1])."""
    scene = np.full((H, W, 3), 0.55)
    scene[PATCH] = np.array(bgr) / 255
    transmission = (1 + np.cos(K1[0] * COLS + K1[1] * ROWS)) * (1 + np.cos(K2[0] * COLS + K2[1] * ROWS)) / 4
    image = scene * (0.3 + 0.7 * transmission)[..., None]
    image = image + np.random.default_rng(seed).normal(0.0, 0.01, image.shape)
    return np.clip(image, 0, 1).astype(np.float32)


def band_energy(gray, k_px, radius_bins=3.0):
    """Spectral energy within `radius_bins` of +-k (the moire band)."""
    spectrum = np.abs(np.fft.fft2(gray - gray.mean())) ** 2
    f_row, f_col = np.fft.fftfreq(H)[:, None], np.fft.fftfreq(W)[None, :]
    energy = 0.0
    for sign in (1, -1):
        d = np.hypot((f_col - sign * k_px[0] / (2 * np.pi)) * W, (f_row - sign * k_px[1] / (2 * np.pi)) * H)
        energy += spectrum[d < radius_bins].sum()
    return energy


def gray_of(image):
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def test_spectral_peaks_find_the_moire():
    image = scene_through_sensor(COLOURS["green"])
    peaks = find_spectral_peaks(gray_of(image), 4, px_per_mm=PX_PER_MM)
    expected = [physical(k) for k in (MOIRE, K1, K2, SUM_ALIAS)]
    bin_size = 2 * np.pi / W * PX_PER_MM
    for k in expected:  # each expected wavevector is among the peaks (up to sign)
        assert min(min(np.linalg.norm(p - k), np.linalg.norm(p + k)) for p in peaks) < 0.5 * bin_size


@pytest.mark.parametrize("name", list(COLOURS))
def test_notch_removes_moire_and_keeps_hue(name):
    image = scene_through_sensor(COLOURS[name])
    wavevectors = np.array([physical(k) for k in (MOIRE, K1, K2, K1 + K2)])
    notch = MoireNotch((H, W), wavevectors, px_per_mm=PX_PER_MM)
    cleaned = notch(image)
    assert cleaned.dtype == np.float32 and cleaned.shape == image.shape
    assert band_energy(gray_of(cleaned), MOIRE) < 0.1 * band_energy(gray_of(image), MOIRE)
    # The same with automatically found peaks.
    automatic = suppress_moire(image, n_peaks=4)
    assert band_energy(gray_of(automatic), MOIRE) < 0.1 * band_energy(gray_of(image), MOIRE)
    # The fringes are gone from the patch and its colour class is unchanged.
    assert np.std(gray_of(cleaned)[PATCH]) < 0.3 * np.std(gray_of(image)[PATCH])
    truth = cv2.cvtColor(np.uint8([[COLOURS[name]]]), cv2.COLOR_BGR2HSV)[0, 0, 0]
    for frame in (image, cleaned):
        match = classify_patch(frame[PATCH])
        assert match.name == name
        assert abs((match.hue - truth + 90) % 180 - 90) < 3


def test_notch_on_uint8_and_gray_frames():
    image = (scene_through_sensor(COLOURS["cyan"]) * 255).astype(np.uint8)
    notch = MoireNotch((H, W), np.array([physical(MOIRE)]), px_per_mm=PX_PER_MM, harmonics=2)
    cleaned = notch(image)
    assert cleaned.dtype == np.uint8
    gray = gray_of(image)
    assert band_energy(notch(gray).astype(float), MOIRE) < 0.1 * band_energy(gray.astype(float), MOIRE)
    with pytest.raises(ValueError, match="differs"):
        notch(np.zeros((10, 10)))


def test_notch_wraps_aliased_wavevectors():
    # A fringe beyond Nyquist shows at its alias; the notch must land there.
    k_alias = np.array([2 * np.pi * (1 - 0.3), 0.0])  # 0.7 cycles/px aliases to -0.3
    fringe = 0.5 + 0.4 * np.cos(k_alias[0] * COLS)
    cleaned = MoireNotch((H, W), np.array([physical(k_alias)]), px_per_mm=PX_PER_MM)(fringe)
    assert np.std(cleaned) < 0.05 * np.std(fringe)


def test_hue_histogram_ignores_dark_and_gray_pixels():
    patch = np.zeros((20, 20, 3), np.uint8)
    patch[:10] = COLOURS["yellow"]
    patch[10:15] = (5, 5, 5)  # dark fringe: no reliable hue
    patch[15:] = (128, 128, 128)  # gray: no hue
    hist = hue_histogram(patch)
    assert hist.shape == (180,) and hist.sum() == 200
    assert identify_colour(hist).name == "yellow"
    assert identify_colour(np.zeros(180)).name == "none"


def test_red_wraps_around_hue_zero():
    hist = np.zeros(180)
    hist[[177, 178, 179, 0, 1, 2]] = 10
    match = identify_colour(hist)
    assert match.name == "red" and min(match.hue, 180 - match.hue) < 1.5 and match.support == 1.0
    for name, centre in HUE_CLASSES.items():
        hist = np.zeros(180)
        hist[int(centre)] = 1
        assert identify_colour(hist).name == name


def test_colour_probe_as_vision_hook():
    image = (scene_through_sensor(COLOURS["orange"]) * 255).astype(np.uint8)
    frame = Frame(0, 0.0, gray_of(image).astype(np.float32) / 255, image)
    notch = MoireNotch((H, W), np.array([physical(k) for k in (MOIRE, K1, K2)]), px_per_mm=PX_PER_MM)
    message = ColourProbe(notch, PATCH)(frame)
    assert message.startswith("colour=orange ")
    assert ColourProbe()(Frame(0, 0.0, frame.gray, None)) is None


def test_colour_probe_keeps_the_brightness_of_a_small_field():
    """On a 16 mm field the moiré lies four frequency bins from zero; the notch must not
    reach the zero frequency there, or every restored frame comes out dimmer."""
    import moirejax as mj
    from moirejax.live import make_colour_probe

    device = mj.preset("mid", height=256, width=256)
    notch = make_colour_probe(device).notch
    assert notch.gain[0, 0] > 0.98
    flat = np.full((256, 256, 3), 0.4)
    np.testing.assert_allclose(notch(flat).mean(), 0.4, rtol=0.02)
