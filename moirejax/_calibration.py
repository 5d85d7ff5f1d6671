r"""Calibration: fit a unit's physical parameters to frames with reference wrenches.

The unknowns are a small set of physical parameters shared by every frame (a *recipe*
names them: pitches, angles, separation, stiffness, optical gains) and, per frame, the
latent contact (centre, radius) and exposure. The wrench of every frame is known. The
fit alternates two least-squares problems, each solved with optimistix:

1. the shared parameters, with the latents fixed, over a subset of frames
   (Levenberg–Marquardt; a dense Jacobian of a few hundred thousand rows by ~9 columns);
2. the latents of every frame, with the parameters fixed (a vmapped 4-unknown solve).

Parameters that must stay positive are fitted in log space. Their uncertainties come
from the Gauss–Newton information of step 1 at the end, scaled by the residual variance.
"""

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from ._band_model import complex_ratio, predicted_bands
from ._contact import Contact, NMM_PER_NM
from ._device import Device
from ._inversion import Inverter
from ._observables import FringeFields


@dataclasses.dataclass(frozen=True)
class Recipe:
    """What a calibration fits and how.

    - `free`: dotted names of [`Device`][] fields to fit. The grating geometry is left
      out by default: the moiré wavevector measured on the reference frame fixes the
      apparent upper pitch and angle, and what it leaves (the common scale of both
      pitches, the separation) is degenerate with the stiffness in every load response.
      Freeing them let a 200-frame fit wander 28% along that valley and generalise worse.
    - `log`: the subset fitted in log space (positive quantities).
    - `rounds`: alternations of parameter and latent solves.
    - `parameter_frames`: frames used in each parameter solve (a random subset).
    - `parameter_steps`, `latent_steps`: solver step limits.
    """

    name: str = "unit"
    free: tuple[str, ...] = ("elastomer.E", "optics.glow_gain", "optics.rim_gain", "optics.gain", "optics.defocus")
    log: tuple[str, ...] = ("elastomer.E", "optics.glow_gain", "optics.rim_gain", "optics.gain", "optics.defocus")
    rounds: int = 3
    parameter_frames: int = 48
    parameter_steps: int = 12
    latent_steps: int = 20

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# Transfer keeps the design-level split between the gratings and refits what differs
# from unit to unit.
TRANSFER_RECIPE = Recipe(
    name="transfer",
    free=("elastomer.E", "optics.glow_gain", "optics.gain"),
    log=("elastomer.E", "optics.glow_gain", "optics.gain"),
    rounds=3,
    parameter_frames=20,
)


def _getter(name: str):
    def get(device):
        obj = device
        for part in name.split("."):
            obj = getattr(obj, part)
        return obj

    return get


def parameter_vector(device: Device, recipe: Recipe) -> jax.Array:
    """The recipe's free parameters of `device`, log-transformed where the recipe says."""
    values = [_getter(n)(device) for n in recipe.free]
    return jnp.stack([jnp.log(v) if n in recipe.log else v for n, v in zip(recipe.free, values)])


def with_parameters(device: Device, recipe: Recipe, theta: jax.Array) -> Device:
    """`device` with the recipe's free parameters replaced by `theta`."""
    values = [jnp.exp(t) if n in recipe.log else t for n, t in zip(recipe.free, theta)]
    return eqx.tree_at(lambda d: [_getter(n)(d) for n in recipe.free], device, values)


def latents_from_wrench(wrench: np.ndarray) -> np.ndarray:
    """Per-frame latent start `(x0, y0, log r, log exposure)`: the contact centred on the
    centre of pressure that the reference wrench implies."""
    fz = np.maximum(wrench[:, 2], 0.05)
    x0 = np.where(wrench[:, 2] > 0.05, -wrench[:, 4] * NMM_PER_NM / fz, 0.0)
    y0 = np.where(wrench[:, 2] > 0.05, wrench[:, 3] * NMM_PER_NM / fz, 0.0)
    return np.stack([x0, y0, np.full_like(x0, math.log(3.5)), np.zeros_like(x0)], axis=1)


class _Problem(eqx.Module):
    inverter: Inverter
    recipe_free: tuple[str, ...] = eqx.field(static=True)
    recipe_log: tuple[str, ...] = eqx.field(static=True)

    def device(self, theta):
        recipe = Recipe(free=self.recipe_free, log=self.recipe_log)
        return with_parameters(self.inverter.device, recipe, theta)

    def frame_residuals(self, theta, latent, wrench, observed: FringeFields, model_reference: FringeFields):
        inv = self.inverter
        device = self.device(theta)
        contact = Contact(x0=latent[0], y0=latent[1], radius=jnp.exp(latent[2]))
        predicted = predicted_bands(
            device,
            inv.demodulator,
            wrench,
            contact,
            jnp.exp(latent[3]),
            model_shape=inv.model_shape,
            reference_wavevector=observed.reference_wavevector,
        )
        fringe = predicted.fringe * complex_ratio(inv.reference.fringe, model_reference.fringe)
        brightness = predicted.brightness - model_reference.brightness + inv.reference.brightness
        df = (observed.fringe - fringe) * inv.fringe_weight.astype(fringe.dtype)
        db = (observed.brightness - brightness) * inv.brightness_weight
        # A weak prior keeps the radius of light contacts from running off.
        prior = (latent[2] - math.log(3.5)) / 0.6 * 1e-3
        return jnp.concatenate([df.real.ravel(), df.imag.ravel(), db.ravel(), prior[None]])

    def model_reference(self, theta):
        inv = self.inverter
        return predicted_bands(
            self.device(theta),
            inv.demodulator,
            jnp.zeros(6, theta.dtype),
            Contact(),
            model_shape=inv.model_shape,
            reference_wavevector=inv.reference.reference_wavevector,
        )


