r"""The forward model in the demodulated domain: what the moiré band and the brightness
band of a frame should contain, without rendering the frame.

Expanding the product of the two gratings, the only term of the `model`-fidelity frame
inside the band of family $f$ is the beat of the fundamentals of line set $f$,
$$\tfrac12\, g\, B(\mathbf x)\, c_1(d_1)\, c_1(d_2)\, M_\text{defocus}\, M_\text{psf}
\prod_{s \ne f} d_1 d_2 \;\cos\!\big(\varphi_{1f}(\mathbf x) - \varphi_{2f}(\mathbf x)\big),$$
and the low-frequency part of the frame adds the mean transmission $\prod_s d_1 d_2$
times the scene radiance and the light scattered in the elastomer times $\prod_s d_2$.
That low-frequency frame is evaluated on a grid a few times coarser than the image and
pushed through the demodulator's own band-passes, so that prediction and measurement
see the same filter, including the leak of a contact's glow into the fringe bands.
This is about a hundred times cheaper than rendering and demodulating a frame, which
is what makes a per-frame least-squares inversion run at camera rate.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from ..physics import (
    background_radiance,
    binary_harmonics,
    Contact,
    Device,
    gaussian_mtf,
    image_coordinates,
    line_transmission,
    Mechanics,
    mechanics,
    reference_grating_phase,
    upper_grating_phase,
)
from ._observables import BAND_FRACTION, Demodulator, FringeFields, RealBandPass


def beat_coefficients(device: Device) -> tuple[Float[Array, "sets n"], Float[Array, ""]]:
    r"""Coefficients of the low-frequency beats $n(\varphi_{1s} - \varphi_{2s})$ of each line set.

    The product of two line sets holds $d_1 d_2 + \sum_n \tfrac12 c_{1n} c_{2n}
    \cos n(\varphi_1 - \varphi_2)$ below the carriers; the defocus of the far grating and
    the lens PSF attenuate harmonic $n$ at $n|k_1'|$ and $n|K|$. Returns the per-set
    harmonic weights (DC first) and the mean transmission of the reference grating.
    """
    n = jnp.arange(device.harmonics + 1, dtype=float)
    k1_apparent = jnp.linalg.norm(device.apparent_upper_wavevectors(), axis=-1)
    K = jnp.linalg.norm(device.moire_wavevectors(), axis=-1)
    c1 = binary_harmonics(device.duty1, device.harmonics)
    c2 = binary_harmonics(device.duty2, device.harmonics)
    half = jnp.where(n > 0, 0.5, 1.0)
    defocus = gaussian_mtf(n[None] * k1_apparent[:, None], device.optics.defocus)
    psf = gaussian_mtf(n[None] * K[:, None], device.optics.psf_sigma / device.px_per_mm)
    weights = half[None] * (c1 * c2)[None] * defocus * psf
    return weights, c2[0] ** device.n_sets


class BandModel(eqx.Module):
    """[`predicted_bands`][] for one device, demodulator, model grid and reference
    wavevector, with everything that does not depend on the load precomputed: the elastomer's
    response, the reference grating's phase, the scene radiance and the band-passes
    ([`band_model`][]). An inversion evaluates the model a few times per frame on a fixed
    unit; this is what makes each evaluation cost little more than the load's own work.
    Call it with `(wrench, contact, exposure)`."""

    mechanics: Mechanics
    x: Float[Array, "h w"]
    y: Float[Array, "h w"]
    reference_phase: Float[Array, "sets h w"]
    radiance: Float[Array, "h w"]
    beat_weights: Float[Array, "sets n"]
    mean_reference: Float[Array, ""]
    band_pass: RealBandPass
    reference_wavevector: Float[Array, "families 2"]

    def __call__(self, wrench: Float[Array, "6"], contact: Contact, exposure: ArrayLike = 1.0) -> FringeFields:
        device = self.mechanics.device
        state = self.mechanics(wrench, contact)
        beat = upper_grating_phase(device, self.x, self.y, state.displacement) - self.reference_phase
        # Everything of the frame below the carriers: the product over line sets of their
        # beats, and the elastomer light seen through the reference grating. The light is a
        # bump a few mm wide, so it reaches into the fringe bands too.
        transmission = jnp.prod(jax.vmap(line_transmission)(beat, self.beat_weights), axis=0)
        gain = device.optics.gain * jnp.asarray(exposure)
        low = device.optics.offset + gain * (self.radiance * transmission + self.mean_reference * state.light)
        fringe, brightness = self.band_pass(low)
        return FringeFields(fringe=fringe, brightness=brightness, reference_wavevector=self.reference_wavevector)


def band_model(
    device: Device,
    demodulator: Demodulator,
    model_shape: tuple[int, int] = (64, 64),
    reference_wavevector: Float[Array, "families 2"] | None = None,
) -> BandModel:
    """The [`BandModel`][] of [`predicted_bands`][] (same arguments, less the load)."""
    if demodulator.num_families != device.n_sets:
        raise ValueError(f"demodulator has {demodulator.num_families} families, device {device.n_sets} line sets")
    x, y = image_coordinates(device, model_shape)
    weights, mean_reference = beat_coefficients(device)
    return BandModel(
        mechanics=mechanics(device, model_shape),
        x=x,
        y=y,
        reference_phase=reference_grating_phase(device, x, y),
        radiance=background_radiance(device, x, y),
        beat_weights=weights,
        mean_reference=mean_reference,
        # Phases refer to the demodulator's nominal wavevectors; the measured reference
        # wavevector only sets the normalisation.
        band_pass=demodulator.real_band_pass(model_shape, reference_wavevector, x.dtype),
        reference_wavevector=demodulator.wavevectors if reference_wavevector is None else reference_wavevector,
    )


def predicted_bands(
    device: Device,
    demodulator: Demodulator,
    wrench: Float[Array, "6"],
    contact: Contact,
    exposure: ArrayLike = 1.0,
    *,
    model_shape: tuple[int, int] = (64, 64),
    reference_wavevector: Float[Array, "families 2"] | None = None,
) -> FringeFields:
    """The [`FringeFields`][] that `demodulator` would measure on a `model`-fidelity frame.

    **Arguments:**

    - `device`, `wrench`, `contact`, `exposure`: as for [`render_frame`][].
    - `demodulator`: the measurement's demodulator (its band-pass is applied).
    - `model_shape`: grid (covering the image) on which the mechanics and the baseband
      fields are evaluated; it must resolve the fringe phase near a contact.
    - `reference_wavevector`: the wavevectors the measurement refers its phase to (the
      demodulator's own if omitted).

    **Returns:** predicted fringe fields (families on the first axis) and brightness.
    Many loads on one unit: build its [`band_model`][] once.
    """
    return band_model(device, demodulator, model_shape, reference_wavevector)(wrench, contact, exposure)


def fringe_phase(fields: FringeFields) -> Float[Array, "families m n"]:
    """Wrapped phase of each fringe family."""
    return jnp.angle(fields.fringe)


def complex_ratio(
    numerator: Complex[Array, "*s"], denominator: Complex[Array, "*s"], floor: float = 1e-6
) -> Complex[Array, "*s"]:
    """`numerator / denominator` with the denominator's magnitude floored (no division by zero)."""
    safe = jnp.where(jnp.abs(denominator) > floor, denominator, floor)
    return numerator / safe


def stray_beat_clearance(
    device: Device, band_fraction: float = BAND_FRACTION, max_order: int | None = None
) -> Float[Array, " sets"]:
    r"""How far the gratings' mixed-order beats stay from the demodulated bands, per family.

    Harmonics $n$ of the upper grating and $m$ of the reference beat at
    $n\mathbf{k}_1' - m\mathbf{k}_2 = n\mathbf{K} + (n - m)\mathbf{k}_2$. For $n \ne m$
    these are not moiré fringes of the design, and no band model includes them; when the
    pitch ratio $p_1'/p_2$ is near $(q + 1)/q$ for small $q$, some land on the fringe band
    ($\pm\mathbf{K}$) or the brightness band (0) and bias the phase there (at
    $p_1'/p_2 = 4/3$, $3\mathbf{k}_1' - 2\mathbf{k}_2 = -\mathbf{K}$ with a tenth of the
    fringe's amplitude). Returns, per family, the smallest distance of any such beat
    ($1 \le n, m \le$ `max_order`, default the device's `harmonics`; binary gratings
    carry higher orders at a few per cent, the paper's Dense design has one at orders 3
    and 4) to a band centre over that band's radius (`band_fraction`
    of $|\mathbf{K}_f|$, of the smallest $|\mathbf{K}|$ for brightness, as the
    [`Demodulator`][] uses): above 1 the bands are clean.
    """
    max_order = device.harmonics if max_order is None else max_order
    k1 = device.apparent_upper_wavevectors()
    k2 = device.reference_wavevectors()
    K = k1 - k2
    orders = [(n, m) for n in range(1, max_order + 1) for m in range(1, max_order + 1) if n != m]
    n = jnp.asarray([o[0] for o in orders], K.dtype)[:, None, None]
    m = jnp.asarray([o[1] for o in orders], K.dtype)[:, None, None]
    beats = n * k1[None] - m * k2[None]  # (orders, sets, 2)
    fringe_radius = band_fraction * jnp.linalg.norm(K, axis=-1)
    brightness_radius = band_fraction * jnp.min(jnp.linalg.norm(K, axis=-1))
    # A real frame holds every beat with its conjugate, so -K is as bad as K.
    to_fringe = jnp.minimum(jnp.linalg.norm(beats - K[None], axis=-1), jnp.linalg.norm(beats + K[None], axis=-1))
    clearance = jnp.minimum(to_fringe / fringe_radius[None], jnp.linalg.norm(beats, axis=-1) / brightness_radius)
    return jnp.min(clearance, axis=0)
