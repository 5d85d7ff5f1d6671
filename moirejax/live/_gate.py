r"""GateER: the contact gate that switches between vision and tactile mode, frame by frame.

A touch moves the upper grating, which sits on the elastomer: its fine fringes (the carrier,
a few pixels per period) shift in phase under the contact. Everything else that changes a
see-through frame multiplies it: the illumination, and in vision mode the scene seen through
the sensor, whose light reaches every pixel scaled by what the object there reflects. The
moiré fringes themselves are a slow envelope over the carrier, so a scene with structure at
the moiré period, an object coming down onto the pad, changes them as much as a touch does.
The gate therefore asks how much of the carrier change no local gain can explain:

1. the frame $F$ (less the black level) is fitted to the no-contact baseline $R$ as a smooth
   local gain,
   $$g = \frac{G_s * (F R)}{G_s * R^2}, \qquad r = F - g R,$$
   with a Gaussian window $G_s$ half a carrier period wide (sigma): wide enough that a gain
   cannot shift a carrier fringe, narrow against the moiré period, so $g$ absorbs the
   lighting, the scene and the motion of the moiré envelope, and $r$ keeps the carrier
   fringes that moved;
2. $r$ and $R$ are demodulated at each upper-grating carrier $K$,
   $z_K = G_d * (r\,e^{-iK\cdot x})$ and $b_K = G_d * (R\,e^{-iK\cdot x})$, on a grid
   area-averaged to a working size;
3. what is left in phase with the baseline's carrier is an error of the fitted gain, so the
   local unexplained share over a window $W$ of half a moiré period is
   $$E(x) = \frac{W * \sum_K |z_K|^2 - (W * \sum_K \mathrm{Re}\, z_K \bar b_K)^2 / W * \sum_K |b_K|^2}
   {W * \sum_K |b_K|^2},$$
   about $\sin^2\Delta\phi$ for a local carrier phase shift $\Delta\phi$ and 0 for any
   smooth change of brightness;
4. the gate's statistic (`energy_ratio`) is the maximum of $E(x)$ over the interior, so a
   small touch is not diluted by the untouched area.

Its threshold is the noise floor's: without contact, $E$ is camera noise in the carrier band
over the carrier's energy, and the gate keeps a moving average of the statistic on quiet
vision-mode frames (started from the warm-up frames against their mean). It switches to
tactile above `noise_factor` times that floor and back below `1 - hysteresis` times the on
threshold. The baseline is an exponential moving average of quiet vision-mode frames, so it
follows slow drift but never absorbs a contact; its demodulated carriers are recomputed every
`1 / (2 baseline_rate)` quiet frames, well inside its own memory of `1 / baseline_rate`.

Limits: a press built up more slowly than the baseline adapts is taken for drift; scene
texture as fine as the carrier (an object in focus on the pad, not above it) is not a gain
and can look like contact; a frame-wide change of the carrier phase (a shear that slides the
whole surface) is seen everywhere at once and so raises the same maximum as a local one.
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
    - `energy_ratio`: the gate's statistic for this frame, the largest local share of the
        carrier change no gain explains (0 during warm-up).
    - `switched`: whether this frame changed the mode.
    - `threshold`: the on threshold in force for this frame (off is `1 - hysteresis` of it).
    """

    mode: Mode
    energy_ratio: float
    switched: bool
    threshold: float


@dataclasses.dataclass(frozen=True)
class _Reference:
    """The baseline and what each frame's comparison needs of it."""

    frame: np.ndarray  # R, black level removed
    gain_scale: np.ndarray  # R / (G_s * R^2): the gain fit is g R = (G_s * F R) * gain_scale
    carriers: np.ndarray  # b_K, (work h, work w, 2 n): real and imaginary parts per carrier
    carrier_power: np.ndarray  # sum over the field of |b_K|^2, (n,)
    energy: np.ndarray  # W * sum_K |b_K|^2 on the window grid


