r"""Gratings, illumination and camera: from surface deformation to radiance and pixels.

Each grating is a set of line sets (one for line gratings, two for crossed grids of
open squares); a line set with duty cycle $d$ has the binary transmission
$$L(\varphi) = d + \sum_{n \ge 1} c_n \cos(n\varphi), \qquad c_n = \frac{2\sin(\pi n d)}{\pi n},$$
truncated at `harmonics` terms in the model. The reference grating is seen directly;
the upper grating, on the contact surface, is seen through parallax: the camera ray
through reference-plane point $x$ meets it at $x (Z + a - w)/Z$, where $w$ is the local
compression, and reads the grating at the material point displaced by $u$.

Light from the scene passes both gratings; light scattered inside the elastomer (the
pressure glow and the LED contact rim) passes the reference grating only.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._contact import Contact, SurfaceGrid
from ._device import Device
from ._fourier import wavenumber_grid


def binary_harmonics(duty: ArrayLike, harmonics: int) -> Float[Array, " n"]:
    r"""Fourier cosine coefficients $(d, c_1, \dots, c_N)$ of a binary grating of duty `duty`."""
    n = jnp.arange(1, harmonics + 1, dtype=float)
    duty = jnp.asarray(duty)
    return jnp.concatenate([duty[None], 2 * jnp.sin(jnp.pi * n * duty) / (jnp.pi * n)])


def line_transmission(phase: Float[Array, "*s"], coefficients: Float[Array, " n"]) -> Float[Array, "*s"]:
    r"""$L(\varphi) = c_0 + \sum_n c_n \cos(n \varphi)$, by the complex power recurrence.

    One complex exponential per pixel; higher harmonics are powers of it, which is
    several times faster than one cosine per harmonic.
    """
    carrier = jax.lax.complex(jnp.cos(phase), jnp.sin(phase))
    total = jnp.full(phase.shape, coefficients[0], dtype=phase.dtype)
    power = carrier
    for c in coefficients[1:]:
        total = total + c * power.real
        power = power * carrier
    return total


def gaussian_mtf(frequency: ArrayLike, sigma: ArrayLike) -> Array:
    """Modulation transfer of a Gaussian blur of std `sigma` at angular `frequency` (same length units)."""
    return jnp.exp(-0.5 * (jnp.asarray(frequency) * jnp.asarray(sigma)) ** 2)


def image_coordinates(
    device: Device, shape: tuple[int, int] | None = None
) -> tuple[Float[Array, "h w"], Float[Array, "h w"]]:
    """Rectified-plane coordinates (mm) of the cell centres of a grid covering the image.

    With `shape=None` the grid is the pixel grid; a coarser `shape` has cells of
    `height/shape[0]` pixels, centred as `jax.image.resize` centres them.
    """
    h, w = (device.height, device.width) if shape is None else shape
    step_x = device.width / w / device.px_per_mm
    step_y = device.height / h / device.px_per_mm
    x = (jnp.arange(w, dtype=float) - (w - 1) / 2) * step_x
    y = ((h - 1) / 2 - jnp.arange(h, dtype=float)) * step_y
    X, Y = jnp.meshgrid(x, y, indexing="xy")
    return X, Y


def background_radiance(device: Device, x: Float[Array, "h w"], y: Float[Array, "h w"]) -> Float[Array, "h w"]:
    """Scene radiance through open gratings, with a quadratic vignetting fall-off to the corners."""
    corner2 = (device.width / 2 / device.px_per_mm) ** 2 + (device.height / 2 / device.px_per_mm) ** 2
    return device.optics.background * (1 - device.optics.vignetting * (x**2 + y**2) / corner2)


def gaussian_blur_fft(field: Float[Array, "h w"], sigma: ArrayLike, spacing: ArrayLike) -> Float[Array, "h w"]:
    """Periodic Gaussian blur of std `sigma` (mm) of a field sampled at `spacing` (mm)."""
    h, w = field.shape
    # rfft2 keeps columns 0..w/2; the transfer is even in k, so only |k| matters.
    kx, ky = wavenumber_grid((h, w), spacing, real=True)
    # From |k|^2 directly: sqrt at k = 0 would make the derivative in `spacing` NaN.
    transfer = jnp.exp(-0.5 * jnp.asarray(sigma) ** 2 * (ky[:, None] ** 2 + kx[None, :] ** 2))
    spectrum = jnp.fft.rfft2(field)
    return jnp.fft.irfft2(spectrum * transfer.astype(spectrum.dtype), s=(h, w))


def contact_light(
    device: Device,
    pressure: Float[Array, "h w"],
    normal_force: Float[Array, ""],
    contact: Contact,
    grid: SurfaceGrid,
) -> Float[Array, "h w"]:
    r"""Light scattered inside the elastomer at a contact, on the surface grid.

    The glow $\kappa (P * h)$ follows the blurred pressure; the LED rim is a ring at the
    contact edge whose brightness grows as $\sqrt{F_z}$ (its area grows with the radius).
    """
    optics = device.optics
    glow = optics.glow_gain * gaussian_blur_fft(pressure, optics.glow_width, grid.spacing)
    rho = jnp.sqrt((grid.X - contact.x0) ** 2 + (grid.Y - contact.y0) ** 2 + 1e-12)
    ring = jnp.exp(-0.5 * ((rho - contact.radius) / optics.rim_width) ** 2)
    pressing = jnp.maximum(normal_force, 0.0)
    # ~sqrt(Fz) for firm presses, zero without contact, finite slope at zero.
    rim = optics.rim_gain * pressing / jnp.sqrt(pressing + 0.05) * ring
    return glow + rim


def camera_response(device: Device, radiance: Float[Array, "h w"], exposure: ArrayLike = 1.0) -> Float[Array, "h w"]:
    """Pixel value `offset + gain * (exposure * radiance) ** (1/gamma)` (not clipped)."""
    optics = device.optics
    scaled = jnp.asarray(exposure) * radiance
    # Truncated Fourier gratings undershoot slightly below zero (Gibbs). A sign-preserving
    # power keeps the response smooth there, and exactly linear for gamma = 1.
    return optics.offset + optics.gain * jnp.sign(scaled) * jnp.abs(scaled) ** (1 / optics.gamma)


def separable_gaussian_blur(image: Float[Array, "h w"], sigma_px: ArrayLike, radius: int = 3) -> Float[Array, "h w"]:
    """Gaussian blur of std `sigma_px` pixels with a small separable kernel (edge-replicated)."""
    offsets = jnp.arange(-radius, radius + 1, dtype=image.dtype)
    kernel = jnp.exp(-0.5 * (offsets / jnp.maximum(jnp.asarray(sigma_px, image.dtype), 1e-3)) ** 2)
    kernel = kernel / jnp.sum(kernel)
    padded = jnp.pad(image, radius, mode="edge")
    h, w = image.shape
    rows = sum(kernel[i] * padded[i : i + h, :] for i in range(2 * radius + 1))
    return sum(kernel[j] * rows[:, j : j + w] for j in range(2 * radius + 1))
