"""From a solution of the band inversion to an [`Estimate`][]: the covariance of the wrench, the
contact test, the status, and the [`Track`][] a stream continues from."""

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from .._conventions import WRENCH_SCALE
from ._solvers import _covariance_shape
from ._state import Estimate, LoadState, N_UNKNOWNS, Status, Track


if TYPE_CHECKING:
    from ._inversion import _Screen, Inverter


# A contact frame whose fringe phase residual, above the pixel noise, keeps more than this
# share of its change from the reference (also above the noise) is one the model does not
# explain.
_UNEXPLAINED_SHARE = 0.5
# A fit needing more than this many calibrated ranges on any axis (12 N of normal force) is
# not a load the model describes either: a foreign scene, another unit, a moved camera or an
# occlusion is "explained" by an absurd load as readily as by a small one.
_IMPLAUSIBLE_RANGES = 10.0
# A frame whose fringe phase disagrees with the reference's over the field (`_Screen.disagrees`:
# a grasp load, or not this unit's fringes) is refused as a bad frame unless its fit leaves
# at most this share of the phase change, with a plausible load. Spheres pressed with
# 4.6-7.3 N left 0.1-0.3%; noise, natural images and frames of other designs, fitted all
# the same, left 39-62%.
_DISAGREEING_SHARE = 0.15
# Beyond the calibrated normal force (1.2 N) no calibration has checked the model, and a
# fit must explain the frame more closely to be believed: at most this share of the phase
# change. Spheres pressed with 4.6-7.3 N left 0.1-0.3% and were read within 0.08 of each
# axis' range (the independent renderer's, on line gratings: 0.9-1.3%); flat punches pressed with 4.2-8.9 N, which the round patch does not describe,
# left 2.4-21%, those above 10% with errors of 0.9-2.2 ranges.
_HEAVY_SHARE = 0.1
# How many standard errors a fit's centre of pressure may lie off the imaged contact surface
# (`_off_the_surface`) before the load is one no contact in view applies.
_SURFACE_SIGMAS = 3.0
# Side (coarse-grid cells) of the tiles whose disagreement measures the model error in the
# covariance: wider than the demodulated noise's correlation, so that tiles are independent
# under noise alone, and small enough that a frame has dozens of them.
_TILE_CELLS = 4


def reweighing_step(jtj: Float[Array, "n n"], gradient: Float[Array, " n"]) -> Float[Array, " n"]:
    """The Gauss–Newton step of `finish`'s reweighed priors (normal matrix `jtj`, gradient
    `gradient`), without the directions the working precision cannot resolve (a plain
    pseudo-inverse): along a direction the data barely see, a full step leaves the region
    where the linearisation holds. On two simulated fingertips, taking it at unit diagonal
    as the covariance does (`_covariance_shape`, which must keep every direction: dropped,
    a barely seen axis would read as known almost exactly) moved one frame's Fx by 1.07 of
    its range."""
    return -jnp.linalg.pinv(jtj, hermitian=True) @ gradient


