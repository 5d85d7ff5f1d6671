r"""The forward model: wrench and contact → tractions → deformation → frame.

Two fidelities share the mechanics and illumination:

- `model` renders what the inversion assumes: truncated Fourier gratings, Gaussian
  defocus of the far grating applied per harmonic, a Gaussian lens PSF, an ideal
  rectification. Deterministic and differentiable in the wrench, the contact and every
  device parameter.
- `high` renders what a real unit adds: supersampled binary gratings (all harmonics,
  area-sampled as a sensor integrates them, whatever aliasing remains included), defocus and PSF as real convolutions, pixel integration, residual
  lens distortion, a slowly varying grating phase error from fabrication, and shot and
  read noise with 8-bit quantisation. The unit's parameters themselves may deviate from
  the nominal design; that is the caller's choice of `device`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ._contact import Contact, grid_shape, surface_grid, surface_tractions, SurfaceGrid, traction_spectrum
from ._device import Device
from ._elastomer import layer_response, LayerResponse
from ._optics import (
    background_radiance,
    binary_harmonics,
    camera_response,
    contact_light,
    gaussian_blur_fft,
    gaussian_mtf,
    image_coordinates,
    line_transmission,
    separable_gaussian_blur,
)


class Deformation(eqx.Module):
    """Mechanical state of the contact surface on a [`SurfaceGrid`][].

    `displacement` is `(ux, uy, w)` in mm (w > 0 into the sensor), `tractions` is
    `(tx, ty, p)` in MPa, `light` the brightness scattered in the elastomer (glow and rim).
    """

    grid: SurfaceGrid
    tractions: Float[Array, "3 h w"]
    displacement: Float[Array, "3 h w"]
    light: Float[Array, "h w"]


class Mechanics(eqx.Module):
    """The contact surface's grid and the elastomer's response on it: everything
    [`deformation`][] needs besides the load, built once per device and grid
    ([`mechanics`][]). Call it with a wrench and a [`Contact`][] for the [`Deformation`][]."""

    device: Device
    grid: SurfaceGrid
    response: LayerResponse

    def __call__(self, wrench: Float[Array, "6"], contact: Contact) -> Deformation:
        tractions = surface_tractions(wrench, contact, self.grid)
        light = contact_light(self.device, tractions[2], wrench[2], contact, self.grid)
        displacement = self.response.displacement_of_spectrum(traction_spectrum(wrench, contact, self.grid))
        return Deformation(grid=self.grid, tractions=tractions, displacement=displacement, light=light)


def mechanics(device: Device, shape: tuple[int, int]) -> Mechanics:
    """The [`Mechanics`][] of `device` on a surface grid of `shape` cells."""
    grid = surface_grid(shape, device.px_per_mm, (device.height, device.width), device.a, device.Z)
    e = device.elastomer
    return Mechanics(device=device, grid=grid, response=layer_response(shape, grid.spacing, e.E, e.nu, e.thickness))


def deformation(device: Device, wrench: Float[Array, "6"], contact: Contact, shape: tuple[int, int]) -> Deformation:
    """Solve the elastomer for `wrench` applied through `contact`, on a grid of `shape` cells."""
    return mechanics(device, shape)(wrench, contact)


def grating_phases(
    device: Device,
    x: Float[Array, "h w"],
    y: Float[Array, "h w"],
    displacement: Float[Array, "3 h w"],
) -> tuple[Float[Array, "sets h w"], Float[Array, "sets h w"]]:
    r"""Phases of every line set of the upper and reference grating at rectified points (x, y).

    Upper grating: $\varphi_1 = k_1 \cdot (X (1 - w/(Z + a)) - u) + \phi_1$ with
    $X = x (Z + a)/Z$ the surface point on the undeformed ray; reference grating:
    $\varphi_2 = k_2 \cdot x + \phi_2$.
    """
    return upper_grating_phase(device, x, y, displacement), reference_grating_phase(device, x, y)


def upper_grating_phase(
    device: Device, x: Float[Array, "h w"], y: Float[Array, "h w"], displacement: Float[Array, "3 h w"]
) -> Float[Array, "sets h w"]:
    r"""The upper grating's phase $\varphi_1$ of [`grating_phases`][]: the only one a load moves.

    The grating is printed on the elastomer's material, so the camera ray through $x$ sees
    the material point $X_0$ that the load carried to where the ray meets the surface,
    $X_s = x\,(Z + a - w)/Z$: $X_s = X_0 + u(X_0)$. The displacement is known at the
    ray's points, not at the material ones; $X_0 = X_s - (I + \nabla u)^{-1} u$ inverts the
    map exactly where $u$ is affine and to second order in $u$ elsewhere. The first-order
    $X_0 = X_s - u(X_s)$ misses $(u\cdot\nabla) u$, which under a twist of a few mN·m
    (0.3 mm of slip, rotating the pad by 0.1 rad) is 0.03 mm, half a radian of phase.
    `displacement` is sampled at the points (x, y), which must form a smooth grid.
    """
    ux, uy, w = displacement
    magnification = device.surface_magnification
    shrink = 1 - w / (device.Z + device.a)
    material_x, material_y = _material_offset(ux, uy, x * magnification, y * magnification)
    X = x * magnification * shrink - material_x
    Y = y * magnification * shrink - material_y
    k1 = device.upper_wavevectors()
    return k1[:, 0, None, None] * X[None] + k1[:, 1, None, None] * Y[None] + device.optics.phase1[:, None, None]


def _material_offset(
    ux: Float[Array, "h w"], uy: Float[Array, "h w"], X: Float[Array, "h w"], Y: Float[Array, "h w"]
) -> tuple[Float[Array, "h w"], Float[Array, "h w"]]:
    """$(I + \nabla u)^{-1} u$ on a smooth grid of surface points (X, Y), by central differences."""
    # Derivatives along the grid's columns (j) and rows (i), then to (X, Y) through the
    # grid's own 2x2 Jacobian (a regular grid, or one bent by lens distortion).
    Xj, Xi = jnp.gradient(X, axis=1), jnp.gradient(X, axis=0)
    Yj, Yi = jnp.gradient(Y, axis=1), jnp.gradient(Y, axis=0)
    det = Xj * Yi - Xi * Yj

    def spatial(u):
        uj, ui = jnp.gradient(u, axis=1), jnp.gradient(u, axis=0)
        return (uj * Yi - ui * Yj) / det, (ui * Xj - uj * Xi) / det

    uxX, uxY = spatial(ux)
    uyX, uyY = spatial(uy)
    jacobian_det = (1 + uxX) * (1 + uyY) - uxY * uyX
    return ((1 + uyY) * ux - uxY * uy) / jacobian_det, ((1 + uxX) * uy - uyX * ux) / jacobian_det


def reference_grating_phase(device: Device, x: Float[Array, "h w"], y: Float[Array, "h w"]) -> Float[Array, "sets h w"]:
    r"""The reference grating's phase $\varphi_2$ of [`grating_phases`][]."""
    k2 = device.reference_wavevectors()
    return k2[:, 0, None, None] * x[None] + k2[:, 1, None, None] * y[None] + device.optics.phase2[:, None, None]


