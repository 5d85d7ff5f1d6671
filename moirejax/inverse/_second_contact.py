r"""A second contact patch, for a frame that one patch does not explain.

A gripper's two fingertips on one pad, or an object resting on it at two places, is not one
round patch. Read through one, such a load comes out badly wrong: the patch sits between the
two contacts, and to reproduce two separate fringe disturbances its pressure tilts and its
radius grows, which moves every axis of the wrench (on two simulated fingertips 1-6 mm
apart, one patch read Fz at R² −0.9 and Ty at −1.4).

The elastomer layer is linear: two contacts deform it by the sum of what each does alone,
and the light each scatters adds too ([`BandModel.of_contacts`][moirejax.BandModel.of_contacts]).
So a second patch costs twelve more unknowns (its wrench about the origin, its centre, its
radius, flatness and elongation, which the pair holds round; the frame's exposure is shared) and
no new physics. The frame's wrench is
the sum of the two, and its covariance is that sum's, from the Jacobian of all twenty-five unknowns.

A second patch can explain noise and model error as readily as a second contact, so it is
tried only on a frame that one patch leaves poorly explained, and kept only where it
removes most of what that patch left (`_SECOND_CONTACT_GAIN`) with both patches pressing
(`both_press`). It starts from the one patch and a second where, away from it, a contact
explains most of what it leaves (a matched filter over the field), or from the one patch's
load split in two, half moved to where its fringe-phase misfit is largest.
"""

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float

from .._conventions import NMM_PER_NM
from ..physics import Contact
from ._solvers import Marquardt
from ._state import ELONGATION_COORDINATES, LoadState, N_PRIORS, N_UNKNOWNS


if TYPE_CHECKING:
    from ._inversion import Inverter


# The solvers' coordinates of two patches: the first patch's thirteen, then the second's
# twelve (all but the exposure: it shares the frame's).
N_PAIR_UNKNOWNS = 2 * N_UNKNOWNS - 1
# Both patches' elongation among them: the pair is solved with round patches.
_PAIR_ELONGATION = (*ELONGATION_COORDINATES, *(N_UNKNOWNS + k for k in ELONGATION_COORDINATES))
# A one-patch solution that leaves more than this share of the fringe phase's change
# unexplained (`Estimate.misfit`) is tried with a second patch. Spherical contacts left
# 0.1-0.3 % on the simulator's own unit and 0.9-4.4 % on the independent renderer's; two
# fingertips read through one patch 25-43 %, lines 10-50 %, rings 4-12 %.
_SECOND_CONTACT_TRIGGER = 0.05
# A second patch is kept when it leaves less than this share of the one patch's misfit.
# On single contacts a second patch took at most a quarter of it away (the rest is noise and
# what the model does not describe, which a second patch does not explain either); on two
# separate contacts it took 80-99.6 %.
_SECOND_CONTACT_GAIN = 0.5
# A start whose solution leaves less than this share of the one patch's misfit has found the
# two contacts (right solutions on simulated fingertips left 0.4-1.2 %), and the next start
# is not tried; one stuck in a wrong basin left a fifth.
_SECOND_CONTACT_FOUND = 0.02
# A two-patch solution that leaves more than this share of the fringe phase's change is
# `unexplained` (one patch: half). Two contacts read with two patches left at most 2 %; three
# contacts read with two leave a third, and the two patches' wrench misses the third's load.
_PAIR_UNEXPLAINED_SHARE = 0.15
# How far (mm) beyond the one patch's edge a start's second patch goes.
_CLEARANCE = 2.0
# The matched search for a second press (`_matched_press`): every this many coarse-grid
# points each way (about 2 mm), probe loads of this many newtons.
_SEARCH_STEP = 2
_PROBE_FORCE = 0.3
# The share of the one patch's load that a start moves to the second patch.
_SPLIT = 0.5


def pair_states(y: Float[Array, "25"]) -> tuple[LoadState, LoadState]:
    """The two patches' [`LoadState`][]s of a two-patch coordinate vector (shared exposure)."""
    first = y[:N_UNKNOWNS]
    second = jnp.concatenate([y[N_UNKNOWNS:], y[N_UNKNOWNS - 1 : N_UNKNOWNS]])
    return LoadState.from_vector(first), LoadState.from_vector(second)


