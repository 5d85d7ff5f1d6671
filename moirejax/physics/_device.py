"""The description of one sensor unit: gratings, stack geometry, elastomer, optics and camera."""

import dataclasses
import math
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._fileio import read_json, validate_json, write_json
from ._geometry import apparent_pitch, grating_wavevector


Layout = Literal["lines", "crossed"]
LAYOUTS = ("lines", "crossed")


def _scalar(x) -> Array:
    return jnp.asarray(x, dtype=float)


def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


class Elastomer(eqx.Module):
    """A linear elastic layer bonded to a rigid carrier.

    **Arguments:**

    - `E`: Young's modulus (MPa).
    - `nu`: Poisson ratio, in [0, 0.5); PDMS is about 0.49.
    - `thickness`: layer thickness (mm).
    """

    E: Float[Array, ""] = eqx.field(converter=_scalar, default=1.0)
    nu: Float[Array, ""] = eqx.field(converter=_scalar, default=0.49)
    thickness: Float[Array, ""] = eqx.field(converter=_scalar, default=3.0)

    def __check_init__(self):
        if _is_concrete(self.E, self.nu, self.thickness):
            if not float(self.E) > 0:
                raise ValueError(f"elastomer E must be positive, got {float(self.E)} MPa")
            if not 0 <= float(self.nu) < 0.5:
                raise ValueError(f"elastomer nu must be in [0, 0.5), got {float(self.nu)}")
            if not float(self.thickness) > 0:
                raise ValueError(f"elastomer thickness must be positive, got {float(self.thickness)} mm")


class Optics(eqx.Module):
    """Illumination, blur and camera response.

    **Arguments:**

    - `defocus`: Gaussian blur (mm, reference plane) of the far grating, which is out of focus.
    - `psf_sigma`: Gaussian optical point-spread function of the lens (pixels).
    - `background`: radiance reaching the camera through fully open gratings (0..1 scale).
    - `vignetting`: fractional fall-off of radiance at the image corner.
    - `glow_gain`: brightness added per MPa of contact pressure (light scattered by the
      pressed elastomer, the paper's $I \\approx I_0 + \\kappa (P * h)$).
    - `glow_width`: width (mm) of the kernel $h$ that spreads the pressure glow.
    - `rim_gain`: brightness of the LED contact rim per sqrt(N) of normal force.
    - `rim_width`: radial width (mm) of the rim.
    - `gain`, `offset`, `gamma`: camera response, `pixel = offset + gain * radiance ** (1/gamma)`.
    - `phase1`, `phase2`: registration phase of each line set of the upper and reference
      grating (rad); one entry per line set of the layout.
    """

    defocus: Float[Array, ""] = eqx.field(converter=_scalar, default=0.02)
    psf_sigma: Float[Array, ""] = eqx.field(converter=_scalar, default=0.6)
    background: Float[Array, ""] = eqx.field(converter=_scalar, default=0.9)
    vignetting: Float[Array, ""] = eqx.field(converter=_scalar, default=0.15)
    glow_gain: Float[Array, ""] = eqx.field(converter=_scalar, default=4.0)
    glow_width: Float[Array, ""] = eqx.field(converter=_scalar, default=1.0)
    rim_gain: Float[Array, ""] = eqx.field(converter=_scalar, default=0.15)
    rim_width: Float[Array, ""] = eqx.field(converter=_scalar, default=0.6)
    gain: Float[Array, ""] = eqx.field(converter=_scalar, default=0.9)
    offset: Float[Array, ""] = eqx.field(converter=_scalar, default=0.05)
    gamma: Float[Array, ""] = eqx.field(converter=_scalar, default=1.0)
    phase1: Float[Array, " sets"] = eqx.field(converter=lambda x: jnp.asarray(x, dtype=float), default=(0.0, 0.0))
    phase2: Float[Array, " sets"] = eqx.field(converter=lambda x: jnp.asarray(x, dtype=float), default=(0.0, 0.0))

    def __check_init__(self):
        if _is_concrete(self.psf_sigma, self.defocus, self.gamma, self.glow_width, self.rim_width):
            for name in ("psf_sigma", "defocus"):
                if not float(getattr(self, name)) >= 0:
                    raise ValueError(f"optics {name} must be non-negative")
            for name in ("gamma", "glow_width", "rim_width"):
                if not float(getattr(self, name)) > 0:
                    raise ValueError(f"optics {name} must be positive")


