"""The two solvers of the band inversion: Levenberg–Marquardt for a frame without a usable
last solution (several starts, then a refinement on the fringe phase), and frozen-Jacobian
Gauss–Newton iterations for the next frame of a stream.

Each takes the problem (an [`Inverter`][]: its residual, Jacobians and priors) and works on
the solvers' coordinates of [`LoadState.vector`][moirejax.LoadState.vector].
"""

from collections.abc import Callable
from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ._state import ELONGATION_COORDINATES, LoadState, N_PRIORS


if TYPE_CHECKING:
    from ._inversion import Inverter


# A cold solve whose cost is above this fraction of the zero-load cost tries more starts.
_UNEXPLAINED = 0.004
# Starts are solved to this many standard errors of each unknown before their costs are
# compared; the best is then polished to the inverter's tolerance.
_SEARCH_TOLERANCE = 0.5
# Above the calibrated normal force the shear fallbacks grow as the normal force (in units of
# its range) to this power: a grasp's friction carries more shear (`grasp_limits`: 0.2 N at
# 1.2 N, about 1 N at 10 N).
_HEAVY_SHEAR = 0.75
# A start twisted by more than this share of Tz's range also tries the patch wider by
# `_WIDER_PATCH`, and half the twist: a twisted press can settle on a patch too small
# carrying too much twist (on the independent renderer, 0.78 N with 7.5 mN*m on a 3.8 mm
# patch read as 0.65 N with 9.9 mN*m on 3.1 mm, 8.5 % of the phase change left; either start
# finds the right basin, 0.4 %). Below it the trade has too little twist to work with, and
# the two starts would only add to the cost of every poorly explained frame.
_TWISTED = 0.5
_WIDER_PATCH = 1.25


def _gauss_newton(jtj, gradient, noise):
    """The Gauss–Newton step of a whitened least-squares problem (normal matrix `jtj`,
    gradient `gradient`, residuals whose noise has standard deviation `noise`), and the
    standard error of each unknown there."""
    inverse = _covariance_shape(jtj)
    return -inverse @ gradient, _standard_errors(jtj, inverse, noise)


def _covariance_shape(jtj):
    # The pseudo-inverse of the normal matrix, taken at unit diagonal: the unknowns'
    # information spans many decades (a contact centre in mm against a prior-held
    # flatness), which single precision cannot invert unscaled.
    scale = jax.lax.rsqrt(jnp.maximum(jnp.diagonal(jtj), 1e-30 * jnp.max(jnp.diagonal(jtj))))
    return scale[:, None] * jnp.linalg.pinv(jtj * scale[:, None] * scale[None, :], hermitian=True) * scale[None, :]


def _standard_errors(jtj, inverse, noise):
    """Each unknown's standard error at the noise level `noise` (normal matrix `jtj`, its
    pseudo-inverse `inverse`); infinite for an unknown neither the data nor the priors
    inform: on the fringe phase alone the exposure is not seen at all, and takes no step."""
    information = jnp.diagonal(jtj)
    informed = information > 1e-9 * jnp.max(information)
    sigma = noise * jnp.sqrt(jnp.clip(jnp.diagonal(inverse), 1e-30, None))
    return jnp.where(informed, sigma, jnp.inf)


def _largest_move(dy, sigma):
    """The largest move of an informed unknown in a step `dy`, in its standard errors."""
    return jnp.max(jnp.where(jnp.isinf(sigma), 0.0, jnp.abs(dy) / sigma))


class _MarquardtState(eqx.Module):
    residual: Array
    jacobian: Array
    # The unknowns' standard errors at the current point.
    sigma: Array
    damping: Array
    converged: Bool[Array, ""]


