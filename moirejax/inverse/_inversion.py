r"""Per-frame wrench inversion: observed frame → wrench, contact, covariance, status.

**Domain.** The residual lives in the demodulated domain: the complex fringe field of
each family and the brightness, on the demodulator's coarse grid (32 × 32 by default),
compared in the Fourier domain of that grid bin by bin inside each band. Three reasons:

- *fast*: one FFT of the frame, then every solver step works on a few thousand numbers
  and a 96 × 96 mechanics grid (Mid), never on a rendered 512 × 512 image;
- *well conditioned*: the fringe phase responds linearly to surface displacement over a
  wide range (rendered intensities wrap and saturate), and the carriers and their
  aliasing, which no model reproduces exactly, are filtered out before comparing;
- *statistically honest*: inside the band, the frame's Fourier coefficients of white
  pixel noise are independent with equal variance, so dividing the coarse-grid spectrum
  by the band window whitens the residual, and $(J^\top J)^{-1}$ scaled by the residual
  variance is the Gauss–Newton covariance without a correlation fudge.

**Reference.** Every unit has fixed-pattern deviations from any model (grating phase
errors, vignetting, residual distortion). They are removed with a no-contact reference
frame: the predicted fringe field is multiplied by the ratio of the observed to the
predicted reference fringe field, and the predicted brightness change is added to the
observed reference brightness.

**Phase, not amplitude.** Each fringe residual is split into its part along the predicted
fringe phasor (the fringes' amplitude) and across it (their phase). The amplitude moves
with contrast, exposure, illumination and the scene behind the sensor, none of which a
unit's model knows exactly; the phase moves only with displacement. The brightness and
the amplitude help a cold start find its basin; the estimate is refined on the phase alone
([`Inverter.solve`][]), and streams stay on that problem.

**Unknowns.** The scaled wrench (each axis over the paper's range), the contact centre,
the log contact radius and the log exposure. Two weak priors make the problem well posed
at light load: the centre of pressure stays near the contact centre (a pressure tilt
is allowed but costs), and the radius stays near a typical indenter.

**Contact** is decided from the data, not from the fit: a frame is in contact when its
fringe phase has moved from the reference by more than the frame's and the reference's
pixel noise put there, somewhere on the frame ([`Inverter.phase_change`][]). Exposure,
illumination and the fringes' contrast do not move the phase, and a load the model
explains badly still moves it, so such a load is never reported as no contact.

The package's modules: the problem (`Inverter`: the residual, its priors, the frame
screen and the contact test) here; its two solvers in `_solvers.py`; the covariance and
status of a solution in `_estimate.py`; what an inversion returns in `_state.py`; the entry
points in `_invert.py`. This module stays long because the residual's pieces (the band
residual, the priors, the zero-load residual, the phase-change statistic, the cold guess)
all read the same `Inverter` fields and the same layout of the residual vector.
"""

import math
import os
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Complex, Float, Real

from .._conventions import NMM_PER_NM, WRENCH_SCALE
from ..observe import (
    BAND_FRACTION,
    band_model,
    BandModel,
    carrier_band_radius,
    complex_ratio,
    DemodulationWindowTooSmall,
    Demodulator,
    FringeFields,
    match_reference_geometry,
    predicted_bands,
    stray_beat_clearance,
    white_noise_map,
    white_noise_variance,
)
from ..physics import Contact, Device, grid_shape
from ._estimate import finish
from ._second_contact import (
    _PAIR_UNEXPLAINED_SHARE,
    _SECOND_CONTACT_GAIN,
    _SECOND_CONTACT_TRIGGER,
    ContactPair,
    solve_pair,
)
from ._solvers import best_start, chord, levenberg_marquardt, solve_cold
from ._state import Estimate, LoadState, N_PRIORS, N_UNKNOWNS, Status, Track, TYPICAL_RADIUS


# Prior width of the centre-of-pressure offset from the contact centre (N*mm of moment); the
# radius has the prior of `LoadState.radius_misfit`. A pressure not centred on its contact is a tilted
# indenter; along line gratings it moves the fringes almost as the shear along the lines
# does (docs/physics.md), and a wider prior trades one for the other.
_TILT_PRIOR_NMM = 0.25
# Width of the wrench prior, in units of WRENCH_SCALE: a load is a priori about as large as
# the calibrated range. Data that see an axis override it; data that do not (the shear
# across a line grating's lines sees the fringes only through second-order effects) leave
# that axis near zero with an uncertainty of about its range, instead of at a wild value.
_WRENCH_PRIOR = 1.0
# Width of the log-exposure prior. The fringe phase does not see the exposure at all: without
# a prior a phase-only refinement can drift it by rounding alone until the model overflows.
_EXPOSURE_PRIOR = 1.0
# Radius of the cuts around the reference grating's carrier (and its sidebands) in a carrier
# band, over |K|: that carrier lies |K| from the upper grating's, and its glow-modulated
# spread must stay inside the cut while the upper grating's own spectrum stays outside.
_CARRIER_NOTCH = 0.6
# Window (mm, Gaussian sd) over which the phase change is averaged to detect a contact.
_CONTACT_WINDOW = 2.0
# The least agreement of a frame's fringe phase with the reference's over the field (the
# weighted mean of the unit phasors of their ratio) for the frame to show this unit's
# fringes. A contact moves the phase near itself and leaves the far field: the renderer's
# and the independent renderer's frames inside the paper's ranges keep 0.89 or more, a
# 10 N press 0.70, and with a natural scene seen through the sensor (multiplying the
# fringes, or adding up to 60% of the image) 0.66 or more. Natural images and noise in
# their place keep 0.1-0.5. Grasp loads go lower: spheres pressed with 4.6-7.3 N, up to
# 0.8 N of shear and 0.035 N*m of twist, kept 0.29-0.8 on some fringe family, and the
# model explained them to 0.3% of their phase change. So a frame below this is not refused
# before the solve but after it, unless a plausible load explains it closely
# (`_estimate._DISAGREEING_SHARE`); only below `_FRINGE_AGREEMENT_FLOOR` is it refused
# unsolved. Noise, natural images and other designs' frames had some family at 0.02-0.13
# (with the carrier families; 0.04-0.25 on the moiré families alone).
_FRINGE_AGREEMENT = 0.5
_FRINGE_AGREEMENT_FLOOR = 0.2
# The largest share of clipped pixels a frame may have. Clipping folds harmonics of the
# fringes into the bands: on the renderer's frames of one load, 1% clipped read within 2%
# of each axis' range, 3.4% within 7%, 7.3% within 20%, and 15% three and a half ranges off.
_CLIPPED_SHARE = 0.05
# Side (pixels) of the squares whose white pixel noise `_Screen.corrupt` compares, and how
# many times the frame's median square's noise (at least an 8-bit camera's, `_NOISE_FLOOR`)
# two neighbouring squares must carry for the frame to hold corrupt pixels. On the renderer's
# `high`-fidelity frames the loudest square carried 2-3 times the median without contact or
# under a sphere inside the paper's ranges, 7-25 under lines, squares and 8-10 N presses (the
# fringes' own leakage), at most 9 in every mismatch family of `benchmarks/mismatch_families.py`
# and 2.4 on the independent renderer's frames; one stuck-white pixel 47 times, in one square.
# A patch of random pixels over 1% of the field carried 830-1180 times.
_NOISE_BLOCK = 32
_CORRUPT_NOISE_RATIO = 100.0
_NOISE_FLOOR = (2.0 / 255.0) ** 2
# The most contact light a frame may be explained with, in units of the device's (glow and
# rim, `Inverter.contact_light_scale`): units scatter between none and a few times the
# nominal; more than this is a load that the light would be made to stand in for.
_LIGHT_SCALE_MAX = 8.0