def _upsample(field: Float[Array, "*c h w"], shape: tuple[int, int]) -> Float[Array, "*c H W"]:
    # Cubic, not linear: the upper grating multiplies the displacement by |k1| (18
    # rad/mm on Mid), so linear interpolation's curvature error h^2 u''/8 near a contact shows
    # as a fringe-phase bias. From a 128 grid it moved pixels by 0.05 of full scale and
    # biased the recovered shear by 1-2% of range; cubic cuts that threefold.
    return jax.image.resize(field, (*field.shape[:-2], *shape), method="cubic")


def render_deformed(
    device: Device,
    displacement: Float[Array, "3 h w"],
    light: Float[Array, "h w"],
    exposure: ArrayLike = 1.0,
) -> Float[Array, "h w"]:
    """The `model`-fidelity frame for a given surface displacement and elastomer light.

    `displacement` `(ux, uy, w)` (mm) and `light` are sampled at the surface point on
    the undeformed ray of every pixel.
    """
    radiance = separable_gaussian_blur(scene_radiance(device, displacement, light), device.optics.psf_sigma)
    return camera_response(device, radiance, exposure)


def scene_radiance(
    device: Device, displacement: Float[Array, "3 h w"], light: Float[Array, "h w"]
) -> Float[Array, "h w"]:
    """Radiance behind the reference grating at every pixel, before the lens PSF and the camera.

    Arguments as for [`render_deformed`][].
    """
    x, y = image_coordinates(device)
    phase1, phase2 = grating_phases(device, x, y, displacement)
    # The far grating is out of focus: each harmonic is attenuated by the defocus MTF.
    k1_apparent = jnp.linalg.norm(device.apparent_upper_wavevectors()[0])
    harmonic = jnp.arange(device.harmonics + 1, dtype=float)
    c1 = binary_harmonics(device.duty1, device.harmonics) * gaussian_mtf(harmonic * k1_apparent, device.optics.defocus)
    c2 = binary_harmonics(device.duty2, device.harmonics)
    upper = jnp.prod(jax.vmap(line_transmission, in_axes=(0, None))(phase1, c1), axis=0)
    reference = jnp.prod(jax.vmap(line_transmission, in_axes=(0, None))(phase2, c2), axis=0)
    return reference * (background_radiance(device, x, y) * upper + light)