class Marquardt(optx.AbstractLeastSquaresSolver):
    r"""Levenberg–Marquardt for the small whitened problems of the inversion, stopped by
    statistics rather than by arithmetic.

    A frame's problem has a dozen or two unknowns and thousands of residuals whose noise
    level `noise` is known. The solver stops when the Gauss–Newton step from its current
    point would move no unknown by more than `tolerance` of that unknown's standard error:
    closer than that, the data cannot tell the points apart. Where the model does not
    describe the frame exactly the cost is not the quadratic that step assumes, and a
    rejected step shorter than the tolerance ends the solve too. (optimistix's own solvers
    stop on a tolerance on the unknowns' values and the residuals, which knows nothing of
    the noise: in single precision they spent steps on changes of the cost that rounding
    hides, and on a poorly measured axis, such as the shear along line gratings, kept
    walking down a valley the data do not resolve.)

    The damping is optimistix's `LevenbergMarquardt`'s, step for step: $J^\top J +
    \lambda I$ in the solvers' coordinates, $\lambda$ starting at 1, divided by 3.5
    after a step that achieves more than 99 % of the reduction its linear model predicts,
    multiplied by 4 after one that achieves less than 1 % (and is rejected). A cold solve's
    basin depends on that path: Marquardt's damping relative to the diagonal with
    Nielsen's update converged in a quarter of the steps on frames of an independent
    renderer, with the same estimates, but sent a sheared 6 N grasp press into a wrong
    basin that this path avoids. A rejected step costs one evaluation of the residual;
    the Jacobian is taken only where a step is accepted.

    `held` names coordinates the solve keeps at their start: a round patch's elongation, which
    the model then does not see. They take no step and no column of the Jacobian, so the
    solve is the one of the remaining unknowns alone, in the same arithmetic and at their
    cost.
    """

    noise: Float[Array, ""]
    tolerance: float | Float[Array, ""] = 0.05
    held: tuple[int, ...] = eqx.field(static=True, default=())
    # Unused (the stopping rule is `tolerance`); optimistix's solvers declare them.
    rtol: float = 0.0
    atol: float = 0.0
    norm: Callable = optx.max_norm

    def _free(self, y):
        return tuple(k for k in range(y.shape[0]) if k not in self.held)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        residual, jacobian = _residual_and_jacobian(fn, y, args, self._free(y))
        dy, sigma = _gauss_newton(jacobian.T @ jacobian, jacobian.T @ residual, self.noise)
        converged = _largest_move(dy, sigma) < self.tolerance
        return _MarquardtState(residual, jacobian, sigma, jnp.asarray(1.0, residual.dtype), converged)

    def step(self, fn, y, args, options, state, tags):
        jtj = state.jacobian.T @ state.jacobian
        gradient = state.jacobian.T @ state.residual
        free = self._free(y)
        dy = -jnp.linalg.solve(jtj + state.damping * jnp.eye(len(free), dtype=y.dtype), gradient)
        y_new = y.at[jnp.asarray(free)].add(dy)
        # One evaluation of the model at the trial point, its Jacobian taken only if the
        # step is accepted: a second traced model for the trial's cost alone made the
        # compiled program larger.
        residual_new, linear, aux = jax.linearize(lambda v: fn(v, args), y_new, has_aux=True)
        cost = jnp.sum(state.residual**2)
        cost_new = jnp.sum(residual_new**2)
        # The reduction the linear model predicts, and the share of it the step achieved.
        predicted = cost - jnp.sum((state.residual + state.jacobian @ dy) ** 2)
        gain = (cost - cost_new) / jnp.where(predicted > 0, predicted, jnp.inf)
        accept = jnp.isfinite(cost_new) & (predicted > 0) & (gain >= 0.01)
        residual = jnp.where(accept, residual_new, state.residual)
        jacobian = jax.lax.cond(accept, lambda: _columns(linear, y, free), lambda: state.jacobian)
        y = jnp.where(accept, y_new, y)
        damping = state.damping * jnp.where(accept, jnp.where(gain > 0.99, 1 / 3.5, 1.0), 4.0)
        # A rejected step is measured in the standard errors of the point it left.
        stalled = ~accept & (_largest_move(dy, state.sigma) < self.tolerance)
        gauss_newton, sigma = _gauss_newton(jacobian.T @ jacobian, jacobian.T @ residual, self.noise)
        converged = (_largest_move(gauss_newton, sigma) < self.tolerance) | stalled
        return y, _MarquardtState(residual, jacobian, sigma, damping, converged), aux

    def terminate(self, fn, y, args, options, state, tags):
        return state.converged, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


