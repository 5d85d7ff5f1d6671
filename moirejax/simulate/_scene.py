r"""Scenes above the sensor: what the camera sees through both gratings before contact.

The sensor is see-through. Light from an object above the contact surface crosses the
upper grating, the elastomer and the reference grating on its way to the camera, so a
vision frame is the scene multiplied by the gratings' transmission, with the optics the
tactile frames use: parallax of the upper grating, defocus of the far grating, the lens
PSF, vignetting, shot and read noise, 8 bits, in colour.

Geometry, with the pinhole of [`Device`][] (reference grating at $Z$, contact surface at
$Z + a$): a point of an object at height $h$ above the surface, at $(X, Y)$ in the wrench
frame, is seen at $x = X\,Z/(Z + a + h)$ in the rectified (reference) plane. The layers
are thin: refraction in the elastomer is not modelled.

Defocus: the lens is focused on the reference grating, and
[`Optics.defocus`][moirejax.Optics] is the blur (reference plane, mm) of the upper grating,
$a$ beyond focus. A thin lens blurs a point at distance $D$ into a disc of radius
$A\,(D - Z)/D$ in the focal plane ($A$ the aperture radius), so with the same aperture an
object at height $h$ is blurred by
$$\sigma(h) = \sigma_\mathrm{defocus}\,\frac{(a + h)/(Z + a + h)}{a/(Z + a)},$$
which grows with height and saturates at $\sigma_\mathrm{defocus} (Z + a)/a$ far away.
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from ..physics import (
    background_radiance,
    camera_noise,
    camera_response,
    Device,
    gaussian_blur_fft,
    HighFidelity,
    image_coordinates,
    scene_radiance,
    separable_gaussian_blur,
)


SCENE_SHAPES = ("disc", "ring", "rectangle", "texture")
# Images that ship inside scikit-image (no download), used as scene textures.
SCENE_TEXTURES = ("astronaut", "chelsea", "coffee", "rocket", "camera")
# A neutral grey behind the object: what an empty frame shows.
BACKDROP_RGB = (0.8, 0.8, 0.8)


def _scalar(x) -> Array:
    return jnp.asarray(x, dtype=float)


def _rgb(x) -> Array:
    return jnp.asarray(x, dtype=float).reshape(-1)


def _image(x) -> Array | None:
    return None if x is None else jnp.asarray(x, dtype=float)


class SceneObject(eqx.Module):
    """One object above the sensor, at a pose in the wrench frame. Build it with
    [`scene_disc`][], [`scene_ring`][], [`scene_rectangle`][] or [`scene_texture`][].

    **Arguments:**

    - `shape`: one of `"disc"`, `"ring"`, `"rectangle"`, `"texture"` (static).
    - `x`, `y`: centre (mm) in the wrench frame (x right, y up, origin on the image centre).
    - `yaw_deg`: rotation (degrees) from +x towards +y.
    - `height`: distance (mm) above the contact surface; 0 lies on it.
    - `length`: outer diameter of a disc or ring, long side of a rectangle, width of a
        texture (mm).
    - `width`: hole diameter of a ring, short side of a rectangle, height of a texture (mm);
        0 for a disc.
    - `rgb`: colour of a shape, linear RGB in [0, 1].
    - `image`: a texture's RGB image `(th, tw, 3)` in [0, 1]; `None` for shapes.
    """

    shape: str = eqx.field(static=True)
    x: Float[Array, ""] = eqx.field(converter=_scalar)
    y: Float[Array, ""] = eqx.field(converter=_scalar)
    yaw_deg: Float[Array, ""] = eqx.field(converter=_scalar)
    height: Float[Array, ""] = eqx.field(converter=_scalar)
    length: Float[Array, ""] = eqx.field(converter=_scalar)
    width: Float[Array, ""] = eqx.field(converter=_scalar)
    rgb: Float[Array, "3"] = eqx.field(converter=_rgb)
    image: Float[Array, "th tw 3"] | None = eqx.field(converter=_image, default=None)

    def __check_init__(self):
        if self.shape not in SCENE_SHAPES:
            raise ValueError(f"scene shape must be one of {SCENE_SHAPES}, got {self.shape!r}")
        if (self.image is None) != (self.shape != "texture"):
            raise ValueError(
                "a texture needs an image and a shape none: build scenes with scene_disc/ring/rectangle/texture"
            )
        if self.rgb.shape != (3,):
            raise ValueError(f"rgb needs three values in [0, 1], got shape {self.rgb.shape}")
        values = (self.height, self.length, self.width, self.rgb)
        if not any(isinstance(v, jax.core.Tracer) for v in values):
            if not float(self.height) >= 0:
                raise ValueError(f"scene height must be >= 0 mm above the surface, got {float(self.height)}")
            if not float(self.length) > 0:
                raise ValueError(f"scene length must be positive, got {float(self.length)} mm")
            if self.shape == "texture" and not float(self.width) > 0:
                raise ValueError(f"a texture's height must be positive, got {float(self.width)} mm")
            if self.shape != "texture" and not 0 <= float(self.width) < float(self.length):
                raise ValueError(
                    f"{self.shape} width must be in [0, length={float(self.length)}) mm, got {float(self.width)}"
                )
            if not bool(jnp.all((self.rgb >= 0) & (self.rgb <= 1))):
                raise ValueError(f"rgb must lie in [0, 1], got {np.asarray(self.rgb).tolist()}")


def scene_disc(x: float, y: float, diameter: float, *, height: float = 0.0, rgb=(0.1, 0.7, 0.2)) -> SceneObject:
    """A flat disc of `diameter` mm and colour `rgb`, centred at (`x`, `y`) mm, `height` mm above the surface."""
    return SceneObject("disc", x, y, 0.0, height, diameter, 0.0, rgb)


def scene_ring(
    x: float, y: float, diameter: float, hole: float, *, height: float = 0.0, rgb=(0.1, 0.7, 0.2)
) -> SceneObject:
    """A flat ring (a cap seen from below, an O-ring) of outer `diameter` and inner `hole` diameter (mm)."""
    return SceneObject("ring", x, y, 0.0, height, diameter, hole, rgb)


def scene_rectangle(
    x: float, y: float, length: float, width: float, *, yaw_deg: float = 0.0, height: float = 0.0, rgb=(0.8, 0.2, 0.1)
) -> SceneObject:
    """A flat `length` x `width` rectangle (mm), its long side at `yaw_deg` from +x."""
    return SceneObject("rectangle", x, y, yaw_deg, height, length, width, rgb)


def scene_texture(
    image: str | np.ndarray, length: float, *, x: float = 0.0, y: float = 0.0, yaw_deg: float = 0.0, height: float = 0.0
) -> SceneObject:
    """A flat picture `length` mm wide (its height follows the image's aspect) at a pose.

    **Arguments:**

    - `image`: an RGB (or gray) image in [0, 1] or uint8, or the name of one of the images
        that ship inside scikit-image (`SCENE_TEXTURES`: `"astronaut"`, `"chelsea"`, `"coffee"`,
        `"rocket"`, `"camera"`).
    - `length`: its width (mm) in the object plane.
    - `x`, `y`, `yaw_deg`, `height`: its pose, as for [`SceneObject`][].
    """
    if isinstance(image, str):
        if image not in SCENE_TEXTURES:
            raise ValueError(f"unknown scene texture {image!r}; choose from {', '.join(SCENE_TEXTURES)}")
        import skimage.data  # imported on demand: it loads slowly

        image = getattr(skimage.data, image)()
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, axis=-1)
    if arr.ndim != 3 or arr.shape[-1] not in (3, 4) or min(arr.shape[:2]) < 2:
        raise ValueError(f"a texture must be an (h, w) or (h, w, 3) image, got shape {arr.shape}")
    arr = arr[..., :3]
    scaled = arr / np.iinfo(arr.dtype).max if np.issubdtype(arr.dtype, np.integer) else arr.astype(np.float64)
    tex_height = length * arr.shape[0] / arr.shape[1]
    return SceneObject("texture", x, y, yaw_deg, height, length, tex_height, (0.0, 0.0, 0.0), scaled)


def scene_defocus(device: Device, height: ArrayLike) -> Float[Array, ""]:
    r"""Gaussian blur (mm, reference plane) of an object `height` mm above the contact surface.

    $\sigma(h) = \sigma_\mathrm{defocus} \frac{(a + h)/(Z + a + h)}{a/(Z + a)}$: the thin
    lens's blur of a point at distance $D = Z + a + h$ from a camera focused at $Z$, with
    the aperture that blurs the upper grating by [`Optics.defocus`][moirejax.Optics].
    """
    h = jnp.asarray(height, dtype=float)
    a, Z = device.a, device.Z
    return device.optics.defocus * ((a + h) / (Z + a + h)) / (a / (Z + a))


def scene_magnification(device: Device, height: ArrayLike) -> Float[Array, ""]:
    """Millimetres in the object plane per millimetre of the rectified plane, `(Z + a + h) / Z`."""
    return (device.Z + device.a + jnp.asarray(height, dtype=float)) / device.Z


class SceneFrame(eqx.Module):
    """A see-through frame of a scene and its ground truth.

    **Fields:**

    - `frame`: `(h, w, 3)` BGR frame in [0, 1] as a colour camera delivers it (noisy,
        quantised), channels in OpenCV's order like the live frame sources.
    - `grating_free`: `(h, w, 3)` BGR, the same scene through the same optics with each
        grating replaced by its mean transmission: noise-free, unquantised. What restoration
        should recover.
    - `scene`: the [`SceneObject`][] (its pose is the localisation's truth), or `None` for
        an empty frame.
    """

    frame: Float[Array, "h w 3"]
    grating_free: Float[Array, "h w 3"]
    scene: SceneObject | None


def _coverage(scene: SceneObject, u: Array, v: Array, pixel: Array) -> Array:
    """Area fraction of a sample (`pixel` mm wide in the object plane) inside a shape, from its signed distance."""
    if scene.shape == "rectangle":
        distance = jnp.maximum(jnp.abs(u) - scene.length / 2, jnp.abs(v) - scene.width / 2)
    else:
        rho = jnp.sqrt(u**2 + v**2)
        distance = rho - scene.length / 2
        if scene.shape == "ring":
            distance = jnp.maximum(distance, scene.width / 2 - rho)
    return jnp.clip(0.5 - distance / pixel, 0.0, 1.0)


def _scene_rgb(
    device: Device, scene: SceneObject | None, backdrop: Array, x: Array, y: Array, pixel: ArrayLike
) -> Array:
    """`(3, H, W)` linear RGB of the scene at rectified points (x, y), defocused by its height."""
    if scene is None:
        return jnp.broadcast_to(backdrop[:, None, None], (3, *x.shape))
    m = scene_magnification(device, scene.height)
    yaw = jnp.deg2rad(scene.yaw_deg)
    dx, dy = x * m - scene.x, y * m - scene.y
    # Coordinates along the object's own axes.
    u = jnp.cos(yaw) * dx + jnp.sin(yaw) * dy
    v = -jnp.sin(yaw) * dx + jnp.cos(yaw) * dy
    if scene.image is None:
        cover = _coverage(scene, u, v, m * jnp.asarray(pixel, dtype=float))
        rgb = cover[None] * scene.rgb[:, None, None] + (1 - cover[None]) * backdrop[:, None, None]
    else:
        th, tw = scene.image.shape[:2]
        cols = (u / scene.length + 0.5) * tw - 0.5
        rows = (0.5 - v / scene.width) * th - 0.5
        inside = (cols >= -0.5) & (cols <= tw - 0.5) & (rows >= -0.5) & (rows <= th - 0.5)
        sample = jax.vmap(
            lambda channel: jax.scipy.ndimage.map_coordinates(channel, [rows, cols], order=1, mode="nearest")
        )
        picture = sample(jnp.moveaxis(scene.image, -1, 0))
        rgb = jnp.where(inside[None], picture, backdrop[:, None, None])
    blur = jax.vmap(lambda c: gaussian_blur_fft(c, scene_defocus(device, scene.height), pixel))
    return blur(rgb)


@eqx.filter_jit
def render_scene(
    key: PRNGKeyArray,
    device: Device,
    scene: SceneObject | None,
    fidelity: HighFidelity = HighFidelity(),
    *,
    backdrop: tuple[float, float, float] = BACKDROP_RGB,
    exposure: ArrayLike = 1.0,
    supersample: int = 2,
    harmonics: int = 7,
) -> SceneFrame:
    r"""A see-through colour frame of `scene` above an untouched sensor, and its ground truth.

    Each colour channel's radiance behind the reference grating is the scene's, times the
    product of both gratings' transmissions, times the illumination with its vignetting
    (the physics' `scene_radiance` of the undeformed sensor). It is rendered on a
    grid `supersample` times finer than the pixels with `harmonics` Fourier harmonics per
    line set, so that the binary gratings' higher harmonics alias into the image as the
    pixels integrate them; then the lens PSF, pixel integration, the camera response, and
    [`camera_noise`][moirejax.camera_noise] (shot and read noise, `fidelity.bit_depth`
    bits) per channel. The grating-free image replaces each line set by its open fraction
    (duty), so the scene is multiplied by the mean transmission $d_1^n d_2^n$ ($n$ line
    sets per grating) instead.

    An object's picture is sampled in its own plane, at $(Z + a + h)/Z$ times the rectified
    coordinates, and blurred by [`scene_defocus`][] (periodically at the image border).

    **Arguments:**

    - `key`: draws the camera noise.
    - `device`: the sensor [`Device`][].
    - `scene`: the [`SceneObject`][], or `None` for an empty view of the backdrop.
    - `fidelity`: the camera's noise and bit depth ([`HighFidelity`][]).
    - `backdrop`: linear RGB in [0, 1] behind the object.
    - `exposure`: multiplies the radiance, as for [`render_frame`][moirejax.render_frame].
    - `supersample`: samples per pixel along each axis (static).
    - `harmonics`: Fourier harmonics of each binary line set (static).

    **Returns:** a [`SceneFrame`][].
    """
    if supersample < 1 or harmonics < 1:
        raise ValueError(f"supersample and harmonics must be >= 1, got {supersample} and {harmonics}")
    s = supersample
    h, w = device.height, device.width
    fine = dataclasses.replace(device, px_per_mm=device.px_per_mm * s, height=h * s, width=w * s, harmonics=harmonics)
    x, y = image_coordinates(fine)
    rgb = _scene_rgb(device, scene, jnp.asarray(backdrop, dtype=float), x, y, 1 / fine.px_per_mm)
    untouched = scene_radiance(fine, jnp.zeros((3, h * s, w * s)), jnp.zeros((h * s, w * s)))
    mean_transmission = (device.duty1 * device.duty2) ** device.n_sets
    plain = background_radiance(fine, x, y) * mean_transmission

    def camera(radiance):
        blurred = separable_gaussian_blur(radiance, device.optics.psf_sigma * s, radius=3 * s)
        pooled = blurred.reshape(h, s, w, s).mean(axis=(1, 3))
        return camera_response(device, pooled, exposure)

    clean = jax.vmap(camera)(rgb * untouched[None])
    truth = jax.vmap(camera)(rgb * plain[None])
    noisy = jax.vmap(lambda k, c: camera_noise(k, c, fidelity))(jax.random.split(key, 3), clean)
    # RGB planes -> BGR images.
    return SceneFrame(
        frame=jnp.moveaxis(noisy[::-1], 0, -1), grating_free=jnp.moveaxis(truth[::-1], 0, -1), scene=scene
    )


def empty_scene_reference(
    key: PRNGKeyArray, device: Device, fidelity: HighFidelity = HighFidelity(), *, frames: int = 8, **kwargs
) -> Float[Array, "n h w 3"]:
    """`frames` noisy frames of the empty backdrop: the no-contact reference a unit records
    once for restoration. Keyword arguments go to [`render_scene`][]."""
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    keys = jax.random.split(key, frames)
    return jnp.stack([render_scene(k, device, None, fidelity, **kwargs).frame for k in keys])


@eqx.filter_jit
def scene_reflectance(
    device: Device, scene: SceneObject | None, *, backdrop: tuple[float, float, float] = BACKDROP_RGB
) -> Float[Array, "h w 3"]:
    """What the scene sends down through the sensor at each pixel, relative to the empty
    view: `(h, w, 3)` BGR, 1 on the backdrop.

    The object is sampled in its own plane and defocused by its height as in
    [`render_scene`][], at the pixels (no supersampling). Multiplying the light of a tactile
    frame above the camera's black level by it, channel by channel, gives the colour frame
    of the scene seen through a sensor that may be pressed: the gratings and the contact
    modulate the light, the scene tints it. It is how the live [`SimulatedSensor`][moirejax.live.SimulatedSensor]
    shows a scene.
    """
    if scene is None:
        return jnp.ones((device.height, device.width, 3))
    x, y = image_coordinates(device)
    background = jnp.asarray(backdrop, dtype=float)
    rgb = _scene_rgb(device, scene, background, x, y, 1 / device.px_per_mm) / background[:, None, None]
    return jnp.moveaxis(rgb[::-1], 0, -1)


# Saturated colours near the six hue classes of the paper's colour card (linear RGB).
_SCENE_COLOURS = (
    (0.8, 0.1, 0.1),
    (0.9, 0.45, 0.05),
    (0.85, 0.8, 0.1),
    (0.1, 0.7, 0.2),
    (0.1, 0.7, 0.8),
    (0.5, 0.15, 0.7),
)
# The kinds of the vision protocol: the shapes, then each shipped texture by name.
SCENE_KINDS = ("disc", "ring", "rectangle", *SCENE_TEXTURES)


def scene_schedule(
    device: Device, n: int, seed: int = 0, *, max_height: float = 30.0
) -> list[tuple[str, SceneObject] | None]:
    """The scenes of `n` see-through frames that mix objects, poses and heights: each an
    entry `(kind, object)`, the kind one of `SCENE_KINDS` (`"disc"`, `"ring"`,
    `"rectangle"` or a texture's name), or `None` for an empty view.

    The session starts with a few empty frames (`None`: the empty view a unit records for
    restoration), and every tenth frame after them is empty too. The others take a disc, a
    ring, a rectangle and a picture (the textures of `SCENE_TEXTURES` in turn) in turn, at
    a height drawn uniformly in [0, `max_height`] mm above the pad, a yaw drawn uniformly
    and one of six saturated colours. Sizes and positions scale with what the camera sees
    at that height, $(Z + a + h)/Z$ times the rectified field: the object spans 25-50% of
    the field and lies wholly inside it.
    """
    if n < 1:
        raise ValueError(f"need at least one frame, got n={n}")
    if not max_height >= 0:
        raise ValueError(f"max_height must be >= 0 mm, got {max_height}")
    rng = np.random.default_rng(seed)
    empty = max(2, min(8, n // 50)) if n >= 4 else 0
    schedule: list[tuple[str, SceneObject] | None] = [None] * min(empty, n)
    textures: dict[str, SceneObject] = {}
    shown = 0
    for i in range(n - len(schedule)):
        if i % 10 == 9:
            schedule.append(None)
            continue
        kind = ("disc", "ring", "rectangle", "texture")[shown % 4]
        texture = SCENE_TEXTURES[(shown // 4) % len(SCENE_TEXTURES)]
        name = texture if kind == "texture" else kind
        shown += 1
        height = float(rng.uniform(0.0, max_height))
        half = float(scene_magnification(device, height) * min(device.height, device.width) / 2 / device.px_per_mm)
        length = float(rng.uniform(0.5, 1.0)) * half
        yaw = float(rng.uniform(-90.0, 90.0))
        rgb = _SCENE_COLOURS[int(rng.integers(len(_SCENE_COLOURS)))]
        if kind == "texture":
            if texture not in textures:
                textures[texture] = scene_texture(texture, 1.0)
            image = textures[texture].image
            assert image is not None
            aspect = image.shape[0] / image.shape[1]
            reach = length / 2 * math.hypot(1.0, aspect)
        elif kind == "rectangle":
            width = length * float(rng.uniform(0.25, 0.6))
            reach = math.hypot(length, width) / 2
        else:
            reach = length / 2
        x, y = (float(u) * max(half - reach, 0.0) for u in rng.uniform(-1.0, 1.0, 2))
        if kind == "disc":
            scene = scene_disc(x, y, length, height=height, rgb=rgb)
        elif kind == "ring":
            scene = scene_ring(x, y, length, length * float(rng.uniform(0.4, 0.7)), height=height, rgb=rgb)
        elif kind == "rectangle":
            scene = scene_rectangle(x, y, length, width, yaw_deg=yaw, height=height, rgb=rgb)
        else:
            scene = dataclasses.replace(
                textures[texture], x=x, y=y, yaw_deg=yaw, height=height, length=length, width=length * aspect
            )
        schedule.append((name, scene))
    return schedule


def scene_summary(entry: tuple[str, SceneObject] | None) -> dict[str, float]:
    """The ground truth of an entry of [`scene_schedule`][moirejax.scene_schedule] as numbers:
    `kind` (its index in `SCENE_KINDS`: disc, ring, rectangle, then each texture), the pose
    `x`, `y` (mm, wrench frame), `yaw_deg` and `height` (mm above the pad), the size `length`
    and `width` (mm, as for [`SceneObject`][]), and the colour `r`, `g`, `b` (linear, of a
    shape; NaN for a texture); all NaN for an empty view."""
    keys = ("kind", "x", "y", "yaw_deg", "height", "length", "width", "r", "g", "b")
    if entry is None:
        return dict.fromkeys(keys, math.nan)
    kind, scene = entry
    rgb = (math.nan,) * 3 if scene.shape == "texture" else tuple(float(c) for c in scene.rgb)
    pose = (scene.x, scene.y, scene.yaw_deg, scene.height, scene.length, scene.width)
    return dict(zip(keys, (float(SCENE_KINDS.index(kind)), *(float(v) for v in pose), *rgb)))
