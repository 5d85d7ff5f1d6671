r"""One-time pixel-to-millimetre rectification from an image of a pressed cylinder array.

A grid of cylinders pressed on the sensor shows as a grid of bright (or dark) blobs.
Their sub-pixel centroids, ordered into the grid, are matched to their known positions
in mm and a homography (optionally with radial distortion $k_1, k_2$ fitted jointly)
maps camera pixels to the contact-plane frame of `docs/conventions.md`: x right, y up,
origin at the grid centre. The rectified output of `out_size = (w, h)` pixels at
`px_per_mm` puts that origin at the image centre, so pixel (i, j) sits at
$x_j = (j - (w-1)/2)/\text{px\_per\_mm}$, $y_i = ((h-1)/2 - i)/\text{px\_per\_mm}$.

Radial distortion acts on undistorted pixel coordinates $u$ about the image centre $c$,
normalised by the half-diagonal $R$: with $d = (u - c)/R$, the observed pixel is
$c + R\,d\,(1 + k_1|d|^2 + k_2|d|^4)$.

It is one module because blob detection, grid ordering and the fit all serve one
calibration image, and the `Rectification` they produce is what applies the result.
"""

import dataclasses
import functools
import os
from typing import Literal

import cv2
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._fileio import DataError, read_json, validate_json, write_json
from ._types import Real


FORMAT = "moirejax-rectification"
VERSION = 1