def _residual_and_jacobian(fn, y, args, free):
    residual, linear = jax.linearize(lambda v: fn(v, args)[0], y)
    return residual, _columns(linear, y, free)


def _columns(linear, y, free):
    # The Jacobian's columns of the free coordinates `free` only.
    return jax.vmap(linear, out_axes=1)(jnp.eye(y.shape[0], dtype=y.dtype)[jnp.asarray(free)])


def chord(problem: "Inverter", y, r, jacobian, args):
    r"""Gauss–Newton iterations from the last frame's Jacobian, kept current by Broyden updates.

    At camera rate consecutive frames are close, so the data Jacobian barely changes;
    reusing it makes each iteration one model evaluation instead of thirteen. Each step
    $\Delta y$ and the residual change $\Delta r$ it caused (exact: same frame, same
    model) update the Jacobian along that direction,
    $J \leftarrow J + (\Delta r - J\Delta y)\Delta y^\top / \Delta y^\top\Delta y$,
    so it follows the load along the stream instead of going stale. `r` is the
    residual at `y` (a stream knows it from the last frame's prediction). The iterations
    stop when the next step would move every unknown by less than `chord_tolerance`
    of its standard error; that last step is returned as `pending`, for the estimate to
    take without a model run to check it (its error is the Jacobian's relative error
    times the step, a small fraction of a standard error). The frame is handed to
    Levenberg–Marquardt if that has not happened after `chord_steps` iterations or if
    the cost rises. Returns `(y, r, jacobian, steps, accepted, pending)`, `r` and
    `jacobian` at `y`.
    """
    observed, noise = args

    def step(y, r, jacobian):
        prior_jac = problem._prior_jacobian(y, noise)
        jtj = jacobian.T @ jacobian + prior_jac.T @ prior_jac
        gradient = jacobian.T @ r[:-N_PRIORS] + prior_jac.T @ r[-N_PRIORS:]
        # Unscaled, so that single precision drops the directions the data barely see
        # (the shear along line gratings, the exposure on the fringe phase) instead of
        # stepping along them: taken at unit diagonal as `_gauss_newton` does, the
        # chord steps of a simulated press-twist-release stream failed more often and the
        # stream sustained 1.0 frames/s instead of 2.8.
        inverse = jnp.linalg.pinv(jtj, hermitian=True)
        dy = -inverse @ gradient
        return dy, _largest_move(dy, _standard_errors(jtj, inverse, noise))

    cost0 = jnp.sum(r**2)
    dy, size = step(y, r, jacobian)

    def cond(carry):
        *_, size, k, ok = carry
        return ok & (size > problem.chord_tolerance) & (k < problem.chord_steps)

    def body(carry):
        y, r, jacobian, dy, size, k, _ = carry
        y_new = y + dy
        r_new = problem.residuals(y_new, args)
        # Below ~1e-4 of an axis' range the residual change is rounding, not secant.
        secant = jnp.max(jnp.abs(dy)) > 1e-4
        mismatch = (r_new - r)[:-N_PRIORS] - jacobian @ dy
        update = jnp.outer(mismatch, dy) / jnp.maximum(jnp.sum(dy**2), 1e-30)
        jacobian = jnp.where(secant & jnp.all(jnp.isfinite(update)), jacobian + update, jacobian)
        dy_new, size_new = step(y_new, r_new, jacobian)
        # A rising cost or a growing step means the Jacobian is too far from the truth:
        # give the frame to Levenberg–Marquardt. (Single precision resolves the cost to
        # about 1e-6 of itself, a step of ~0.1 standard error, hence the slack.)
        shrinking = (size_new < size) | (size_new <= problem.chord_tolerance)
        ok = (jnp.sum(r_new**2) <= cost0 * (1 + 1e-5)) & shrinking & jnp.all(jnp.isfinite(r_new))
        return y_new, r_new, jacobian, dy_new, size_new, k + 1, ok

    init = (y, r, jacobian, dy, size, jnp.asarray(0, jnp.int32), jnp.all(jnp.isfinite(r)))
    y, r, jacobian, dy, size, steps, ok = jax.lax.while_loop(cond, body, init)
    accepted = ok & (size <= problem.chord_tolerance)
    return y, r, jacobian, steps, accepted, jnp.where(accepted, dy, 0.0)


