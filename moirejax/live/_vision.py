"""Vision mode: restoring the see-through image, locating objects before contact, and
hue-based colour identification.

With no contact the camera sees the scene through both gratings: the scene times a
periodic transmission. Notching the transmission's spectral peaks (the moiré wavevectors
K_f, the apparent carrier wavevectors k1', k2, and optionally their harmonics) in every
colour channel leaves the scene times the mean transmission, so colours keep their hue.
Hue is read in OpenCV's HSV scale (0-179) as in the paper's colour-card experiment, and
a patch is assigned the nearest of the paper's six colour classes.

A notch leaves everything else of the transmission: the gratings' higher harmonics and
their aliases, and the moiré's dark bands where little light passes. [`SeeThrough`][]
does better with a reference frame of the empty view: the frame is the scene times the
reference's transmission, so a local least-squares ratio of the two recovers the scene
wherever light passes, and multiplying by the reference's smooth envelope gives the
image through gratings of uniform mean transmission. [`locate`][] segments what differs
from the empty view and fits each object's centre, axis and size, in mm in the wrench
frame. [`classify`][] hands the restored image to any classifier the user brings.
"""

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import cv2
import numpy as np

from ..physics import Device, wavenumber_grid
from ._camera import Frame
from ._spectrum import spectral_peaks, to_physical_wavevectors
from ._types import Real


# Hue centres of the paper's six colour classes, OpenCV scale (degrees / 2).
HUE_CLASSES: dict[str, float] = {
    "red": 0.0,
    "orange": 15.0,
    "yellow": 30.0,
    "green": 60.0,
    "cyan": 90.0,
    "purple": 145.0,
}


def find_spectral_peaks(gray: np.ndarray, n_peaks: int, *, px_per_mm: Real = 1.0, min_cycles: Real = 3.0) -> np.ndarray:
    """The `n_peaks` strongest non-DC spectral peaks of an image, as wavevectors.

    **Arguments:**

    - `gray`: `(h, w)` image (for colour, pass a grayscale version).
    - `n_peaks`: how many peaks; each is reported once (not with its mirror image).
    - `px_per_mm`: image resolution, for the units of the result.
    - `min_cycles`: ignore frequencies below this many cycles per image.

    **Returns:** `(n_peaks, 2)` wavevectors `(kx, ky)` in rad/mm (y up), strongest first.
    """
    return to_physical_wavevectors(spectral_peaks(gray, n_peaks, min_cycles=min_cycles), px_per_mm)


