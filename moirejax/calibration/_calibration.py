r"""Calibration: fit a unit's physical parameters to frames with reference wrenches.

The unknowns are a small set of physical parameters shared by every frame (a *recipe*
names them: pitches, angles, separation, stiffness, optical gains) and, per frame, the
latent contact (centre, radius) and exposure. The wrench of every frame is known. The
residual is the inversion's own ([`Inverter.band_residual`][]). The fit alternates
least-squares problems, each solved with optimistix:

1. the mechanical and geometric parameters, with the latents fixed, over a subset of
   frames, on the fringe phase alone ([`Inverter.phase_only`][]): the quantity the
   inversion reads the load from, and one that a unit's contrast, defocus and lighting
   move only through the light a contact scatters;
2. the photometric parameters (`optics.*`: gains, glow, rim, defocus), the others held,
   on the fringe phase too: the inversion reads the load from it, and the photometry
   reaches it only through the share of a contact's light in the fringe bands. Fitted to
   the fringe amplitude and brightness as well, the photometry of a unit the model does
   not describe exactly took whatever values explained those best, however far from the
   unit's (an independent renderer's unit: 27 times the nominal gain and 5 times its
   defocus), and the wrench read from the phase through them was lost;
3. the contact centre and radius of every frame, with the parameters fixed, on the fringe
   phase (a 3-unknown solve, frame after frame; the exposure is held at its start).

Parameters that must stay positive are fitted in log space. A recipe may put a Gaussian
prior on a parameter around its starting value; its residual is scaled by the data's own
noise level (a robust estimate from the residuals), so the prior weighs as many frames'
worth of evidence whatever the camera noise. The uncertainties come from the
Gauss–Newton information of steps 1 and 2 at the end (prior included), scaled by the
residual variance; the covariance between the two blocks is not estimated.
"""

import dataclasses
import importlib.resources
from collections.abc import Sequence
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from .._conventions import NMM_PER_NM, WRENCH_SCALE
from .._fileio import DataError, read_json
from ..inverse import Inverter, LoadState
from ..observe import band_model, BandModel, FringeFields
from ..physics import Contact, Device, Elastomer, Optics


@dataclasses.dataclass(frozen=True)
class Recipe:
    """What a calibration fits and how; the files in `moirejax/fits/recipes/` hold the named ones.

    - `name`, `description`: what the recipe is for.
    - `free`: dotted names of [`Device`][] fields to fit.
    - `log`: the subset fitted in log space (positive quantities).
    - `prior_sd`: a Gaussian prior on a free parameter around its starting value (the
      nominal design, or the unit a transfer starts from), as a standard deviation in
      the fitted coordinate (relative for `log` ones). Parameters without one are free.
    - `rounds`: alternations of parameter and latent solves.
    - `parameter_frames`: frames used in each parameter solve (a random subset).
    - `parameter_steps`, `latent_steps`: solver step limits.
    - `head_frames`: how many of the calibration frames ([`spanning_frames`][] of them) are
      inverted cold to train the residual head and to report the fit on. The head is
      linear in a dozen terms, so a few hundred frames do not teach it more than 160 spanning
      ones (on a simulated unit and an independent renderer's, held-out R² within 0.013 on
      every axis of a head trained on all 492 or 200), and each cold solve costs about a
      second.
    """

    name: str
    free: tuple[str, ...]
    log: tuple[str, ...] = ()
    prior_sd: tuple[tuple[str, float], ...] = ()
    rounds: int = 3
    parameter_frames: int = 48
    parameter_steps: int = 12
    latent_steps: int = 20
    head_frames: int = 160
    description: str = ""

    def __post_init__(self):
        for name in self.free:
            head, _, field = name.partition(".")
            owner = Device if not field else {"elastomer": Elastomer, "optics": Optics}.get(head)
            if owner is None or (field or head) not in {f.name for f in dataclasses.fields(owner)}:
                raise ValueError(f"recipe {self.name!r}: {name!r} is not a Device parameter")
        unknown = set(self.log) - set(self.free)
        unknown |= {n for n, _ in self.prior_sd} - set(self.free)
        if unknown:
            raise ValueError(f"recipe {self.name!r}: {sorted(unknown)} are not among its free parameters")
        if any(sd <= 0 for _, sd in self.prior_sd):
            raise ValueError(f"recipe {self.name!r}: prior standard deviations must be positive")

    def replace(self, **changes) -> "Recipe":
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict[str, Any]:
        obj = dataclasses.asdict(self)
        obj["free"], obj["log"] = list(self.free), list(self.log)
        obj["prior_sd"] = dict(self.prior_sd)
        return obj

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> "Recipe":
        fields = dict(obj)
        fields["free"], fields["log"] = tuple(obj["free"]), tuple(obj.get("log", ()))
        fields["prior_sd"] = tuple(obj.get("prior_sd", {}).items())
        return cls(**fields)


