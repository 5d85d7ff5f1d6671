r"""GateER: the gated-energy-ratio contact gate that switches between vision and tactile mode.

Contact moves the moiré fringes locally (phase shift, period or orientation change);
illumination drift and, in vision mode, the scene seen through the sensor mostly change
brightness and fringe contrast. The energy ratio is built to see the first and not the
second:

1. the frame is area-averaged to a working size and divided by its local mean, giving
   the fringe contrast $c = I/\bar I - 1$ (high-passed once more), which does not change
   when the illumination is scaled by a smooth field;
2. each moiré component $K$ is demodulated, $z_K = G_\sigma * (c\,e^{-iK\cdot x})$, a
   complex fringe-amplitude map;
3. against an adaptive no-contact baseline $\bar z_K$, the part of $z$ that no
   non-negative real gain $g$ can explain within a window $W$ of about half a moiré
   period is the fringe motion, and the local energy ratio is
   $$E(x) = \frac{\min_{g \ge 0} W * \sum_K |z_K - g\,\bar z_K|^2}{W * \sum_K |\bar z_K|^2},$$
   which is $\sin^2\Delta\phi$ for a local phase shift $\Delta\phi$ (1 beyond $\pi/2$) and
   0 for any change of brightness or contrast;
4. the gate's energy ratio is the maximum of $E(x)$ over the interior, so a small touch
   is not diluted by the untouched area.

The baseline is an exponential moving average of $z$ updated only in vision mode and
only on quiet frames (below the off threshold), so it tracks slow drift but never absorbs
a contact. The on threshold adapts to the noise floor (`noise_factor` times a moving
average of the quiet energy ratio, never below `on_threshold`); the off threshold is
`1 - hysteresis` times it. A switch happens on the first frame past a threshold (after
`min_dwell_frames` in the current mode).

Limits: changes slower than about `1 / baseline_rate` frames are drift by definition, so a
press that builds up that slowly is missed; a scene with structure at the moiré period
(an in-focus object edge the size of a fringe) can look like contact.
"""

import dataclasses
from typing import Literal

import cv2
import numpy as np

from ._spectrum import spectral_peaks, to_index_wavevectors
from ._types import Real


Mode = Literal["vision", "tactile"]


@dataclasses.dataclass(frozen=True)
class GateDecision:
    """Result of one gate update.

    **Fields:**

    - `mode`: `"vision"` (no contact) or `"tactile"`.
    - `energy_ratio`: the gated energy ratio of this frame (0 during warm-up).
    - `switched`: whether this frame changed the mode.
    - `threshold`: the on threshold in force for this frame (off is `1 - hysteresis` of it).
    """

    mode: Mode
    energy_ratio: float
    switched: bool
    threshold: float


def _blur_complex(z: np.ndarray, sigma: float) -> np.ndarray:
    pair = np.stack([z.real, z.imag], axis=-1).astype(np.float32)
    pair = cv2.GaussianBlur(pair, (0, 0), sigma)
    return pair[..., 0] + 1j * pair[..., 1]


