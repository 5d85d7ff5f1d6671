r"""Indenters of other shapes than the inversion's Hertz patch, for the simulator.

A robot presses with a fingertip (a sphere), a flat face (a flat punch), a bottle cap's rim
(a ring), an edge (a line), a box corner or face (a square punch), or two fingertips at
once. Each [`Indenter`][] gives an unnormalised pressure profile on the contact surface, its
normal force, the shear force it transmits (spread like its pressure, as under full
stick) and a twist about its own centre of pressure (an azimuthal traction growing with
the distance from it, also weighted by the pressure). The profiles are the classical
contact pressures of rigid indenters on a soft layer, with their singular edges where
the theory has them:

- sphere: $\sqrt{1 - \rho^2/r^2}$ (Hertz);
- flat punch: $1/\sqrt{1 - \rho^2/r^2}$ (Boussinesq), capped at ten times its centre value;
- ring (a cap's rim of radius $r$ and half-width $b$): $\sqrt{1 - (\rho - r)^2/b^2}$;
- line (an edge of half-length $l$, half-width $b$, at angle $\theta$): $\sqrt{1 - d^2/b^2}$
  across it, with rounded ends;
- square punch (half-side $a$, at angle $\theta$): $1/\sqrt{(1 - u^2/a^2)(1 - v^2/a^2)}$,
  capped likewise.

The fields are averaged over each cell from a grid `supersample` times finer, so the
singular edges carry their load where it belongs, and the wrench of the fields is their
exact resultant ([`traction_resultant`][]). The inversion's patch blends a sphere's and a
flat punch's pressures on one round contact, from their exact transforms, with the loads
spread alike; rings, lines, squares and several contacts it does not describe, and even
its own two limits reach it here through another path (sampled, capped, averaged over
cells): frames of these indenters test it on loads it does not describe exactly.

Lengths are mm, forces N, torques N·m.
"""

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._conventions import NMM_PER_NM, PAPER_RANGES
from ..physics import (
    Device,
    gaussian_blur_fft,
    grid_shape,
    layer_response,
    surface_grid,
    SurfaceGrid,
    traction_resultant,
)


CONTACT_SHAPES = ("sphere", "flat", "ring", "line", "square")
# Flat and square punches: the edge singularity is capped at this multiple of the centre
# pressure (a real punch's edge is rounded).
_PUNCH_CAP = 10.0


class Indenter(eqx.Module):
    """One contact: its shape, where it is, and the load it carries.

    **Arguments:**

    - `shape`: one of `"sphere"`, `"flat"`, `"ring"`, `"line"`, `"square"` (static).
    - `x0`, `y0`: its centre on the contact surface (mm, wrench frame).
    - `size`: radius (sphere, flat punch, ring), half-length (line) or half-side (square).
    - `width`: half-width of a ring's or a line's band (mm); unused otherwise.
    - `angle`: direction of a line, orientation of a square (rad).
    - `force`: `(fx, fy, fz)` it transmits (N).
    - `twist`: torque about its own centre of pressure (N·m).
    """

    shape: str = eqx.field(static=True)
    x0: float = 0.0
    y0: float = 0.0
    size: float = 3.0
    width: float = 1.0
    angle: float = 0.0
    force: tuple[float, float, float] = (0.0, 0.0, 1.0)
    twist: float = 0.0

    def __check_init__(self):
        if self.shape not in CONTACT_SHAPES:
            raise ValueError(f"unknown indenter shape {self.shape!r}; choose from {', '.join(CONTACT_SHAPES)}")
        if not (float(self.size) > 0 and float(self.width) > 0):
            raise ValueError("an indenter's size and width must be positive")
        if float(self.force[2]) < 0:
            raise ValueError("an indenter presses: its normal force must not be negative")

    def profile(self, X: Float[Array, "h w"], Y: Float[Array, "h w"]) -> Float[Array, "h w"]:
        """The unnormalised pressure profile at the points (X, Y) (mm)."""
        dX, dY = X - self.x0, Y - self.y0
        c, s = math.cos(self.angle), math.sin(self.angle)
        along, across = c * dX + s * dY, -s * dX + c * dY
        r, b = self.size, self.width
        if self.shape == "sphere":
            return jnp.sqrt(jnp.clip(1 - (dX**2 + dY**2) / r**2, 0.0, None))
        if self.shape == "flat":
            return _punch(jnp.sqrt(dX**2 + dY**2) / r)
        if self.shape == "ring":
            return jnp.sqrt(jnp.clip(1 - (jnp.sqrt(dX**2 + dY**2) - r) ** 2 / b**2, 0.0, None))
        if self.shape == "line":
            beyond = jnp.clip(jnp.abs(along) - max(r - b, 0.0), 0.0, None)
            return jnp.sqrt(jnp.clip(1 - (across**2 + beyond**2) / b**2, 0.0, None))
        return _punch(jnp.abs(along) / r) * _punch(jnp.abs(across) / r)