@eqx.filter_jit
def _mechanics_shape(device: Device, shape: tuple[int, int] | None) -> tuple[int, int]:
    return grid_shape((device.height, device.width), 256) if shape is None else shape


def render_frame(
    device: Device,
    wrench: Float[Array, "6"],
    contact: Contact,
    *,
    exposure: ArrayLike = 1.0,
    mechanics_shape: tuple[int, int] | None = None,
) -> Float[Array, "h w"]:
    """Render the `model`-fidelity frame (float, unclipped, noise-free) of `device` under `wrench`.

    **Arguments:**

    - `device`: the sensor [`Device`][].
    - `wrench`: `[fx, fy, fz, tx, ty, tz]` in N and N·m (moirejax wrench convention).
    - `contact`: the [`Contact`][] patch carrying the load.
    - `exposure`: multiplies the radiance (an exposure or illumination change).
    - `mechanics_shape`: grid on which the elastomer is solved, then interpolated
      (cubic) to the pixels; `None` for 256 cells along the image's longer side
      ([`grid_shape`][]). The displacement is smooth on the scale of the layer
      thickness, but a small contact's edge is not: 256 x 256 (0.16 mm on
      the Mid design's contact surface) stays within 0.003 of full scale of a 1024 x 1024 solve, where
      128 x 128 strayed by 0.017 (0.05 with linear interpolation) beside a 2.6 mm contact.

    **Returns:** the frame, shape `(device.height, device.width)`, in camera units (about 0..1).
    """
    state = deformation(device, wrench, contact, _mechanics_shape(device, mechanics_shape))
    shape = (device.height, device.width)
    return render_deformed(device, _upsample(state.displacement, shape), _upsample(state.light, shape), exposure)


class HighFidelity(eqx.Module):
    """What a real unit adds on top of its physical parameters (see the module docstring).

    **Arguments:**

    - `supersample`: samples per pixel along each axis for the binary gratings.
    - `distortion`: residual radial distortion left after rectification: a pixel at
      radius r actually sees the point at `r (1 + distortion (r/r_corner)^2)`.
    - `phase_error`: RMS (rad) of a smooth random phase error of the upper grating
      (laser-cut slits are not perfectly periodic; 0.05 rad is about 3 um of slit
      placement error at the Mid pitch). It interacts with the band-limited reference
      correction of the inversion; at 0.15 rad the shear error grows several-fold.
    - `phase_error_scale`: correlation length of that error (mm).
    - `full_well`: electrons at pixel value 1 (shot noise).
    - `read_noise`: read noise (electrons).
    - `bit_depth`: quantisation of the output.
    """

    supersample: int = eqx.field(static=True, default=2)
    distortion: float = 0.004
    phase_error: float = 0.05
    phase_error_scale: float = 6.0
    full_well: float = 4000.0
    read_noise: float = 4.0
    bit_depth: int = eqx.field(static=True, default=8)


