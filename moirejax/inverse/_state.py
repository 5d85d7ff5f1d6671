"""What an inversion estimates and returns: the unknowns of a frame ([`LoadState`][]), the
per-frame [`Estimate`][] and its [`Status`][], and the [`Track`][] a stream carries.

[`LoadState`][] is the one place that knows how the unknowns are laid out as the solvers'
coordinate vector; everything else reads them by name.
"""

import enum
import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._conventions import WRENCH_SCALE
from ..physics import Contact


# A typical indenter's contact radius (mm): the contact guess of a frame before any fit, and
# the centre of the prior on the radius, whose width is RADIUS_PRIOR_WIDTH in log radius.
TYPICAL_RADIUS = 3.5
RADIUS_PRIOR_WIDTH = 0.6
# The contact's flatness (`Contact.flatness`) has a prior centred on a rounded indenter's 0,
# this wide: a flat face (1) is one width away. A light load barely shows the pressure's
# shape, and the prior then keeps it rounded.
FLATNESS_PRIOR_WIDTH = 1.0
_FLATNESS_OVERSHOOT = 0.05
# The contact's elongation (`Contact.stretch_x`, `Contact.stretch_xy`) has a prior centred on a
# round patch, this wide in each component of the log-stretch: an edge ten times as long as
# wide (k = 1.15) is about one width away, and a light load keeps the patch round.
STRETCH_PRIOR_WIDTH = 1.0
# How many unknowns a frame has, and where the scaled wrench sits among the solvers'
# coordinates (`LoadState.vector`).
N_UNKNOWNS = 13
# The problem's prior residuals (`Inverter`): the tilt (2), the radius (1), the flatness (1),
# the elongation (2), the wrench (6) and the exposure (1); the exposure's comes last.
N_PRIORS = 13
WRENCH_COORDINATES = slice(0, 6)
# Where the elongation (`stretch_x`, `stretch_xy`) sits among the solvers' coordinates: a solve
# that keeps the patch round holds these.
ELONGATION_COORDINATES = (10, 11)