def _punch(t):
    """A rigid punch's edge-singular profile $1/\\sqrt{1 - t^2}$ for $t < 1$, capped."""
    inside = t < 1
    safe = jnp.where(inside, 1 - t * t, 1.0)
    return jnp.where(inside, jnp.minimum(jax.lax.rsqrt(safe), _PUNCH_CAP), 0.0)


def indenter_tractions(indenters: Sequence[Indenter], grid: SurfaceGrid, supersample: int = 4) -> Float[Array, "3 h w"]:
    """Traction fields `(tx, ty, p)` (MPa) of `indenters` pressing together, cell-averaged on `grid`.

    Each indenter's pressure integrates to its normal force and its shear to its shear
    force; its twist is an azimuthal traction proportional to the distance from its centre
    of pressure times its pressure, scaled to its torque.
    """
    h, w = grid.X.shape
    spacing = grid.spacing
    offsets = (jnp.arange(supersample, dtype=grid.X.dtype) + 0.5) / supersample - 0.5
    fine_x = jnp.broadcast_to(
        (grid.X[:, None, :, None] + offsets[None, None, None, :] * spacing), (h, supersample, w, supersample)
    )
    fine_y = jnp.broadcast_to(
        (grid.Y[:, None, :, None] - offsets[None, :, None, None] * spacing), (h, supersample, w, supersample)
    )
    fine_x, fine_y = fine_x.reshape(h * supersample, w * supersample), fine_y.reshape(h * supersample, w * supersample)
    area = (spacing / supersample) ** 2
    total = jnp.zeros((3, h * supersample, w * supersample), fine_x.dtype)
    for indenter in indenters:
        shape = indenter.profile(fine_x, fine_y)
        weight = jnp.sum(shape) * area
        if float(weight) <= 0:
            raise ValueError(f"indenter {indenter.shape} at ({indenter.x0}, {indenter.y0}) lies outside the field")
        fx, fy, fz = (float(v) for v in indenter.force)
        cx, cy = jnp.sum(shape * fine_x) * area / weight, jnp.sum(shape * fine_y) * area / weight
        dX, dY = fine_x - cx, fine_y - cy
        torsion = jnp.sum(shape * (dX**2 + dY**2)) * area
        twist = float(indenter.twist) * NMM_PER_NM / torsion
        total = total + jnp.stack(
            [shape * (fx / weight - twist * dY), shape * (fy / weight + twist * dX), shape * fz / weight]
        )
    return total.reshape(3, h, supersample, w, supersample).mean(axis=(2, 4))


class IndenterFrame(eqx.Module):
    """The deformation of the contact surface under indenters, with the wrench they apply."""

    wrench: Float[Array, "6"]
    tractions: Float[Array, "3 h w"]
    displacement: Float[Array, "3 h w"]
    light: Float[Array, "h w"]
    grid: SurfaceGrid


def indenter_deformation(
    device: Device, indenters: Sequence[Indenter], shape: tuple[int, int] | None = None, supersample: int = 4
) -> IndenterFrame:
    """Solve the elastomer under `indenters` on a mechanics grid of `shape` covering the image
    (`None`: 256 cells along its longer side, [`grid_shape`][moirejax.grid_shape])
    ([`traction_deformation`][moirejax.traction_deformation] of their
    [`indenter_tractions`][moirejax.indenter_tractions])."""
    if shape is None:
        shape = grid_shape((device.height, device.width), 256)
    grid = surface_grid(shape, device.px_per_mm, (device.height, device.width), device.a, device.Z)
    return traction_deformation(device, indenter_tractions(indenters, grid, supersample))