def both_press(y: Float[Array, "25"]) -> Bool[Array, ""]:
    """Whether both patches of a two-patch coordinate vector press (normal force above zero).

    A contact pushes: a patch that pulls is no second contact, however much of the misfit
    a push-pull pair takes away. On a centred 0.9 N press rendered by an independent
    renderer whose grating aliasing one patch cannot explain, such a pair (one patch
    pulling harder than the other pushed) halved the misfit and read the press as a pull of
    0.9 N, with status `converged`.
    """
    return jnp.all(jnp.stack([state.scaled_wrench[2] for state in pair_states(y)]) > 0)


def _pair_vector(first: LoadState, second: LoadState) -> Float[Array, "25"]:
    return jnp.concatenate([first.vector(), second.vector()[: N_UNKNOWNS - 1]])


class ContactPair(eqx.Module):
    """The band inversion of an [`Inverter`][] with two contact patches: the same residual,
    priors on each patch, and what [`finish`][moirejax.inverse._estimate.finish] reads."""

    inverter: "Inverter"

    def _predict(self, y):
        first, second = pair_states(y)
        wrenches = jnp.stack([first.wrench, second.wrench])
        contacts = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), first.contact, second.contact)
        contacts = self.inverter._modelled_contact(contacts)
        return self.inverter.model.of_contacts(wrenches, contacts, first.exposure)

    def _data_residuals(self, y, observed):
        return self.inverter.band_residual(observed, self._predict(y))

    def _prior_residuals(self, y, noise):
        first, second = pair_states(y)
        # Each patch's priors, the shared exposure's once (it is the last prior residual).
        return jnp.concatenate(
            [
                self.inverter._prior_residuals(first.vector(), noise),
                self.inverter._prior_residuals(second.vector(), noise)[: N_PRIORS - 1],
            ]
        )

    def residuals(self, y, args):
        observed, noise = args
        return jnp.concatenate([self._data_residuals(y, observed), self._prior_residuals(y, noise)])

    def _data_jacobian(self, y, observed):
        return jax.jacfwd(self._data_residuals)(y, observed)

    def _prior_jacobian(self, y, noise):
        return jax.jacfwd(self._prior_residuals)(y, noise)

    def _wrench_rows(self, dtype) -> Float[Array, "6 25"]:
        # The frame's scaled wrench is the sum of the patches'.
        eye = jnp.eye(6, dtype=dtype)
        return jnp.concatenate(
            [eye, jnp.zeros((6, N_UNKNOWNS - 6), dtype), eye, jnp.zeros((6, N_PAIR_UNKNOWNS - N_UNKNOWNS - 6), dtype)],
            axis=1,
        )

    def _summary(self, y) -> tuple[LoadState, Contact, Float[Array, "6"]]:
        # The reported state: the whole wrench on the patch that carries the more normal
        # force; the other patch and its share of the wrench beside it.
        first, second = pair_states(y)
        swap = second.scaled_wrench[2] > first.scaled_wrench[2]
        main, other = (
            jax.tree_util.tree_map(lambda a, b: jnp.where(swap, b, a), first, second),
            jax.tree_util.tree_map(lambda a, b: jnp.where(swap, a, b), first, second),
        )
        total = eqx.tree_at(lambda s: s.scaled_wrench, main, first.scaled_wrench + second.scaled_wrench)
        return total, other.contact, other.wrench

    # What `finish` reads of the problem, the inverter's own.
    @property
    def noise_residuals(self):
        return self.inverter.noise_residuals

    @property
    def noise_power(self):
        return self.inverter.noise_power

    @property
    def fringe_weight(self):
        return self.inverter.fringe_weight

    @property
    def unit_phase_noise(self):
        return self.inverter.unit_phase_noise

    @property
    def reference_noise(self):
        return self.inverter.reference_noise

    @property
    def device(self):
        return self.inverter.device

    @property
    def contact_threshold(self):
        return self.inverter.contact_threshold

    def _phase_change_statistic(self, observed, screen):
        return self.inverter._phase_change_statistic(observed, screen)