class LoadState(eqx.Module):
    """The unknowns of one frame: the load, where it sits, and the exposure (a batch has a
    leading axis on every field).

    - `scaled_wrench`: `[fx, fy, fz, tx, ty, tz]`, each over the paper's range of its axis
      ([`PAPER_RANGES`][moirejax.PAPER_RANGES]), so that every axis weighs alike in a solve.
    - `x0`, `y0`: the contact's centre on the contact surface, mm.
    - `log_radius`: the log of the contact radius (mm).
    - `flatness`: how flat the pressure is across the contact, from a sphere's (0) to a flat
      punch's (1) ([`Contact`][moirejax.Contact]).
    - `stretch_x`, `stretch_xy`: the contact's elongation from a round patch (0, 0)
      ([`Contact`][moirejax.Contact]).
    - `log_exposure`: the log of the frame's exposure factor against the device's.

    [`Estimate.state`][moirejax.Estimate] is one; pass it as `init` to warm-start the next
    frame ([`Inverter.solve`][]), or build one from a known load with
    [`LoadState.from_load`][].
    """

    scaled_wrench: Float[Array, "*b 6"]
    x0: Float[Array, "*b"]
    y0: Float[Array, "*b"]
    log_radius: Float[Array, "*b"]
    flatness: Float[Array, "*b"]
    stretch_x: Float[Array, "*b"]
    stretch_xy: Float[Array, "*b"]
    log_exposure: Float[Array, "*b"]

    @classmethod
    def at_rest(cls, x0: float = 0.0, y0: float = 0.0, radius: float = TYPICAL_RADIUS, dtype=float) -> "LoadState":
        """No load, a contact guess at `(x0, y0)` of `radius` mm, the device's exposure."""
        scalar = lambda v: jnp.asarray(v, dtype)  # noqa: E731
        zero = scalar(0.0)
        return cls(jnp.zeros(6, dtype), scalar(x0), scalar(y0), scalar(math.log(radius)), zero, zero, zero, zero)

    @classmethod
    def from_load(
        cls, wrench: Float[ArrayLike, "6"], contact: Contact, exposure: float | Float[ArrayLike, ""] = 1.0, dtype=None
    ) -> "LoadState":
        """The state of a known load: `wrench` in N and N·m on `contact`, at `exposure`."""
        wrench = jnp.asarray(wrench, dtype)
        dtype = wrench.dtype
        return cls(
            wrench / jnp.asarray(WRENCH_SCALE, dtype),
            jnp.asarray(contact.x0, dtype),
            jnp.asarray(contact.y0, dtype),
            jnp.log(jnp.asarray(contact.radius, dtype)),
            jnp.asarray(contact.flatness, dtype),
            jnp.asarray(contact.stretch_x, dtype),
            jnp.asarray(contact.stretch_xy, dtype),
            jnp.log(jnp.asarray(exposure, dtype)),
        )

    @property
    def wrench(self) -> Float[Array, "*b 6"]:
        """`[fx, fy, fz, tx, ty, tz]` in N and N·m."""
        return self.scaled_wrench * jnp.asarray(WRENCH_SCALE, self.scaled_wrench.dtype)

    @property
    def contact(self) -> Contact:
        return Contact(
            x0=self.x0,
            y0=self.y0,
            radius=jnp.exp(self.log_radius),
            flatness=self.contact_flatness,
            stretch_x=self.stretch_x,
            stretch_xy=self.stretch_xy,
        )

    @property
    def exposure(self) -> Float[Array, "*b"]:
        return jnp.exp(self.log_exposure)

    def radius_misfit(self) -> Float[Array, "*b"]:
        """How far the contact radius is from a typical indenter's, in widths of its prior:
        at light load the fringes barely see the radius, and this keeps it from running off."""
        return (self.log_radius - math.log(TYPICAL_RADIUS)) / RADIUS_PRIOR_WIDTH

    def flatness_misfit(self) -> Float[Array, "*b"]:
        """How far the pressure's shape is from a rounded indenter's, in widths of its prior."""
        return self.flatness / FLATNESS_PRIOR_WIDTH

    def stretch_misfit(self) -> Float[Array, "*b 2"]:
        """How far the contact is from a round patch, each component in widths of its prior."""
        return jnp.stack([self.stretch_x, self.stretch_xy], axis=-1) / STRETCH_PRIOR_WIDTH

    @property
    def contact_flatness(self) -> Float[Array, "*b"]:
        """The contact's flatness: the `flatness` coordinate between a sphere's 0 and a flat
        punch's 1, and beyond them saturating smoothly within `_FLATNESS_OVERSHOOT`. A shape
        outside those two is not a contact's: below 0 the pressure would pull at the edge,
        which let one patch mimic three presses far apart."""
        f = self.flatness
        margin = _FLATNESS_OVERSHOOT
        low = margin * jnp.tanh(jnp.minimum(f, 0.0) / margin)
        high = 1.0 + margin * jnp.tanh(jnp.maximum(f - 1.0, 0.0) / margin)
        return jnp.where(f < 0.0, low, jnp.where(f > 1.0, high, f))

    def unloaded(self) -> "LoadState":
        """This state with no load: the contact guess and exposure kept."""
        return eqx.tree_at(lambda s: s.scaled_wrench, self, jnp.zeros_like(self.scaled_wrench))

    def with_shear(self, fx: float | Float[Array, ""], fy: float | Float[Array, ""]) -> "LoadState":
        """This state with its shear forces set, each in units of its axis' range."""
        shear = jnp.stack([jnp.asarray(fx, self.scaled_wrench.dtype), jnp.asarray(fy, self.scaled_wrench.dtype)])
        return eqx.tree_at(lambda s: s.scaled_wrench, self, self.scaled_wrench.at[..., :2].set(shear))

    def with_twist_scaled(self, factor: float) -> "LoadState":
        """This state with its torque about the normal (Tz) multiplied by `factor`."""
        return eqx.tree_at(lambda s: s.scaled_wrench, self, self.scaled_wrench.at[..., 5].multiply(factor))

    def with_radius_scaled(self, factor: float) -> "LoadState":
        """This state with its contact radius multiplied by `factor`."""
        return eqx.tree_at(lambda s: s.log_radius, self, self.log_radius + math.log(factor))

    def with_contact_at(self, x0: Float[Array, ""], y0: Float[Array, ""]) -> "LoadState":
        """This state with the contact centred at `(x0, y0)` mm."""
        return eqx.tree_at(
            lambda s: (s.x0, s.y0), self, (jnp.asarray(x0, self.x0.dtype), jnp.asarray(y0, self.y0.dtype))
        )

    def vector(self) -> Float[Array, "*b 13"]:
        """The solvers' coordinates: the scaled wrench, the contact centre, the log radius, the
        flatness, the elongation and the log exposure, in that order (the exposure last: two
        contacts share it)."""
        tail = jnp.stack(
            [self.x0, self.y0, self.log_radius, self.flatness, self.stretch_x, self.stretch_xy, self.log_exposure],
            axis=-1,
        )
        return jnp.concatenate([self.scaled_wrench, tail], axis=-1)

    @classmethod
    def from_vector(cls, y: Float[Array, "*b 13"]) -> "LoadState":
        """The state whose [`vector`][moirejax.LoadState.vector] is `y`."""
        if y.shape[-1] != N_UNKNOWNS:
            raise ValueError(f"a load state has {N_UNKNOWNS} coordinates, got shape {y.shape}")
        return cls(y[..., WRENCH_COORDINATES], *(y[..., k] for k in range(6, N_UNKNOWNS)))