def _named_recipes() -> Traversable:
    """The folder of the recipes that ship with the package, read through `importlib.resources`
    so that it is found in a wheel, a zip or a checkout alike."""
    return importlib.resources.files("moirejax").joinpath("fits", "recipes")


def load_recipe(spec: "str | Path | Recipe") -> Recipe:
    """A [`Recipe`][]: itself, a named one of the package's `moirejax/fits/recipes/`
    (`"unit"`, `"transfer"`), or a recipe JSON file (validated against
    `data_schema/recipe.schema.json`)."""
    if isinstance(spec, Recipe):
        return spec
    path = Path(spec)
    named = _named_recipes().joinpath(f"{spec}.json")
    if not path.suffix and named.is_file():
        with importlib.resources.as_file(named) as file:
            return _recipe_from_file(file)
    if not path.exists():
        names = ", ".join(
            sorted(p.name.removesuffix(".json") for p in _named_recipes().iterdir() if p.name.endswith(".json"))
        )
        raise DataError(f"{spec}: no such recipe file or named recipe (named: {names})")
    return _recipe_from_file(path)


def _recipe_from_file(path: Path) -> Recipe:
    obj = read_json(path, "recipe")
    try:
        return Recipe.from_json(obj)
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None


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


def latents_from_wrench(wrench: np.ndarray, dtype=None) -> LoadState:
    """Every frame's [`LoadState`][moirejax.LoadState] at the start of a calibration (a leading
    frame axis): its reference wrench, on a typical contact centred on the centre of pressure
    that wrench implies, at the device's exposure."""
    wrench = np.asarray(wrench)
    fz = np.maximum(wrench[:, 2], 0.05)
    x0 = np.where(wrench[:, 2] > 0.05, -wrench[:, 4] * NMM_PER_NM / fz, 0.0)
    y0 = np.where(wrench[:, 2] > 0.05, wrench[:, 3] * NMM_PER_NM / fz, 0.0)
    scaled = jnp.asarray(wrench / WRENCH_SCALE, dtype)
    rest = LoadState.at_rest(dtype=scaled.dtype)
    full = lambda v: jnp.full(len(wrench), v, scaled.dtype)  # noqa: E731
    return LoadState(
        scaled,
        jnp.asarray(x0, scaled.dtype),
        jnp.asarray(y0, scaled.dtype),
        full(rest.log_radius),
        *(full(0.0) for _ in range(4)),
    )


def _photometric(name: str) -> bool:
    """Whether a device field is photometric (of the optics: gains, glow, rim, defocus), which
    calibration fits after the mechanical and geometric ones, with those held."""
    return name.startswith("optics.")


class _Problem(eqx.Module):
    inverter: Inverter
    recipe_free: tuple[str, ...] = eqx.field(static=True)
    recipe_log: tuple[str, ...] = eqx.field(static=True)

    def device(self, theta):
        recipe = Recipe(name="fit", free=self.recipe_free, log=self.recipe_log)
        return with_parameters(self.inverter.device, recipe, theta)

    def model(self, theta) -> BandModel:
        """The band model of the unit at `theta`, built once for every frame it predicts.
        Observed fields refer to the reference frame's wavevectors ([`Inverter.observe`][])."""
        inv = self.inverter
        return band_model(self.device(theta), inv.demodulator, inv.model_shape, inv.reference.reference_wavevector)

    def frame_residuals(
        self, model: BandModel, state: LoadState, observed: FringeFields, model_reference: FringeFields
    ):
        predicted = model(state.wrench, state.contact, state.exposure)
        # A weak prior keeps the radius of light contacts from running off.
        prior = state.radius_misfit() * 1e-3
        return jnp.concatenate([self.inverter.band_residual(observed, predicted, model_reference), prior[None]])