def _wrap(phase: Array) -> Array:
    return (phase + jnp.pi) % (2 * jnp.pi) - jnp.pi


def _area_sampled_line(phase: Array, duty: ArrayLike, width: ArrayLike) -> Array:
    r"""A binary line set (open where the wrapped phase is within $\pi d$ of a slit
    centre) averaged over a sample `width` wide in phase.

    Point-sampling a binary grating aliases its harmonics into the moiré band far more
    than a camera does, since a sensor integrates light over its area. The average is
    exact through the integral of the square wave, $d\,t + P(t)$ with the periodic
    $P(t) = \mathrm{clip}(t, -\pi d, \pi d) - d\,t$ on $(-\pi, \pi]$.
    """
    duty = jnp.asarray(duty)

    def periodic(t):
        t = _wrap(t)
        return jnp.clip(t, -jnp.pi * duty, jnp.pi * duty) - duty * t

    half = 0.5 * width
    return duty + (periodic(phase + half) - periodic(phase - half)) / width


def _smooth_random_field(key: PRNGKeyArray, shape: tuple[int, int], spacing: Array, scale: float) -> Array:
    noise = jr.normal(key, shape)
    field = gaussian_blur_fft(noise, scale, spacing)
    return field / (jnp.std(field) + 1e-12)


@eqx.filter_jit
def render_frame_high(
    key: PRNGKeyArray,
    device: Device,
    wrench: Float[Array, "6"],
    contact: Contact,
    fidelity: HighFidelity = HighFidelity(),
    *,
    exposure: ArrayLike = 1.0,
    mechanics_shape: tuple[int, int] | None = None,
    fabrication_key: PRNGKeyArray | None = None,
) -> Float[Array, "h w"]:
    """Render a `high`-fidelity frame, noisy and quantised to `fidelity.bit_depth` (values in [0, 1]).

    `fabrication_key` fixes the unit's grating phase error (the same for every frame of
    one unit); `key` draws the per-frame noise.
    """
    state = deformation(device, wrench, contact, _mechanics_shape(device, mechanics_shape))
    return render_deformed_high(
        key, device, state.displacement, state.light, fidelity, exposure=exposure, fabrication_key=fabrication_key
    )