@eqx.filter_jit
def _parameter_solve(problem: _Problem, theta, latents, wrenches, observed, steps: int):
    def residuals(theta, args):
        latents, wrenches, observed = args
        reference = problem.model_reference(theta)
        per_frame = jax.vmap(problem.frame_residuals, in_axes=(None, 0, 0, 0, None))(
            theta, latents, wrenches, observed, reference
        )
        return per_frame.ravel()

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-7, linear_solver=lx.QR())
    sol = optx.least_squares(residuals, solver, theta, args=(latents, wrenches, observed), max_steps=steps, throw=False)
    r = residuals(sol.value, (latents, wrenches, observed))
    J = jax.jacfwd(residuals)(sol.value, (latents, wrenches, observed))
    dof = r.size - theta.size - 4 * latents.shape[0]
    covariance = jnp.linalg.pinv(J.T @ J, hermitian=True) * jnp.sum(r**2) / dof
    return sol.value, covariance, jnp.sum(r**2)


@eqx.filter_jit
def _latent_solve(problem: _Problem, theta, latents, wrenches, observed, steps: int):
    reference = problem.model_reference(theta)

    def one(latent, wrench, obs):
        def residuals(latent, args):
            return problem.frame_residuals(theta, latent, wrench, obs, reference)

        solver = optx.LevenbergMarquardt(rtol=1e-5, atol=1e-6, linear_solver=lx.QR())
        sol = optx.least_squares(residuals, solver, latent, max_steps=steps, throw=False)
        return sol.value

    return jax.vmap(one)(latents, wrenches, observed)


@dataclasses.dataclass
class CalibrationResult:
    device: Device
    uncertainty: dict[str, float]
    latents: np.ndarray
    history: list[dict]
    inverter: Inverter


def fit_physical_parameters(
    nominal: Device,
    reference: np.ndarray,
    frames: np.ndarray,
    wrenches: np.ndarray,
    recipe: Recipe = Recipe(),
    *,
    seed: int = 0,
    progress: bool = True,
) -> CalibrationResult:
    """Fit the recipe's parameters of a unit to `frames` with known `wrenches`.

    **Arguments:**

    - `nominal`: the starting [`Device`][] (the design, or another unit's fit).
    - `reference`: a no-contact frame of the unit (the mean of several is better).
    - `frames`: `(n, h, w)` frames in contact; `wrenches`: `(n, 6)` reference readings.
    - `recipe`: the [`Recipe`][].

    **Returns:** a [`CalibrationResult`][] with the fitted device and 1-sigma uncertainties
    of the free parameters (in their own units).
    """
    from tqdm.auto import tqdm

    inverter = Inverter(nominal, reference=reference)
    dtype = np.asarray(inverter.device.p1).dtype
    observed = jax.lax.map(inverter.observe, jnp.asarray(frames, dtype=dtype))
    wrenches_j = jnp.asarray(wrenches, dtype=dtype)
    latents = jnp.asarray(latents_from_wrench(np.asarray(wrenches)), dtype=dtype)
    problem = _Problem(inverter, recipe.free, recipe.log)
    theta = parameter_vector(inverter.device, recipe)
    rng = np.random.default_rng(seed)
    n = len(frames)
    history = []
    covariance = jnp.zeros((theta.size, theta.size), dtype)
    bar = tqdm(total=recipe.rounds * 2 + 1, desc="calibrate", disable=not progress)
    latents = _latent_solve(problem, theta, latents, wrenches_j, observed, recipe.latent_steps)
    bar.update()
    for round_ in range(recipe.rounds):
        subset = np.sort(rng.choice(n, size=min(n, recipe.parameter_frames), replace=False))
        observed_subset = jax.tree_util.tree_map(lambda a, s=subset: a[s], observed)
        theta, covariance, cost = _parameter_solve(
            problem, theta, latents[subset], wrenches_j[subset], observed_subset, recipe.parameter_steps
        )
        bar.update()
        latents = _latent_solve(problem, theta, latents, wrenches_j, observed, recipe.latent_steps)
        bar.update()
        history.append({"round": round_, "cost": float(cost)})
        bar.set_postfix(cost=f"{float(cost):.3g}")
    bar.close()
    device = problem.device(theta)
    values = [_getter(name)(device) for name in recipe.free]
    sd = np.sqrt(np.clip(np.diag(np.asarray(covariance)), 0, None))
    # Log-space sd to the parameter's own units (first order: sd * value).
    uncertainty = {
        name: float(s * float(v)) if name in recipe.log else float(s) for name, s, v in zip(recipe.free, sd, values)
    }
    return CalibrationResult(
        device=device, uncertainty=uncertainty, latents=np.asarray(latents), history=history, inverter=inverter
    )