def levenberg_marquardt(
    problem: "Inverter",
    y0,
    args,
    *,
    more_starts: bool | Bool[Array, ""] = True,
    when_unexplained: bool | Bool[Array, ""] = True,
    polish: bool | Bool[Array, ""] = True,
    elongated: bool = False,
):
    """Levenberg–Marquardt from `y0`, then again from its solution with the shear
    forces zeroed; the lower cost wins. The patch is round (its elongation held at `y0`'s
    and not modelled) unless `elongated`.

    From a cold start the contact and normal load are wrong at first, and the shear can
    absorb part of that error and settle in a wrong basin (on one unit's held-out
    loads, 1 frame in 98 ended with Fy 0.18 N off and 3.7x the residual). Once contact
    and normal load are right, a second solve with no shear finds the right basin; when
    the first solve was already right it converges back in a few steps.

    When neither converges (a strong wrong basin: a light, strongly sheared press whose
    brightness centroid misplaces the contact by 1.7 mm ended at 300x the right cost),
    or when the better one leaves more than `_UNEXPLAINED` of the zero-load residual
    unexplained, seven more starts in turn: the contact where the fringes changed most
    ([`Inverter.fringe_change_centre`][moirejax.Inverter.fringe_change_centre]), the contact
    halfway to the centre, the frame's own cold start placed by its fringes
    ([`Inverter.fringe_placed_guess`][moirejax.Inverter.fringe_placed_guess]: no earlier
    solve's basin in it, for a refinement whose first solve the brightness misled), and each
    shear direction at half its range (more above the calibrated normal force, `_HEAVY_SHEAR`);
    from a twisted start also a wider patch and half the twist (`_TWISTED`). The second test catches a wrong basin the solver
    calls converged: on 200 mixed noise-free and noisy loads, correct fits left at most
    0.14% unexplained and two wrong ones (Fx 116% and Fy 35% of range off) 1.3-1.8%.
    A faint contact in noise also leaves much unexplained and pays for the extra starts.

    `when_unexplained=False` runs them only when neither of the first two converged: for
    a first solve whose answer a refinement on another residual replaces (see
    [`solve_cold`][]).

    `more_starts=False` (streams) stops after the first two starts. On a `high`-fidelity
    recording of an uncalibrated unit with illumination drift, right fits leave 0.3-3%
    unexplained (6% without contact) and faint presses often end at `max_steps`, so the
    further starts ran at most cold solves and took them from 0.7 to 2-3.5 s, which a live
    stream pays in dropped frames at each contact onset. A stream's cold start is usually
    a light press at contact onset, the stream follows the load from there, and a frame
    that did not converge is retried cold on the next frame.

    Each start is solved to `_SEARCH_TOLERANCE` standard errors, enough to compare basins;
    with `polish` the best is then solved to the inverter's `tolerance`. (A refinement
    whose answer only starts the next one needs no polish.)
    """
    problem = eqx.tree_at(lambda i: i.fitted_elongation, problem, jnp.asarray(elongated))
    held = () if elongated else ELONGATION_COORDINATES
    zero_cost = jnp.sum(problem._zero_residuals(args[0]) ** 2)
    fringe_centre = problem.fringe_change_centre(args[0])
    first = LoadState.from_vector(y0)
    # Half the shear a press of this normal force can carry (`_HEAVY_SHEAR`): half the
    # calibrated range up to the calibrated normal force, more under a grasp.
    reach = 0.5 * jnp.maximum(first.scaled_wrench[2], 1.0) ** _HEAVY_SHEAR
    fallbacks = jnp.stack(
        [
            first.with_shear(0.0, 0.0).with_contact_at(fringe_centre[0], fringe_centre[1]).vector(),
            first.with_contact_at(0.5 * first.x0, 0.5 * first.y0).vector(),
            problem.fringe_placed_guess(args[0]).vector().astype(y0.dtype),
            first.with_shear(reach, first.scaled_wrench[1]).vector(),
            first.with_shear(-reach, first.scaled_wrench[1]).vector(),
            first.with_shear(first.scaled_wrench[0], reach).vector(),
            first.with_shear(first.scaled_wrench[0], -reach).vector(),
            first.with_radius_scaled(_WIDER_PATCH).vector(),
            first.with_twist_scaled(0.5).vector(),
        ]
    )

    # One solver inside a loop over the starts, not one per start: each traced solve
    # is a copy of the whole model in the compiled program, and compilation was most of
    # a first frame's cost (35 s with three copies).
    twisted = jnp.abs(first.scaled_wrench[5]) > _TWISTED
    tried = jnp.where(twisted, fallbacks.shape[0], fallbacks.shape[0] - 2)

    def searching(k, more):
        return (k < 2) | (more & (k < 2 + tried))

    def cond(carry):
        k, *_, more, polished = carry
        return searching(k, more) | ~polished

    def body(carry):
        k, y, residual, jacobian, cost, result, steps, more, polished = carry
        polishing = ~searching(k, more)
        no_shear = LoadState.from_vector(y).with_shear(0.0, 0.0).vector()
        start = jnp.where(
            k == 0, y0, jnp.where(k == 1, no_shear, fallbacks[jnp.clip(k - 2, 0, fallbacks.shape[0] - 1)])
        )
        start = jnp.where(polishing, y, start)
        tolerance = jnp.where(polishing, problem.tolerance, max(problem.tolerance, _SEARCH_TOLERANCE))
        solver = Marquardt(noise=args[1], tolerance=tolerance, held=held)
        sol = optx.least_squares(problem.residuals, solver, start, args=args, max_steps=problem.max_steps, throw=False)
        # The solver's state holds the residual and its Jacobian at its solution: no model
        # run to cost it, nor a Jacobian taken again for its covariance.
        new_residual = sol.state.residual
        new_cost = jnp.sum(new_residual**2)
        new_cost = jnp.where(jnp.isfinite(new_cost), new_cost, jnp.inf)
        better = (k == 0) | (new_cost < cost) | (polishing & (new_cost <= cost))
        y = jnp.where(better, sol.value, y)
        residual = jnp.where(better, new_residual, residual)
        jacobian = jnp.where(better, sol.state.jacobian, jacobian)
        cost = jnp.where(better, new_cost, cost)
        result = optx.RESULTS.where(better, sol.result, result)
        steps = steps + jnp.asarray(sol.stats["num_steps"], jnp.int32)
        # After the first two starts, the fallbacks run only if neither converged or
        # the better one explains the frame poorly.
        poor = (cost > _UNEXPLAINED * zero_cost) & when_unexplained
        more = jnp.where(k == 1, more_starts & ((result != optx.RESULTS.successful) | poor), more)
        return k + 1, y, residual, jacobian, cost, result, steps, more, polished | polishing

    n_residuals = jax.eval_shape(problem.residuals, y0, args).shape[0]
    free = tuple(k for k in range(y0.shape[0]) if k not in held)
    init = (
        jnp.asarray(0, jnp.int32),
        y0,
        jnp.zeros(n_residuals, y0.dtype),
        jnp.zeros((n_residuals, len(free)), y0.dtype),
        jnp.asarray(jnp.inf, y0.dtype),
        optx.RESULTS.successful,
        jnp.asarray(0, jnp.int32),
        jnp.asarray(False),
        ~jnp.asarray(polish),
    )
    _, y, residual, jacobian, _, result, steps, _, _ = jax.lax.while_loop(cond, body, init)
    # The data rows of the free columns; a held coordinate is not in the model (zero column).
    data_jacobian = jnp.zeros((n_residuals - N_PRIORS, y0.shape[0]), jacobian.dtype)
    return y, residual, data_jacobian.at[:, jnp.asarray(free)].set(jacobian[:-N_PRIORS]), steps, result


