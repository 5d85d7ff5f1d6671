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

**Carriers.** Where the camera resolves the upper grating itself, the frame also holds its
carrier near the apparent wavevector $\mathbf k_1'$ of each line set: with the far
grating's complex harmonics $a_n$ (defocused) and the reference grating's $b_m$, the terms
$n\mathbf k_1' + m\mathbf k_2$ near $\mathbf k_1'$ are $n = 1 + j$, $m = -j$, so the
carrier's baseband is
$$e^{i(\varphi_1 - \mathbf k_1'\cdot\mathbf x)} \sum_j a_{1+j}\, b_{-j}\, M_\mathrm{psf}
(|\mathbf k_1' + j\mathbf K|)\, e^{ij(\varphi_1 - \varphi_2)},$$
times the scene radiance and, for crossed grids, the other line set's low-frequency
transmission. Its phase is the upper grating's own phase: the same displacement signal as
the moiré band's, at the resolution of a band a few times wider. The $j = -1$ term is the
reference grating's carrier, which does not move; the inversion removes it from the
measurement with the reference frame ([`moirejax.Inverter`][]), and the model leaves out
its part at zero load. A demodulator whose families are the moiré wavevectors followed by
the apparent upper wavevectors (one per line set each) gets both.
"""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
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
from ._observables import BAND_FRACTION, BasebandPass, Demodulator, FringeFields, RealBandPass


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


# The carrier bands need this much contrast left after defocus and the lens PSF, and must lie
# below this fraction of the Nyquist limit, for the camera to resolve the upper grating.
_CARRIER_CONTRAST = 0.1
_CARRIER_NYQUIST = 0.9


def carrier_band_radius(device: Device, crop_shape: tuple[int, int] = (32, 32)) -> float | None:
    r"""Band radius (rad/mm) of the upper grating's carrier bands (module notes), or `None`
    where the camera does not resolve that grating.

    The band is as wide as a demodulator window of `crop_shape` allows (three bins clear of
    its border on its narrower side), which on a coarse grid of about 1 mm is a resolution
    of about 1.3 mm, against the moiré band's 5 mm on the Mid design. It is resolved when the
    band lies below 0.9 of the pixel Nyquist limit and the carrier keeps a tenth of its
    contrast through the far grating's defocus and the lens PSF. Needs concrete values.
    """
    m, n = (int(c) for c in crop_shape)
    field_y, field_x = device.height / float(device.px_per_mm), device.width / float(device.px_per_mm)
    radius = (min(m, n) // 2 - 3) * 2 * math.pi / max(field_x, field_y)
    k1 = np.linalg.norm(np.asarray(device.apparent_upper_wavevectors()), axis=-1)
    nyquist = math.pi * float(device.px_per_mm)
    contrast = np.asarray(
        gaussian_mtf(k1, device.optics.defocus) * gaussian_mtf(k1, device.optics.psf_sigma / device.px_per_mm)
    )
    if np.any(k1 + radius > _CARRIER_NYQUIST * nyquist) or np.any(contrast < _CARRIER_CONTRAST) or radius <= 0:
        return None
    return float(radius)


def carrier_coefficients(device: Device) -> Float[Array, "sets orders"]:
    r"""Weights $a_{1+j} b_{-j} M_\mathrm{psf}(|\mathbf k_1' + j\mathbf K|)$ of the carrier
    series of each line set (module notes), for $j = -N, \dots, N-1$ (every pair of
    harmonics up to the device's `harmonics` $N$); the reference grating's own carrier
    ($j = -1$) included."""
    orders = carrier_orders(device)
    k1 = device.apparent_upper_wavevectors()
    K = device.moire_wavevectors()
    c1 = binary_harmonics(device.duty1, device.harmonics)
    c2 = binary_harmonics(device.duty2, device.harmonics)

    def complex_harmonic(c, n):
        # a_0 = c_0 (the duty), a_{+-n} = c_n / 2.
        n = jnp.abs(n).astype(int)
        return jnp.where(n == 0, c[0], 0.5 * c[n])

    n = 1 + orders
    far = complex_harmonic(c1, n)[None] * gaussian_mtf(
        jnp.abs(n)[None] * jnp.linalg.norm(k1, axis=-1)[:, None], device.optics.defocus
    )
    near = complex_harmonic(c2, -orders)[None]
    frequency = jnp.linalg.norm(k1[:, None, :] + orders[None, :, None] * K[:, None, :], axis=-1)
    return far * near * gaussian_mtf(frequency, device.optics.psf_sigma / device.px_per_mm)


def carrier_orders(device: Device) -> Float[Array, " orders"]:
    """The orders $j$ of [`carrier_coefficients`][]."""
    return jnp.arange(-device.harmonics, device.harmonics, dtype=float)


class BandModel(eqx.Module):
    """[`predicted_bands`][] for one device, demodulator, model grid and reference
    wavevector, with everything that does not depend on the load precomputed: the elastomer's
    response, the reference grating's phase, the scene radiance and the band-passes
    ([`band_model`][]). An inversion evaluates the model a few times per frame on a fixed
    unit; this is what makes each evaluation cost little more than the load's own work.
    Call it with `(wrench, contact, exposure)`.

    With `carrier_pass` the prediction also holds the upper grating's carriers (module
    notes), after the moiré families."""

    mechanics: Mechanics
    x: Float[Array, "h w"]
    y: Float[Array, "h w"]
    reference_phase: Float[Array, "sets h w"]
    radiance: Float[Array, "h w"]
    beat_weights: Float[Array, "sets n"]
    mean_reference: Float[Array, ""]
    band_pass: RealBandPass
    reference_wavevector: Float[Array, "families 2"]
    carrier_pass: BasebandPass | None
    carrier_weights: Float[Array, "sets orders"] | None
    carrier_phase: Float[Array, "sets h w"] | None
    static_carrier: Complex[Array, "sets h w"] | None
    others_at_rest: Float[Array, "sets h w"] | None
    light_carrier: Complex[Array, "sets h w"] | None

    def __call__(self, wrench: Float[Array, "6"], contact: Contact, exposure: ArrayLike = 1.0) -> FringeFields:
        state = self.mechanics(wrench, contact)
        return self.of_deformation(state.displacement, state.light, exposure)

    def of_contacts(
        self, wrenches: Float[Array, "contacts 6"], contacts: Contact, exposure: ArrayLike = 1.0
    ) -> FringeFields:
        """The bands of several contacts pressing at once: `wrenches[i]` (N, N·m, about the
        origin) through the patch `contacts` holds in row `i` (a [`Contact`][] whose fields
        have a leading axis). The layer is linear, so the contacts' displacements add, and
        so does the light each scatters."""
        states = jax.vmap(self.mechanics)(wrenches, contacts)
        return self.of_deformation(jnp.sum(states.displacement, axis=0), jnp.sum(states.light, axis=0), exposure)

    def of_deformation(
        self, displacement: Float[Array, "3 h w"], light: Float[ArrayLike, "*#h #w"] = 0.0, exposure: ArrayLike = 1.0
    ) -> FringeFields:
        """The bands of any surface `displacement` `(ux, uy, w)` (mm) on the model grid, with
        the elastomer's own `light` there (the glow a contact scatters; none by default)."""
        device = self.mechanics.device
        light = jnp.broadcast_to(jnp.asarray(light, displacement.dtype), displacement.shape[1:])
        upper = upper_grating_phase(device, self.x, self.y, displacement)
        beat = upper - self.reference_phase
        # Everything of the frame below the carriers: the product over line sets of their
        # beats, and the elastomer light seen through the reference grating. The light is a
        # bump a few mm wide, so it reaches into the fringe bands too.
        low_sets = jax.vmap(line_transmission)(beat, self.beat_weights)
        transmission = jnp.prod(low_sets, axis=0)
        gain = device.optics.gain * jnp.asarray(exposure)
        low = device.optics.offset + gain * (self.radiance * transmission + self.mean_reference * light)
        fringe, brightness = self.band_pass(low)
        # The elastomer's light alone, which the reference correction must leave unscaled.
        light_fringe, _ = self.band_pass(gain * self.mean_reference * light)
        if self.carrier_pass is not None and self.light_carrier is not None:
            # The scene's light through both gratings, and the elastomer's light through the
            # reference grating alone, whose carrier sits beside the upper one's.
            elastomer = self.light_carrier * light.astype(fringe.dtype)[None]
            carriers = self._carriers(upper, beat, low_sets) * self.radiance.astype(fringe.dtype)[None] + elastomer
            cast = gain.astype(fringe.dtype)
            fringe = jnp.concatenate([fringe, self.carrier_pass(cast * carriers)])
            light_fringe = jnp.concatenate([light_fringe, self.carrier_pass(cast * elastomer)])
        return FringeFields(
            fringe=fringe, brightness=brightness, reference_wavevector=self.reference_wavevector, light=light_fringe
        )

    def _carriers(self, upper, beat, low_sets) -> Complex[Array, "sets h w"]:
        """The carriers' baseband before the radiance and the gain; the reference grating's
        own carrier only as far as the other line sets' moiré moves it away from its
        zero-load value (which the inversion removes from the measurement)."""
        assert self.carrier_weights is not None and self.carrier_phase is not None
        assert self.static_carrier is not None and self.others_at_rest is not None
        complex_dtype = _complex_dtype(upper.dtype)
        sets, orders = self.carrier_weights.shape
        # The orders j = -H .. H-1 by the complex power recurrence, as in `line_transmission`;
        # the j = -1 term is the static one, left out here.
        weights = self.carrier_weights.astype(complex_dtype)[:, :, None, None]
        middle = orders // 2
        unit = jax.lax.complex(jnp.cos(beat), jnp.sin(beat))
        series = jnp.broadcast_to(weights[:, middle], unit.shape)
        power = jnp.ones_like(unit)
        for j in range(1, middle + 1):
            power = power * unit
            if j < middle:
                series = series + weights[:, middle + j] * power
            if j > 1:
                series = series + weights[:, middle - j] * jnp.conj(power)
        own = upper - self.carrier_phase
        carrier = jax.lax.complex(jnp.cos(own), jnp.sin(own)) * series
        # Each carrier rides on the other line sets' low-frequency transmission.
        others = jnp.stack([_product_except(low_sets, s) for s in range(sets)])
        return carrier * others.astype(complex_dtype) + self.static_carrier * (others - self.others_at_rest).astype(
            complex_dtype
        )


def _complex_dtype(real_dtype):
    return jnp.complex64 if jnp.dtype(real_dtype) == jnp.float32 else jnp.complex128


def _product_except(fields: Float[Array, "sets h w"], skip: int) -> Float[Array, "h w"]:
    """The product of every line set's field but one (ones for a single set)."""
    rest = [fields[s] for s in range(fields.shape[0]) if s != skip]
    return functools.reduce(jnp.multiply, rest, jnp.ones_like(fields[0]))


def band_model(
    device: Device,
    demodulator: Demodulator,
    model_shape: tuple[int, int] = (64, 64),
    reference_wavevector: Float[Array, "families 2"] | None = None,
) -> BandModel:
    """The [`BandModel`][] of [`predicted_bands`][] (same arguments, less the load).

    A demodulator with one family per line set gets the moiré bands; one with two per line
    set (the moiré wavevectors, then the apparent upper wavevectors) gets the carriers too.
    """
    sets = device.n_sets
    if demodulator.num_families not in (sets, 2 * sets):
        raise ValueError(
            f"demodulator has {demodulator.num_families} families, device {sets} line sets "
            f"(give {sets} moiré families, or those and {sets} carriers)"
        )
    x, y = image_coordinates(device, model_shape)
    weights, mean_reference = beat_coefficients(device)
    reference_phase = reference_grating_phase(device, x, y)
    radiance = background_radiance(device, x, y)
    carrier_pass = carrier_weights = carrier_phase = static_carrier = others_at_rest = light_carrier = None
    if demodulator.num_families == 2 * sets:
        # The lens PSF and the far grating's defocus act on a carrier at its local
        # wavenumber, which a load moves by a few rad/mm: they are applied as the filters they
        # are, and the weights keep only what differs from them at each order's own wavenumber.
        def blur(wavenumber):
            return gaussian_mtf(wavenumber, device.optics.psf_sigma / device.px_per_mm) * gaussian_mtf(
                wavenumber, device.optics.defocus
            )

        carrier_pass = demodulator.baseband_pass(
            model_shape, tuple(range(sets, 2 * sets)), reference_wavevector, x.dtype, blur=blur
        )
        orders = carrier_orders(device)
        order_wavenumber = jnp.linalg.norm(
            device.apparent_upper_wavevectors()[:, None, :]
            + orders[None, :, None] * device.moire_wavevectors()[:, None, :],
            axis=-1,
        )
        carrier_weights = carrier_coefficients(device) / blur(order_wavenumber)
        # The carrier's baseband is referred to the demodulator's nominal wavevector.
        nominal = demodulator.wavevectors[sets:].astype(x.dtype)
        carrier_phase = nominal[:, 0, None, None] * x[None] + nominal[:, 1, None, None] * y[None]
        # The reference grating's carrier at zero load (the j = -1 term).
        orders = carrier_weights.shape[1]
        static_weight = carrier_weights[:, orders // 2 - 1]
        own = reference_phase - carrier_phase
        static_carrier = static_weight[:, None, None].astype(_complex_dtype(x.dtype)) * jax.lax.complex(
            jnp.cos(own), jnp.sin(own)
        )
        # The elastomer's light passes the reference grating alone: its carrier there, and the
        # other line sets' mean transmission.
        c2 = binary_harmonics(device.duty2, 1)
        k2_wavenumber = jnp.linalg.norm(device.reference_wavevectors(), axis=-1)
        light_weight = (
            0.5
            * c2[1]
            * c2[0] ** (sets - 1)
            * gaussian_mtf(k2_wavenumber, device.optics.psf_sigma / device.px_per_mm)
            / blur(k2_wavenumber)
        )
        light_carrier = light_weight[:, None, None].astype(_complex_dtype(x.dtype)) * jax.lax.complex(
            jnp.cos(own), jnp.sin(own)
        )
        at_rest = jax.vmap(line_transmission)(
            upper_grating_phase(device, x, y, jnp.zeros((3, *x.shape), x.dtype)) - reference_phase, weights
        )
        others_at_rest = jnp.stack([_product_except(at_rest, s) for s in range(sets)])
    return BandModel(
        mechanics=mechanics(device, model_shape),
        x=x,
        y=y,
        reference_phase=reference_phase,
        radiance=radiance,
        beat_weights=weights,
        mean_reference=mean_reference,
        # Phases refer to the demodulator's nominal wavevectors; the measured reference
        # wavevector only sets the normalisation.
        band_pass=demodulator.real_band_pass(model_shape, reference_wavevector, x.dtype, families=tuple(range(sets))),
        reference_wavevector=demodulator.wavevectors if reference_wavevector is None else reference_wavevector,
        carrier_pass=carrier_pass,
        carrier_weights=carrier_weights,
        carrier_phase=carrier_phase,
        static_carrier=static_carrier,
        others_at_rest=others_at_rest,
        light_carrier=light_carrier,
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