@dataclasses.dataclass(frozen=True)
class Rectification:
    """A fitted camera-to-contact-plane mapping; `apply` resamples frames through it.

    **Fields:**

    - `homography`: 3x3, undistorted input pixel `(col, row, 1)` -> mm `(x, y, 1)` (y up).
    - `input_size`: `(width, height)` of the camera frames it applies to.
    - `output_size`: `(width, height)` of rectified frames.
    - `px_per_mm`: output resolution.
    - `k1`, `k2`: radial distortion (see the module docstring); zero for none.
    - `rms_residual_px`: RMS of the calibration residuals in input pixels.
    - `grid_shape`, `spacing_mm`: the cylinder array it was fitted from, if known.
    """

    homography: np.ndarray
    input_size: tuple[int, int]
    output_size: tuple[int, int]
    px_per_mm: Real
    k1: Real = 0.0
    k2: Real = 0.0
    rms_residual_px: Real = 0.0
    grid_shape: tuple[int, int] | None = None
    spacing_mm: Real | None = None

    def __post_init__(self):
        h = np.asarray(self.homography, dtype=np.float64)
        if h.shape != (3, 3) or not np.all(np.isfinite(h)) or abs(np.linalg.det(h)) < 1e-300:
            raise ValueError(f"homography must be a finite invertible 3x3 matrix, got {self.homography!r}")
        if self.px_per_mm <= 0 or min(self.input_size) < 1 or min(self.output_size) < 1:
            raise ValueError("px_per_mm and image sizes must be positive")
        object.__setattr__(self, "homography", h / h[2, 2] if h[2, 2] != 0 else h)
        for name in ("px_per_mm", "k1", "k2", "rms_residual_px"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.spacing_mm is not None:
            object.__setattr__(self, "spacing_mm", float(self.spacing_mm))

    @property
    def distortion_center(self) -> tuple[float, float]:
        """Centre `c` of the radial distortion: the input image centre (px)."""
        w, h = self.input_size
        return ((w - 1) / 2, (h - 1) / 2)

    @property
    def distortion_radius(self) -> float:
        """Normalising radius `R` of the radial distortion: half the input diagonal (px)."""
        return 0.5 * float(np.hypot(*self.input_size))

    def output_to_mm(self) -> np.ndarray:
        """3x3 matrix taking output pixels `(col, row, 1)` to mm `(x, y, 1)`."""
        w, h = self.output_size
        s = self.px_per_mm
        return np.array([[1 / s, 0, -(w - 1) / (2 * s)], [0, -1 / s, (h - 1) / (2 * s)], [0, 0, 1]])

    def mm_to_pixel(self, points_mm: np.ndarray) -> np.ndarray:
        """Input-image pixel positions `(col, row)` (distortion included) of points in mm `(..., 2)`."""
        undistorted = _apply_h(np.linalg.inv(self.homography), np.asarray(points_mm, dtype=np.float64))
        return _distort(undistorted, self.k1, self.k2, self.distortion_center, self.distortion_radius)

    def pixel_to_mm(self, points_px: np.ndarray) -> np.ndarray:
        """Contact-plane positions (mm) of input-image pixels `(..., 2)` as `(col, row)`."""
        undistorted = _undistort(
            np.asarray(points_px, dtype=np.float64), self.k1, self.k2, self.distortion_center, self.distortion_radius
        )
        return _apply_h(self.homography, undistorted)

    @functools.cached_property
    def _maps(self) -> tuple[np.ndarray, np.ndarray]:
        w, h = self.output_size
        cols, rows = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        out_px = np.stack([cols, rows], axis=-1)
        source = self.mm_to_pixel(_apply_h(self.output_to_mm(), out_px)).astype(np.float32)
        # Fixed-point maps make cv2.remap several times faster than float maps.
        return cv2.convertMaps(source[..., 0], source[..., 1], cv2.CV_16SC2)

    def apply(self, frame: np.ndarray) -> np.ndarray:
        """Rectify a frame (`(h, w)` or `(h, w, c)`, any OpenCV dtype) by bilinear resampling.

        Pixels that fall outside the input are 0. The remap tables are built on first use.

        **Raises:** `ValueError` if the frame size is not `input_size`.
        """
        frame = np.asarray(frame)
        if (frame.shape[1], frame.shape[0]) != tuple(self.input_size):
            raise ValueError(f"frame is {frame.shape[1]}x{frame.shape[0]}, rectification expects {self.input_size}")
        map1, map2 = self._maps
        return cv2.remap(frame, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def to_json(self) -> dict:
        """JSON-ready dict following `data_schema/rectification.schema.json`."""
        obj = {
            "format": FORMAT,
            "version": VERSION,
            "homography": self.homography.tolist(),
            "input_size": [int(v) for v in self.input_size],
            "output_size": [int(v) for v in self.output_size],
            "px_per_mm": float(self.px_per_mm),
            "distortion": {"k1": float(self.k1), "k2": float(self.k2)},
            "rms_residual_px": float(self.rms_residual_px),
        }
        if self.grid_shape is not None and self.spacing_mm is not None:
            obj["grid"] = {"shape": [int(v) for v in self.grid_shape], "spacing_mm": float(self.spacing_mm)}
        return obj

    @classmethod
    def from_json(cls, obj: dict, *, source: str = "<memory>") -> "Rectification":
        """Inverse of [`Rectification.to_json`][]; `DataError` names `source` and the field."""
        validate_json(obj, "rectification", source=source)
        grid = obj.get("grid", {})
        try:
            return cls(
                homography=np.array(obj["homography"], dtype=np.float64),
                input_size=(obj["input_size"][0], obj["input_size"][1]),
                output_size=(obj["output_size"][0], obj["output_size"][1]),
                px_per_mm=float(obj["px_per_mm"]),
                k1=float(obj["distortion"]["k1"]),
                k2=float(obj["distortion"]["k2"]),
                rms_residual_px=float(obj.get("rms_residual_px", 0.0)),
                grid_shape=tuple(grid["shape"]) if "shape" in grid else None,
                spacing_mm=float(grid["spacing_mm"]) if "spacing_mm" in grid else None,
            )
        except ValueError as e:
            # Everything else is checked by the schema; this is the invertibility check.
            raise DataError(f"{source}: field 'homography': {e}") from None


def save_rectification(path: str | os.PathLike, rectification: Rectification) -> None:
    """Validate and atomically write a rectification as JSON."""
    write_json(path, rectification.to_json(), "rectification")


def load_rectification(path: str | os.PathLike) -> Rectification:
    """Read and validate a rectification JSON file (raises `DataError` naming file and field)."""
    return Rectification.from_json(read_json(path), source=str(path))


def _apply_h(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    homogeneous = points @ h[:, :2].T + h[:, 2]
    return homogeneous[..., :2] / homogeneous[..., 2:3]


def _distort(points: np.ndarray, k1: float, k2: float, center: tuple[float, float], radius: float) -> np.ndarray:
    d = (points - np.asarray(center)) / radius
    r2 = np.sum(d * d, axis=-1, keepdims=True)
    return np.asarray(center) + radius * d * (1 + k1 * r2 + k2 * r2 * r2)


def _undistort(points: np.ndarray, k1: float, k2: float, center: tuple[float, float], radius: float) -> np.ndarray:
    observed = (points - np.asarray(center)) / radius
    d = observed.copy()
    # Fixed-point iteration d = observed / (1 + k1 r^2 + k2 r^4): converges for the
    # modest distortion a single-view calibration can fit.
    for _ in range(50):
        r2 = np.sum(d * d, axis=-1, keepdims=True)
        d = observed / (1 + k1 * r2 + k2 * r2 * r2)
    return np.asarray(center) + radius * d


def detect_blobs(
    gray: np.ndarray, polarity: Literal["bright", "dark"] = "bright", *, smooth_px: Real = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Centroids of bright or dark blobs, to sub-pixel precision.

    The background (a wide Gaussian blur) is subtracted, Otsu's threshold splits blobs
    from background, connected components are filtered for compactness, and each
    centroid is weighted by how far its pixels rise above the threshold, which is unbiased
    for symmetric blobs.

    **Arguments:**

    - `gray`: `(h, w)` image (any real dtype).
    - `polarity`: `"bright"` or `"dark"` blobs.
    - `smooth_px`: Gaussian pre-blur (px) to wash out moire fringes or noise; 0 for none.

    **Returns:** centroids `(n, 2)` as `(col, row)` and blob areas `(n,)` in px.
    """
    g = np.asarray(gray, dtype=np.float32)
    if g.ndim != 2:
        raise ValueError(f"expected a 2D grayscale image, got shape {g.shape}")
    if smooth_px > 0:
        g = cv2.GaussianBlur(g, (0, 0), smooth_px)
    background = cv2.GaussianBlur(g, (0, 0), max(g.shape) / 12)
    contrast = g - background if polarity == "bright" else background - g
    lo, hi = float(contrast.min()), float(contrast.max())
    if hi - lo <= 0:
        return np.zeros((0, 2)), np.zeros((0,))
    scaled = np.round((contrast - lo) / (hi - lo) * 255).astype(np.uint8)
    otsu, binary = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    threshold = lo + otsu / 255 * (hi - lo)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    h, w = g.shape
    centres, areas = [], []
    for k in range(1, count):
        x, y, bw, bh, area = (int(v) for v in stats[k])
        touches_border = x == 0 or y == 0 or x + bw == w or y + bh == h
        compact = area >= 5 and area >= 0.5 * bw * bh and 1 / 3 <= bw / bh <= 3
        if touches_border or not compact:
            continue
        window = np.s_[y : y + bh, x : x + bw]
        weights = np.where(labels[window] == k, contrast[window] - threshold, 0.0).clip(min=0)
        total = weights.sum()
        if total <= 0:
            continue
        rows, cols = np.mgrid[y : y + bh, x : x + bw]
        centres.append(((weights * cols).sum() / total, (weights * rows).sum() / total))
        areas.append(area)
    return np.asarray(centres, dtype=np.float64).reshape(-1, 2), np.asarray(areas, dtype=np.float64)


def _quadrilateral(points: np.ndarray) -> np.ndarray | None:
    """The four corners of the convex hull of a (perspective-distorted) grid of points."""
    hull = cv2.convexHull(points.astype(np.float32))
    perimeter = cv2.arcLength(hull, True)
    eps = 0.005 * perimeter
    while eps < 0.3 * perimeter:
        approx = cv2.approxPolyDP(hull, eps, True)
        if len(approx) == 4:
            return approx.reshape(4, 2).astype(np.float64)
        if len(approx) < 4:
            return None
        eps *= 1.25
    return None


def order_grid(points: np.ndarray, grid_shape: tuple[int, int]) -> np.ndarray:
    """Order detected centroids into a `(rows, cols)` grid.

    The hull corners give a first homography to grid indices for each of the eight ways
    to label them; a labelling is valid when every point lands within 0.3 of a distinct
    grid node. Among valid ones the labelling whose columns run most nearly along image
    +x and rows along image +y (down) wins, so the rectified image keeps the camera's
    orientation and handedness.

    **Returns:** `(rows, cols, 2)` centroids `(col, row)`.

    **Raises:** `ValueError` when no consistent ordering exists.
    """
    rows, cols = grid_shape
    if len(points) != rows * cols:
        raise ValueError(f"need {rows * cols} points for a {rows}x{cols} grid, got {len(points)}")
    quad = _quadrilateral(points)
    if quad is None:
        raise ValueError("cannot find the four corners of the blob grid")
    corners = np.array([[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]], dtype=np.float64)
    best, best_score = None, -np.inf
    for flip in (False, True):
        ordered = quad[::-1] if flip else quad
        for shift in range(4):
            src = np.roll(ordered, shift, axis=0)
            to_grid = cv2.getPerspectiveTransform(src.astype(np.float32), corners.astype(np.float32))
            # Two passes: the hull-corner homography, then one refit on all points, which
            # absorbs mild lens distortion that would otherwise break the rounding.
            for _ in range(2):
                grid = _apply_h(to_grid, points)
                index = np.round(grid).astype(int)
                if not _valid_assignment(grid, index, rows, cols):
                    break
                target = index.astype(np.float64)
                to_grid, _ = cv2.findHomography(points, target, 0)
                if to_grid is None:
                    break
            else:
                from_grid = np.linalg.inv(to_grid)
                centre = np.array([(cols - 1) / 2, (rows - 1) / 2])
                step_c = _apply_h(from_grid, centre + [1, 0]) - _apply_h(from_grid, centre)
                step_r = _apply_h(from_grid, centre + [0, 1]) - _apply_h(from_grid, centre)
                score = step_c[0] / np.linalg.norm(step_c) + step_r[1] / np.linalg.norm(step_r)
                if score > best_score:
                    best_score = score
                    out = np.empty((rows, cols, 2))
                    out[index[:, 1], index[:, 0]] = points
                    best = out
    if best is None:
        raise ValueError(f"the detected blobs do not form a {rows}x{cols} grid")
    return best


def _valid_assignment(grid: np.ndarray, index: np.ndarray, rows: int, cols: int) -> bool:
    if np.max(np.abs(grid - index)) > 0.3:
        return False
    if index[:, 0].min() < 0 or index[:, 1].min() < 0 or index[:, 0].max() >= cols or index[:, 1].max() >= rows:
        return False
    return len({(int(c), int(r)) for c, r in index}) == len(index)


def _distortion_residuals(params: jax.Array, args: tuple[jax.Array, jax.Array]) -> jax.Array:
    """Normalised image-space residuals of (homography, k1[, k2]); `params` holds the top 8
    entries of the normalised mm -> undistorted px homography, then the radial terms."""
    mm_norm, observed = args
    g = jnp.append(params[:8], 1.0).reshape(3, 3)
    homogeneous = mm_norm @ g[:, :2].T + g[None, :, 2]
    d = homogeneous[:, :2] / homogeneous[:, 2:3]
    r2 = jnp.sum(d * d, axis=-1, keepdims=True)
    radial = params[8:]
    scale = 1 + radial[0] * r2 + (radial[1] * r2 * r2 if radial.shape[0] > 1 else 0.0)
    return d * scale - observed


def _fit_with_distortion(
    px: np.ndarray, mm: np.ndarray, h0: np.ndarray, center: np.ndarray, radius: float, n_radial: int
) -> tuple[np.ndarray, float, float]:
    """Least-squares fit of (homography, k1[, k2]) minimising image-space residuals.

    Optimistix's Levenberg-Marquardt from the distortion-free homography `h0`, in
    coordinates normalised to order one (pixels about `center` over `radius`, mm over
    their largest magnitude) and in float64 whatever JAX's default precision.
    """
    scale_mm = np.max(np.abs(mm)) or 1.0
    to_px_norm = np.array([[1 / radius, 0, -center[0] / radius], [0, 1 / radius, -center[1] / radius], [0, 0, 1]])
    to_mm_norm = np.diag([1 / scale_mm, 1 / scale_mm, 1.0])
    # g: normalised mm -> normalised undistorted px, with g[2, 2] = 1.
    g = to_px_norm @ np.linalg.inv(h0) @ np.linalg.inv(to_mm_norm)
    g = g / g[2, 2]
    with jax.enable_x64(True):
        start = jnp.asarray(np.concatenate([g.ravel()[:8], np.zeros(n_radial)]))
        args = (jnp.asarray(mm / scale_mm), jnp.asarray((px - center) / radius))
        solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12, linear_solver=lx.QR())
        solution = optx.least_squares(_distortion_residuals, solver, start, args=args, max_steps=200, throw=False)
        params = np.asarray(solution.value)
    g = np.append(params[:8], 1.0).reshape(3, 3)
    # undistorted px -> mm = inverse of (px_norm^-1 . g . mm_norm)
    mm_to_px = np.linalg.inv(to_px_norm) @ g @ to_mm_norm
    k1 = float(params[8])
    k2 = float(params[9]) if n_radial > 1 else 0.0
    return np.linalg.inv(mm_to_px), k1, k2


def calibrate_rectification(
    image: np.ndarray,
    grid_shape: tuple[int, int],
    spacing_mm: Real,
    out_size: tuple[int, int],
    px_per_mm: Real,
    *,
    polarity: Literal["auto", "bright", "dark"] = "auto",
    distortion: Literal["none", "k1", "k1k2"] = "none",
    smooth_px: Real = 0.0,
) -> Rectification:
    """Fit a [`Rectification`][] from one image of a pressed cylinder array.

    **Arguments:**

    - `image`: the camera frame, gray `(h, w)` or BGR `(h, w, 3)`, any OpenCV dtype.
    - `grid_shape`: `(rows, cols)` of the cylinder array; row 0 is the one nearest the top
        of the image, column 0 the one nearest the left.
    - `spacing_mm`: centre-to-centre spacing of the cylinders (mm).
    - `out_size`: `(width, height)` of the rectified frames (px).
    - `px_per_mm`: resolution of the rectified frames.
    - `polarity`: whether the cylinders show as `"bright"` or `"dark"` blobs; `"auto"`
        tries both and keeps the one that forms the grid with the smaller residual.
    - `distortion`: radial terms fitted jointly with the homography.
    - `smooth_px`: Gaussian pre-blur for blob detection (px).

    **Returns:** the rectification; its `rms_residual_px` reports the fit quality.

    **Raises:** `ValueError` when the grid cannot be found or fitted.
    """
    arr = np.asarray(image)
    gray = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY) if arr.ndim == 3 else arr
    rows, cols = grid_shape
    if rows < 2 or cols < 2 or rows * cols < 6:
        raise ValueError(f"grid_shape {grid_shape} too small: need at least 2x3 points")
    if distortion != "none" and rows * cols < 9:
        raise ValueError("fitting distortion needs at least 9 grid points")
    h, w = gray.shape
    errors = []
    best: Rectification | None = None
    for pol in ("bright", "dark") if polarity == "auto" else (polarity,):
        centres, areas = detect_blobs(gray, pol, smooth_px=smooth_px)
        if len(centres) < rows * cols:
            errors.append(f"{pol}: found {len(centres)} blobs, need {rows * cols}")
            continue
        # Spurious detections are usually much smaller or larger than the cylinder imprints.
        keep = np.argsort(np.abs(np.log(areas / np.median(areas))))[: rows * cols]
        try:
            grid_px = order_grid(centres[keep], grid_shape)
        except ValueError as e:
            errors.append(f"{pol}: {e}")
            continue
        r_idx, c_idx = np.mgrid[0:rows, 0:cols]
        mm = np.stack([(c_idx - (cols - 1) / 2) * spacing_mm, ((rows - 1) / 2 - r_idx) * spacing_mm], axis=-1)
        px, mm = grid_px.reshape(-1, 2), mm.reshape(-1, 2).astype(np.float64)
        h0, inliers = cv2.findHomography(px, mm, cv2.RANSAC, 0.25 * spacing_mm)
        if h0 is None or inliers.sum() < max(6, 0.8 * len(px)):
            errors.append(f"{pol}: homography fit failed")
            continue
        inl = inliers.ravel().astype(bool)
        k1 = k2 = 0.0
        homography = h0
        if distortion != "none":
            center = np.array([(w - 1) / 2, (h - 1) / 2])
            radius = 0.5 * float(np.hypot(w, h))
            n_radial = 1 if distortion == "k1" else 2
            homography, k1, k2 = _fit_with_distortion(px[inl], mm[inl], h0, center, radius, n_radial)
        candidate = Rectification(
            homography,
            (w, h),
            (int(out_size[0]), int(out_size[1])),
            float(px_per_mm),
            k1,
            k2,
            grid_shape=(rows, cols),
            spacing_mm=float(spacing_mm),
        )
        residual = candidate.mm_to_pixel(mm[inl]) - px[inl]
        candidate = dataclasses.replace(candidate, rms_residual_px=float(np.sqrt(np.mean(np.sum(residual**2, -1)))))
        if best is None or candidate.rms_residual_px < best.rms_residual_px:
            best = candidate
    if best is None:
        raise ValueError("calibration failed: " + "; ".join(errors))
    return best