def model_grid_for(
    device: Device, samples_per_period: int = 8, samples_per_radius: int = 6, smallest_radius: float = 2.5
) -> tuple[int, int]:
    """The mechanics and fringe grid an [`Inverter`][] needs for `device`: `samples_per_period`
    across the shortest moiré period and `samples_per_radius` across a contact of
    `smallest_radius` mm along the image's longer side, rounded up to a multiple of 16, with
    the image's aspect ratio ([`grid_shape`][]).

    The period term: a coarser grid aliases the fringe's second harmonic and biases shear
    and twist on short-period designs (a 1.8 mm period on a 64 grid over 32 mm read 5%
    off in shear). The contact term: under a small, strongly sheared or twisted contact
    the fringes wind several times within the radius (0.5 mm of slip is 9 rad of upper
    grating phase on Mid), and a grid that does not follow them folds that winding into
    the band. On 200 noise-free mixed loads of Mid, 5 samples per 2.5 mm radius (64 × 64)
    read shear up to 15% of range off; 6 (96 × 96) gave R² 0.9999 on every axis.
    """
    period = float(np.min(2 * np.pi / np.linalg.norm(np.asarray(device.moire_wavevectors()), axis=-1)))
    size_mm = max(device.height, device.width) / float(device.px_per_mm)
    # The mechanics grid spans the contact surface, magnified by (Z + a)/Z over the image.
    surface_mm = size_mm * float(device.surface_magnification)
    needed = max(samples_per_period * size_mm / period, samples_per_radius * surface_mm / smallest_radius)
    return grid_shape((device.height, device.width), 16 * math.ceil(needed / 16))


def default_model_shape(device: Device) -> tuple[int, int]:
    """The model grid an [`Inverter`][] takes when given none: [`model_grid_for`][], unless
    the environment variable `MOIREJAX_MODEL_GRID` names a size (e.g. `64`), which trades
    accuracy on small, strongly sheared contacts for about half the solve time (the test
    suite and quick looks use it; the benchmarks do not)."""
    override = os.environ.get("MOIREJAX_MODEL_GRID", "").strip()
    if not override:
        return model_grid_for(device)
    if not override.isdigit() or int(override) < 16:
        raise ValueError(f"MOIREJAX_MODEL_GRID must be a grid size of at least 16, got {override!r}")
    return grid_shape((device.height, device.width), int(override))


def default_carriers() -> bool | None:
    """Whether an [`Inverter`][] given `carriers=None` demodulates the carriers: `None`
    (where the camera resolves them) unless the environment variable `MOIREJAX_CARRIERS` is
    `0`, which leaves them out: each model evaluation then costs about two thirds, at the
    accuracy of the moiré bands alone (the test suite's end-to-end runs use it; the
    benchmarks do not)."""
    override = os.environ.get("MOIREJAX_CARRIERS", "").strip()
    if override not in ("", "0", "1"):
        raise ValueError(f"MOIREJAX_CARRIERS must be 0 or 1, got {override!r}")
    return None if override in ("", "1") else False


# The coarse demodulation grid of most designs (about 1 mm cells on Mid), and the sizes tried
# above it for designs whose moiré bands do not fit its windows.
_CROP_SIZES = (32, 40, 48, 56, 64, 80, 96, 128)


def _crop_shape_for(device: Device, band_fraction: float) -> tuple[int, int]:
    """The smallest square coarse grid of `_CROP_SIZES` whose demodulation windows hold every
    moiré band of `device` (each band's radius is `band_fraction` of its wavenumber)."""
    moire = np.asarray(device.moire_wavevectors(), np.float64)
    for size in _CROP_SIZES:
        if size + 2 > min(device.height, device.width):
            break
        try:
            Demodulator(
                (device.height, device.width),
                float(device.px_per_mm),
                moire,
                crop_shape=(size, size),
                band_fraction=band_fraction,
            )
        except DemodulationWindowTooSmall:
            continue
        return (size, size)
    raise ValueError(
        f"the moiré bands of this design (wavevectors {np.round(moire, 2).tolist()} rad/mm) do not fit a "
        f"{_CROP_SIZES[-1]} x {_CROP_SIZES[-1]} demodulation grid of a {device.height} x {device.width} frame: "
        "the fringes are too fine for the camera; change p1, p2, a or Z"
    )