def render_deformed_high(
    key: PRNGKeyArray,
    device: Device,
    displacement: Float[Array, "3 mh mw"],
    light: Float[Array, "mh mw"],
    fidelity: HighFidelity = HighFidelity(),
    *,
    exposure: ArrayLike = 1.0,
    fabrication_key: PRNGKeyArray | None = None,
) -> Float[Array, "h w"]:
    """The `high`-fidelity frame of a surface deformation given on a mechanics grid covering
    the image (cell-centred, as [`surface_grid`][] lays it out): `displacement` `(ux, uy, w)`
    (mm) and the elastomer's `light`. [`render_frame_high`][] renders a wrench's; any
    traction field's deformation renders through here.
    """
    s = fidelity.supersample
    H, W = device.height * s, device.width * s
    # Sample points of the supersampled pixels, then distort them as the residual
    # lens distortion would.
    x, y = image_coordinates(device, (H, W))
    corner2 = (device.width / 2 / device.px_per_mm) ** 2 + (device.height / 2 / device.px_per_mm) ** 2
    factor = 1 + fidelity.distortion * (x**2 + y**2) / corner2
    x, y = x * factor, y * factor
    # Mechanics fields at the distorted points (map_coordinates in grid index space).
    mh, mw = displacement.shape[1:]
    step_x = device.width / mw / device.px_per_mm
    step_y = device.height / mh / device.px_per_mm
    cols = x / step_x + (mw - 1) / 2
    rows = (mh - 1) / 2 - y / step_y
    sample = jax.vmap(lambda f: jax.scipy.ndimage.map_coordinates(f, [rows, cols], order=1, mode="nearest"))
    displacement = sample(displacement)
    light = sample(light[None])[0]
    phase1, phase2 = grating_phases(device, x, y, displacement)
    fab_key = jr.PRNGKey(0) if fabrication_key is None else fabrication_key
    error = _smooth_random_field(fab_key, (H, W), 1 / (device.px_per_mm * s), fidelity.phase_error_scale)
    phase1 = phase1 + fidelity.phase_error * error[None]
    # Each supersample integrates over its own width: |k| times the sample pitch in phase.
    sample = 1 / (device.px_per_mm * s)
    width1 = jnp.linalg.norm(device.apparent_upper_wavevectors(), axis=-1)[:, None, None] * sample
    width2 = jnp.linalg.norm(device.reference_wavevectors(), axis=-1)[:, None, None] * sample
    upper = jnp.prod(_area_sampled_line(phase1, device.duty1, width1), axis=0)
    reference = jnp.prod(_area_sampled_line(phase2, device.duty2, width2), axis=0)
    # Defocus of the far grating as a real blur of the binary pattern.
    upper = separable_gaussian_blur(upper, device.optics.defocus * device.px_per_mm * s, radius=4)
    radiance = reference * (background_radiance(device, x, y) * upper + light)
    radiance = separable_gaussian_blur(radiance, device.optics.psf_sigma * s, radius=3 * s)
    # Pixel integration: box average of the supersamples.
    radiance = radiance.reshape(device.height, s, device.width, s).mean(axis=(1, 3))
    return camera_noise(key, camera_response(device, radiance, exposure), fidelity)


def camera_noise(key: PRNGKeyArray, clean: Float[Array, "h w"], fidelity: HighFidelity) -> Float[Array, "h w"]:
    """The camera of a `high`-fidelity frame on a noise-free one: shot and read noise at
    `fidelity.full_well` and `fidelity.read_noise`, then quantisation to `fidelity.bit_depth`."""
    electrons = jnp.clip(clean, 0, None) * fidelity.full_well
    # Shot and read noise together: Gaussian with the Poisson variance plus the read variance.
    noisy = electrons + jnp.sqrt(electrons + fidelity.read_noise**2) * jr.normal(key, electrons.shape)
    levels = 2**fidelity.bit_depth - 1
    return jnp.clip(jnp.round(noisy / fidelity.full_well * levels), 0, levels) / levels


def pixel_noise_variance(frame: Float[Array, "h w"], noise: HighFidelity) -> Float[Array, "h w"]:
    r"""Variance of each pixel (pixel units, 1 = full well) under the camera noise model.

    Shot noise (variance = electrons), read noise and uniform quantisation to
    `bit_depth` bits, as `render_frame_high` draws them:
    $$\sigma^2 = \frac{v N_\mathrm{fw} + \sigma_\mathrm{read}^2}{N_\mathrm{fw}^2} + \frac{1}{12 (2^b - 1)^2}.$$
    """
    electrons = jnp.clip(frame, 0.0, 1.0) * noise.full_well
    levels = 2**noise.bit_depth - 1
    return (electrons + noise.read_noise**2) / noise.full_well**2 + 1 / (12 * levels**2)


def noise_as_arrays(noise: HighFidelity | None, dtype) -> HighFidelity:
    """`noise` (the defaults for `None`) with its noise levels as arrays of `dtype`.

    Floats in a Module are static to `filter_jit`: arrays avoid a recompile per noise level.
    """
    noise = HighFidelity() if noise is None else noise
    return eqx.tree_at(
        lambda n: (n.full_well, n.read_noise),
        noise,
        (jnp.asarray(noise.full_well, dtype), jnp.asarray(noise.read_noise, dtype)),
    )