class GateER:
    """Contact gate on the upper-grating carriers, with an adaptive baseline and hysteresis.

    See the module docstring for the statistic. With no wavevectors given, the gate finds
    the moiré as the strongest coarse peak of the first frame's spectrum and the carriers as
    the `n_carriers` strongest peaks at least three times finer; a sensor's own gate
    ([`make_gate`][moirejax.live.make_gate]) passes its upper grating and moiré instead.

    **Arguments:**

    - `on_threshold`: lowest on threshold, for frames with no noise to measure. 1e-5 is the
        share of a 3 mrad carrier phase shift.
    - `hysteresis`: switch off below `(1 - hysteresis) * threshold` (paper: about 20%).
    - `noise_factor`: the on threshold is this multiple of the quiet noise floor. The
        statistic is a maximum over the field of windowed noise energies; under camera noise
        it stays within about 2.5 times its mean, so 4 leaves a margin on both sides.
    - `baseline_rate`: EMA rate of the baseline per quiet vision-mode frame; the gate
        treats changes slower than about `1 / baseline_rate` frames as drift.
    - `noise_rate`: EMA rate of the noise-floor estimate.
    - `warmup_frames`: frames averaged into the first baseline (reported as vision mode); at
        least 2, since the first noise floor is measured on them.
    - `min_dwell_frames`: frames a mode must last before the gate may leave it.
    - `carrier_wavevectors`: `(n, 2)` wavevectors `(kx, ky)` in rad/mm (y up) of the upper
        grating as seen in the frames (`Device.apparent_upper_wavevectors`).
    - `moire_wavevectors`: `(m, 2)` moiré wavevectors in rad/mm; they set the demodulation
        and window widths.
    - `px_per_mm`: resolution of the frames, to convert the wavevectors.
    - `n_carriers`: carriers to find when `carrier_wavevectors` is `None`. A two-grating
        sensor shows both gratings' carriers; only the upper one moves, so automatic search
        should take both (2 for one fringe family).
    - `black_level`: camera output for no light, removed before the gain fit.
    - `work_size`: the demodulated carriers are area-averaged so the larger side is at most
        this.
    - `window_periods`: width (sigma) of the local window W in moiré periods.
    """

    def __init__(
        self,
        *,
        on_threshold: Real = 1e-5,
        hysteresis: Real = 0.2,
        noise_factor: Real = 4.0,
        baseline_rate: Real = 0.05,
        noise_rate: Real = 0.05,
        warmup_frames: int = 3,
        min_dwell_frames: int = 0,
        carrier_wavevectors: np.ndarray | None = None,
        moire_wavevectors: np.ndarray | None = None,
        px_per_mm: Real = 1.0,
        n_carriers: int = 2,
        black_level: Real = 0.0,
        work_size: int = 128,
        window_periods: Real = 0.5,
    ):
        if not 0 < hysteresis < 1:
            raise ValueError(f"hysteresis must be in (0, 1), got {hysteresis}")
        if on_threshold <= 0 or noise_factor < 1 or warmup_frames < 2 or min_dwell_frames < 0:
            raise ValueError("need on_threshold > 0, noise_factor >= 1, warmup_frames >= 2, min_dwell_frames >= 0")
        if not (0 < baseline_rate <= 1 and 0 < noise_rate <= 1):
            raise ValueError("baseline_rate and noise_rate must be in (0, 1]")
        self.on_threshold = on_threshold
        self.hysteresis = hysteresis
        self.noise_factor = noise_factor
        self.baseline_rate = baseline_rate
        self.noise_rate = noise_rate
        self.warmup_frames = warmup_frames
        self.min_dwell_frames = min_dwell_frames
        self.carrier_wavevectors = None if carrier_wavevectors is None else np.asarray(carrier_wavevectors, np.float64)
        self.moire_wavevectors = None if moire_wavevectors is None else np.asarray(moire_wavevectors, np.float64)
        self.px_per_mm = px_per_mm
        self.n_carriers = n_carriers
        self.black_level = black_level
        self.work_size = work_size
        self.window_periods = window_periods
        # The reference is rebuilt after this many baseline updates.
        self._refresh_every = max(1, round(0.5 / baseline_rate))
        self.reset()

    def reset(self) -> None:
        """Forget the baseline and noise floor; the next frames warm up again in vision mode."""
        self.mode: Mode = "vision"
        self.noise_level = 0.0
        self._frames_in_mode = 0
        self._shape: tuple[int, int] | None = None
        self._warmup: list[np.ndarray] = []
        self._baseline: np.ndarray | None = None
        self._reference: _Reference | None = None
        self._updates = 0
        self._k: np.ndarray | None = None

    @property
    def threshold(self) -> float:
        """Current on threshold."""
        return max(self.on_threshold, self.noise_factor * self.noise_level)

    @property
    def off_threshold(self) -> float:
        """Current off threshold, `(1 - hysteresis) * threshold`."""
        return (1 - self.hysteresis) * self.threshold

    @property
    def carriers_px(self) -> np.ndarray | None:
        """Carrier wavevectors `(k_col, k_row)` in rad per frame pixel, once known."""
        return self._k

    def _initialise(self, frame: np.ndarray) -> None:
        h, w = frame.shape
        scale = max(1.0, max(h, w) / self.work_size)
        self._shape = (h, w)
        self._size = (max(8, round(w / scale)), max(8, round(h / scale)))
        ww, wh = self._size
        if self.moire_wavevectors is None:
            work = cv2.resize(frame.astype(np.float32), self._size, interpolation=cv2.INTER_AREA)
            moire = spectral_peaks(work, 1, min_cycles=3.0, max_cycles_per_px=0.2) * np.array([ww / w, wh / h])
        else:
            moire = to_index_wavevectors(self.moire_wavevectors, self.px_per_mm)
        moire_period = float((2 * np.pi / np.linalg.norm(moire, axis=-1)).max())  # frame px
        if self.carrier_wavevectors is None:
            k = spectral_peaks(
                frame, self.n_carriers, min_cycles=3.0 * max(h, w) / moire_period, max_cycles_per_px=0.45
            )
        else:
            k = to_index_wavevectors(self.carrier_wavevectors, self.px_per_mm)
        carrier_period = float((2 * np.pi / np.linalg.norm(k, axis=-1)).max())
        if carrier_period < 2.2 or 3 * carrier_period > moire_period:
            raise ValueError(
                f"carrier period {carrier_period:.2f} px must be above 2.2 px and below a third of the moiré's"
            )
        self._k = k
        # Half a carrier period (sigma): a window over about two fringes, in which a gain
        # cannot imitate a shifted fringe, and small against the moiré period.
        self._gain_sigma = 0.5 * carrier_period
        # Demodulation and window widths in working pixels, as for the moiré fringes: the
        # carrier beats against the reference grating at the moiré frequency, which
        # 0.35 of its period (sigma) suppresses tenfold.
        period = moire_period * ww / w
        self._demod_sigma = 0.35 * period
        self._window = self.window_periods * period
        self._step = max(1, int(self._window // 4))
        self._margin = min(int(np.ceil(period / 2)), min(wh, ww) // 4)
        rows, cols = np.mgrid[0:h, 0:w]
        phase = k[:, 0, None, None] * cols + k[:, 1, None, None] * rows
        # Channels (cos, -sin) per carrier: r e^{-iK.x} in one multiply.
        self._mixers = np.ascontiguousarray(
            np.stack([np.cos(phase), -np.sin(phase)], axis=-1).transpose(1, 2, 0, 3).reshape(h, w, -1), np.float32
        )
        self._mixed = np.empty_like(self._mixers)

    def _demodulate(self, x: np.ndarray) -> np.ndarray:
        np.multiply(x[..., None], self._mixers, out=self._mixed)
        z = self._mixed
        if (z.shape[1], z.shape[0]) != self._size:
            z = cv2.resize(z, self._size, interpolation=cv2.INTER_AREA)
        return cv2.GaussianBlur(z, (0, 0), self._demod_sigma).reshape(*z.shape[:2], -1)

    def _local(self, field: np.ndarray) -> np.ndarray:
        """W * field on the window grid (decimated by `step`: the window is many pixels wide)."""
        step = self._step
        if step > 1:
            rows, cols = field.shape[0] // step, field.shape[1] // step
            field = cv2.resize(field[: rows * step, : cols * step], (cols, rows), interpolation=cv2.INTER_AREA)
        return cv2.GaussianBlur(field, (0, 0), self._window / step)

    def _prepare(self, frame: np.ndarray) -> np.ndarray:
        return frame.astype(np.float32) - np.float32(self.black_level)

    def _make_reference(self, baseline: np.ndarray) -> _Reference:
        power = cv2.GaussianBlur(baseline * baseline, (0, 0), self._gain_sigma)
        power = np.maximum(power, 1e-6 * float(power.mean()) + 1e-20)
        carriers = self._demodulate(baseline)
        energy = self._local(np.sum(carriers * carriers, axis=-1))
        energy = np.maximum(energy, 1e-6 * float(energy.mean()) + 1e-20)
        power_k = np.sum(np.abs(carriers.view(np.complex64)) ** 2, axis=(0, 1)) + 1e-20
        return _Reference(baseline.copy(), baseline / power, carriers, power_k, energy)

    def _share(self, x: np.ndarray, ref: _Reference) -> np.ndarray:
        residual = x - cv2.GaussianBlur(x * ref.frame, (0, 0), self._gain_sigma) * ref.gain_scale
        z = self._demodulate(residual)
        # A rigid slide of the whole grating (thermal creep, the mount) turns every carrier
        # by one phase: take out each carrier's best field-wide complex multiple of b_K.
        zc, bc = z.view(np.complex64), ref.carriers.view(np.complex64)
        zc -= (np.einsum("hwk,hwk->k", zc, bc.conj()) / ref.carrier_power) * bc
        energy = self._local(np.sum(z * z, axis=-1))
        # The sum over carriers of Re(z conj b), channels interleaved (re, im).
        in_phase = self._local(np.sum(z * ref.carriers, axis=-1))
        return (energy - in_phase**2 / ref.energy) / ref.energy

    def _interior_max(self, share: np.ndarray) -> float:
        m = -(-self._margin // self._step)
        interior = share[m : share.shape[0] - m, m : share.shape[1] - m] if m else share
        return float(interior.max())

    def energy_ratio(self, frame: np.ndarray) -> tuple[float, np.ndarray]:
        """The gate's statistic for a frame against the current baseline, and the map it is the maximum of.

        Does not change any state. Requires a baseline (call after warm-up).

        **Returns:** the statistic and the local unexplained share $E(x)$ on the window grid
        (the working grid decimated by a few pixels).
        """
        if self._reference is None:
            raise ValueError("no baseline yet: feed frames through update() first")
        share = self._share(self._prepare(np.asarray(frame)), self._reference)
        return self._interior_max(share), share

    def step(self, energy_ratio: Real) -> GateDecision:
        """Advance the hysteresis state machine with a statistic computed elsewhere.

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

    def _warm_up(self, x: np.ndarray) -> None:
        self._warmup.append(x)
        n = len(self._warmup)
        if n < self.warmup_frames:
            return
        self._baseline = np.mean(self._warmup, axis=0)
        self._reference = self._make_reference(self._baseline)
        # Each warm-up frame is part of the mean it is compared with, which hides a share
        # 1/n of its noise; a later frame adds that of the mean: noise (1 - 1/n) against
        # (1 + 1/n), hence the factor.
        quiet = np.mean([self._interior_max(self._share(f, self._reference)) for f in self._warmup])
        self.noise_level = float(quiet) * (n + 1) / (n - 1)
        self._warmup = []

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
        x = self._prepare(frame)
        if self._reference is None or self._baseline is None:
            self._warm_up(x)
            return GateDecision(self.mode, 0.0, False, self.threshold)
        ratio = self._interior_max(self._share(x, self._reference))
        decision = self.step(ratio)
        if decision.mode == "vision" and not decision.switched and ratio < self.off_threshold:
            self._baseline += np.float32(self.baseline_rate) * (x - self._baseline)
            self._updates += 1
            if self._updates % self._refresh_every == 0:
                self._reference = self._make_reference(self._baseline)
        return decision