class GateER:
    """Contact gate with an adaptive baseline and hysteresis; see the module docstring.

    **Arguments:**

    - `on_threshold`: lowest on threshold of the energy ratio. 0.02 is a mean phase shift
        of about 0.14 rad over one moiré period of the touched area.
    - `hysteresis`: switch off below `(1 - hysteresis) * threshold` (paper: about 20%).
    - `noise_factor`: the on threshold is at least this multiple of the quiet noise floor.
    - `baseline_rate`: EMA rate of the baseline per quiet vision-mode frame; the gate
        treats changes slower than about `1 / baseline_rate` frames as drift.
    - `noise_rate`: EMA rate of the noise-floor estimate.
    - `warmup_frames`: frames averaged into the first baseline (reported as vision mode).
    - `min_dwell_frames`: frames a mode must last before the gate may leave it.
    - `moire_wavevectors`: `(n, 2)` moiré wavevectors `(kx, ky)` in rad/mm (y up) of the
        frames handed to `update`; `None` finds the `n_moire` strongest spectral peaks of
        the first frame (periods of 5 to `work_size/3` working pixels).
    - `px_per_mm`: resolution of the frames, to convert `moire_wavevectors`.
    - `n_moire`: number of moiré components to find automatically.
    - `work_size`: frames are area-averaged so the larger side is at most this.
    - `window_periods`: width (sigma) of the local window W in moiré periods.
    """

    def __init__(
        self,
        *,
        on_threshold: Real = 0.02,
        hysteresis: Real = 0.2,
        noise_factor: Real = 3.0,
        baseline_rate: Real = 0.05,
        noise_rate: Real = 0.05,
        warmup_frames: int = 3,
        min_dwell_frames: int = 0,
        moire_wavevectors: np.ndarray | None = None,
        px_per_mm: Real = 1.0,
        n_moire: int = 1,
        work_size: int = 128,
        window_periods: Real = 0.5,
    ):
        if not 0 < hysteresis < 1:
            raise ValueError(f"hysteresis must be in (0, 1), got {hysteresis}")
        if on_threshold <= 0 or noise_factor < 1 or warmup_frames < 1 or min_dwell_frames < 0:
            raise ValueError("need on_threshold > 0, noise_factor >= 1, warmup_frames >= 1, min_dwell_frames >= 0")
        if not (0 < baseline_rate <= 1 and 0 < noise_rate <= 1):
            raise ValueError("baseline_rate and noise_rate must be in (0, 1]")
        self.on_threshold = on_threshold
        self.hysteresis = hysteresis
        self.noise_factor = noise_factor
        self.baseline_rate = baseline_rate
        self.noise_rate = noise_rate
        self.warmup_frames = warmup_frames
        self.min_dwell_frames = min_dwell_frames
        self.moire_wavevectors = None if moire_wavevectors is None else np.asarray(moire_wavevectors, np.float64)
        self.px_per_mm = px_per_mm
        self.n_moire = n_moire
        self.work_size = work_size
        self.window_periods = window_periods
        self.reset()

    def reset(self) -> None:
        """Forget the baseline and noise floor; the next frames warm up again in vision mode."""
        self.mode: Mode = "vision"
        self.noise_level = 0.0
        self._frames_in_mode = 0
        self._shape: tuple[int, int] | None = None
        self._baseline: np.ndarray | None = None
        self._warmup_sum: np.ndarray | None = None
        self._warmup_count = 0
        self._carriers: np.ndarray | None = None
        self._period = 0.0

    @property
    def threshold(self) -> float:
        """Current on threshold."""
        return max(self.on_threshold, self.noise_factor * self.noise_level)

    @property
    def off_threshold(self) -> float:
        """Current off threshold, `(1 - hysteresis) * threshold`."""
        return (1 - self.hysteresis) * self.threshold

    @property
    def wavevectors_px(self) -> np.ndarray | None:
        """Moiré wavevectors `(k_col, k_row)` in rad per working pixel, once known."""
        return None if self._carriers is None else self._k_work

    def _initialise(self, frame: np.ndarray) -> None:
        h, w = frame.shape
        scale = max(1.0, max(h, w) / self.work_size)
        size = (max(8, round(w / scale)), max(8, round(h / scale)))
        self._shape = (h, w)
        self._size = size
        work = self._work(frame)
        wh, ww = work.shape
        if self.moire_wavevectors is None:
            k = spectral_peaks(work, self.n_moire, min_cycles=3.0, max_cycles_per_px=0.2)
        else:
            k_full = to_index_wavevectors(self.moire_wavevectors, self.px_per_mm)
            k = k_full * np.array([w / ww, h / wh])
        periods = 2 * np.pi / np.linalg.norm(k, axis=-1)
        if np.any(periods < 3):
            raise ValueError(f"moire periods {periods} working px are too fine: increase work_size")
        self._k_work = k
        self._period = float(periods.max())
        rows, cols = np.mgrid[0:wh, 0:ww]
        self._carriers = np.exp(-1j * (k[:, 0, None, None] * cols + k[:, 1, None, None] * rows)).astype(np.complex64)
        self._demod_sigmas = 0.35 * periods
        self._margin = min(int(np.ceil(self._period / 2)), min(wh, ww) // 4)

    def _work(self, frame: np.ndarray) -> np.ndarray:
        g = frame.astype(np.float32, copy=False)
        if (g.shape[1], g.shape[0]) != self._size:
            g = cv2.resize(g, self._size, interpolation=cv2.INTER_AREA)
        return g

    def _demodulate(self, frame: np.ndarray) -> np.ndarray:
        g = self._work(frame)
        # Blur widths in moire periods, tuned on synthetic frames: narrow enough that a
        # shadow or scene object a period or more across is normalised away, wide enough
        # to leave a light touch above the noise (see tests/test_live_gate.py).
        smooth = 0.3 * self._period
        local_mean = cv2.GaussianBlur(g, (0, 0), smooth)
        # Contrast relative to the local mean is invariant to smooth illumination changes;
        # the floor keeps dark regions from amplifying noise.
        contrast = (g - local_mean) / np.maximum(local_mean, 0.02)
        contrast -= cv2.GaussianBlur(contrast, (0, 0), smooth)
        return np.stack(
            [_blur_complex(contrast * carrier, s) for carrier, s in zip(self._carriers, self._demod_sigmas)]
        )

    def energy_ratio(self, frame: np.ndarray) -> tuple[float, np.ndarray]:
        """Energy ratio of a frame against the current baseline, and its demodulated amplitudes.

        Does not change any state. Requires a baseline (call after warm-up).
        """
        if self._baseline is None:
            raise ValueError("no baseline yet: feed frames through update() first")
        z = self._demodulate(frame)
        base = self._baseline
        window = self.window_periods * self._period
        # The window is many pixels wide, so its sums are smooth: evaluate them on a grid
        # decimated by `step` (area-averaged first), four times cheaper per halving.
        step = max(1, int(window // 4))
        rows, cols = z.shape[1] // step, z.shape[2] // step

        def local(field):
            field = np.sum(field, axis=0).astype(np.float32)
            if step > 1:
                field = cv2.resize(field[: rows * step, : cols * step], (cols, rows), interpolation=cv2.INTER_AREA)
            return cv2.GaussianBlur(field, (0, 0), window / step)

        energy = local(np.abs(z) ** 2)
        fringe = local(np.abs(base) ** 2)
        # The best non-negative real gain in each window absorbs brightness and contrast
        # changes (illumination, stray light, the scene in vision mode); what is left is
        # the fringe motion. Windowed least squares: min_g W|z - g zb|^2 = W|z|^2 - (W Re z zb*)_+^2 / W|zb|^2.
        overlap = np.maximum(local((z * base.conj()).real), 0.0)
        floor = 1e-6 * float(fringe.mean()) + 1e-12
        ratio = (energy - overlap**2 / np.maximum(fringe, floor)) / np.maximum(fringe, floor)
        m = -(-self._margin // step)
        interior = ratio[m : ratio.shape[0] - m, m : ratio.shape[1] - m] if m else ratio
        return float(interior.max()), z

    def step(self, energy_ratio: Real) -> GateDecision:
        """Advance the hysteresis state machine with an energy ratio computed elsewhere.

        Also updates the noise floor on quiet vision-mode frames.
        """
        on = self.threshold
        may_switch = self._frames_in_mode >= self.min_dwell_frames
        switched = False
        if self.mode == "vision" and energy_ratio > on and may_switch:
            self.mode, switched = "tactile", True
        elif self.mode == "tactile" and energy_ratio < (1 - self.hysteresis) * on and may_switch:
            self.mode, switched = "vision", True
        # The switching frame is the first frame of the new mode.
        self._frames_in_mode = 1 if switched else self._frames_in_mode + 1
        if not switched and self.mode == "vision" and energy_ratio < (1 - self.hysteresis) * on:
            self.noise_level += self.noise_rate * (energy_ratio - self.noise_level)
        return GateDecision(self.mode, float(energy_ratio), switched, on)

    def update(self, frame: np.ndarray) -> GateDecision:
        """Gate one frame (`(h, w)` grayscale, float in [0, 1] or any real dtype).

        **Raises:** `ValueError` if the frame size differs from the first frame's.
        """
        frame = np.asarray(frame)
        if frame.ndim != 2:
            raise ValueError(f"GateER expects a 2D grayscale frame, got shape {frame.shape}")
        if self._shape is None:
            self._initialise(frame)
        elif frame.shape != self._shape:
            raise ValueError(f"frame shape {frame.shape} differs from the gate's {self._shape}; call reset()")
        if self._baseline is None:
            z = self._demodulate(frame)
            self._warmup_sum = z if self._warmup_sum is None else self._warmup_sum + z
            self._warmup_count += 1
            if self._warmup_count >= self.warmup_frames:
                self._baseline = self._warmup_sum / self._warmup_count
                self._warmup_sum = None
            return GateDecision(self.mode, 0.0, False, self.threshold)
        ratio, z = self.energy_ratio(frame)
        decision = self.step(ratio)
        if decision.mode == "vision" and not decision.switched and ratio < self.off_threshold:
            self._baseline += self.baseline_rate * (z - self._baseline)
        return decision