def _zero_load(model: BandModel) -> FringeFields:
    return model(jnp.zeros(6, model.x.dtype), Contact())


def _robust_scale(r: jax.Array) -> jax.Array:
    """Standard deviation of the informative residuals (those a zero weight does not blank),
    from their median absolute value."""
    informative = r != 0
    scale = jnp.nanmedian(jnp.where(informative, jnp.abs(r), jnp.nan)) / 0.6745
    return jnp.where(jnp.any(informative), scale, 1.0)


@eqx.filter_jit
def _parameter_solve(
    problem: _Problem, theta, free: jax.Array, latents: LoadState, observed, prior_mean, prior_weight, steps: int
):
    """Levenberg–Marquardt over the entries of `theta` where the mask `free` is set, the
    others held, on the residual each frame keeps once its own contact (centre and radius)
    has taken up what it can: the frames' residuals projected off the directions their
    contacts move them in, at the start (`_contact_directions`).

    Held fixed instead, the contacts pin the parameters they trade with (a stiffer layer
    reads as a smaller patch under the same reading): alternating between the two then
    moves such a parameter little or not at all, however far the data put it."""
    # Every stage solves for the whole vector, its held entries masked out of the model and
    # the prior: their Jacobian columns vanish and the damped steps leave them where they
    # are. One program then serves every stage, instead of one compiled per stage.
    data = (latents, observed)
    start = theta
    directions = jax.lax.stop_gradient(_contact_directions(problem, theta, latents, observed))

    def data_residuals(sub, args):
        latents, observed = args
        model = problem.model(jnp.where(free, sub, theta))
        per_frame = jax.vmap(problem.frame_residuals, in_axes=(None, 0, 0, None))(
            model, latents, observed, _zero_load(model)
        )
        per_frame = per_frame - jnp.einsum("fmk,fk->fm", directions, jnp.einsum("fmk,fm->fk", directions, per_frame))
        return per_frame.ravel()

    noise = jax.lax.stop_gradient(_robust_scale(data_residuals(start, data)))

    def residuals(sub, args):
        prior = jnp.where(free, (sub - prior_mean) * prior_weight, 0.0) * noise
        return jnp.concatenate([data_residuals(sub, args), prior])

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-7, linear_solver=lx.QR())
    sol = optx.least_squares(residuals, solver, start, args=data, max_steps=steps, throw=False)
    # The residual and its Jacobian at the solution from one traced model.
    full, linear = jax.linearize(lambda sub: residuals(sub, data), sol.value)
    J = jax.vmap(linear, out_axes=1)(jnp.eye(sol.value.size, dtype=sol.value.dtype))
    r = full[: full.size - sol.value.size]
    dof = (jnp.sum(r != 0) - jnp.sum(free) - 3 * latents.x0.shape[0]).astype(r.dtype)
    covariance = jnp.linalg.pinv(J.T @ J, hermitian=True) * jnp.sum(r**2) / dof
    return jnp.where(free, sol.value, theta), covariance, jnp.sum(r**2)


def _contact_of(state: LoadState):
    return state.x0, state.y0, state.log_radius


def _contact_directions(problem: _Problem, theta, latents: LoadState, observed) -> Float[Array, "f m 3"]:
    """For every frame, an orthonormal basis `(m, 3)` of the directions its residual moves in
    when its contact's centre and log radius move. A frame's residual depends on its own
    contact only, so one tangent per contact unknown, set in every frame at once, gives each
    frame's three columns."""
    model = problem.model(theta)
    reference = _zero_load(model)

    def residuals(contact):
        states = eqx.tree_at(_contact_of, latents, contact)
        return jax.vmap(problem.frame_residuals, in_axes=(None, 0, 0, None))(model, states, observed, reference)

    contact = _contact_of(latents)
    zero = tuple(jnp.zeros_like(c) for c in contact)
    columns = [
        jax.jvp(
            residuals,
            (contact,),
            (tuple(jnp.ones_like(c) if j == k else z for j, (c, z) in enumerate(zip(contact, zero))),),
        )[1]
        for k in range(3)
    ]
    # A contact unknown a frame does not see (a column of zeros) gives no direction.
    q, r = jnp.linalg.qr(jnp.stack(columns, axis=-1))
    seen = (
        jnp.abs(jnp.diagonal(r, axis1=-2, axis2=-1)) > 1e-6 * jnp.max(jnp.abs(r), axis=(-2, -1), keepdims=True)[..., 0]
    )
    return q * seen[:, None, :].astype(q.dtype)


