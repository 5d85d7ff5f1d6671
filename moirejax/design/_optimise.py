r"""The gradient design search: the design whose worst-axis Cramér–Rao bound is smallest.

[`optimise_design`][] runs Adam on a reparameterised design (pitches, angle, separation,
duty cycles) with the box limits kept exactly and the period, stray-beat and phase limits
as penalties; the bounds are those of `_observability.py`.
"""

import dataclasses
import math
import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float
from tqdm.auto import tqdm

from .._conventions import WRENCH_AXES
from ..observe import stray_beat_clearance
from ..physics import Device, HighFidelity, noise_as_arrays
from ._observability import (
    _check_estimator,
    _REDUCED_FIELD_MM,
    _scaled_information,
    _worst_axes,
    cramer_rao,
    Estimator,
    ESTIMATORS,
    nominal_load,
    phase_range,
    reduced_device,
)


class _Bounds(eqx.Module):
    """Box limits of the design variables; the reparameterisation keeps every iterate inside."""

    pitch_floor: float
    carrier_mm: float
    separation: tuple[float, float]
    duty: tuple[float, float]
    max_angle: float


def _design(z: Float[Array, "6"], base: Device, bounds: _Bounds) -> Device:
    """Device of the unconstrained variables `z` = (p1, p2, Δα, a, duty1, duty2) coordinates."""
    lo, hi = bounds.separation
    a = lo + (hi - lo) * jax.nn.sigmoid(z[3])
    # The far grating's apparent pitch p1 Z/(Z + a) must stay resolvable too.
    p1_floor = jnp.maximum(bounds.pitch_floor, bounds.carrier_mm * (base.Z + a) / base.Z)
    p2_floor = max(bounds.pitch_floor, bounds.carrier_mm)
    d_lo, d_hi = bounds.duty
    return dataclasses.replace(
        base,
        p1=p1_floor + jnp.exp(z[0]),
        p2=p2_floor + jnp.exp(z[1]),
        alpha1=base.alpha2 + bounds.max_angle * jnp.tanh(z[2]),
        a=a,
        duty1=d_lo + (d_hi - d_lo) * jax.nn.sigmoid(z[4]),
        duty2=d_lo + (d_hi - d_lo) * jax.nn.sigmoid(z[5]),
    )


def _coordinates(device: Device, bounds: _Bounds) -> np.ndarray:
    """Inverse of [`_design`][] (designs on or outside a limit start just inside it)."""
    Z, a = float(device.Z), float(device.a)
    lo, hi = bounds.separation
    logit = lambda f: math.log(min(max(f, 1e-3), 1 - 1e-3) / (1 - min(max(f, 1e-3), 1 - 1e-3)))
    p1_floor = max(bounds.pitch_floor, bounds.carrier_mm * (Z + a) / Z)
    p2_floor = max(bounds.pitch_floor, bounds.carrier_mm)
    d_lo, d_hi = bounds.duty
    delta = float(device.alpha1 - device.alpha2) / bounds.max_angle
    return np.array(
        [
            math.log(max(float(device.p1) - p1_floor, 1e-3 * p1_floor)),
            math.log(max(float(device.p2) - p2_floor, 1e-3 * p2_floor)),
            math.atanh(min(max(delta, -0.999), 0.999)),
            logit((a - lo) / (hi - lo)),
            logit((float(device.duty1) - d_lo) / (d_hi - d_lo)),
            logit((float(device.duty2) - d_lo) / (d_hi - d_lo)),
        ]
    )


def _relative_crb(device: Device, noise: HighFidelity, mechanics_shape, estimator: Estimator) -> Float[Array, "6"]:
    """Marginal bound of each wrench axis over its range (the information is in range units)."""
    wrench, contact = nominal_load(device.p1.dtype)
    information = _scaled_information(device, wrench, contact, noise, 1.0, mechanics_shape, 9, estimator)
    return jnp.sqrt(jnp.diag(jnp.linalg.inv(information))[:6])


# Beats must clear a band by a fifth of its radius more: the band window's taper.
_MIN_BEAT_CLEARANCE = 1.2


def _violations(device: Device, min_period, max_period, max_phase, mechanics_shape) -> Float[Array, " n"]:
    """Log-ratios of the penalised limits, <= 0 when met: moiré period (smallest, largest),
    stray beats, then phase range per axis."""
    period = 2 * jnp.pi / jnp.linalg.norm(device.moire_wavevectors(), axis=-1)
    out = [
        jnp.log(min_period / period),
        jnp.log(period / max_period),
        jnp.log(_MIN_BEAT_CLEARANCE / stray_beat_clearance(device)),
    ]
    if max_phase is not None:
        out.append(jnp.log(phase_range(device, mechanics_shape=mechanics_shape) / max_phase))
    return jnp.concatenate(out)