def traction_deformation(device: Device, tractions: Float[Array | np.ndarray, "3 h w"]) -> IndenterFrame:
    """Solve the elastomer under any traction field `(tx, ty, p)` (MPa, pressure positive)
    given on a mechanics grid of shape `(h, w)` covering the image, as
    [`surface_grid`][moirejax.surface_grid] lays it out: a pressure map measured elsewhere,
    drawn by hand, or summed from indenters.

    The light scattered in the elastomer follows the device's optics: the glow is the blurred
    pressure; the LED rim is a band along the edge of the contact region, brighter with the
    normal force. Render the result with [`render_deformed`][moirejax.render_deformed] (after
    resampling to the pixels) or [`render_deformed_high`][moirejax.render_deformed_high].
    """
    tractions = jnp.asarray(tractions)
    if tractions.ndim != 3 or tractions.shape[0] != 3:
        raise ValueError(f"tractions must be (3, h, w) fields (tx, ty, p), got shape {tractions.shape}")
    shape = (int(tractions.shape[1]), int(tractions.shape[2]))
    grid = surface_grid(shape, device.px_per_mm, (device.height, device.width), device.a, device.Z)
    e = device.elastomer
    displacement = layer_response(shape, grid.spacing, e.E, e.nu, e.thickness)(tractions)
    optics = device.optics
    pressure = tractions[2]
    glow = optics.glow_gain * gaussian_blur_fft(pressure, optics.glow_width, grid.spacing)
    support = gaussian_blur_fft(
        (pressure > 1e-6 * jnp.max(pressure)).astype(pressure.dtype), optics.rim_width, grid.spacing
    )
    edge = 4 * jnp.clip(support, 0, 1) * (1 - jnp.clip(support, 0, 1))
    pressing = jnp.clip(jnp.sum(pressure) * grid.spacing**2, 0.0, None)
    rim = optics.rim_gain * pressing / jnp.sqrt(pressing + 0.05) * edge
    return IndenterFrame(
        wrench=traction_resultant(tractions, grid),
        tractions=tractions,
        displacement=displacement,
        light=glow + rim,
        grid=grid,
    )


def grasp_limits(max_force: float) -> tuple[float, float]:
    """The largest shear force (N) and twist (N·m) drawn with normal forces up to `max_force`.

    At the paper's calibration range (1.2 N) they are its 0.2 N and 0.006 N·m; at the grasp
    loads of its cap removal (10 N) about 1 N and 0.035 N·m. In between and beyond they follow
    the power laws through those two points.
    """
    ratio = max(float(max_force), PAPER_RANGES["fz"]) / PAPER_RANGES["fz"]
    return PAPER_RANGES["fx"] * ratio**0.75, 0.006 * ratio**0.84