class Status(enum.IntEnum):
    """Per-frame outcome of an inversion; `message` gives the human version."""

    CONVERGED = 0
    MAX_STEPS = 1
    NONFINITE = 2
    NO_CONTACT = 3
    BAD_FRAME = 4
    WRONG_SIZE = 5
    UNREADABLE = 6
    UNEXPLAINED = 7

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Status.CONVERGED: "converged",
    Status.MAX_STEPS: "solver hit its step limit; wrench is the last iterate and may be inaccurate",
    Status.NONFINITE: "frame or solution contains NaN/inf; no wrench",
    Status.NO_CONTACT: "no contact detected; wrench is zero",
    Status.BAD_FRAME: (
        "frame is black, more than 5% clipped at white (reduce the exposure), does not show this unit's "
        "fringes (its fringe phase disagrees with the reference's and no load explains it), or holds corrupt "
        "pixels (a region with pixel noise a hundred times the rest's); no wrench"
    ),
    Status.WRONG_SIZE: "frame has the wrong size for this device; no wrench",
    Status.UNREADABLE: "frame could not be read or decoded; no wrench",
    Status.UNEXPLAINED: (
        "in contact, but the model explains less than half of how the fringe phase changed (less than nine "
        "tenths beyond the calibrated normal force), or only with a load "
        "ten times its calibrated range; the wrench is the best fit and may be far off (a contact, unit, scene "
        "or camera pose the model does not describe)"
    ),
}


class Estimate(eqx.Module):
    """The result of inverting one frame (or a batch, with a leading axis on every field).

    - `wrench`: `[fx, fy, fz, tx, ty, tz]` in N and N·m.
    - `covariance`: 6x6 covariance of the wrench; `sigma` its square-rooted diagonal.
    - `contact`: the fitted [`Contact`][]; `exposure`: fitted exposure factor.
    - `status`: an integer [`Status`][]; `steps`: solver steps; `rms`: the pixel noise level
      that would explain the fit's residual (frame units); well above the camera noise
      means the model does not explain the frame.
    - `state`: the fitted [`LoadState`][], to warm-start the next frame.
    - `misfit`: the share of the fringe phase's change from the reference (above the pixel
      noise) that the fit leaves: a few thousandths to a few hundredths where the model
      describes the frame; a frame above one half is `unexplained`. Zero without contact.
    - `second_contact`, `second_wrench`: a frame that one patch does not explain and two
      do (two fingertips, an edge pressed at two places) is read with a second patch:
      its [`Contact`][] and the share of `wrench` it carries (about the origin). `contact`
      is then the patch that carries the more normal force. Without a second patch,
      `second_wrench` is zero and `second_contact` NaN.
    """

    wrench: Float[Array, "*b 6"]
    covariance: Float[Array, "*b 6 6"]
    sigma: Float[Array, "*b 6"]
    contact: Contact
    exposure: Float[Array, "*b"]
    status: Int[Array, "*b"]
    steps: Int[Array, "*b"]
    rms: Float[Array, "*b"]
    state: LoadState
    misfit: Float[Array, "*b"]
    second_contact: Contact
    second_wrench: Float[Array, "*b 6"]

    @property
    def contacts(self) -> Int[Array, "*b"]:
        """How many contact patches the frame was read with: 1, or 2 (see `second_contact`)."""
        return 1 + jnp.any(self.second_wrench != 0, axis=-1).astype(jnp.int32)


class Track(eqx.Module):
    """What a stream carries from frame to frame: the last solution, the data Jacobian
    there (against the solution's [`LoadState.vector`][moirejax.LoadState.vector]), and the
    model's predicted change of the data from zero load there (so the next frame's residual
    at the last solution costs no model run); `valid` is false before the first converged
    contact. Make the first one with [`Inverter.cold_track`][]."""

    state: LoadState
    jacobian: Float[Array, "n 13"]
    change: Float[Array, " n"]
    valid: Bool[Array, ""]