# Penalised limits count as met within 1% (log-ratio 0.01).
_LIMIT_TOLERANCE = 0.01


def _summary(
    device: Device, relative: dict[str, np.ndarray], estimator: str, violations: np.ndarray, phases: np.ndarray
) -> dict[str, Any]:
    other = "pixels" if estimator == "bands" else "bands"
    return {
        "p1_mm": float(device.p1),
        "p2_mm": float(device.p2),
        "delta_alpha_deg": math.degrees(float(device.alpha1 - device.alpha2)),
        "a_mm": float(device.a),
        "duty1": float(device.duty1),
        "duty2": float(device.duty2),
        "period_mm": float(np.min(2 * np.pi / np.linalg.norm(np.asarray(device.moire_wavevectors()), axis=-1))),
        "stray_beat_clearance": float(np.min(np.asarray(stray_beat_clearance(device)))),
        "rel_crb": {name: float(v) for name, v in zip(WRENCH_AXES, relative[estimator])},
        "worst_axis": _worst_axes(relative[estimator]),
        "worst_rel_crb": float(np.max(relative[estimator])),
        # The other estimator's bound, for comparison (the search does not see it).
        f"rel_crb_{other}": {name: float(v) for name, v in zip(WRENCH_AXES, relative[other])},
        f"worst_rel_crb_{other}": float(np.max(relative[other])),
        "phase_range_rad": {name: float(v) for name, v in zip(WRENCH_AXES, phases)},
        "max_violation": float(np.max(violations)),
        "within_limits": bool(np.max(violations) <= _LIMIT_TOLERANCE),
    }