def random_indenters(rng: np.random.Generator, family: str, max_force: float = 1.2) -> list[Indenter]:
    """Loads of one contact family inside the paper's calibration ranges (or up to
    `max_force` newtons of normal force): `family` is one of [`CONTACT_SHAPES`][moirejax.CONTACT_SHAPES] or `"two"`
    (two fingertips).

    Normal force uniform in [0.1, `max_force`] N (split between two fingertips), shear and
    twist up to [`grasp_limits`][moirejax.grasp_limits] (0.2 N and 0.006 N·m in the paper's
    range; less under a light press: friction); the contact lies within 4 mm of the centre,
    and above the paper's 1.2 N it grows with the cube root of the force.
    """
    if family not in (*CONTACT_SHAPES, "two"):
        raise ValueError(f"unknown contact family {family!r}; choose from {', '.join((*CONTACT_SHAPES, 'two'))}")
    fz = rng.uniform(0.1, max_force)
    scale = min(1.0, fz / 0.4)
    shear_limit, twist_limit = grasp_limits(max_force)
    shear = tuple(rng.uniform(-shear_limit, shear_limit, 2) * scale)
    twist = rng.uniform(-twist_limit, twist_limit) * scale
    # A harder press spreads the contact (Hertz: radius as the cube root of the force).
    grow = max(1.0, fz / PAPER_RANGES["fz"]) ** (1 / 3)
    x0, y0 = rng.uniform(-4, 4, 2)
    angle = rng.uniform(0, math.pi)
    if family == "two":
        split = rng.uniform(0.3, 0.7)
        gap = rng.uniform(7.0, 11.0) * grow
        dx, dy = 0.5 * gap * math.cos(angle), 0.5 * gap * math.sin(angle)
        x0, y0 = rng.uniform(-2, 2, 2)
        return [
            Indenter(
                "sphere",
                x0 + dx,
                y0 + dy,
                rng.uniform(2.0, 3.0) * grow,
                force=(shear[0] * split, shear[1] * split, fz * split),
                twist=twist * split,
            ),
            Indenter(
                "sphere",
                x0 - dx,
                y0 - dy,
                rng.uniform(2.0, 3.0) * grow,
                force=(shear[0] * (1 - split), shear[1] * (1 - split), fz * (1 - split)),
                twist=twist * (1 - split),
            ),
        ]
    size = {
        "sphere": rng.uniform(2.5, 4.5),
        "flat": rng.uniform(2.0, 4.0),
        "ring": rng.uniform(3.0, 5.0),
        "line": rng.uniform(3.0, 6.0),
        "square": rng.uniform(2.0, 3.5),
    }[family] * grow
    width = {"ring": rng.uniform(0.5, 1.0), "line": rng.uniform(0.6, 1.2)}.get(family, 1.0)
    return [Indenter(family, x0, y0, size, width, angle, force=(shear[0], shear[1], fz), twist=twist)]


CONTACT_FAMILIES = (*CONTACT_SHAPES, "two")


def shape_schedule(
    n: int, seed: int = 0, max_force: float = PAPER_RANGES["fz"], families: Sequence[str] = CONTACT_FAMILIES
) -> list[tuple[str, list[Indenter]] | None]:
    """The contacts of `n` frames that mix contact families: each loaded frame draws a family
    of `families` in turn and its load from [`random_indenters`][moirejax.random_indenters]
    (normal force up to `max_force`); the session starts with a few unloaded frames, the
    unit's no-contact reference (`None`)."""
    if n < 1:
        raise ValueError(f"need at least one frame, got n={n}")
    if not families or any(f not in CONTACT_FAMILIES for f in families):
        raise ValueError(f"contact families must be among {', '.join(CONTACT_FAMILIES)}, got {list(families)}")
    if not float(max_force) > 0:
        raise ValueError(f"max_force must be positive, got {max_force}")
    rng = np.random.default_rng(seed)
    unloaded = max(2, min(8, n // 50)) if n >= 8 else 0
    schedule: list[tuple[str, list[Indenter]] | None] = [None] * unloaded
    for i in range(n - unloaded):
        family = families[i % len(families)]
        schedule.append((family, random_indenters(rng, family, max_force)))
    return schedule


def contact_summary(frame: IndenterFrame) -> dict[str, float]:
    """Where and how large a contact is, from its traction field: the centre of pressure
    (`x0`, `y0`, mm), the area where it presses (`area`, mm²) and the radius of a disc of that
    area (`radius`, mm); NaN without a normal load."""
    pressure = np.asarray(frame.tractions[2])
    cell = float(frame.grid.spacing) ** 2
    fz = pressure.sum() * cell
    if not fz > 0:
        return {"x0": math.nan, "y0": math.nan, "radius": math.nan, "area": math.nan}
    area = float(np.count_nonzero(pressure > 1e-3 * pressure.max()) * cell)
    return {
        "x0": float((pressure * np.asarray(frame.grid.X)).sum() * cell / fz),
        "y0": float((pressure * np.asarray(frame.grid.Y)).sum() * cell / fz),
        "radius": math.sqrt(area / math.pi),
        "area": area,
    }
