"""Vision mode: Fourier notch filtering of the moiré and carrier fringes, and hue-based colour identification.

With no contact the camera sees the scene through both gratings: the scene times a
periodic transmission. Notching the transmission's spectral peaks (the moiré wavevectors
K_f, the apparent carrier wavevectors k1', k2, and optionally their harmonics) in every
colour channel leaves the scene times the mean transmission, so colours keep their hue.
Hue is read in OpenCV's HSV scale (0-179) as in the paper's colour-card experiment, and
a patch is assigned the nearest of the paper's six colour classes.
"""

import dataclasses
from collections.abc import Mapping

import cv2
import numpy as np

from ..physics import wavenumber_grid
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
    - `width`: notch radius (Gaussian sigma) in frequency bins of the larger side.
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
                for sign in (1, -1):
                    # Distance on the periodic frequency torus, so aliased notches land right.
                    dx = (kx[None, :] - sign * m * k_x + period / 2) % period - period / 2
                    dy = (ky[:, None] - sign * m * k_y + period / 2) % period - period / 2
                    gain *= 1 - np.exp(-(dx**2 + dy**2) / (2 * sigma**2))
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
    offsets = np.arange(-10, 11)
    kernel = np.exp(-0.5 * (offsets / 3.0) ** 2)
    smoothed = sum(weight * np.roll(hist, int(o)) for o, weight in zip(offsets, kernel))
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