class MoireNotch:
    """A precomputed Fourier notch filter for frames of one size.

    Each wavevector `k` (and its multiples up to `harmonics`) gets a Gaussian notch at
    `+k` and `-k`, `1 - exp(-|q - k|^2 / (2 width^2))`; aliased positions beyond Nyquist
    are wrapped into the spectrum as the camera samples them.

    **Arguments:**

    - `shape`: `(h, w)` of the frames.
    - `wavevectors`: `(n, 2)` `(kx, ky)` in rad/mm (y up): moiré and carrier wavevectors.
    - `px_per_mm`: frame resolution.
    - `width`: notch radius (Gaussian sigma) in frequency bins of the larger side, narrowed
        to a quarter of a notch's distance from the zero frequency, which keeps the image's
        mean and its coarsest structure.
    - `harmonics`: how many multiples of each wavevector to notch (binary gratings have
        strong odd harmonics).
    """

    def __init__(
        self,
        shape: tuple[int, int],
        wavevectors: np.ndarray,
        *,
        px_per_mm: Real = 1.0,
        width: Real = 2.5,
        harmonics: int = 1,
    ):
        h, w = shape
        kx, ky = wavenumber_grid((h, w), 1 / px_per_mm, real=True, xp=np)
        # The sampled spectrum repeats every 2 pi rad/px (2 pi px_per_mm rad/mm); sigma is
        # `width` bins of the larger side.
        period = 2 * np.pi * px_per_mm
        sigma = period * width / max(h, w)
        gain = np.ones((h, w // 2 + 1))
        for k_x, k_y in np.asarray(wavevectors, dtype=np.float64).reshape(-1, 2):
            for m in range(1, harmonics + 1):
                # No notch reaches the zero frequency: on a small field the moiré lies a few
                # bins from it, and a notch as wide as on a large field would dim the image.
                alias = (np.array([m * k_x, m * k_y]) + period / 2) % period - period / 2
                s = min(sigma, float(np.hypot(*alias)) / 4)
                for sign in (1, -1):
                    # Distance on the periodic frequency torus, so aliased notches land right.
                    dx = (kx[None, :] - sign * m * k_x + period / 2) % period - period / 2
                    dy = (ky[:, None] - sign * m * k_y + period / 2) % period - period / 2
                    gain *= 1 - np.exp(-(dx**2 + dy**2) / (2 * s**2))
        self.shape = (h, w)
        self.gain = gain

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """Filter a gray `(h, w)` or colour `(h, w, c)` frame; returns the same dtype.

        Float frames are clipped to [0, 1], integer frames to their range.
        """
        arr = np.asarray(image)
        if arr.shape[:2] != self.shape:
            raise ValueError(f"frame shape {arr.shape[:2]} differs from the filter's {self.shape}")
        data = arr.astype(np.float64)
        spectrum = np.fft.rfft2(data, axes=(0, 1))
        gain = self.gain if data.ndim == 2 else self.gain[..., None]
        cleaned = np.fft.irfft2(spectrum * gain, s=self.shape, axes=(0, 1))
        if np.issubdtype(arr.dtype, np.integer):
            info = np.iinfo(arr.dtype)
            return np.clip(np.round(cleaned), info.min, info.max).astype(arr.dtype)
        return np.clip(cleaned, 0.0, 1.0).astype(arr.dtype)


def suppress_moire(
    image: np.ndarray,
    wavevectors: np.ndarray | None = None,
    *,
    px_per_mm: Real = 1.0,
    n_peaks: int = 3,
    width: Real = 2.5,
    harmonics: int = 1,
) -> np.ndarray:
    """Notch the moiré/carrier peaks out of one frame (gray or colour).

    With `wavevectors=None` the `n_peaks` strongest non-DC peaks of the frame's grayscale
    are notched. For a stream of frames build one [`MoireNotch`][] and reuse it.
    """
    arr = np.asarray(image)
    if wavevectors is None:
        gray = arr if arr.ndim == 2 else cv2.cvtColor(arr[..., :3], cv2.COLOR_BGR2GRAY)
        wavevectors = find_spectral_peaks(gray, n_peaks, px_per_mm=px_per_mm)
    notch = MoireNotch(arr.shape[:2], wavevectors, px_per_mm=px_per_mm, width=width, harmonics=harmonics)
    return notch(arr)


def _to_uint8_bgr(bgr: np.ndarray) -> np.ndarray:
    arr = np.asarray(bgr)
    if arr.ndim != 3 or arr.shape[2] < 3:
        raise ValueError(f"expected a BGR image (h, w, 3), got shape {arr.shape}")
    arr = arr[..., :3]
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    return (np.clip(arr.astype(np.float64), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def hue_histogram(
    bgr: np.ndarray, *, mask: np.ndarray | None = None, min_saturation: int = 60, min_value: int = 40
) -> np.ndarray:
    """Histogram of OpenCV hue (180 bins, 0-179) over the coloured pixels of a patch.

    Dark pixels (the moiré's dark fringes) and unsaturated ones have no reliable hue and
    are left out.

    **Arguments:**

    - `bgr`: BGR patch, uint8 or float in [0, 1].
    - `mask`: optional boolean `(h, w)` selection.
    - `min_saturation`, `min_value`: HSV thresholds (0-255) for a pixel to count.

    **Returns:** `(180,)` float counts.
    """
    hsv = cv2.cvtColor(_to_uint8_bgr(bgr), cv2.COLOR_BGR2HSV)
    keep = (hsv[..., 1] >= min_saturation) & (hsv[..., 2] >= min_value)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    return np.bincount(hsv[..., 0][keep].ravel(), minlength=180)[:180].astype(np.float64)


@dataclasses.dataclass(frozen=True)
class ColourMatch:
    """Colour identification of a patch.

    **Fields:**

    - `name`: nearest of [`HUE_CLASSES`][], or `"none"` when no pixel was coloured.
    - `hue`: the dominant hue (OpenCV scale, 0-180).
    - `distance`: circular hue distance to the class centre.
    - `support`: fraction of the histogram mass within 10 hue units of the dominant hue.
    """

    name: str
    hue: float
    distance: float
    support: float


def identify_colour(histogram: np.ndarray, classes: Mapping[str, Real] = HUE_CLASSES) -> ColourMatch:
    """Dominant hue of a [`hue_histogram`][] and its nearest colour class (circular distance)."""
    hist = np.asarray(histogram, dtype=np.float64)
    total = hist.sum()
    if total <= 0:
        return ColourMatch("none", float("nan"), float("nan"), 0.0)
    # Circular smoothing, then the circular mean of hue around the smoothed peak.
    kernel = np.exp(-0.5 * (np.arange(-10, 11) / 3.0) ** 2)
    smoothed = np.convolve(np.concatenate([hist[-10:], hist, hist[:10]]), kernel, mode="valid")
    peak = int(np.argmax(smoothed))
    near = (np.arange(180) - peak + 90) % 180 - 90
    window = np.abs(near) <= 10
    hue = (peak + np.sum(hist[window] * near[window]) / max(hist[window].sum(), 1e-12)) % 180
    distances = {name: abs((hue - centre + 90) % 180 - 90) for name, centre in classes.items()}
    name = min(distances, key=distances.__getitem__)
    return ColourMatch(name, float(hue), float(distances[name]), float(hist[window].sum() / total))


def classify_patch(bgr: np.ndarray, **histogram_kwargs) -> ColourMatch:
    """[`identify_colour`][] of the [`hue_histogram`][] of a BGR patch."""
    return identify_colour(hue_histogram(bgr, **histogram_kwargs))


class ColourProbe:
    """A vision hook for [`run_pipeline`][]: notch the fringes, then name the colour of a region.

    **Arguments:**

    - `notch`: a [`MoireNotch`][] for the (rectified) frame size, or `None` to read hue
        through the fringes (dark fringe pixels are ignored anyway).
    - `region`: `(rows, cols)` slices of the frame to classify; `None` for the whole frame.

    Calling it with a [`Frame`][] returns a message such as
    `"colour=green hue=60.2 support=0.97"`, or `None` for frames without colour.
    """

    def __init__(self, notch: MoireNotch | None = None, region: tuple[slice, slice] | None = None):
        self.notch = notch
        self.region = region

    def __call__(self, frame: Frame) -> str | None:
        if frame.color is None:
            return None
        # The notch filters the whole frame: it is built for the frame size.
        image = frame.color if self.notch is None else self.notch(frame.color)
        if self.region is not None:
            image = image[self.region]
        match = classify_patch(image)
        return f"colour={match.name} hue={match.hue:.1f} support={match.support:.2f}"


# ---------------------------------------------------------------------------------------
# Restoration of the see-through image.


def _as_float_frames(image: np.ndarray, name: str) -> np.ndarray:
    """A colour frame (or a stack of them), uint8/uint16 or float in [0, 1], as float32."""
    arr = np.asarray(image)
    if arr.ndim not in (3, 4) or arr.shape[-1] != 3:
        raise ValueError(f"{name} must be a BGR frame (h, w, 3) or a stack (n, h, w, 3), got shape {arr.shape}")
    if np.issubdtype(arr.dtype, np.integer):
        return arr.astype(np.float32) * np.float32(1 / np.iinfo(arr.dtype).max)
    return arr.astype(np.float32, copy=False)


def _envelope(plane: np.ndarray) -> np.ndarray:
    """The smooth part of an image: a quadratic surface fitted by least squares under a
    Hann window, which averages the periodic fringes out (they leak little through the
    window) and keeps the illumination's vignetting, quadratic in radius."""
    h, w = plane.shape
    rows, cols = np.mgrid[0:h, 0:w]
    u, v = (cols - (w - 1) / 2) / w, (rows - (h - 1) / 2) / h
    basis = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=-1).reshape(-1, 6)
    window = (np.hanning(h)[:, None] * np.hanning(w)[None, :]).reshape(-1)
    coefficients = np.linalg.lstsq(basis * window[:, None], plane.reshape(-1) * window, rcond=None)[0]
    return (basis @ coefficients).reshape(h, w)


class SeeThrough:
    r"""Restores see-through frames with a reference of the empty view.

    A frame is $F = o + \mathrm{PSF} * (S\,T)$: the scene $S$ times the transmission $T$ of
    both gratings and the illumination, over the camera's black level $o$; the reference
    (the empty view, $S = S_0$ uniform) is $R = o + \mathrm{PSF} * (S_0 T)$. Where $S$ is
    smooth on the scale of a grating period, the scene relative to the empty view is the
    local least-squares ratio, each pixel weighted by the light it gets,
    $$\hat S / S_0 = \frac{G * [(F - o)(R - o)]}{G * (R - o)^2}$$
    with $G$ a Gaussian window of `window_px` pixels. Dark fringes, where $T$ is near zero,
    carry little weight instead of dividing noise by zero. The restored image is
    $o + (\hat S / S_0)\,E$, with $E$ the smooth envelope of $R - o$ (the mean transmission
    times the illumination, vignetting included): the frame the camera would see through
    gratings of uniform transmission, which is what the moiré and every harmonic and alias of
    both gratings are removed from.

    **Arguments:**

    - `reference`: the empty view, BGR `(h, w, 3)` or a stack `(n, h, w, 3)` of frames
        (averaged, which lowers their noise), uint8 or float in [0, 1]; rectified like the
        frames, with nothing above the sensor but the backdrop and no contact.
    - `black_level`: the camera's pixel value for no light (a [`Device`][moirejax.Device]'s
        `optics.offset`), in [0, 1].
    - `window_px`: standard deviation (pixels) of the window $G$: wider lowers the noise
        from dark fringes, narrower keeps finer detail of the scene.

    The camera response is taken as linear (`optics.gamma` = 1).
    """

    def __init__(self, reference: np.ndarray, *, black_level: Real = 0.0, window_px: Real = 1.6):
        frames = _as_float_frames(reference, "reference")
        mean = frames.mean(axis=0) if frames.ndim == 4 else frames
        if not 0 <= black_level < 1:
            raise ValueError(f"black_level must be in [0, 1), got {black_level}")
        if not window_px > 0:
            raise ValueError(f"window_px must be positive, got {window_px}")
        light = mean - np.float32(black_level)
        if float(np.median(light)) <= 2 / 255:
            raise ValueError("the reference is dark: record it with the light on and nothing above the sensor")
        self.shape = mean.shape[:2]
        self.black_level = float(black_level)
        self.window_px = float(window_px)
        self._light = light
        # (F - o) R' = F R' - o R': the black level's share is subtracted after the blur.
        self._black_light = cv2.GaussianBlur(np.float32(black_level) * light, (0, 0), self.window_px)
        energy = np.maximum(cv2.GaussianBlur(light * light, (0, 0), self.window_px), np.float32(1e-12))
        self._inverse_energy = (np.float32(1) / energy).astype(np.float32)
        self.envelope = np.stack([_envelope(light[..., c]) for c in range(3)], axis=-1).astype(np.float32)
        self._gain = self.envelope * self._inverse_energy
        self._coarse_inverse_energy = _every_second(self._inverse_energy)

    def _weighted(self, data: np.ndarray) -> np.ndarray:
        """$G * [(F - o)(R - o)]$ of a float32 frame (a new array)."""
        if data.shape != (*self.shape, 3):
            raise ValueError(f"frame shape {data.shape} differs from the reference's {(*self.shape, 3)}")
        weighted = cv2.GaussianBlur(cv2.multiply(data, self._light), (0, 0), self.window_px)
        return cv2.subtract(weighted, self._black_light, dst=weighted)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        """The restored BGR image of a frame (uint8 or float in [0, 1]), in the frame's dtype."""
        arr = np.asarray(frame)
        restored = self._weighted(_as_float_frames(arr, "frame"))
        restored = cv2.multiply(restored, self._gain, dst=restored)
        if np.issubdtype(arr.dtype, np.integer):
            info = np.iinfo(arr.dtype)
            restored += np.float32(self.black_level)
            restored *= np.float32(info.max)
            return np.clip(np.round(restored), 0, info.max).astype(arr.dtype)
        restored += np.float32(self.black_level)
        return np.clip(restored, 0.0, 1.0, out=restored).astype(arr.dtype, copy=False)


def restore(frame: np.ndarray, reference: np.ndarray, *, black_level: Real = 0.0, window_px: Real = 1.6) -> np.ndarray:
    """The see-through image of one frame with the gratings' and the moiré's modulation
    removed, by [`SeeThrough`][] (build one and reuse it for a stream of frames).

    **Arguments:**

    - `frame`: BGR `(h, w, 3)`, uint8 or float in [0, 1].
    - `reference`, `black_level`, `window_px`: as for [`SeeThrough`][].

    **Returns:** the restored BGR image, in the frame's dtype.
    """
    return SeeThrough(reference, black_level=black_level, window_px=window_px)(frame)


def _checked_frame(frame: np.ndarray) -> np.ndarray:
    arr = np.asarray(frame)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"expected a BGR image (h, w, 3), got shape {arr.shape}")
    return arr


# ---------------------------------------------------------------------------------------
# Objects located before contact.


def _every_second(image: np.ndarray) -> np.ndarray:
    """`image[::2, ::2]`, contiguous (OpenCV's nearest-neighbour halving is that, and faster, for even sizes)."""
    h, w = image.shape[:2]
    if h % 2 or w % 2:
        return np.ascontiguousarray(image[::2, ::2])
    return cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_NEAREST)


def _contrast(difference: np.ndarray) -> np.ndarray:
    """Per pixel, the Euclidean norm over B, G, R of a float32 `(h, w, 3)` difference (overwritten)."""
    square = np.square(difference, out=difference)
    norm = square[..., 0] + square[..., 1]
    norm += square[..., 2]
    return np.sqrt(norm, out=norm)


# Contrast-to-noise ratio at which an object's confidence reaches 1.
CONFIDENT_CNR = 20.0


@dataclasses.dataclass(frozen=True)
class SeenObject:
    """An object located in a see-through image.

    **Fields:**

    - `x_mm`, `y_mm`: centre in the wrench frame (mm, x right, y up, origin on the image
        centre), in the object's plane.
    - `yaw_deg`: direction of its long axis from +x towards +y, in [-90, 90); `None` for a
        round object (long and short axes within 10%).
    - `size_mm`: its longest extent (a disc's or ring's diameter, a rectangle's length).
    - `hue`: OpenCV hue (0-180) of its colour, `nan` for a gray or dark one.
    - `colour`: the nearest of [`HUE_CLASSES`][], or `"none"`.
    - `confidence`: in [0, 1], its contrast over the noise of the empty surroundings
        (reaching 1 at `CONFIDENT_CNR`) times its solidity (area over convex hull area).
    """

    x_mm: float
    y_mm: float
    yaw_deg: float | None
    size_mm: float
    hue: float
    colour: str
    confidence: float


@dataclasses.dataclass(frozen=True)
class Sighting:
    """What [`locate`][] saw in one image.

    **Fields:**

    - `objects`: the [`SeenObject`][]s, most confident first.
    - `status`: `"ok"` (objects found), `"empty"` (nothing differs from the empty view),
        `"dark"` (no light above the black level) or `"saturated"` (most pixels clipped):
        the last three with no objects.
    """

    objects: list[SeenObject]
    status: str


def locate(
    image: np.ndarray,
    device: Device,
    *,
    see_through: SeeThrough | None = None,
    height: Real | None = None,
    min_contrast: Real = 0.25,
    min_size_mm: Real = 1.0,
) -> Sighting:
    r"""Objects above the sensor in a see-through frame: segmented by their colour difference
    from the empty view, then fitted.

    Each pixel's scene relative to the empty view is `(restored - o) / E` (the envelope $E$ of [`SeeThrough`][])
    (1 on the backdrop); pixels whose colour differs from 1 by more than `min_contrast`
    (Euclidean, over B, G, R) seed an object; objects are found on every second pixel and
    measured at full resolution inside their boxes, so that a 512 x 512 frame takes a few
    milliseconds (`benchmarks/vision.py`). Its outline is then taken at half its own
    contrast, where a defocused edge is symmetric, so the blur of a high object does not
    grow it. From the outline's moments: the centre; from the second moments, the long
    axis; from the minimum-area rectangle, the extent. Pixels are converted to mm in the
    object's plane, `(Z + a + h) / Z / px_per_mm` per pixel ([`scene_magnification`][moirejax.scene_magnification]),
    with `h = height`, or 0 (the contact surface) when the height is not known.

    **Arguments:**

    - `image`: with `see_through`, the raw BGR frame, which is checked for exposure and then
        restored; without, an image restored already. uint8 or float in [0, 1].
    - `device`: the sensor (resolution, `Z`, `a` and `optics.offset`, the black level).
    - `see_through`: the [`SeeThrough`][] of the unit: it restores the frame, and its `envelope` is the empty view.
        Without it the image's own smooth envelope stands in for the empty view, which is
        right only while the objects are small against the view.
    - `height`: the objects' height (mm) above the contact surface, if known.
    - `min_contrast`: the relative colour difference that makes a pixel part of an object.
    - `min_size_mm`: smaller objects (equivalent diameter, object plane) are ignored.

    **Returns:** a [`Sighting`][]: the objects and a status; never an object on an empty,
    dark or saturated frame.
    """
    frame = _as_float_frames(_checked_frame(image), "image")
    h, w = frame.shape[:2]
    if height is not None and not height >= 0:
        raise ValueError(f"height must be >= 0 mm above the contact surface, got {height}")
    if not min_contrast > 0:
        raise ValueError(f"min_contrast must be positive, got {min_contrast}")
    black = float(device.optics.offset)
    sample = frame[::4, ::4]
    brightest = np.maximum(np.maximum(sample[..., 0], sample[..., 1]), sample[..., 2])
    if np.mean(brightest >= 254 / 255) > 0.5:
        return Sighting([], "saturated")
    if float(np.percentile(brightest, 99)) <= black + 2 / 255:
        return Sighting([], "dark")
    # The scene relative to the empty view is `numerator * scale`, formed only where it is needed.
    if see_through is None:
        numerator = frame - np.float32(black)
        base = np.stack([_envelope(numerator[..., c]) for c in range(3)], axis=-1)
        scale = (1 / np.maximum(base, 1e-6)).astype(np.float32)
        coarse_scale = _every_second(scale)
    else:
        numerator, scale = see_through._weighted(frame), see_through._inverse_energy
        coarse_scale = see_through._coarse_inverse_energy
    # Objects are found on every second pixel (the restored image is smooth on that scale),
    # then each is measured at full resolution inside its box.
    coarse = cv2.multiply(_every_second(numerator), coarse_scale)
    coarse = _contrast(np.subtract(coarse, np.float32(1), out=coarse))
    # Pixel noise of the contrast map, from its fine-scale residual (robust to the objects),
    # on every fourth pixel.
    residual = (coarse - cv2.GaussianBlur(coarse, (0, 0), 1.0))[::2, ::2]
    noise = 1.4826 * float(np.median(np.abs(residual))) + 1e-6
    magnification = (float(device.Z) + float(device.a) + (0.0 if height is None else float(height))) / float(device.Z)
    mm_per_px = magnification / float(device.px_per_mm)
    min_area_px = math.pi / 4 * (min_size_mm / mm_per_px) ** 2
    objects, measured = [], set()
    coarse_seeds, _ = cv2.findContours(
        (coarse > min_contrast).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    for coarse_seed in coarse_seeds:
        x0, y0, bw, bh = cv2.boundingRect(coarse_seed)
        if 4 * bw * bh < min_area_px / 2:
            continue
        # The box at full resolution, with room for the outline's margin.
        margin = max(bw, bh) // 2 + 6
        b0, b1 = max(2 * y0 - margin, 0), min(2 * (y0 + bh) + margin, h)
        a0, a1 = max(2 * x0 - margin, 0), min(2 * (x0 + bw) + margin, w)
        relative = numerator[b0:b1, a0:a1] * scale[b0:b1, a0:a1]
        contrast = _contrast(relative - np.float32(1))
        seeds = (contrast > min_contrast).astype(np.uint8)
        contours, _ = cv2.findContours(seeds, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE, offset=(a0, b0))
        # The full-resolution seed through a pixel of the coarse one (the same value there).
        point = (2 * float(coarse_seed[0, 0, 0]), 2 * float(coarse_seed[0, 0, 1]))
        inside = [c for c in contours if cv2.pointPolygonTest(c, point, False) >= 0]
        if not inside:
            continue
        seed = min(inside, key=cv2.contourArea)
        x0, y0, bw, bh = cv2.boundingRect(seed)
        if (x0, y0, bw, bh) in measured or cv2.contourArea(seed) < min_area_px:
            continue
        measured.add((x0, y0, bw, bh))
        pad = max(bw, bh) // 4 + 2
        r0, r1, c0, c1 = max(y0 - pad, b0), min(y0 + bh + pad, b1), max(x0 - pad, a0), min(x0 + bw + pad, a1)
        box = (slice(r0 - b0, r1 - b0), slice(c0 - a0, c1 - a0))
        seed_mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
        cv2.drawContours(seed_mask, [seed], -1, 1, thickness=cv2.FILLED, offset=(-c0, -r0))
        # The seed's own pixels (not a ring's hole) give the object's contrast.
        level = float(np.median(contrast[box][(seed_mask > 0) & (seeds[box] > 0)]))
        outline_mask = (contrast[box] > level / 2).astype(np.uint8)
        outlines, _ = cv2.findContours(outline_mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE, offset=(c0, r0))
        outline = max(outlines, key=cv2.contourArea)
        moments = cv2.moments(outline)
        if moments["m00"] <= 0:
            continue
        cx, cy = moments["m10"] / moments["m00"], moments["m01"] / moments["m00"]
        mu20, mu02, mu11 = (moments[k] / moments["m00"] for k in ("mu20", "mu02", "mu11"))
        spread = math.hypot((mu20 - mu02) / 2, mu11)
        major, minor = (mu20 + mu02) / 2 + spread, (mu20 + mu02) / 2 - spread
        # Image rows run down: the axis angle in the wrench frame (y up) is the image angle negated.
        yaw = -0.5 * math.degrees(math.atan2(2 * mu11, mu20 - mu02))
        round_object = minor > 0 and math.sqrt(major / minor) < 1.1
        # Contour points are pixel centres: the extent reaches half a pixel beyond each end.
        extent = max(cv2.minAreaRect(outline)[1]) + 1.0
        hull_area = cv2.contourArea(cv2.convexHull(outline))
        solidity = moments["m00"] / hull_area if hull_area > 0 else 0.0
        fill = np.zeros((r1 - r0, c1 - c0), np.uint8)
        cv2.drawContours(fill, [outline], -1, 1, thickness=cv2.FILLED, offset=(-c0, -r0))
        # The backdrop maps to mid-gray, so that the object's hue is read at a usable value.
        match = identify_colour(hue_histogram(np.clip(relative[box] * 0.5, 0.0, 1.0), mask=fill > 0))
        objects.append(
            SeenObject(
                x_mm=(cx - (w - 1) / 2) * mm_per_px,
                y_mm=((h - 1) / 2 - cy) * mm_per_px,
                yaw_deg=None if round_object else (yaw + 90) % 180 - 90,
                size_mm=extent * mm_per_px,
                hue=match.hue,
                colour=match.name,
                confidence=float(min(1.0, level / noise / CONFIDENT_CNR) * min(solidity, 1.0)),
            )
        )
    objects.sort(key=lambda o: -o.confidence)
    return Sighting(objects, "ok" if objects else "empty")


# ---------------------------------------------------------------------------------------
# A classifier of the user's own.


@dataclasses.dataclass(frozen=True)
class Classification:
    """What [`classify`][] made of one frame.

    **Fields:**

    - `label`: the model's answer. When the model returns a label (a string, an integer,
        any scalar), that label; when it returns scores, the name in `labels` of the highest
        score, or its index without `labels`. `None` when the model was not called.
    - `scores`: the scores as the model returned them, as a 1-D float64 array (a batch of
        one, `(1, n)`, is flattened), not normalised: logits stay logits, probabilities
        stay probabilities. `None` when the model returned a label or was not called.
    - `status`: `"ok"` (the model was called), or why it was not: `"dark"` (no light above
        the black level), `"saturated"` (most pixels clipped) or `"empty"` (nothing differs
        from the empty view, only checked with a [`SeeThrough`][]).
    """

    label: Any
    scores: np.ndarray | None
    status: str


def _exposure_status(frame: np.ndarray, black_level: float) -> str | None:
    """`"saturated"` or `"dark"` for a float frame that is one of them (the thresholds of [`locate`][]), else `None`."""
    sample = frame[::4, ::4]
    brightest = np.maximum(np.maximum(sample[..., 0], sample[..., 1]), sample[..., 2])
    if np.mean(brightest >= 254 / 255) > 0.5:
        return "saturated"
    if float(np.percentile(brightest, 99)) <= black_level + 2 / 255:
        return "dark"
    return None


def _shows_nothing(restored: np.ndarray, see_through: SeeThrough, min_contrast: float) -> bool:
    """Whether a restored float image nowhere differs from the empty view by `min_contrast`.

    The scene relative to the empty view, `(restored - o) / E`, is 1 on the backdrop; its
    colour difference from 1 is smoothed over a few pixels (on every second pixel) so that
    the camera noise of single pixels does not count as an object.
    """
    relative = (_every_second(restored) - np.float32(see_through.black_level)) / _every_second(see_through.envelope)
    contrast = cv2.GaussianBlur(_contrast(relative - np.float32(1)), (0, 0), 2.0)
    return float(contrast.max()) <= min_contrast


def classify(
    image: np.ndarray,
    model: Callable[[np.ndarray], Any],
    *,
    see_through: SeeThrough | None = None,
    labels: Sequence[Any] | None = None,
    black_level: Real | None = None,
    min_contrast: Real | None = 0.25,
) -> Classification:
    """Hands a see-through frame to any image classifier: restored first, and only if it shows something.

    The frame is checked for exposure; a dark or saturated frame is not passed to the model.
    With a [`SeeThrough`][] the frame is restored (the gratings' and the moiré's modulation
    removed, see [`restore`][]), and a frame that shows only the empty view is not passed
    either. Otherwise `model(image)` gets the image as a numpy array. moirejax depends on no
    machine-learning runtime: the model is any callable, and wrapping one is its caller's
    business. An ONNX Runtime session whose input is named `"image"` and takes one RGB
    float image in channels-first order:

    ```python
    session = onnxruntime.InferenceSession("model.onnx")
    model = lambda im: session.run(None, {"image": im[None, ..., ::-1].transpose(0, 3, 1, 2).astype("float32")})[0]
    ```

    A PyTorch module (in `eval()` mode) on the same input:

    ```python
    to_tensor = lambda im: torch.from_numpy(im[..., ::-1].transpose(2, 0, 1).copy()).float()[None]
    model = lambda im: net(to_tensor(im)).detach().numpy()
    ```

    Convert uint8 frames to the model's scale in the same lambda (`im / 255`), and resize
    them if it was trained on another size (`cv2.resize`).

    **Arguments:**

    - `image`: a BGR frame `(h, w, 3)`, uint8 or float in [0, 1]: with `see_through`, the
        raw frame; without, the image the model gets as it is.
    - `model`: `model(image) -> label | scores`, called with a BGR `(h, w, 3)` array in
        the frame's dtype (the restored image with `see_through`). It returns a label (a
        scalar: a string, an integer) or an array of scores, one per class, `(n,)` or
        `(1, n)`.
    - `see_through`: the unit's [`SeeThrough`][]: it restores the frame, and its
        `black_level` is the default for `black_level`.
    - `labels`: the class names, in the order of the scores: the label of scores is then
        the name of the highest one.
    - `black_level`: the camera's value for no light, in [0, 1], for the dark-frame check;
        `see_through.black_level` by default, else 0.
    - `min_contrast`: with `see_through`, the relative colour difference from the empty
        view that a region must reach for the frame not to be `"empty"` (as for
        [`locate`][]); `None` passes empty views to the model too.

    **Returns:** a [`Classification`][]: the label, the scores and the status.

    **Raises:** `RuntimeError` when the model raises, naming its exception (which is
    chained as the cause): a model that fails is a bug to see, not a status. In
    [`run_pipeline`][] a [`VisionClassifier`][] that raises becomes a `vision_error`
    record and the loop goes on. `ValueError` for an answer that is neither a scalar nor
    numbers, for scores that are not one row, and for scores whose length differs from that
    of `labels`.
    """
    arr = _checked_frame(image)
    if black_level is None:
        black_level = 0.0 if see_through is None else see_through.black_level
    if not 0 <= black_level < 1:
        raise ValueError(f"black_level must be in [0, 1), got {black_level}")
    if min_contrast is not None and not min_contrast > 0:
        raise ValueError(f"min_contrast must be positive or None, got {min_contrast}")
    frame = _as_float_frames(arr, "image")
    status = _exposure_status(frame, float(black_level))
    if status is not None:
        return Classification(None, None, status)
    if see_through is not None:
        arr = see_through(arr)
        if min_contrast is not None and _shows_nothing(
            _as_float_frames(arr, "image"), see_through, float(min_contrast)
        ):
            return Classification(None, None, "empty")
    try:
        answer = model(arr)
    except Exception as e:
        raise RuntimeError(f"the classifier raised {type(e).__name__}: {e}") from e
    if np.ndim(answer) == 0:
        # NumPy, JAX and PyTorch scalars become Python ones.
        return Classification(answer.item() if hasattr(answer, "item") else answer, None, "ok")
    try:
        scores = np.asarray(answer, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"the classifier returned neither a label nor scores: {e}") from e
    if scores.size == 0 or sum(n > 1 for n in scores.shape) > 1:
        raise ValueError(f"the classifier returned scores of shape {scores.shape}: expected (n,) or (1, n)")
    scores = scores.reshape(-1)
    if labels is None:
        return Classification(int(np.argmax(scores)), scores, "ok")
    if len(labels) != scores.size:
        raise ValueError(f"the classifier returned {scores.size} scores for {len(labels)} labels")
    return Classification(labels[int(np.argmax(scores))], scores, "ok")


class VisionClassifier:
    """A vision hook for [`run_pipeline`][]: [`classify`][] every colour frame in vision mode.

    **Arguments:**

    - `model`, `see_through`, `labels`, and any keyword argument of [`classify`][].

    Calling it with a [`Frame`][] returns the record's message, such as
    `"label=chelsea status=ok"` (or `"label=none status=empty"` when the model was not
    called), or `None` for frames without colour; the whole [`Classification`][] is kept
    in `last`.
    """

    def __init__(
        self,
        model: Callable[[np.ndarray], Any],
        *,
        see_through: SeeThrough | None = None,
        labels: Sequence[Any] | None = None,
        **classify_kwargs: Any,
    ):
        self.model = model
        self.see_through = see_through
        self.labels = labels
        self.classify_kwargs = classify_kwargs
        self.last: Classification | None = None

    def __call__(self, frame: Frame) -> str | None:
        if frame.color is None:
            return None
        self.last = classify(
            frame.color, self.model, see_through=self.see_through, labels=self.labels, **self.classify_kwargs
        )
        label = "none" if self.last.label is None else self.last.label
        return f"label={label} status={self.last.status}"