class Device(eqx.Module):
    """One moiré sensor unit, nominal or fitted.

    Grating 1 is the upper (far) grating on the contact surface, at distance `Z + a` from
    the camera; grating 2 is the fixed reference (near) grating at distance `Z`. Angles
    give the direction of each grating's wavevector. With `layout="crossed"` each grating
    is a grid of open squares: a second line set at `alpha + cross_angle`.

    **Arguments:**

    - `p1`, `p2`: pitches (mm).
    - `alpha1`, `alpha2`: wavevector directions (rad).
    - `duty1`, `duty2`: open fraction of each period, in (0, 1).
    - `a`: separation of the two gratings (mm), `0 < a < Z`.
    - `Z`: camera (pinhole) distance to the reference grating (mm).
    - `px_per_mm`: rectified resolution in the reference-grating plane.
    - `height`, `width`: rectified image size (pixels, static).
    - `elastomer`: the [`Elastomer`][] layer; its thickness must not exceed `a`.
    - `optics`: the [`Optics`][].
    - `tilt`: the 2x2 matrix $M$ of the paper's Eq. 9, $[T_x, T_y] \\approx M (c - c_0)$,
      with $c$ the brightness centroid (mm) times normal force; fitted by calibration and
      used to start the per-frame solve.
    - `layout`: `"lines"` or `"crossed"` (static).
    - `cross_angle`: angle between the two line sets of a crossed grid (rad).
    - `harmonics`: Fourier harmonics kept per line set in the `model` rendering (static).
    """

    p1: Float[Array, ""] = eqx.field(converter=_scalar)
    p2: Float[Array, ""] = eqx.field(converter=_scalar)
    alpha1: Float[Array, ""] = eqx.field(converter=_scalar, default=0.0)
    alpha2: Float[Array, ""] = eqx.field(converter=_scalar, default=0.0)
    duty1: Float[Array, ""] = eqx.field(converter=_scalar, default=0.6)
    duty2: Float[Array, ""] = eqx.field(converter=_scalar, default=0.6)
    a: Float[Array, ""] = eqx.field(converter=_scalar, default=3.0)
    Z: Float[Array, ""] = eqx.field(converter=_scalar, default=12.0)
    px_per_mm: Float[Array, ""] = eqx.field(converter=_scalar, default=16.0)
    height: int = eqx.field(static=True, default=512)
    width: int = eqx.field(static=True, default=512)
    # Factories, not instances: an instance made at import would fix its arrays' dtype to the
    # precision JAX had then, and mix it with the precision of every later computation.
    elastomer: Elastomer = eqx.field(default_factory=Elastomer)
    optics: Optics = eqx.field(default_factory=Optics)
    tilt: Float[Array, "2 2"] = eqx.field(
        converter=lambda x: jnp.asarray(x, dtype=float), default=((0.0, 0.0), (0.0, 0.0))
    )
    layout: str = eqx.field(static=True, default="crossed")
    cross_angle: Float[Array, ""] = eqx.field(converter=_scalar, default=math.pi / 2)
    harmonics: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {self.layout!r}")
        if self.height < 16 or self.width < 16:
            raise ValueError(f"image size must be at least 16x16 pixels, got {self.height}x{self.width}")
        if self.harmonics < 1:
            raise ValueError(f"harmonics must be >= 1, got {self.harmonics}")
        if self.optics.phase1.shape != (self.n_sets,) or self.optics.phase2.shape != (self.n_sets,):
            raise ValueError(
                f"optics phase1/phase2 need one entry per line set ({self.n_sets}) for layout {self.layout!r}"
            )
        if _is_concrete(self.p1, self.p2, self.a, self.Z, self.duty1, self.duty2, self.px_per_mm):
            if not (float(self.p1) > 0 and float(self.p2) > 0):
                raise ValueError(f"pitches must be positive, got p1={float(self.p1)}, p2={float(self.p2)} mm")
            if not 0 < float(self.a) < float(self.Z):
                raise ValueError(f"need 0 < a < Z, got a={float(self.a)}, Z={float(self.Z)} mm")
            for name in ("duty1", "duty2"):
                if not 0 < float(getattr(self, name)) < 1:
                    raise ValueError(f"{name} must be in (0, 1), got {float(getattr(self, name))}")
            if not float(self.px_per_mm) > 0:
                raise ValueError(f"px_per_mm must be positive, got {float(self.px_per_mm)}")
            if _is_concrete(self.elastomer.thickness) and float(self.elastomer.thickness) > float(self.a) + 1e-9:
                raise ValueError(
                    f"elastomer thickness {float(self.elastomer.thickness)} mm exceeds the grating separation a={float(self.a)} mm"
                )

    @property
    def n_sets(self) -> int:
        """Number of line sets per grating: 1 for lines, 2 for crossed grids."""
        return 1 if self.layout == "lines" else 2

    @property
    def field_of_view(self) -> tuple[float, float]:
        """Rectified field (height, width) in mm in the reference plane (needs concrete values)."""
        return self.height / float(self.px_per_mm), self.width / float(self.px_per_mm)

    @property
    def surface_magnification(self) -> Float[Array, ""]:
        """$(Z + a)/Z$: how much larger a length on the contact surface is than its image in
        the reference plane, whose field the rectified frame shows. The contact surface lies
        $a$ farther from the camera."""
        return (self.Z + self.a) / self.Z

    def set_angles(self) -> tuple[Float[Array, " sets"], Float[Array, " sets"]]:
        """Wavevector direction of each line set of the upper and reference grating."""
        if self.layout == "lines":
            return self.alpha1[None], self.alpha2[None]
        return (
            jnp.stack([self.alpha1, self.alpha1 + self.cross_angle]),
            jnp.stack([self.alpha2, self.alpha2 + self.cross_angle]),
        )

    def upper_wavevectors(self) -> Float[Array, "sets 2"]:
        """Wavevectors of the upper grating in its own (surface) plane, rad/mm."""
        return grating_wavevector(self.p1, self.set_angles()[0])

    def apparent_upper_wavevectors(self) -> Float[Array, "sets 2"]:
        """Wavevectors of the upper grating as seen in the reference plane (exact parallax)."""
        return grating_wavevector(apparent_pitch(self.p1, self.a, self.Z), self.set_angles()[0])

    def reference_wavevectors(self) -> Float[Array, "sets 2"]:
        """Wavevectors of the reference grating, rad/mm."""
        return grating_wavevector(self.p2, self.set_angles()[1])

    def moire_wavevectors(self) -> Float[Array, "sets 2"]:
        """Moiré wavevector $K = k_1' - k_2$ of each fringe family in the reference plane."""
        return self.apparent_upper_wavevectors() - self.reference_wavevectors()