@eqx.filter_jit
def _latent_solve(problem: _Problem, theta, latents: LoadState, observed, steps: int) -> LoadState:
    """Every frame's contact centre and radius, on the fringe phase; the wrench (the reference
    reading) and the exposure are held."""
    model = problem.model(theta)
    reference = _zero_load(model)

    def one(state: LoadState, obs):
        def residuals(contact, args):
            return problem.frame_residuals(model, eqx.tree_at(_contact_of, state, contact), obs, reference)

        solver = optx.LevenbergMarquardt(rtol=1e-5, atol=1e-6, linear_solver=lx.QR())
        sol = optx.least_squares(residuals, solver, _contact_of(state), max_steps=steps, throw=False)
        return eqx.tree_at(_contact_of, state, sol.value)

    # One frame after another, not vmapped: a vmapped solve steps every frame until the
    # slowest has converged and holds every frame's intermediates at once, so its memory
    # grew with the number of frames.
    return jax.lax.map(lambda pair: one(*pair), (latents, observed))


@dataclasses.dataclass
class CalibrationResult:
    """What [`fit_physical_parameters`][] found.

    - `device`: the fitted [`Device`][].
    - `uncertainty`: the 1-sigma uncertainty of each free parameter, in its own units.
    - `latents`: every frame's [`LoadState`][moirejax.LoadState] (a leading frame axis): its
      reference wrench, and for the frames the parameter solves used the contact centre and
      radius fitted to its fringe phase (the others keep their start).
    - `history`: each round's phase and photometric costs.
    - `inverter`: the [`Inverter`][] of the nominal device the fit started from.
    """

    device: Device
    uncertainty: dict[str, float]
    latents: LoadState
    history: list[dict]
    inverter: Inverter


# Frames demodulated per compiled call when a calibration reads its frames: bounds the
# memory a large set needs to a chunk of frames and the fringe fields of all.
_OBSERVE_CHUNK = 64


@eqx.filter_jit
def _observe_chunk(inverter: Inverter, frames: Float[Array, "b h w"]) -> FringeFields:
    return jax.lax.map(inverter.observe, frames)


def observe_frames(inverter: Inverter, frames: np.ndarray | Sequence) -> FringeFields:
    """The fringe fields of every frame of `frames` (`(n, h, w)`: an array, or a sequence
    that reads frames when indexed), demodulated a chunk at a time: what a calibration keeps
    of its frames. Every chunk but a short last one runs one compiled program."""
    n = len(frames)
    if n == 0:
        raise ValueError("no frames to observe")
    dtype = np.asarray(inverter.device.p1).dtype
    size = min(n, _OBSERVE_CHUNK)
    parts = []
    for start in range(0, n, size):
        chunk = np.asarray(frames[start : start + size], dtype=dtype)
        parts.append(jax.device_get(_observe_chunk(inverter, jnp.asarray(chunk))))
    return jax.tree_util.tree_map(lambda *a: jnp.asarray(np.concatenate(a)), *parts)