def best_start(candidates, residuals):
    """The candidate with the lowest cost, and its residual."""
    costs = jnp.stack([jnp.sum(r**2) for r in residuals])
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    best = jnp.argmin(costs)
    return jnp.stack(candidates)[best], jnp.stack(residuals)[best]


def solve_cold(problem: "Inverter", y0, args, *, more_starts: bool | Bool[Array, ""]):
    """Levenberg–Marquardt on the full residual from `y0` (the brightness places a cold
    start in the right basin on a unit that glows), then, unless the inverter fits the
    brightness, two refinements on the fringe phase alone: with the contact light the
    device describes, then from there with the light each load explains best
    ([`Inverter.contact_light_scale`][moirejax.Inverter.contact_light_scale]). Returns
    `(y, r, jacobian, steps, result)`, `r` and `jacobian` those of `problem._fit`.

    The further starts of a poorly explained frame run in the last refinement, whose
    answer is the estimate, not in the first solve: on a unit the model does not describe
    exactly, the full residual (fringe amplitude and brightness too) leaves every frame
    poorly explained (all 40 loads of the independent renderer's set), so the first
    solve's further starts ran on every frame, for a large share of its cost, and moved no
    estimate there by more than 0.02% of its range. When neither of the first solve's two
    starts converges, they run there too.

    Refining with the fitted light straight from the full residual's solution can end in
    a wrong basin: on a line-grating unit whose fringes see the normal force weakly, the
    fit let the normal force fall to nothing while the light rose to its bound (0.84 N read
    as 0.01 N, at four times the cost of the right solution). From the fixed light's
    solution, which is in the right basin, the fitted light only lowers the cost.

    The contact's flatness is held at a sphere's until the last refinement, for the same
    reason: freed from the cold start, it let a 6 N sheared sphere end in a wrong basin
    (flatness 1.9, the shear 3.4 ranges off), which the rounded patch's solution avoids; from
    there it takes a flat punch's pressure to its edge (an 8 N punch: 4.5 % of the phase
    change left by the rounded patch, 0.2 % with its flatness fitted).
    """
    rounded = eqx.tree_at(
        lambda i: i.fitted_flatness, problem, jnp.asarray(problem.brightness) & problem.fitted_flatness
    )
    if problem.brightness:
        return levenberg_marquardt(rounded, y0, args, more_starts=more_starts, when_unexplained=True, polish=True)
    fit = problem._fit

    def refinement(fitted: bool):
        light = jnp.asarray(fitted)
        return eqx.tree_at(lambda i: (i.fitted_light, i.fitted_flatness), fit, (light, light & problem.fitted_flatness))

    # The three stages are one traced solver in a scan over the problems' differing leaves:
    # each traced solve is a copy of the whole model in the compiled program.
    problems = _stacked([rounded, refinement(False), refinement(True)])
    more = jnp.asarray(more_starts) & jnp.asarray([True, False, True])
    unexplained = jnp.asarray([False, True, True])
    polished = jnp.asarray([False, False, True])

    def stage(y, k):
        solution = levenberg_marquardt(
            problems(k), y, args, more_starts=more[k], when_unexplained=unexplained[k], polish=polished[k]
        )
        return solution[0], solution

    _, (ys, rs, jacobians, steps, results) = jax.lax.scan(stage, y0, jnp.arange(3))
    last = jax.tree_util.tree_map(lambda a: a[-1], (ys, rs, jacobians, results))
    return *last[:3], jnp.sum(steps).astype(steps.dtype), last[3]


def _stacked(problems: list) -> Callable[[Int[Array, ""]], "Inverter"]:
    """The problem at index `k` of `problems` (one structure, some leaves replaced): the
    leaves they share are kept once, the others stacked along a leading axis."""
    flat = [jax.tree_util.tree_flatten(p) for p in problems]
    (leaves, treedef), others = flat[0], flat[1:]
    if any(other_def != treedef for _, other_def in others):
        raise ValueError("the problems of one scan must share their structure")
    columns = list(zip(leaves, *(other for other, _ in others)))
    shared = [all(leaf is column[0] for leaf in column) for column in columns]
    stacked = [column[0] if same else jnp.stack(column) for column, same in zip(columns, shared)]

    def at(k):
        return jax.tree_util.tree_unflatten(treedef, [leaf if same else leaf[k] for leaf, same in zip(stacked, shared)])

    return at