# ---------------------------------------------------------------------------------------
# Presets and JSON.

PRESET_PITCHES = {"dense": (0.20, 0.20), "mid": (0.35, 0.30), "sparse": (0.30, 0.25)}


def preset(name: str, **overrides: Any) -> Device:
    """The paper's three designs (Sec. Sensitivity Tuning), with a/Z = 0.25.

    `name` is `"dense"`, `"mid"` or `"sparse"`; keyword arguments override any
    [`Device`][] field (e.g. `layout="lines"`).
    """
    if name not in PRESET_PITCHES:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESET_PITCHES)}")
    p1, p2 = PRESET_PITCHES[name]
    kwargs: dict[str, Any] = dict(p1=p1, p2=p2, a=3.0, Z=12.0)
    if overrides.get("layout") == "lines" and "optics" not in overrides:
        # One line set transmits more light: a lower gain keeps the same mean pixel level.
        kwargs["optics"] = Optics(phase1=(0.0,), phase2=(0.0,), gain=0.8)
    kwargs.update(overrides)
    return Device(**kwargs)


_GEOMETRY_FIELDS = ("p1", "p2", "alpha1", "alpha2", "duty1", "duty2", "a", "Z", "px_per_mm", "cross_angle")


def _to_python(x):
    arr = np.asarray(x, dtype=float)
    return arr.tolist() if arr.ndim else float(arr)


def device_to_json(device: Device, *, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """A JSON-ready dict of `device` (angles in radians, lengths in mm, stiffness in MPa)."""
    out: dict[str, Any] = {"format": "moirejax-device", "version": 1}
    out.update({name: _to_python(getattr(device, name)) for name in _GEOMETRY_FIELDS})
    out.update(height=device.height, width=device.width, layout=device.layout, harmonics=device.harmonics)
    out["elastomer"] = {
        f.name: _to_python(getattr(device.elastomer, f.name)) for f in dataclasses.fields(device.elastomer)
    }
    out["optics"] = {f.name: _to_python(getattr(device.optics, f.name)) for f in dataclasses.fields(device.optics)}
    out["tilt"] = _to_python(device.tilt)
    if extra:
        out.update(extra)
    return out


def device_from_json(obj: Any, *, source: str = "<memory>") -> Device:
    """Inverse of [`device_to_json`][]. `obj` is any parsed JSON value: it is validated
    against `data_schema/device.schema.json`, and anything else than a device object raises
    [`DataError`][moirejax.DataError] naming `source` and the field."""
    validate_json(obj, "device", source=source)
    kwargs: dict[str, Any] = {name: obj[name] for name in _GEOMETRY_FIELDS if name in obj}
    for name in ("height", "width", "layout", "harmonics"):
        if name in obj:
            kwargs[name] = obj[name]
    if "tilt" in obj:
        kwargs["tilt"] = obj["tilt"]
    kwargs["elastomer"] = Elastomer(**obj.get("elastomer", {}))
    optics = dict(obj.get("optics", {}))
    if "phase1" not in optics and obj.get("layout", "crossed") == "lines":
        optics.update(phase1=(0.0,), phase2=(0.0,))
    kwargs["optics"] = Optics(**optics)
    try:
        return Device(**kwargs)
    except ValueError as e:
        raise ValueError(f"{source}: {e}") from None


def save_device(path, device: Device, *, extra: dict[str, Any] | None = None) -> None:
    """Write `device` as schema-validated JSON, atomically."""
    write_json(path, device_to_json(device, extra=extra), "device")


def load_device(path) -> Device:
    """Read a device JSON file written by [`save_device`][] (or by hand)."""
    return device_from_json(read_json(path), source=str(path))