class Inverter(eqx.Module):
    """Inverts frames of one unit into wrenches. Build once per unit (and reference).

    **Arguments:**

    - `device`: the (nominal or calibrated) [`Device`][] the model uses.
    - `reference`: a no-contact frame of this unit (the mean of a few is better), or
      `None` to take the model's own prediction (then fixed-pattern deviations of the
      unit are not removed).
    - `match_reference`: set the upper grating's pitch and angle so that the model's moiré
      wavevectors match those measured on `reference` ([`match_reference_geometry`][]).
    - `register_gratings`: shift the model's grating phase so that its fringes at zero load
      lie where the reference's do; `None` does it exactly when `match_reference` does. A
      new reference of a unit whose geometry is already matched (a tare) registers
      without matching: the geometry, and with it the compiled solver, stays.
    - `crop_shape`: coarse demodulation grid. Default: 32 x 32, or the smallest square grid
        above it whose windows hold the moiré bands (a design of fine fringes, such as the
        paper's Dense, needs a wider window: its bands are wider in wavenumber).
    - `model_shape`: grid of the mechanics and the predicted fringe field; `None` for
      [`default_model_shape`][]: [`model_grid_for`][] (8 samples per moiré period and 6
      across a 2.5 mm contact radius: 96 × 96 on the paper's Mid design) unless the
      environment sets `MOIREJAX_MODEL_GRID`.
    - `band_fraction`: band radius over |K| of the demodulator.
    - `max_steps`, `tolerance`: Levenberg–Marquardt settings. A solve stops when its next
      Gauss–Newton step would move no unknown by more than `tolerance` of that unknown's
      standard error (closer than that the data cannot tell two solutions apart), or after
      `max_steps` steps.
    - `contact_threshold`: how many times its noise level the fringe phase must move, in a
      window somewhere on the frame, for the frame to count as in contact
      ([`Inverter.phase_change`][]).
    - `carriers`: demodulate the upper grating's own carriers beside the moiré bands
      (see [`band_model`][]): the same displacement signal, at about four times the moiré
      band's resolution, which the shear along line gratings and small contacts need.
      `None` uses them where the camera resolves that grating ([`carrier_band_radius`][]),
      unless the environment says otherwise ([`default_carriers`][]).
    - `brightness`: fit the brightness band too, through the device's law of the light a
      contact scatters (glow and rim). Off by default: a unit need not follow that law (an
      elastomer that does not glow, other lighting), and a law the unit does not follow
      biases the normal force; the fringe phase alone carries the load. Turn it on for a
      unit whose calibration frames show the brightness response the device describes.
    """

    device: Device
    demodulator: Demodulator
    model: BandModel
    reference: FringeFields
    model_reference: FringeFields
    fringe_weight: Float[Array, "families m n"]
    brightness_weight: Float[Array, "m n"]
    amplitude_weight: Float[Array, ""]
    noise_residuals: Float[Array, "samples n"]
    noise_power: Float[Array, ""]
    glow_per_newton: Float[Array, ""]
    unit_phase_noise: Float[Array, "families m n"]
    reference_noise: Float[Array, ""]
    fitted_light: Bool[Array, ""]
    fitted_flatness: Bool[Array, ""]
    fitted_elongation: Bool[Array, ""]
    model_shape: tuple[int, int] = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    tolerance: float = eqx.field(static=True)
    contact_threshold: float = eqx.field(static=True)
    brightness: bool = eqx.field(static=True)
    chord_steps: int = eqx.field(static=True)
    chord_tolerance: float = eqx.field(static=True)

    def __init__(
        self,
        device: Device,
        reference=None,
        *,
        crop_shape: tuple[int, int] | None = None,
        model_shape: tuple[int, int] | None = None,
        band_fraction: float = BAND_FRACTION,
        max_steps: int = 40,
        tolerance: float = 0.05,
        contact_threshold: float = 10.0,
        brightness: bool = False,
        match_reference: bool = True,
        register_gratings: bool | None = None,
        chord_steps: int = 4,
        chord_tolerance: float = 0.25,
        carriers: bool | None = None,
    ):
        if reference is not None:
            reference = np.asarray(reference, dtype=np.asarray(device.p1).dtype)
            if reference.shape != (device.height, device.width):
                raise ValueError(
                    f"reference frame has shape {reference.shape}, device expects {(device.height, device.width)}"
                )
            if match_reference:
                device = match_reference_geometry(device, reference)
        self.device = device
        clearance = float(np.min(np.asarray(stray_beat_clearance(device, band_fraction))))
        if clearance < 1.0:
            warnings.warn(
                f"a mixed-order grating beat lies inside a demodulated band (clearance {clearance:.2f} < 1, "
                "see moirejax.stray_beat_clearance): the band model does not include it and the wrench "
                "will be biased; change p1, p2 or a",
                stacklevel=2,
            )
        self.max_steps = max_steps
        self.tolerance = tolerance
        self.contact_threshold = contact_threshold
        self.brightness = bool(brightness)
        self.fitted_light = jnp.asarray(False)
        self.fitted_flatness = jnp.asarray(True)
        self.fitted_elongation = jnp.asarray(False)
        self.chord_steps = chord_steps
        self.chord_tolerance = chord_tolerance
        sets = device.n_sets
        moire = np.asarray(device.moire_wavevectors())
        if carriers is None:
            carriers = default_carriers()
        if crop_shape is None:
            crop_shape = _crop_shape_for(device, band_fraction)
        radius = carrier_band_radius(device, crop_shape) if carriers in (None, True) else None
        if carriers and radius is None:
            raise ValueError("this camera does not resolve the upper grating's carriers; use carriers=False")
        if radius is None:
            wavevectors, band_radius, peak_radius, notches, notch_radius = moire, None, None, None, None
        else:
            # The carrier band also holds the reference grating's carrier, |K| away, and on a
            # crossed grid its sidebands from the other line set's fringes: they do not move
            # under load but follow the illumination and a contact's glow, so they are cut
            # out; and the peak is sought closer than them.
            moire = moire.astype(np.float64)
            wavevectors = np.concatenate([moire, np.asarray(device.apparent_upper_wavevectors(), np.float64)])
            k2 = np.asarray(device.reference_wavevectors(), np.float64)
            moire_norm = np.linalg.norm(moire, axis=-1)
            band_radius = np.asarray([np.nan] * sets + [radius] * sets)
            peak_radius = np.concatenate([np.full(sets, np.nan), band_fraction * moire_norm])
            sidebands = [
                [k2[s], *(k2[s] + side * moire[b] for b in range(sets) if b != s for side in (-1, 1))]
                for s in range(sets)
            ]
            notches = [[] for _ in range(sets)] + sidebands
            notch_radius = np.concatenate([np.zeros(sets), _CARRIER_NOTCH * moire_norm])
        self.demodulator = Demodulator(
            (device.height, device.width),
            float(device.px_per_mm),
            wavevectors,
            crop_shape=crop_shape,
            band_fraction=band_fraction,
            band_radius=band_radius,
            peak_radius=peak_radius,
            notches=notches,
            notch_radius=notch_radius,
        )
        if model_shape is None:
            # A size from the environment (`MOIREJAX_MODEL_GRID`) never goes below what the
            # bands need: a coarser grid would fold the fringe band over its Nyquist limit.
            needed = self.demodulator.smallest_band_grid(tuple(range(sets)))
            rows, cols = default_model_shape(device)
            if min(rows, cols) < needed:
                rows, cols = grid_shape((device.height, device.width), -(-needed * max(rows, cols) // min(rows, cols)))
            model_shape = (rows, cols)
        self.model_shape = (int(model_shape[0]), int(model_shape[1]))
        zero = LoadState.at_rest(dtype=device.p1.dtype)
        if reference is None:
            self.model_reference = self._predict_now(zero, None)
            self.reference = self.model_reference
        else:
            reference = jnp.asarray(reference, dtype=device.p1.dtype)
            if reference.shape != (device.height, device.width):
                raise ValueError(
                    f"reference frame has shape {reference.shape}, device expects {(device.height, device.width)}"
                )
            self.reference = self.demodulator(reference)
            self.model_reference = self._predict_now(zero, self.reference.reference_wavevector)
            if match_reference if register_gratings is None else register_gratings:
                # Register the gratings: the model's fringe phase at zero load must match
                # the unit's, or the contact glow that leaks into the fringe band would be
                # mis-phased against the moire term by the reference correction.
                weight = self.demodulator.fringe_envelope.astype(self.reference.fringe.dtype)
                product = self.reference.fringe * jnp.conj(self.model_reference.fringe) * weight
                # The moiré families register the upper grating against the reference one; a
                # carrier's phase is the upper grating's alone, which the reference correction
                # takes care of.
                offset = jnp.angle(jnp.sum(product, axis=(1, 2)))[:sets]
                self.device = eqx.tree_at(lambda d: d.optics.phase1, self.device, self.device.optics.phase1 + offset)
                self.model_reference = self._predict_now(zero, self.reference.reference_wavevector)
        # Every model evaluation of a solve refers to this unit and this reference: what does
        # not depend on the load is computed once.
        self.model = band_model(self.device, self.demodulator, self.model_shape, self.reference.reference_wavevector)
        # The demodulator divides by the apodization envelope, which amplifies noise near
        # the border; weighting by the envelope undoes that (and drops the border).
        self.fringe_weight = self.demodulator.fringe_envelope.astype(zero.x0.dtype)
        self.brightness_weight = self.demodulator.brightness_envelope.astype(zero.x0.dtype)
        self.amplitude_weight = jnp.ones((), zero.x0.dtype)
        self.noise_residuals = self._unit_noise_residuals()
        self.noise_power = jnp.sum(self.noise_residuals**2) / self.noise_residuals.shape[0]
        # Integrated brightness excess per newton of a centred press: starts Fz.
        press = LoadState.from_load(jnp.asarray([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], zero.x0.dtype), zero.contact)
        excess = self._predict_now(press, None).brightness - self._predict_now(zero, None).brightness
        self.glow_per_newton = jnp.sum(excess * self.demodulator.brightness_envelope.astype(zero.x0.dtype))
        # The phase noise of a frame against the reference at each coarse-grid point, per unit
        # of white pixel variance: the part of the unit-noise fringe residual across the
        # fringe phasor (half of it). A frame's own pixel variance and the reference's
        # ([`white_noise_variance`][]) scale it.
        families, m, n = self.fringe_weight.shape
        unit_fringe = self.noise_residuals[:, : 2 * families * m * n].reshape(-1, 2, families, m, n)
        self.unit_phase_noise = 0.5 * jnp.mean(jnp.sum(unit_fringe**2, axis=1), axis=0)
        self.reference_noise = (
            jnp.zeros((), zero.x0.dtype)
            if reference is None
            else white_noise_variance(jnp.asarray(reference, zero.x0.dtype))
        )

    def _predict_now(self, state: LoadState, reference_wavevector) -> FringeFields:
        # The constructor's predictions, compiled as one program: run op by op, each of the
        # model's operations compiles on its own. They stand for measured bands (the reference
        # of a unit without one), so they carry no light share (`FringeFields.light`).
        fields = _bands_at_state(self.device, self.demodulator, state, reference_wavevector, self.model_shape)
        return eqx.tree_at(lambda f: f.light, fields, None, is_leaf=lambda x: x is None)

    def _predict(self, y) -> FringeFields:
        # Observed fields refer to the reference frame's wavevectors (`observe`), as the model does.
        state = LoadState.from_vector(y)
        return self.model(state.wrench, self._modelled_contact(state.contact), state.exposure)

    def _modelled_contact(self, contact: Contact) -> Contact:
        # A solve that holds the contact's flatness (the first stages of a cold solve,
        # `solve_cold`; the starts of a two-patch solve) sees a sphere's pressure, and one
        # that holds its elongation (all but `Inverter.second_contact`'s) a round patch. The
        # held flatness keeps its start, pulled only by its prior; the held elongation takes
        # no step at all (`Marquardt.held`).
        return eqx.tree_at(
            lambda c: (c.flatness, c.stretch_x, c.stretch_xy),
            contact,
            (
                jnp.where(self.fitted_flatness, contact.flatness, 0.0),
                jnp.where(self.fitted_elongation, contact.stretch_x, 0.0),
                jnp.where(self.fitted_elongation, contact.stretch_xy, 0.0),
            ),
        )

    def _unit_noise_residuals(self, samples: int = 48) -> Float[Array, "samples n"]:
        """Data residuals that unit white pixel noise alone produces, `samples` draws.

        Demodulation is linear, so these carry the full correlation of the coarse fields;
        the per-frame covariance is a sandwich estimate over them (see [`Inverter.solve`][]).
        """
        rng = np.random.default_rng(0)
        frames = jnp.asarray(rng.normal(size=(samples, *self.demodulator.frame_shape)), dtype=self.fringe_weight.dtype)

        def residual(frame):
            # Noise is circular: its split along and across the reference's fringes is that
            # of any prediction's.
            fields = self.demodulator(frame)
            return self._band_residual(fields.fringe, fields.brightness, self.reference.fringe)

        return jax.lax.map(residual, frames)

    def _band_residual(self, fringe_change, brightness_change, fringe) -> Float[Array, " n"]:
        """The whitened residual vector of a change of the bands (observed minus predicted).

        The fringe change is split at every coarse-grid point into its component along the
        `fringe` phasor there (a change of the fringes' amplitude: contrast, exposure,
        illumination) and across it (a change of their phase: displacement), so that the
        amplitude can be weighed apart (`amplitude_weight`). Layout: the amplitude
        components, the phase components, then the brightness.
        """
        direction = jnp.conj(fringe) * jax.lax.rsqrt(fringe.real**2 + fringe.imag**2 + 1e-24).astype(fringe.dtype)
        rotated = fringe_change * direction * self.fringe_weight.astype(fringe.dtype)
        return jnp.concatenate(
            [
                rotated.real.ravel() * self.amplitude_weight,
                rotated.imag.ravel(),
                (brightness_change * self.brightness_weight).ravel(),
            ]
        )

    def band_residual(
        self, observed: FringeFields, predicted: FringeFields, model_reference: FringeFields | None = None
    ) -> Float[Array, " n"]:
        """The whitened residual of `observed` bands against `predicted` ones, the one misfit
        that inversion and calibration both minimise.

        The prediction is first corrected for the unit's fixed pattern: scaled by this unit's
        reference bands over the model's no-load bands (`model_reference`, by default those of
        this inverter's model; calibration passes those of the parameters it is trying),
        all but the elastomer's own light (`FringeFields.light`), which passes the
        reference grating alone; after `phase_only(None)` that light is scaled to explain the
        frame best ([`Inverter.contact_light_scale`][]).
        Layout: the fringe change along the predicted fringe phasor at every coarse-grid point
        (amplitude), across it (phase), then the brightness change, each with this inverter's
        weights ([`Inverter.phase_only`][] zeroes all but the phase).
        """
        if model_reference is None:
            model_reference = self.model_reference
        fringe = self._gratings_share(predicted, model_reference)
        if predicted.light is not None:
            # The elastomer's light passes the reference grating alone: the unit's contrast
            # of the gratings' product, which the reference correction scales by, does not
            # apply to it.
            scale = jnp.where(self.fitted_light, self._light_scale(observed, fringe, predicted.light), 1.0)
            fringe = fringe + scale.astype(fringe.dtype)[:, None, None] * predicted.light
        brightness = predicted.brightness - model_reference.brightness + self.reference.brightness
        return self._band_residual(observed.fringe - fringe, observed.brightness - brightness, fringe)

    def contact_light_scale(
        self, observed: FringeFields, predicted: FringeFields, model_reference: FringeFields | None = None
    ) -> Float[Array, " families"]:
        """How many times the light the device says a contact scatters (glow and rim) best
        explains the fringe phase of `observed` bands, given a prediction of them (its
        `light` share at the device's light): one scale per band family, within [0, 8].
        [`Inverter.band_residual`][] uses it on an inverter from `phase_only(None)`.

        A unit's elastomer need not glow as its device says: it may not glow at all, or
        glow several times more and wider. The light leaks into the fringe bands under the
        contact, so the wrong amount of it moves the fitted wrench. The light enters the
        bands linearly, so at a given load its best scale has a closed form: the
        least-squares fit of the light's phase component (across the predicted fringes) to
        the phase misfit of the rest of the prediction. A solve over the load sees the
        light's best amount at every trial load, and the data Jacobian, taken through it,
        gives the load's covariance with the light marginalised.

        The moiré bands share one scale and the carrier bands another. The light reaches
        the moiré bands through the reference grating's mean transmission, at low
        frequency, and the carrier bands through the reference grating's carrier, at the
        gratings' own frequency, where the lens attenuates it: a unit whose lens blurs more
        than its device says passes less of its light into the carriers (with twice the
        device's point-spread function, 0.4 of it on the Mid design), and one common scale
        cannot be right for both.
        """
        if predicted.light is None:
            raise ValueError(
                "`predicted` has no light share: pass bands from the model (Inverter.model), not a frame's"
            )
        gratings = self._gratings_share(predicted, model_reference)
        return self._light_scale(observed, gratings, predicted.light)

    def _gratings_share(self, predicted: FringeFields, model_reference: FringeFields | None):
        # The prediction's fringes but the elastomer's light, corrected for the unit's fixed
        # pattern by its reference bands over the model's.
        if model_reference is None:
            model_reference = self.model_reference
        ratio = complex_ratio(self.reference.fringe, model_reference.fringe)
        return predicted.fringe * ratio if predicted.light is None else (predicted.fringe - predicted.light) * ratio

    def _light_scale(
        self, observed: FringeFields, gratings: Complex[Array, "families m n"], light: Complex[Array, "families m n"]
    ) -> Float[Array, " families"]:
        full = gratings + light
        direction = jnp.conj(full) * jax.lax.rsqrt(full.real**2 + full.imag**2 + 1e-24).astype(full.dtype)
        weight = self.fringe_weight.astype(full.dtype)
        misfit = ((observed.fringe - gratings) * direction * weight).imag
        response = (light * direction * weight).imag
        # The light reaches the moiré bands through the reference grating's mean transmission,
        # and the carrier bands through its carrier, which the lens blurs: a unit's lens and
        # duty set how much of it the second path passes, so each path has its own scale.
        carrier = jnp.arange(full.shape[0]) >= self.device.n_sets
        paths = jnp.stack([~carrier, carrier]).astype(misfit.dtype)
        power = paths @ jnp.sum(response**2, axis=(1, 2))
        cross = paths @ jnp.sum(misfit * response, axis=(1, 2))
        total = paths @ jnp.sum(misfit**2 + jnp.abs(full * weight) ** 2, axis=(1, 2))
        # Without a contact there is no light to scale (nor a derivative of its scale): the
        # scale is then zero, and the division is kept off that case so that its derivative
        # stays finite. A path without bands has no light either.
        lit = power > 1e-12 * total
        scale = jnp.where(lit, cross / jnp.where(lit, power, 1.0), 0.0)
        return jnp.clip(scale, 0.0, _LIGHT_SCALE_MAX) @ paths

    def _data_residuals(self, y, observed: FringeFields):
        return self.band_residual(observed, self._predict(y))

    def _prior_residuals(self, y, noise):
        state = LoadState.from_vector(y)
        wrench = state.wrench
        fz = wrench[2]
        tilt = (
            jnp.stack([fz * state.y0 - wrench[3] * NMM_PER_NM, fz * state.x0 + wrench[4] * NMM_PER_NM])
            / _TILT_PRIOR_NMM
        )
        radius = state.radius_misfit()
        flatness = state.flatness_misfit()
        exposure = state.log_exposure / _EXPOSURE_PRIOR
        # Priors are in units of the data noise so their weight does not depend on it.
        misfits = [tilt, radius[None], flatness[None], state.stretch_misfit(), state.scaled_wrench / _WRENCH_PRIOR]
        return jnp.concatenate([*misfits, exposure[None]]) * noise

    def residuals(self, y, args):
        """Whitened data residuals followed by the prior residuals (optimistix signature)."""
        observed, noise = args
        return jnp.concatenate([self._data_residuals(y, observed), self._prior_residuals(y, noise)])

    def _wrench_rows(self, dtype) -> Float[Array, "6 13"]:
        # The scaled wrench among the solvers' coordinates, as the rows of a linear map.
        return jnp.eye(6, N_UNKNOWNS, dtype=dtype)

    def _summary(self, y) -> tuple[LoadState, Contact, Float[Array, "6"]]:
        # The state an estimate reports, its second contact (none) and that one's wrench.
        nan = jnp.full((), jnp.nan, y.dtype)
        return LoadState.from_vector(y), Contact(nan, nan, nan, nan, nan, nan), jnp.zeros(6, y.dtype)

    def observe(self, frame: Float[Array, "h w"]) -> FringeFields:
        """Demodulate a frame, normalised at the reference frame's wavevectors."""
        return self.demodulator(frame, self.reference.reference_wavevector)

    def _zero_residuals(self, observed: FringeFields):
        # The zero-load prediction, reference-corrected, is the reference itself.
        return self._band_residual(
            observed.fringe - self.reference.fringe,
            observed.brightness - self.reference.brightness,
            self.reference.fringe,
        )

    def _phase_change_map(self, observed: FringeFields) -> Float[Array, "families m n"]:
        r"""Energy of the fringe phase change against the reference at each coarse-grid
        point: $w^2 |f - |f|\,f_\text{ref}/|f_\text{ref}||^2$, which a change of the fringes'
        amplitude alone (exposure, illumination, the scene behind the sensor) leaves at zero."""
        reference = self.reference.fringe
        unit = reference * jax.lax.rsqrt(reference.real**2 + reference.imag**2 + 1e-24).astype(reference.dtype)
        change = (observed.fringe - jnp.abs(observed.fringe).astype(unit.dtype) * unit) * self.fringe_weight.astype(
            unit.dtype
        )
        return change.real**2 + change.imag**2

    def _phase_noise_floor(self, screen: "_Screen") -> Float[Array, "families m n"]:
        """Expected phase-change energy at each coarse-grid point from the frame's and the
        reference's white pixel noise alone (a noise-free frame against a noise-free
        reference has none; the floor then only keeps the ratio finite)."""
        variance = screen.noise_variance + self.reference_noise
        return jnp.maximum(variance * self.unit_phase_noise, jnp.finfo(self.unit_phase_noise.dtype).tiny * 1e6)

    def _quiet_mask(self) -> Bool[Array, "m n"]:
        # The inner field, where the apodization leaves the fringes their full weight.
        return self.fringe_weight[0] > 0.5 * jnp.max(self.fringe_weight[0])

    def _phase_change_statistic(self, observed: FringeFields, screen: "_Screen") -> Float[Array, ""]:
        energy = self._phase_change_map(observed) / self._phase_noise_floor(screen)
        x, _ = self.demodulator.coarse_grid()
        weight = self._quiet_mask()
        normalised = jnp.mean(energy, axis=0)
        # Separable Gaussian window on the coarse grid (same spacing both ways).
        offsets = jnp.arange(x.shape[1], dtype=energy.dtype) * (x[0, 1] - x[0, 0])
        kernel = jnp.exp(-0.5 * ((offsets[:, None] - offsets[None, :]) / _CONTACT_WINDOW) ** 2).astype(energy.dtype)
        local = kernel @ jnp.where(weight, normalised, 0.0) @ kernel.T
        coverage = kernel @ weight.astype(energy.dtype) @ kernel.T
        ratio = local / jnp.maximum(coverage, 1e-30)
        return jnp.max(jnp.where(coverage > 0.5 * jnp.max(coverage), ratio, 0.0))

    def phase_change(self, frame: Real[Array, "h w"]) -> Float[Array, ""]:
        """How far the fringe phase of `frame` has moved from the reference, in units of its noise.

        The phase-change energy at each point of the coarse grid, over what the frame's and
        the reference's pixel noise put there ([`white_noise_variance`][]), averaged in a
        Gaussian window (`_CONTACT_WINDOW` mm) around every point; this is the largest window
        average. About one without contact, whatever the illumination or exposure; a
        contact raises it where its fringes move. The contact gate compares it with
        `contact_threshold`: contact is decided from the data, not from how well a model
        fits, so a load the model explains badly is never reported as no contact.
        """
        screen, observed, _, _ = self._prepare(frame)
        return self._phase_change_statistic(observed, screen)

    def misfit_map(
        self, frame: Real[Array, "h w"], wrenches: Float[Array, "patches 6"], contacts: Contact
    ) -> Float[Array, "2 m n"]:
        """Where a reading of `frame` explains its fringes and where it does not.

        At every point of the coarse grid (`demodulator.coarse_grid()`, mm on the contact
        surface): the fringe phase's change from the reference (row 0), and what is left of
        it once the patches of `contacts` (fields with a leading axis) carrying `wrenches`
        (N, N·m, about the origin) are modelled (row 1), each in units of what the frame's
        and the reference's pixel noise alone put there (about 1 where nothing is left), the
        mean over the band families. The residual is the one the estimate is refined on (the
        fringe phase, with the contact light each family explains best), so a frame read
        `unexplained` shows here where its model falls short. Pure and jit-able."""
        screen, observed, _, _ = self._prepare(frame)
        fit = eqx.tree_at(lambda i: (i.fitted_flatness, i.fitted_elongation), self._fit, (True, True))
        predicted = fit.model.of_contacts(jnp.asarray(wrenches, observed.brightness.dtype), contacts)
        size = self.fringe_weight.size
        floor = self._phase_noise_floor(screen)

        def energy(residual):
            return jnp.mean(residual[size : 2 * size].reshape(self.fringe_weight.shape) ** 2 / floor, axis=0)

        return jnp.stack([energy(fit._zero_residuals(observed)), energy(fit.band_residual(observed, predicted))])

    def initial_guess(self, observed: FringeFields) -> LoadState:
        """A cold start from the brightness excess: its centroid places the contact, its
        integral sets Fz through the model's glow per newton, and a centred pressure gives
        Tx, Ty."""
        # Only a start: the brightness excess places it whether or not the residual uses the
        # brightness band (a unit that does not glow falls back on the fringe change).
        excess = (observed.brightness - self.reference.brightness) * self.demodulator.brightness_envelope.astype(
            observed.brightness.dtype
        )
        # Centroid of the excess relative to the reference's own brightness, in a window
        # around its peak: the glow rides on the illumination, whose fall-off towards the
        # edges (and the envelope's) would pull the peak of the plain excess to the image
        # centre, by about a third of the way for a press 8 mm out; and the band-limited
        # brightness rings, so a global centroid would be pulled there too.
        relative = (observed.brightness - self.reference.brightness) / jnp.maximum(
            jnp.abs(self.reference.brightness), 1e-6 * jnp.max(jnp.abs(self.reference.brightness)) + 1e-30
        )
        inside = self.demodulator.brightness_envelope > 0.2 * jnp.max(self.demodulator.brightness_envelope)
        x0, y0 = self._peak_centroid(jnp.where(inside, jnp.maximum(relative, 0.0), 0.0).astype(excess.dtype))
        fz = jnp.clip(jnp.sum(excess) / self.glow_per_newton, 0.0, 3.0)
        return _centred_press(fz, x0, y0)

    def fringe_placed_guess(self, observed: FringeFields) -> LoadState:
        """The cold start of [`Inverter.initial_guess`][] moved to where the fringes changed
        most ([`Inverter.fringe_change_centre`][]), with the moments of a centred pressure
        there.

        The brightness places a contact only where the light behind the sensor is the
        reference's: a scene that changes between the reference and the frame moves the
        brightness centroid anywhere (a 0.69 N press at (-6.4, 0.4) mm placed at (6.8, -9.6)
        mm), the solve from there ends in a wrong basin, and the further starts built from
        that solution stay near it. The fringe phase does not see the scene's light.
        """
        guess = self.initial_guess(observed)
        x0, y0 = self.fringe_change_centre(observed)
        return _centred_press(guess.wrench[2], x0, y0)

    def fringe_change_centre(self, observed: FringeFields) -> Float[Array, "2"]:
        """Where the fringes changed most from the reference: the centroid (mm, contact
        surface) of the fringe-change energy in a 3 mm window around its peak.

        Less reliable than the brightness centroid of [`Inverter.initial_guess`][] on the
        whole (a stray peak can sit anywhere), but right where that one is misled: a light
        press with strong shear or twist, whose glow is faint and off-centre. Read on the
        moiré families: a carrier's change wraps where its phase winds fast (at a twisted
        contact's rim), and its energy peaks there, not at the centre.
        """
        return jnp.stack(self._peak_centroid(self._fringe_change_energy(observed)))

    def _fringe_change_energy(self, observed: FringeFields) -> Float[Array, "m n"]:
        # The moiré families' change from the reference at each coarse-grid point.
        sets = self.device.n_sets
        return jnp.sum(
            jnp.abs(observed.fringe[:sets] - self.reference.fringe[:sets]) ** 2 * self.fringe_weight[:sets] ** 2, axis=0
        )

    def _peak_centroid(self, weight: Float[Array, "m n"]) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """Centroid of a non-negative coarse-grid field in a 3 mm window around its peak,
        in mm on the contact surface."""
        x, y = self.demodulator.coarse_grid()
        peak = jnp.argmax(weight)
        window = jnp.exp(-0.5 * ((x - x.ravel()[peak]) ** 2 + (y - y.ravel()[peak]) ** 2) / 3.0**2)
        local = weight * window
        total = jnp.sum(local) + 1e-12
        to_surface = self.device.surface_magnification
        return jnp.sum(local * x) / total * to_surface, jnp.sum(local * y) / total * to_surface

    def cold_track(self) -> "Track":
        """The [`Track`][] of a stream before its first frame (or after a reset)."""
        dtype = self.device.p1.dtype
        n = self.noise_residuals.shape[1]
        return Track(
            state=LoadState.from_vector(jnp.full(N_UNKNOWNS, jnp.nan, dtype)),
            jacobian=jnp.zeros((n, N_UNKNOWNS), dtype),
            change=jnp.zeros(n, dtype),
            valid=jnp.asarray(False),
        )

    def _prepare(self, frame):
        if frame.shape != (self.device.height, self.device.width):
            raise ValueError(f"frame has shape {frame.shape}, device expects {(self.device.height, self.device.width)}")
        if frame.dtype in (jnp.uint8, jnp.uint16):
            # As a camera or `cv2.imread` delivers it: the inversion reads frames in [0, 1].
            frame = frame.astype(self.device.p1.dtype) / jnp.iinfo(frame.dtype).max
        frame = frame.astype(self.device.p1.dtype)
        observed = self.observe(frame)
        # Every Fourier coefficient sums every pixel, so one NaN or inf pixel makes the whole
        # coarse field non-finite: checking it costs nothing, unlike a pass over the frame.
        # The solve then runs on the reference (no load) and the status reports the frame.
        finite = jnp.all(jnp.isfinite(observed.brightness)) & jnp.all(jnp.isfinite(observed.fringe))
        observed = jax.tree_util.tree_map(lambda o, ref: jnp.where(finite, o, ref), observed, self.reference)
        # Exposure checks on every 4th pixel each way: a sixteenth of the memory traffic,
        # and a share of clipped pixels estimated to within 1%.
        sample = frame[::4, ::4]
        reference = self.reference.fringe
        contrast = jnp.mean(jnp.abs(observed.fringe)) / jnp.maximum(jnp.mean(jnp.abs(reference)), 1e-12)
        ratio = observed.fringe * jnp.conj(reference)
        weight = self.fringe_weight.astype(ratio.dtype)
        unit_ratio = ratio * jax.lax.rsqrt(ratio.real**2 + ratio.imag**2 + 1e-30).astype(ratio.dtype)
        agreement = jnp.abs(jnp.sum(unit_ratio * weight, axis=(1, 2))) / jnp.sum(self.fringe_weight, axis=(1, 2))
        clean = jnp.where(jnp.isfinite(frame), frame, 0.0)
        screen = _Screen(
            finite=finite,
            dark=jnp.max(sample) < 0.02,
            saturated=jnp.mean(sample >= 0.995) > _CLIPPED_SHARE,
            foreign=(contrast < 0.2) | jnp.any(agreement < _FRINGE_AGREEMENT_FLOOR),
            disagrees=jnp.any(agreement < _FRINGE_AGREEMENT),
            corrupt=_corrupt_pixels(clean),
            noise_variance=jnp.where(finite, white_noise_variance(clean), 0.0),
        )
        r_zero = self._zero_residuals(observed)
        # Robust noise level: the median absolute whitened phase residual of zero load (most
        # of the field is outside any contact; a change of exposure or illumination moves
        # only the amplitude components), scaled to a Gaussian sigma. Every second value is
        # plenty (1024 for crossed grids: 4% scatter); the level only weighs the priors and
        # sizes the steps in standard errors.
        size = self.fringe_weight.size
        noise = jnp.maximum(_median(jnp.abs(r_zero[size : 2 * size : 2])) / 0.6745, 1e-9)
        return screen, observed, r_zero, noise

    def _prior_jacobian(self, y, noise):
        return jax.jacfwd(self._prior_residuals)(y, noise)

    def _data_jacobian(self, y, observed):
        return jax.jacfwd(self._data_residuals)(y, observed)

    def phase_only(self, light: float | Float[Array, ""] | None = 1.0) -> "Inverter":
        """This inverter with a residual of the fringe phase alone (the weights of the
        brightness and of the fringes' amplitude, and their shares of the unit-noise draws,
        set to zero), and the light a contact scatters (glow and rim) scaled by `light` in
        the model: 1 for a unit that scatters it as the device says, 0 for one that does
        not, `None` for the scale that best explains each frame
        ([`Inverter.contact_light_scale`][]). The light leaks into the fringe bands, so a
        law the unit does not follow biases the fringe fit too.

        The amplitude is left out because photometry moves it: on frames of an independent
        renderer, the fringe amplitude at the true load differed from the model's by up to
        10% (contrast under compression, defocus), three to seven times the phase misfit,
        and pulled the wrench off by more than its range on the axes the phase sees weakly."""
        size = self.fringe_weight.size
        noise_residuals = self.noise_residuals.at[:, :size].set(0.0).at[:, 2 * size :].set(0.0)
        optics = self.model.mechanics.device.optics
        scale = 1.0 if light is None else light
        return eqx.tree_at(
            lambda i: (
                i.brightness_weight,
                i.amplitude_weight,
                i.noise_residuals,
                i.noise_power,
                i.model.mechanics.device.optics.glow_gain,
                i.model.mechanics.device.optics.rim_gain,
                i.fitted_light,
            ),
            self,
            (
                jnp.zeros_like(self.brightness_weight),
                jnp.zeros_like(self.amplitude_weight),
                noise_residuals,
                jnp.sum(noise_residuals**2) / noise_residuals.shape[0],
                optics.glow_gain * scale,
                optics.rim_gain * scale,
                jnp.asarray(light is None),
            ),
        )

    @property
    def _fit(self) -> "Inverter":
        """The problem a solution is refined on: this inverter itself when it fits the
        brightness, else [`Inverter.phase_only`][] with the contact light each load explains
        best."""
        return self if self.brightness else self.phase_only(None)

    def track(self, frame: Real[Array, "h w"], track: "Track") -> tuple[Estimate, "Track"]:
        """Invert one frame of a stream; pure and jit-able (see [`frame_tracker`][]).

        With a valid `track`, a few frozen-Jacobian Gauss–Newton iterations from the last
        solution on the problem cold solutions are refined on (the fringe phase, with the
        contact light each load explains best; about three model evaluations), then the same
        iterations with a
        fresh Jacobian. If neither converges, or without a valid track, the cold solve of
        [`Inverter.solve`][] from the best of the last solution, the iterations' end and
        the cold guess (its first two starts only, so that a stream does not stall; see
        `_solvers.levenberg_marquardt`). Returns the estimate and the track for the next frame.
        """
        screen, observed, _, noise = self._prepare(frame)
        args = (observed, noise)
        cold = self.initial_guess(observed).vector()
        last = track.state.vector()
        usable = track.valid & jnp.all(jnp.isfinite(last))
        warm = jnp.where(usable, last, cold)
        fit = self._fit
        # The zero-load residual has no contact light: one for the whole frame.
        r_zero = fit._zero_residuals(observed)
        # The last frame's prediction at `warm` gives its residual here without a model run.
        r_warm = jax.lax.cond(
            usable,
            lambda: jnp.concatenate([r_zero - track.change, fit._prior_residuals(warm, noise)]),
            lambda: fit.residuals(cold, args),
        )
        y_chord, r_chord, j_chord, chord_steps, accepted, pending = chord(fit, warm, r_warm, track.jacobian, args)
        accepted = usable & accepted

        def fast(_):
            return y_chord, r_chord, j_chord, chord_steps, optx.RESULTS.successful, pending

        def slow(_):
            # Second tier: the same iterations with a Jacobian evaluated afresh at the best
            # point so far (about one Levenberg–Marquardt step's cost).
            chord_ok = jnp.all(jnp.isfinite(y_chord)) & usable
            start, r_start = best_start(
                [cold, warm, jnp.where(chord_ok, y_chord, cold)],
                [fit.residuals(cold, args), r_warm, jnp.where(chord_ok, r_chord, jnp.inf)],
            )
            y_fresh, r_fresh, j_fresh, fresh_steps, fresh_ok, fresh_pending = chord(
                fit, start, r_start, fit._data_jacobian(start, observed), args
            )

            def refreshed(_):
                steps = chord_steps + fresh_steps
                return y_fresh, r_fresh, j_fresh, steps, optx.RESULTS.successful, fresh_pending

            def cold_solve(_):
                # The start is chosen on the full residual, as the cold solve's first stage
                # sees it, between the cold guess and the last solution: after a jump to an
                # unrelated load, iterations on the phase alone from the last solution end
                # in its basin, and the brightness points to the new contact.
                start, _ = best_start([cold, warm], [self.residuals(cold, args), self.residuals(warm, args)])
                y, r, jacobian, steps, result = solve_cold(self, start, args, more_starts=False)
                return y, r, jacobian, steps, result, jnp.zeros_like(y)

            return jax.lax.cond(usable & fresh_ok, refreshed, cold_solve, None)

        y, r, jacobian, steps, result, pending = jax.lax.cond(accepted, fast, slow, None)
        estimate, next_track = finish(
            fit, screen, observed, r_zero, noise, y, r, jacobian, steps, result, warm, pending
        )
        return estimate, next_track

    def solve(self, frame: Real[Array, "h w"], init: LoadState | None = None) -> Estimate:
        """Invert one frame with Levenberg–Marquardt. Pure and jit-able; see [`invert`][].

        `init` warm-starts the solver (a [`LoadState`][]: the previous frame's
        `Estimate.state`, or [`LoadState.from_load`][] of a known load and contact); `None` or a non-finite `init` means a cold start from the brightness
        excess. A warm start that explains the frame better than the cold guess is solved
        from there alone, without the further starts a cold solve may try. Streams are faster
        through [`Inverter.track`][]. A frame is read in [0, 1]; 8- and 16-bit integer
        frames, as a camera delivers them, are scaled to it.

        Without `brightness`, the solution of the full residual (fringe fields and
        brightness), whose glow places a cold start in the right basin on a unit that glows,
        is refined on the fringe phase alone, with as much of the contact light the device
        describes as best explains the frame at each load ([`Inverter.contact_light_scale`][]):
        neither the unit's brightness, nor its fringes' amplitude, which photometry moves,
        nor how much its elastomer glows biases the estimate.

        The solution has one contact patch; [`Inverter.second_contact`][] reads a frame
        that one patch leaves poorly explained with two.
        """
        screen, observed, r_zero, noise = self._prepare(frame)
        args = (observed, noise)
        cold = self.initial_guess(observed).vector()
        if init is None:
            y0, more_starts = cold, jnp.asarray(True)
        else:
            # Warm start when it explains the frame better than the cold guess does: true
            # for a camera stream, false after a jump to an unrelated load.
            start = init.vector().astype(cold.dtype)
            usable = jnp.all(jnp.isfinite(start))
            warm = jnp.where(usable, start, cold)
            y0, _ = best_start([cold, warm], [self.residuals(cold, args), self.residuals(warm, args)])
            # A warm start that wins is in the right basin already: the further starts are
            # for cold guesses (on a unit the model does not describe exactly, every frame
            # leaves enough unexplained to try them all).
            more_starts = ~(usable & jnp.all(y0 == warm))

        def solved(_):
            return solve_cold(self, y0, args, more_starts=more_starts)

        def skipped(_):
            # No load to find: the unknowns stay at zero load, where the Jacobian still gives
            # the interval of a load the noise could hide.
            fit = self._fit
            y = LoadState.from_vector(y0).unloaded().vector()
            steps = jnp.zeros((), jnp.int32)
            return y, fit.residuals(y, args), fit._data_jacobian(y, observed), steps, optx.RESULTS.successful

        # A frame without contact, or one the screen refuses, is not solved: its status sets
        # the wrench (zero, or NaN) whatever a solver would return.
        needed = (
            screen.finite & ~screen.refused & (self._phase_change_statistic(observed, screen) > self.contact_threshold)
        )
        y, r, jacobian, steps, result = jax.lax.cond(needed, solved, skipped, None)
        fit = self._fit
        return finish(fit, screen, observed, fit._zero_residuals(observed), noise, y, r, jacobian, steps, result, y0)[0]

    def second_contact(self, frame: Real[Array, "h w"], estimate: Estimate) -> Estimate:
        """`estimate` of `frame`, read again where its round patch leaves more than 5 % of
        the fringe phase's change unexplained (`Estimate.misfit`): with one elongated patch
        and with two round ones, each a candidate where it leaves less than half of what
        the round patch left, the better of the candidates kept; otherwise `estimate`
        itself. Pure and jit-able.

        An edge or a cylinder pressed along its length, or two fingertips on the pad, read
        through one round patch come out wrong on every axis. [`invert`][] and `moirejax
        invert` call this on every frame whose estimate needs it (a stream from a camera
        does not: the solves take seconds). The estimate's `contact` then has an
        elongation ([`Contact.aspect_ratio`][moirejax.Contact.aspect_ratio]), or its
        `second_contact` and `second_wrench` say where the second patch is and what it
        carries; see `moirejax.inverse._second_contact` for how it is found and when it is
        kept. A frame a round patch explains keeps it: a free elongation would trade the
        normal force for the shape of a round contact's misfit (on an independent
        renderer's spheres, whose misfit is its aliasing, it took Fz from R² 0.91 to 0.83).
        """
        screen, observed, _, noise = self._prepare(frame)
        args = (observed, noise)
        fit = self._fit
        r_zero = fit._zero_residuals(observed)
        y = estimate.state.vector().astype(r_zero.dtype)
        r = fit.residuals(y, args)
        status = estimate.status
        believed = (status == Status.CONVERGED) | (status == Status.MAX_STEPS) | (status == Status.UNEXPLAINED)
        needed = believed & (estimate.contacts == 1) & (estimate.misfit > _SECOND_CONTACT_TRIGGER)

        def reread(_):
            elongated = eqx.tree_at(lambda i: i.fitted_elongation, fit, jnp.asarray(True))
            y1, r1, jacobian1, steps1, result1 = levenberg_marquardt(fit, y, args, more_starts=False, elongated=True)
            n_data = r.shape[0] - N_PRIORS
            round_cost, long_cost = jnp.sum(r[:n_data] ** 2), jnp.sum(r1[:n_data] ** 2)
            long_kept = jnp.isfinite(long_cost) & (long_cost < _SECOND_CONTACT_GAIN * round_cost)
            single = finish(
                elongated,
                screen,
                observed,
                r_zero,
                noise,
                y1,
                r1,
                jacobian1,
                estimate.steps + steps1,
                result1,
                y1,
            )[0]
            single = jax.tree_util.tree_map(lambda a, b: jnp.where(long_kept, a, b), single, estimate)
            y2, r2, jacobian2, steps2, result2, kept = solve_pair(fit, y, r, args)
            # Both halve the round patch's misfit: the one that explains the frame better.
            kept = kept & ~(long_kept & (long_cost <= jnp.sum(r2[:n_data] ** 2)))
            pair = finish(
                ContactPair(fit),
                screen,
                observed,
                r_zero,
                noise,
                y2,
                r2,
                jacobian2,
                single.steps + steps2,
                result2,
                y2,
                unexplained_share=_PAIR_UNEXPLAINED_SHARE,
            )[0]
            return jax.tree_util.tree_map(lambda a, b: jnp.where(kept, a, b), pair, single)

        return jax.lax.cond(needed, reread, lambda _: estimate, None)

    def chord_batch(self, frames: Real[Array, "b h w"], track: "Track") -> tuple[Estimate, Bool[Array, " b"], "Track"]:
        """Frozen-Jacobian iterations for a batch of nearby frames from one shared `track`.

        Vectorises well (no Levenberg–Marquardt branch inside the vmap). Returns the
        estimates, which frames converged this way (the others need [`Inverter.track`][]),
        and each frame's track (a leading batch axis) to continue a stream from.
        """

        fit = self._fit

        def one(frame):
            screen, observed, _, noise = self._prepare(frame)
            args = (observed, noise)
            r_zero = fit._zero_residuals(observed)
            last = track.state.vector()
            r_start = jnp.concatenate([r_zero - track.change, fit._prior_residuals(last, noise)])
            y, r, jacobian, steps, accepted, pending = chord(fit, last, r_start, track.jacobian, args)
            estimate, frame_track = finish(
                fit, screen, observed, r_zero, noise, y, r, jacobian, steps, optx.RESULTS.successful, y, pending
            )
            # A frame the chord settles is done whatever its verdict; a frame that needs no
            # solution (bad, non-finite) is done too.
            status = estimate.status
            settled = accepted & ((status == Status.CONVERGED) | (status == Status.NO_CONTACT))
            done = settled | (status == Status.BAD_FRAME) | (status == Status.NONFINITE)
            return estimate, done, frame_track

        return jax.vmap(one)(frames)


def _centred_press(fz: Float[Array, ""], x0: Float[Array, ""], y0: Float[Array, ""]) -> LoadState:
    """A round patch of typical size at `(x0, y0)` mm pressing with `fz` newtons and no
    shear or twist: its moments are those of that force at the patch's centre."""
    scale = jnp.asarray(WRENCH_SCALE, fz.dtype)
    zero = jnp.zeros((), fz.dtype)
    moment = fz / NMM_PER_NM
    scaled = jnp.stack([zero, zero, fz / scale[2], y0 * moment / scale[3], -x0 * moment / scale[4], zero])
    return LoadState(scaled, x0, y0, jnp.log(jnp.asarray(TYPICAL_RADIUS, fz.dtype)), zero, zero, zero, zero)


@eqx.filter_jit
def _bands_at_state(
    device: Device, demodulator: Demodulator, state: LoadState, reference_wavevector, model_shape
) -> FringeFields:
    return predicted_bands(
        device,
        demodulator,
        state.wrench,
        state.contact,
        state.exposure,
        model_shape=model_shape,
        reference_wavevector=reference_wavevector,
    )


class _Screen(eqx.Module):
    """What a frame shows before any solve: finite pixels, too dark, too many pixels clipped,
    not this unit's fringes (too faint, or of a phase unrelated to the reference's: another
    scene, noise), part of it corrupt (pixel noise far above the rest's), and the variance of
    its white pixel noise. A frame whose phase agrees
    with the reference's less than a light press's does (`disagrees`: a grasp load, or not
    this unit's fringes) is solved, and refused afterwards unless a load explains it."""

    finite: Bool[Array, ""]
    dark: Bool[Array, ""]
    saturated: Bool[Array, ""]
    foreign: Bool[Array, ""]
    disagrees: Bool[Array, ""]
    corrupt: Bool[Array, ""]
    noise_variance: Float[Array, ""]

    @property
    def refused(self) -> Bool[Array, ""]:
        return self.dark | self.saturated | self.foreign | self.corrupt


def _corrupt_pixels(frame: Float[Array, "h w"]) -> Bool[Array, ""]:
    """Whether two neighbouring squares of `frame` carry white pixel noise far above its
    median square's (`_CORRUPT_NOISE_RATIO`): pixels that no camera and no load put there
    (a transmission fault, a patch of another image). Where the phase is read from such
    pixels, a fit can place an absurd load that explains the rest of the field; the fringe
    phase there is noise, and the misfit tests, which compare the phase with its change,
    do not see data that is missing."""
    if frame.shape[0] < _NOISE_BLOCK or frame.shape[1] < _NOISE_BLOCK:
        return jnp.asarray(False)
    noise = white_noise_map(frame, _NOISE_BLOCK)
    loud = noise > _CORRUPT_NOISE_RATIO * jnp.maximum(jnp.median(noise), _NOISE_FLOOR)
    return jnp.any(loud[1:] & loud[:-1]) | jnp.any(loud[:, 1:] & loud[:, :-1])


def _median(values: Float[Array, " n"]) -> Float[Array, ""]:
    """`jnp.median` by partition instead of a full sort: the same number, without sorting
    the values a frame's noise level is taken from."""
    n = values.shape[0]
    upper = jnp.partition(values, n // 2)
    return upper[n // 2] if n % 2 else 0.5 * (jnp.max(upper[: n // 2]) + upper[n // 2])
