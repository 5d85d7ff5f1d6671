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

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from ._contact import Contact
from ._device import Device
from ._observables import Demodulator, FringeFields
from ._optics import background_radiance, binary_harmonics, gaussian_mtf, image_coordinates
from ._render import deformation, grating_phases


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
    """
    if demodulator.num_families != device.n_sets:
        raise ValueError(f"demodulator has {demodulator.num_families} families, device {device.n_sets} line sets")
    state = deformation(device, wrench, contact, model_shape)
    x, y = image_coordinates(device, model_shape)
    phase1, phase2 = grating_phases(device, x, y, state.displacement)
    weights, mean_reference = beat_coefficients(device)
    harmonic = jnp.arange(device.harmonics + 1, dtype=float)
    beats = jnp.cos(harmonic[None, :, None, None] * (phase1 - phase2)[:, None])
    # Everything of the frame below the carriers: the product over line sets of their
    # beats, and the elastomer light seen through the reference grating. The light is a
    # bump a few mm wide, so it reaches into the fringe bands too.
    transmission = jnp.prod(jnp.einsum("sn,snhw->shw", weights, beats), axis=0)
    gain = device.optics.gain * jnp.asarray(exposure)
    low = device.optics.offset + gain * (
        background_radiance(device, x, y) * transmission + mean_reference * state.light
    )
    # A real field F holds a e^{iK.x} + conj; F e^{-iK.x} puts a at baseband and the
    # conjugate at -2K, which the band-pass removes. Phases refer to the demodulator's
    # nominal wavevectors; the measured reference wavevector only sets the normalisation.
    K = demodulator.wavevectors
    shift = -(K[:, 0, None, None] * x[None] + K[:, 1, None, None] * y[None])
    baseband = jax.lax.complex(low[None] * jnp.cos(shift), low[None] * jnp.sin(shift))
    return FringeFields(
        fringe=demodulator.filter_baseband(baseband, reference_wavevector),
        brightness=demodulator.filter_brightness(low),
        reference_wavevector=K if reference_wavevector is None else reference_wavevector,
    )


def fringe_phase(fields: FringeFields) -> Float[Array, "families m n"]:
    """Wrapped phase of each fringe family."""
    return jnp.angle(fields.fringe)


def complex_ratio(
    numerator: Complex[Array, "*s"], denominator: Complex[Array, "*s"], floor: float = 1e-6
) -> Complex[Array, "*s"]:
    """`numerator / denominator` with the denominator's magnitude floored (no division by zero)."""
    safe = jnp.where(jnp.abs(denominator) > floor, denominator, floor)
    return numerator / safe