def finish(
    problem: "Inverter",
    screen,
    observed,
    r_zero,
    noise,
    y,
    r,
    jacobian,
    steps,
    result,
    start,
    pending=None,
    unexplained_share: float = _UNEXPLAINED_SHARE,
):
    """Covariance, contact test and status of a solution `y` with residual `r`; the
    estimate is at `y + pending` (see `_solvers.chord`), the track stays at `y`,
    where its prediction is known. A solution that leaves more than `unexplained_share`
    of the fringe phase's change (above the noise) is `unexplained`. `problem` is an
    [`Inverter`][] or its [`ContactPair`][moirejax.inverse._second_contact.ContactPair];
    the latter's solution hands on no [`Track`][] (`None`)."""
    dtype = y.dtype
    r_data = r[: jacobian.shape[0]]
    # The priors were weighed against the pixel noise. Where the model misses part of
    # the frame (a unit or renderer it does not describe exactly), the residual is larger
    # than that noise, the data say less than the pixel noise suggests, and the priors
    # must weigh as much against the residual's actual size: one Gauss-Newton step with
    # the priors at that weight, from the solution and its Jacobian, moves the unknowns
    # the data do not see back towards their priors. On a frame the model explains to the
    # noise level the weight is unchanged and the step is the solver's own tolerance.
    # The residual's size where the unknowns' signal lives (each datum weighed by how much
    # the unknowns move it): a misfit near the contact is diluted by the far field in a
    # plain mean.
    signal = jnp.sum(jacobian**2, axis=1)
    misfit = jnp.sqrt(jnp.sum(r_data**2 * signal) / jnp.maximum(jnp.sum(signal), 1e-30))
    prior_weight = jnp.maximum(noise, misfit)
    prior_jac = problem._prior_jacobian(y, prior_weight)
    jtj = jacobian.T @ jacobian + prior_jac.T @ prior_jac
    reweigh = reweighing_step(jtj, jacobian.T @ r_data + prior_jac.T @ problem._prior_residuals(y, prior_weight))
    inverse = _covariance_shape(jtj)
    pending = jnp.where(jnp.all(jnp.isfinite(reweigh)), reweigh, 0.0) + (0.0 if pending is None else pending)
    # Sandwich covariance for correlated noise: the estimate moves by A e for a data
    # noise e, A = (J^T J)^-1 J_data^T; E[e e^T] comes from the stored unit-noise draws.
    # The pixel variance is what makes the residual's expected size match its actual one.
    # Every product ordered with samples leading: (samples, n) @ (n, unknowns) first, no
    # transposes; XLA's CPU dots are several times slower the other way round.
    moved = (problem.noise_residuals @ jacobian) @ inverse  # (samples, unknowns), A e per draw
    samples = problem.noise_residuals.shape[0]
    unit_cov = moved.T @ moved / samples
    explained = jnp.sum(moved * (moved @ (jacobian.T @ jacobian))) / samples
    unit_rss = problem.noise_power - explained
    variance = jnp.sum(r_data**2) / jnp.maximum(unit_rss, 1e-30)
    # The priors act as observations with the residual's noise level: their share of the
    # uncertainty is what keeps an axis the data do not see at about its prior width.
    prior_part = inverse @ (prior_jac.T @ prior_jac) @ inverse * prior_weight**2
    # Model error: where the model misses part of the frame, different parts of the field
    # disagree about the unknowns by more than their noise, and the white-noise sandwich
    # above, however scaled, does not see it (the misfit along the Jacobian went into the
    # estimate). The cluster-robust sandwich does: each tile of the coarse grid's score
    # J_c^T r_c is what leaving that tile out would move the estimate by, to first order, and
    # their spread estimates the data part of the covariance whatever the residual's cause.
    # Its excess over the noise part (the positive part, so that on a frame the model
    # explains it adds only its own sampling noise) is the model's share of the uncertainty.
    tiles = _tile_index(problem.fringe_weight.shape, r_data.shape[0])
    count = int(tiles.max()) + 1
    scores = jax.ops.segment_sum(jacobian * r_data[:, None], jnp.asarray(tiles), num_segments=count)
    robust = inverse @ (scores.T @ scores) @ inverse * (count / (count - 1.0))
    values, vectors = jnp.linalg.eigh(robust - unit_cov * variance)
    model_part = (vectors * jnp.clip(values, 0.0, None)[None, :]) @ vectors.T
    cov_y = unit_cov * variance + model_part + prior_part
    scale = jnp.asarray(WRENCH_SCALE, dtype)
    rows = problem._wrench_rows(dtype)
    covariance = (rows @ cov_y @ rows.T) * scale[:, None] * scale[None, :]
    y_out = y + pending
    solution, second, second_wrench = problem._summary(y_out)
    wrench, contact, exposure = solution.wrench, solution.contact, solution.exposure
    # Contact from the data: has the fringe phase moved beyond its noise somewhere?
    in_contact = problem._phase_change_statistic(observed, screen) > problem.contact_threshold
    status = _status(result, screen, in_contact, y)
    # How much of the fringe phase's change from the reference the fit leaves, both above
    # what the frame's and the reference's pixel noise alone would leave there: judged on
    # the phase, which the wrench rests on, whatever else the residual holds.
    size = problem.fringe_weight.size
    noise_cost = (screen.noise_variance + problem.reference_noise) * jnp.sum(problem.unit_phase_noise)
    left = jnp.sum(r_data[size : 2 * size] ** 2) - noise_cost
    change = jnp.sum(r_zero[size : 2 * size] ** 2) - noise_cost
    implausible = jnp.any(jnp.abs(solution.scaled_wrench) > _IMPLAUSIBLE_RANGES) | _off_the_surface(
        problem.device, wrench, covariance
    )
    heavy = solution.scaled_wrench[2] > 1.0
    share = jnp.where(heavy, jnp.minimum(_HEAVY_SHARE, unexplained_share), unexplained_share)
    unexplained = (left > share * jnp.maximum(change, 0.0)) | implausible
    # A frame whose fringes disagree with the reference's is this unit's only if a load explains it.
    ok = (status == Status.CONVERGED) | (status == Status.MAX_STEPS)
    foreign = screen.disagrees & ((left > _DISAGREEING_SHARE * jnp.maximum(change, 0.0)) | implausible)
    status = jnp.where(ok & foreign, Status.BAD_FRAME, status).astype(status.dtype)
    # An unexplained frame keeps its wrench and covariance, and a converged one still
    # seeds the next frame of a stream: the flag is for the user, not the solver.
    ok = (status == Status.CONVERGED) | (status == Status.MAX_STEPS)
    converged = status == Status.CONVERGED
    status = jnp.where(ok & unexplained, Status.UNEXPLAINED, status).astype(status.dtype)
    nan6 = jnp.full(6, jnp.nan, dtype)
    wrench = jnp.where(ok, wrench, jnp.where(status == Status.NO_CONTACT, jnp.zeros(6, dtype), nan6))
    covariance = jnp.where(ok | (status == Status.NO_CONTACT), covariance, jnp.full((6, 6), jnp.nan, dtype))
    sigma = jnp.sqrt(jnp.clip(jnp.diagonal(covariance), 0.0, None))
    second_wrench = jnp.where(ok, second_wrench, jnp.zeros(6, dtype))
    estimate = Estimate(
        wrench=wrench,
        covariance=covariance,
        sigma=sigma,
        contact=contact,
        exposure=exposure,
        status=status,
        steps=steps,
        rms=jnp.sqrt(variance),
        state=problem._summary(jnp.where(ok, y_out, start))[0],
        misfit=jnp.where(change > 0, jnp.maximum(left, 0.0) / jnp.where(change > 0, change, 1.0), 0.0),
        second_contact=second,
        second_wrench=second_wrench,
    )
    if y.shape[-1] != N_UNKNOWNS:
        # A solution with a second contact has no one-patch linearisation to hand on.
        return estimate, None
    # Only a converged contact is a good linearisation point for the next frame.
    track = Track(
        state=LoadState.from_vector(jnp.where(ok, y, jnp.nan)),
        jacobian=jacobian,
        change=r_zero - r_data,
        valid=converged,
    )
    return estimate, track