def optimise_design(
    device: Device,
    *,
    min_pitch: float = 0.15,
    max_fringe_density: float | None = None,
    min_fringes: float = 4.0,
    min_carrier_px: float = 2.5,
    max_phase_range: float | None = None,
    duty_range: tuple[float, float] = (0.25, 0.75),
    max_angle_deg: float = 10.0,
    max_separation: float | None = None,
    no_axis_worse: bool = True,
    steps: int = 300,
    learning_rate: float = 0.03,
    temperature: float = 0.05,
    penalty: float = 1000.0,
    noise: HighFidelity | None = None,
    field_mm: float = _REDUCED_FIELD_MM,
    mechanics_shape: tuple[int, int] = (64, 64),
    estimator: Estimator = "bands",
    progress: bool = True,
) -> tuple[Device, dict[str, Any]]:
    r"""Gradient descent (Adam) on the design for the best worst-axis single-frame Cramér–Rao bound.

    The objective is a smooth maximum over the six axes,
    $\tau \log \sum_i \exp(\log r_i / \tau)$, of $\log r_i$, the marginal bound of axis $i$
    over its range in the paper (at the nominal load, contact estimated too) for the
    `estimator` that will read the frames, computed through the model on the central crop
    of about `field_mm` of the frame ([`reduced_device`][]). Design variables: p1, p2, Δα
    (α1 moves, α2 stays), a and both duty cycles; everything else is `device`'s.

    Limits kept exactly by reparameterisation: both pitches at least `min_pitch` (what the
    laser can cut) and at least `min_carrier_px` pixels in the image (p2 and p1's
    apparent pitch p1 Z/(Z + a), so that the camera resolves the carriers); `a` between
    the elastomer thickness and `max_separation` (default Z/2); duty cycles within
    `duty_range`; |Δα| below `max_angle_deg`. Limits kept by a quadratic penalty on their
    log-ratio: the moiré period of every family at least `1/max_fringe_density` (default
    8 pixels) and at most the frame's shorter side over `min_fringes`; no mixed-order grating beat up to the modelled harmonic within 1.2 band radii of
    a demodulated band ([`stray_beat_clearance`][]: a beat there biases the fringe phase
    and no band model includes it); with each wrench axis alone over the paper's range,
    the fringe phase change nowhere above `max_phase_range` (rad; `None`, the default,
    drops it: see below); with
    `no_axis_worse`, no axis's bound above the start's, so that the optimum gains on the
    worst axis without giving up another. The returned design is the best iterate that
    meets the penalised limits to 1% (the last one if none does).

    Optimise for the estimator you will run. The default, `"bands"`, is the bound of the
    band inversion ([`Inverter`][], `moirejax invert`), which reads only the moiré and
    brightness bands; on Mid its scatter is within 20% of that bound
    (`benchmarks/crb_vs_scatter.py`). `"pixels"` is the bound of an efficient estimator of
    the whole frame ([`refine_in_pixels`][]), which counts the information in the grating
    carriers too: optimised for it, the search from Mid found coarse pitches whose gain
    lay in the carriers, and the band inversion scattered 5x as much as on Mid there.
    `benchmarks/design_check.py` checks an optimum by inverting simulated frames: from Mid,
    the default search ends at p1 0.327, p2 0.321 mm, Δα −2.1°, a 1.40 mm period, with
    0.34x Mid's worst-axis band bound; at the same camera noise its band inversion reads
    40 mixed loads with 0.57-0.94x Mid's RMSE on every axis, at about 1.8x the solve
    time (a 192 x 192 model grid against 96 x 96, [`model_grid_for`][]).

    **Arguments:** the limits above, and

    - `min_fringes`: fringes across the frame. Without this limit the search for the
      whole-frame bound from Mid ended at p1' = p2 within 0.3% (a 226 mm period, no fringes
      in a 32 mm frame): that bound still counts the carriers, but nothing is left for the
      band inversion, whose
      bands are centred on the moiré wavevector with a radius of 0.45 |K| and so need
      a few Fourier bins between the fringe band and the brightness band. The paper's
      designs have 5.3 (Sparse) to 40 (Dense) fringes across a 32 mm frame.
    - `no_axis_worse`: penalise every axis whose bound rises above the start's (on the
      reduced frame, to 1%). A smooth maximum trades the other axes for the worst one:
      from Mid, the band search without it (and with a phase limit of π) gained 29% on
      shear and gave up 4% on Fz and 9% on Tz.
    - `steps`, `learning_rate`: Adam iterations and step size (in the unconstrained coordinates).
    - `temperature`: $\tau$ of the smooth maximum.
    - `max_phase_range`: for a solver that must not see a fringe move by more than half a
      period. The band inversion does not need it: Mid's twist range turns the fringes by
      6.3 rad near the contact edge and its cold solves still read Tz at R² 0.99998. At π,
      the search from Mid doubled p1 (halving every phase change per newton) and its
      optimum, though 0.71x Mid's worst-axis bound, read mixed loads worse than Mid after
      inversion (model floor 2-4x Mid's).
    - `penalty`: weight of the squared log-violations. From Mid (whose twist range wraps at
      6.3 rad), 150 steps at a weight of 100 ended 24% over the phase limit of π with no iterate
      inside it; 300 steps at 1000 reach it.
    - `noise`: camera noise ([`HighFidelity`][] defaults for `None`).
    - `field_mm`, `mechanics_shape`: reduced frame and mechanics grid of the optimisation.
    - `estimator`: `"bands"` or `"pixels"`, whose bound to minimise (see [`fisher_information`][]).
    - `progress`: show a progress bar on stderr.

    **Returns:** `(optimum, report)`, `report` a JSON-ready dict with the start and the
    optimum (design, per-axis relative bounds on the full frame for both estimators,
    phase ranges, worst limit violation), the objective history and the limits.
    """
    if steps < 0:
        raise ValueError(f"steps must be non-negative, got {steps}")
    _check_estimator(estimator)
    px = float(device.px_per_mm)
    thickness, Z = float(device.elastomer.thickness), float(device.Z)
    hi = 0.5 * Z if max_separation is None else float(max_separation)
    if not thickness < hi < Z:
        raise ValueError(f"max_separation must lie between the elastomer thickness {thickness} mm and Z = {Z} mm")
    if not 0 < duty_range[0] < duty_range[1] < 1:
        raise ValueError(f"duty_range must satisfy 0 < low < high < 1, got {duty_range}")
    max_density = px / 8 if max_fringe_density is None else float(max_fringe_density)
    if not min_fringes > 0:
        raise ValueError(f"min_fringes must be positive, got {min_fringes}")
    max_period = min(device.field_of_view) / float(min_fringes)
    bounds = _Bounds(
        pitch_floor=float(min_pitch),
        carrier_mm=min_carrier_px / px,
        separation=(thickness, hi),
        duty=(float(duty_range[0]), float(duty_range[1])),
        max_angle=math.radians(max_angle_deg),
    )
    small = reduced_device(device, field_mm)
    dtype = small.p1.dtype
    noise_arrays = noise_as_arrays(noise, dtype)
    min_period, max_phase = 1 / max_density, max_phase_range

    def loss(z):
        design = _design(z, small, bounds)
        log_relative = jnp.log(_relative_crb(design, noise_arrays, mechanics_shape, estimator))
        smooth_max = temperature * jax.nn.logsumexp(log_relative / temperature)
        violation = _violations(design, min_period, max_period, max_phase, mechanics_shape)
        if no_axis_worse:
            violation = jnp.concatenate([violation, log_relative - log_start])
        return smooth_max + penalty * jnp.sum(jax.nn.relu(violation) ** 2), (smooth_max, jnp.max(violation))

    optimiser = optax.adam(learning_rate)

    @eqx.filter_jit
    def step(z, state):
        (value, aux), grad = jax.value_and_grad(loss, has_aux=True)(z)
        # optax mixes its int32 step count with floats, which strict promotion refuses.
        with jax.numpy_dtype_promotion("standard"):
            updates, state = optimiser.update(grad, state, z)
            return optax.apply_updates(z, updates), state, value, aux

    start = time.perf_counter()
    z = jnp.asarray(_coordinates(device, bounds), dtype)
    # The start as the search sees it: a design outside the box limits starts just inside.
    log_start = jnp.log(
        eqx.filter_jit(_relative_crb)(_design(z, small, bounds), noise_arrays, mechanics_shape, estimator)
    )
    state = optimiser.init(z)
    history: list[float] = []
    best: tuple[float, Array] | None = None
    bar = tqdm(range(steps + 1), desc="optimise design", disable=not progress, unit="step")
    for i in bar:
        # The last pass only scores the final iterate.
        new_z, new_state, value, (smooth_max, violation) = step(z, state)
        history.append(float(value))
        if float(violation) <= _LIMIT_TOLERANCE and (best is None or float(smooth_max) < best[0]):
            best = (float(smooth_max), jnp.asarray(z))
        bar.set_postfix(objective=f"{float(value):.3f}", violation=f"{float(violation):+.3f}")
        if i < steps:
            z, state = new_z, new_state
    chosen = z if best is None else best[1]
    optimum = _design(chosen, device, bounds)

    limits = eqx.filter_jit(
        lambda d: (
            _violations(d, min_period, max_period, max_phase, mechanics_shape),
            phase_range(d, mechanics_shape=mechanics_shape),
        )
    )

    def evaluate(design: Device) -> dict[str, Any]:
        wrench, contact = nominal_load(design.p1.dtype)
        relative = {
            name: np.array(list(cramer_rao(design, wrench, contact, noise, estimator=name)["relative"].values()))
            for name in ESTIMATORS
        }
        violations, phases = limits(reduced_device(design, field_mm))
        return _summary(design, relative, estimator, np.asarray(violations), np.asarray(phases))

    report = {
        "objective": f"smooth max (log-sum-exp, temperature {temperature}) of log(CRB/range) of the "
        f"{estimator!r} estimator, marginal over the contact",
        "reduced_frame": f"central {small.height}x{small.width} px crop at {px:.4g} px/mm during the search; "
        f"bounds below on the full {device.height}x{device.width} frame",
        "limits": {
            "min_pitch_mm": float(min_pitch),
            "min_carrier_px": float(min_carrier_px),
            "max_fringe_density_per_mm": max_density,
            "max_period_mm": max_period,
            "max_phase_range_rad": None if max_phase_range is None else float(max_phase_range),
            "separation_mm": [thickness, hi],
            "duty_range": [float(duty_range[0]), float(duty_range[1])],
            "max_angle_deg": float(max_angle_deg),
            "no_axis_worse_than_start": no_axis_worse,
        },
        "estimator": estimator,
        "estimator_note": (
            "the bound of the band inversion (`moirejax invert`), which reads the moire and brightness bands only"
            if estimator == "bands"
            else "the bound of an efficient whole-frame estimator (refine_in_pixels); the band inversion of "
            "`invert` can rank designs otherwise"
        )
        + "; check a design by inverting simulated frames: benchmarks/design_check.py",
        "start": evaluate(device),
        "optimum": evaluate(optimum),
        "feasible": best is not None,
        "steps": steps,
        "history": history,
        "seconds": time.perf_counter() - start,
    }
    return optimum, report