def fit_physical_parameters(
    nominal: Device,
    reference: np.ndarray,
    frames: np.ndarray | Sequence,
    wrenches: np.ndarray,
    recipe: "Recipe | str | Path" = "unit",
    *,
    seed: int = 0,
    progress: bool = True,
) -> CalibrationResult:
    """Fit the recipe's parameters of a unit to `frames` with known `wrenches`.

    **Arguments:**

    - `nominal`: the starting [`Device`][] (the design, or another unit's fit).
    - `reference`: a no-contact frame of the unit (the mean of several is better).
    - `frames`: `(n, h, w)` frames in contact, an array or a sequence such as
      [`Dataset.frames`][moirejax.Dataset.frames] that reads them when indexed (they are
      read a chunk at a time, and only their fringe fields are kept); `wrenches`: `(n, 6)`
      reference readings.
    - `recipe`: a [`Recipe`][] or anything [`load_recipe`][] takes. Its priors centre on
      the parameters of `nominal`.

    **Returns:** a [`CalibrationResult`][] with the fitted device and 1-sigma uncertainties
    of the free parameters (in their own units).
    """
    from tqdm.auto import tqdm

    recipe = load_recipe(recipe)
    inverter = Inverter(nominal, reference=reference)
    dtype = np.asarray(inverter.device.p1).dtype
    observed = observe_frames(inverter, frames)
    latents = latents_from_wrench(np.asarray(wrenches), dtype)
    # Every parameter is fitted to the fringe phase, the inversion's observable, which a
    # unit's photometry moves only through a contact's light: the mechanics and geometry
    # first, then the photometry, the others held.
    phase = _Problem(inverter.phase_only(), recipe.free, recipe.log)
    stages = [
        (name, free)
        for name, free in (
            ("phase", tuple(i for i, n in enumerate(recipe.free) if not _photometric(n))),
            ("photometric", tuple(i for i, n in enumerate(recipe.free) if _photometric(n))),
        )
        if free
    ]
    theta = parameter_vector(inverter.device, recipe)
    prior_mean = theta
    sd = dict(recipe.prior_sd)
    prior_weight = jnp.asarray([1.0 / sd[n] if n in sd else 0.0 for n in recipe.free], dtype=dtype)
    rng = np.random.default_rng(seed)
    n = len(frames)
    subsets = [
        np.sort(rng.choice(n, size=min(n, recipe.parameter_frames), replace=False)) for _ in range(recipe.rounds)
    ]
    # Only the frames some parameter solve uses need their contact solved: each frame's is
    # solved on its own, so the others' would change nothing the fit sees.
    used = np.unique(np.concatenate(subsets))
    history = []
    covariance = np.zeros((theta.size, theta.size))
    bar = tqdm(total=recipe.rounds * (len(stages) + 1) + 1, desc="calibrate", disable=not progress)

    def solve_latents(latents):
        pick = lambda a: a[used]  # noqa: E731
        solved = _latent_solve(
            phase,
            theta,
            jax.tree_util.tree_map(pick, latents),
            jax.tree_util.tree_map(pick, observed),
            recipe.latent_steps,
        )
        return jax.tree_util.tree_map(lambda a, b: a.at[used].set(b), latents, solved)

    latents = solve_latents(latents)
    bar.update()
    for round_ in range(recipe.rounds):
        subset = subsets[round_]
        observed_subset = jax.tree_util.tree_map(lambda a, s=subset: a[s], observed)
        costs = {}
        for name, free in stages:
            theta, block, cost = _parameter_solve(
                phase,
                theta,
                jnp.asarray(np.isin(np.arange(theta.size), free)),
                jax.tree_util.tree_map(lambda a, s=subset: a[s], latents),
                observed_subset,
                prior_mean,
                prior_weight,
                recipe.parameter_steps,
            )
            covariance[np.ix_(free, free)] = np.asarray(block)[np.ix_(free, free)]
            costs[f"{name}_cost"] = float(cost)
            bar.update()
        latents = solve_latents(latents)
        bar.update()
        history.append({"round": round_, **costs})
        bar.set_postfix({k: f"{v:.3g}" for k, v in costs.items()})
    bar.close()
    device = phase.device(theta)
    values = [_getter(name)(device) for name in recipe.free]
    sd = np.sqrt(np.clip(np.diag(np.asarray(covariance)), 0, None))
    # Log-space sd to the parameter's own units (first order: sd * value).
    uncertainty = {
        name: float(s * float(v)) if name in recipe.log else float(s) for name, s, v in zip(recipe.free, sd, values)
    }
    return CalibrationResult(
        device=device, uncertainty=uncertainty, latents=jax.device_get(latents), history=history, inverter=inverter
    )