def _split(first: LoadState, x: Float[Array, ""], y: Float[Array, ""]) -> Float[Array, "25"]:
    """A two-patch start: `_SPLIT` of the patch's forces moved to a patch at `(x, y)` of the
    same radius, pressing at its own centre; the first patch keeps the rest of the wrench."""
    wrench = first.wrench
    force = wrench[:3] * _SPLIT
    moved = jnp.concatenate([force, jnp.stack([y * force[2], -x * force[2]]) / NMM_PER_NM, jnp.zeros(1, wrench.dtype)])
    second = LoadState.from_load(moved, Contact(x, y, first.contact.radius), first.exposure)
    kept = LoadState.from_load(wrench - moved, first.contact, first.exposure)
    return _pair_vector(kept, second)


def _matched_press(pair: ContactPair, first: LoadState, observed, x, y, away, r_one) -> Float[Array, "25"]:
    """The one patch, and a second patch where a contact explains most of what the one patch
    leaves: at every `_SEARCH_STEP`-th coarse-grid point `away` from the one patch, the data
    residual's changes under a `_PROBE_FORCE` press and shear each way there, and the
    least-squares load on them (a matched filter; three model evaluations per point)."""
    to_surface = pair.inverter.device.surface_magnification
    rows = slice(_SEARCH_STEP // 2, None, _SEARCH_STEP)
    candidates = jnp.stack([x[rows, rows].ravel(), y[rows, rows].ravel()], axis=-1) * to_surface
    allowed = away[rows, rows].ravel()
    dtype = first.scaled_wrench.dtype

    def at(point, force):
        # `force` (N) through a patch at `point` pressing at its own centre, as a pair vector.
        moment = jnp.stack([point[1] * force[2], -point[0] * force[2]]) / NMM_PER_NM
        wrench = jnp.concatenate([force, moment, jnp.zeros(1, dtype)])
        second = LoadState.from_load(wrench, Contact(point[0], point[1], first.contact.radius), first.exposure)
        return _pair_vector(first, second)

    def probe(point):
        unit = jnp.eye(3, dtype=dtype)[jnp.asarray([2, 0, 1])] * _PROBE_FORCE
        changes = jnp.stack([pair._data_residuals(at(point, f), observed) - r_one for f in unit], axis=1)
        normal = changes.T @ changes + 1e-12 * jnp.trace(changes.T @ changes) * jnp.eye(3, dtype=dtype)
        amounts = -jnp.linalg.solve(normal, changes.T @ r_one)
        gain = jnp.where(amounts[0] > 0, -(r_one @ changes) @ amounts, 0.0)
        return gain, amounts

    gains, amounts = jax.lax.map(probe, candidates)
    best = jnp.argmax(jnp.where(allowed, gains, -1.0))
    load = amounts[best] * _PROBE_FORCE
    return at(candidates[best], jnp.stack([load[1], load[2], load[0]]))


def solve_pair(problem: "Inverter", y1, r1, args):
    """Two patches from a one-patch solution `y1` (residual `r1`) of `problem`: Levenberg–
    Marquardt from the one patch and a second press where, away from it, a press explains
    most of what it leaves (`_matched_press`), and again from there without shear; then,
    unless that found the two contacts (`_SECOND_CONTACT_FOUND`), the same from the one
    patch with half its load moved to where, away from it, its fringe-phase misfit is
    largest. Returns `(y, r, jacobian, steps,
    result, kept)` of the best
    (`r` and `jacobian` those of [`ContactPair`][moirejax.inverse._second_contact.ContactPair]),
    `kept` whether it beats the one patch by `_SECOND_CONTACT_GAIN`. The runs from the starts
    hold both patches rounded; a last run from the best frees their flatness (both stay
    round: an elongated single patch is `Inverter.second_contact`'s other candidate)."""
    observed, _ = args
    pair = ContactPair(problem)
    first = LoadState.from_vector(y1)
    n_data = r1.shape[0] - N_PRIORS
    one_cost = jnp.sum(r1[:n_data] ** 2)
    size = problem.fringe_weight.size
    sets = problem.device.n_sets
    # Away from the one patch: near it, a load it describes badly (a twisted or sheared
    # contact winds the fringes fast at its rim) leaves a larger misfit than a second contact
    # it does not reach at all.
    x, y = problem.demodulator.coarse_grid()
    to_surface = problem.device.surface_magnification
    away = jnp.hypot(x * to_surface - first.x0, y * to_surface - first.y0) > first.contact.radius + _CLEARANCE
    misfit = jnp.sum(r1[size : 2 * size].reshape(problem.fringe_weight.shape)[:sets] ** 2, axis=0)
    misfit_x, misfit_y = problem._peak_centroid(jnp.where(away, misfit, 0.0))
    starts = jnp.stack(
        [_matched_press(pair, first, observed, x, y, away, r1[:n_data]), _split(first, misfit_x, misfit_y)]
    )
    solver = Marquardt(noise=args[1], tolerance=problem.tolerance, held=_PAIR_ELONGATION)
    # The starts are solved with both patches rounded, and the flatness is freed only from
    # the best of them, as in a cold solve of one patch (`solve_cold`): freed from the starts,
    # a twisted line contact ended at `max_steps` with twice the misfit and Fz 0.45 of its
    # range off, where the rounded pair converged with Fz within 0.01 of it.
    rounded = ContactPair(eqx.tree_at(lambda i: i.fitted_flatness, problem, jnp.asarray(False)))

    def data_cost(sol):
        # From the residual the solver holds at its solution: no model run.
        cost = jnp.sum(sol.state.residual[:n_data] ** 2)
        return jnp.where(jnp.isfinite(cost), cost, jnp.inf)

    # Runs: each start, then the better solution so far with both patches' shear zeroed (shear
    # absorbs a misplaced patch; once the patches sit right, a solve without it finds the
    # right basin, and converges back in a few steps where it already was). The second
    # start runs only if the first pair of runs did not find the two contacts.
    def cond(carry):
        k, _, cost, *_ = carry
        found = cost < _SECOND_CONTACT_FOUND * one_cost
        return (k < 2) | ((k < 2 * starts.shape[0]) & ~found)

    def body(carry):
        k, y, cost, result, steps = carry
        first, second = pair_states(y)
        no_shear = _pair_vector(first.with_shear(0.0, 0.0), second.with_shear(0.0, 0.0))
        start = jnp.where(k % 2 == 0, starts[k // 2], no_shear)
        sol = optx.least_squares(
            rounded.residuals, solver, start, args=args, max_steps=2 * problem.max_steps, throw=False
        )
        new_cost = data_cost(sol)
        better = new_cost < cost
        return (
            k + 1,
            jnp.where(better, sol.value, y),
            jnp.where(better, new_cost, cost),
            optx.RESULTS.where(better, sol.result, result),
            steps + jnp.asarray(sol.stats["num_steps"], jnp.int32),
        )

    init = (
        jnp.asarray(0, jnp.int32),
        starts[0],
        jnp.asarray(jnp.inf, y1.dtype),
        optx.RESULTS.successful,
        jnp.asarray(0, jnp.int32),
    )
    _, y, cost, result, steps = jax.lax.while_loop(cond, body, init)
    freed = optx.least_squares(pair.residuals, solver, y, args=args, max_steps=2 * problem.max_steps, throw=False)
    # The rounded solution's residual as the freed pair sees it (the same load, the flatness
    # its state holds).
    rounded_residual = pair.residuals(y, args)
    freed_cost, rounded_cost = data_cost(freed), jnp.sum(rounded_residual[:n_data] ** 2)
    better = jnp.isfinite(freed_cost) & (freed_cost <= rounded_cost)
    y = jnp.where(better, freed.value, y)
    residual = jnp.where(better, freed.state.residual, rounded_residual)
    cost = jnp.where(better, freed_cost, rounded_cost)
    result = optx.RESULTS.where(better, freed.result, result)
    steps = steps + jnp.asarray(freed.stats["num_steps"], jnp.int32)
    kept = both_press(y) & (cost < _SECOND_CONTACT_GAIN * one_cost)
    return y, residual, pair._data_jacobian(y, observed), steps, result, kept