def _off_the_surface(device, wrench, covariance):
    r"""Whether a wrench's centre of pressure lies off the contact surface the camera sees,
    by more than `_SURFACE_SIGMAS` standard errors.

    A contact pushes (pressure is not negative) and its shear acts in the surface, whose
    moments about a point of that surface are zero; so the centre of pressure,
    $(-T_y/F_z,\ T_x/F_z)$, lies inside the contact region, on the imaged surface:
    $|T_x| \le F_z h/2$ and $|T_y| \le F_z w/2$ for a surface $w$ wide and $h$ high. The
    excess $|T_x| - F_z h/2$ (and $|T_y| - F_z w/2$) is compared with its standard error
    from the wrench's covariance. Two cases fall under it without being named so: a pull
    ($F_z$ negative beyond its error), which a pushing pressure cannot give, and a contact
    mostly outside the camera's view, which the model does not describe either. A fit that
    needs such a load has explained the frame with a load no contact in view applies (on a
    frame of a natural scene seen through the sensor: Ty of -0.027 N·m with 0.76 N, a centre
    of pressure 35 mm off the centre of a surface 40 mm wide).
    """
    half_height = 0.5e-3 * device.height / device.px_per_mm * device.surface_magnification
    half_width = 0.5e-3 * device.width / device.px_per_mm * device.surface_magnification

    def beyond(moment, half):
        sign = jnp.sign(wrench[moment])
        excess = sign * wrench[moment] - half * wrench[2]
        variance = covariance[moment, moment] + half**2 * covariance[2, 2] - 2 * sign * half * covariance[moment, 2]
        return excess > _SURFACE_SIGMAS * jnp.sqrt(jnp.clip(variance, 0.0, None))

    return beyond(3, half_height) | beyond(4, half_width)


def _tile_index(fringe_shape: tuple[int, int, int], size: int) -> np.ndarray:
    """The tile of the coarse grid (`_TILE_CELLS` cells a side) of every datum of the band
    residual's layout (amplitude and phase of every family, then the brightness), all
    families and components of one place in one tile. Static: built from shapes at trace time."""
    families, m, n = fringe_shape
    rows, cols = np.divmod(np.arange(m * n), n)
    per_cell = (rows // _TILE_CELLS) * -(-n // _TILE_CELLS) + cols // _TILE_CELLS
    tiles = np.concatenate([np.tile(per_cell, 2 * families), per_cell])
    if tiles.size != size:
        raise ValueError(f"band residual of {size} values does not have the layout of {fringe_shape} fields")
    return tiles


def _status(result, screen: "_Screen", in_contact, y):
    solution_finite = jnp.all(jnp.isfinite(y))
    status = jnp.where(result == optx.RESULTS.successful, Status.CONVERGED, Status.MAX_STEPS)
    status = jnp.where(in_contact, status, Status.NO_CONTACT)
    status = jnp.where(screen.refused, Status.BAD_FRAME, status)
    status = jnp.where(screen.finite & solution_finite, status, Status.NONFINITE)
    return status.astype(jnp.int32)
