"""Optimised design against Mid, by the bound and after inversion: `python benchmarks/design_check.py --json`.

1. `optimise_design` from Mid (the CLI's defaults: `moirejax design --optimise`, which
   minimises the band inversion's bound, no axis worse than Mid's) and the per-axis
   relative Cramér–Rao bound (CRB over the paper's range) of start and optimum at the
   nominal load (centred press, r = 3.5 mm, Fz = 0.6 N).
2. A simulated check of both designs at the same camera noise. Each design renders the
   same loads as `model`-fidelity frames (no fabrication deviations, so the design is the
   only difference) and a camera with the noise the bound assumes adds shot noise (4000 e-
   full well), read noise (4 e-) and 8-bit quantisation, as `render_frame_high` does. An
   `Inverter` built on the design's own noise-free zero-load frame inverts every frame
   from a cold start, on the design's own model grid (`model_grid_for`). Loads: `--loads`
   `mixed` loads in contact (spread over the field, shear, twist), and `--repeats` noisy
   copies of the nominal load (the bound's own load). Optionally (`--pixel-repeats`)
   noisy copies of the nominal load through the efficient whole-frame estimator, the
   band inversion refined by `refine_in_pixels` (frames rendered on its mechanics grid),
   which is where a ranking by the whole-frame bound (`--estimator pixels`) should show.
3. The same loads without noise: the error left is the model floor (the renderer's
   256 x 256 mechanics, full-resolution image and every grating harmonic it keeps, against
   the inversion's model grid and band model), not noise. The noise-driven error, what
   the bound predicts, is the RMS of (noisy estimate - noise-free estimate) of the same load.
4. For each design, the mixed-order grating beats n k1' - m k2 (n != m) that land in the
   demodulated bands: the band model leaves them out, so they set a model floor that no
   amount of light removes. And the bound again with the gratings cut at 2, 3 (the
   presets' `harmonics`) and 5 harmonics: a ranking that holds at one truncation only
   is the renderer's, not the gratings'.

Per axis and design: RMSE of the noisy and noise-free mixed loads, noise-driven RMS, all
over the paper's range too, the worst axis, the scatter and bias of the nominal repeats
against the bound, solver statuses, and the ratio optimum / Mid of each.
"""

import argparse
import dataclasses
import json
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj
from moirejax import (
    axis_ranges,
    binary_harmonics,
    camera_noise,
    Contact,
    cramer_rao,
    gaussian_mtf,
    HighFidelity,
    invert,
    Inverter,
    load_schedule,
    nominal_load,
    optimise_design,
    refine_in_pixels,
    render_frame,
    WRENCH_AXES,
)


RANGES = np.asarray(axis_ranges(), np.float64)
# Band radius over |K| of the Inverter's demodulator (its default `band_fraction`).
BAND_FRACTION = 0.45
# Grating harmonics kept by the `model` renderer for the bound's sensitivity to that
# truncation (the presets keep 3; binary gratings have them all).
HARMONICS = (2, 3, 5)
# Mechanics grid of the pixel check's frames, bound and fits (refine_in_pixels' default).
PIXEL_MECHANICS = (64, 64)


def _per_axis(values, digits=6) -> dict[str, float]:
    return {a: round(float(v), digits) for a, v in zip(WRENCH_AXES, values)}


def _worst(relative: np.ndarray) -> dict:
    return {"axis": WRENCH_AXES[int(np.argmax(relative))], "value": round(float(np.max(relative)), 6)}


def _errors(estimates: np.ndarray, truth: np.ndarray) -> dict:
    """RMSE per axis in N / N·m and over the paper's range, and the worst axis."""
    rmse = np.sqrt(np.mean((estimates - truth) ** 2, axis=0))
    return {"rmse": _per_axis(rmse), "rel_rmse": _per_axis(rmse / RANGES), "worst": _worst(rmse / RANGES)}


def _statuses(statuses) -> dict[str, int]:
    values, counts = np.unique(statuses, return_counts=True)
    return {mj.Status(int(v)).name.lower(): int(c) for v, c in zip(values, counts)}


def _bands(design, orders: int = 6) -> dict:
    """The design's moiré band and the mixed-order beats n k1' - m k2 (n != m) that fall in a band.

    The inversion's band model (`mj.band_model`) keeps only the same-order beats
    n (k1' - k2) below the carriers; a mixed-order beat inside the fringe band (within
    `BAND_FRACTION` |K| of +-K) or the brightness band (within it of 0) is a fringe the model
    lacks, whose phase moves n times as fast as the fundamental's. Amplitudes are relative
    to the fundamental beat, for binary gratings (the far one defocused); the `model`
    renderer keeps harmonics up to `design.harmonics`, a real grating has them all.
    """
    k1 = np.asarray(design.apparent_upper_wavevectors(), np.float64)[0]
    k2 = np.asarray(design.reference_wavevectors(), np.float64)[0]
    K = k1 - k2
    radius = BAND_FRACTION * np.linalg.norm(K)
    harmonic = jnp.arange(orders + 1, dtype=float)
    c1 = np.asarray(
        binary_harmonics(design.duty1, orders) * gaussian_mtf(harmonic * np.linalg.norm(k1), design.optics.defocus)
    )
    c2 = np.asarray(binary_harmonics(design.duty2, orders))
    stray = []
    for n in range(1, orders + 1):
        for m in range(1, orders + 1):
            beat = n * k1 - m * k2
            to_fringe = min(np.linalg.norm(beat - K), np.linalg.norm(beat + K))
            band = "fringe" if to_fringe < radius else "brightness" if np.linalg.norm(beat) < radius else None
            if n != m and band:
                stray.append(
                    {
                        "beat": f"{n}k1'-{m}k2",
                        "band": band,
                        "distance_to_band_centre_rad_per_mm": round(
                            float(to_fringe if band == "fringe" else np.linalg.norm(beat)), 3
                        ),
                        "amplitude_over_fundamental": round(float(c1[n] * c2[m] / (c1[1] * c2[1])), 4),
                        "in_model_frames": max(n, m) <= design.harmonics,
                    }
                )
    return {
        "period_mm": round(float(2 * np.pi / np.linalg.norm(K)), 4),
        "band_radius_rad_per_mm": round(float(radius), 3),
        "stray_beats": stray,
    }


def _bound_by_harmonics(design, noise: HighFidelity, estimator: str) -> dict:
    """Relative bound of each axis and the worst one with the gratings cut at each of `HARMONICS`."""
    wrench, contact = nominal_load()
    out = {}
    for harmonics in HARMONICS:
        bound = cramer_rao(
            dataclasses.replace(design, harmonics=harmonics), wrench, contact, noise, estimator=estimator
        )
        relative = np.array([bound["relative"][a] for a in WRENCH_AXES])
        out[str(harmonics)] = {"rel_crb": _per_axis(relative, 7), "worst": _worst(relative)}
    return out


def _check(
    design, loads, nominal, repeats: int, noise: HighFidelity, rel_crb: dict, model_shape, estimator: str
) -> dict:
    """Invert the loads' noise-free and noisy frames and the noisy nominal repeats of one design."""
    start = time.perf_counter()
    render = jax.jit(lambda w, x0, y0, r: render_frame(design, w, Contact(x0, y0, r)))
    reference = jnp.clip(render(jnp.zeros(6), 0.0, 0.0, 3.5), 0.0, 1.0)
    inverter = Inverter(design, reference=reference, model_shape=model_shape)
    camera = jax.jit(lambda key, clean: camera_noise(key, clean, noise))

    def invert(frame):
        estimate = invert(inverter, frame)
        return np.asarray(estimate.wrench, np.float64), int(estimate.status)

    # The same keys for both designs: each load meets the same noise draw in either.
    keys = jax.random.split(jax.random.PRNGKey(0), len(loads) + repeats)
    clean_out, noisy_out = [], []
    for key, (wrench, x0, y0, radius) in zip(keys, loads):
        clean = render(jnp.asarray(wrench), x0, y0, radius)
        clean_out.append(invert(jnp.clip(clean, 0.0, 1.0)))
        noisy_out.append(invert(camera(key, clean)))
    nominal_clean = render(*nominal)
    nominal_out = [invert(camera(key, nominal_clean)) for key in keys[len(loads) :]]
    floor_at_nominal = invert(jnp.clip(nominal_clean, 0.0, 1.0))[0] - np.asarray(nominal[0], np.float64)

    truth = np.array([load[0] for load in loads], np.float64)
    clean_est, clean_status = map(np.array, zip(*clean_out))
    noisy_est, noisy_status = map(np.array, zip(*noisy_out))
    nominal_est, nominal_status = map(np.array, zip(*nominal_out))
    # Non-converged frames stay in: a failed inversion is part of the design's error. A
    # frame judged out of contact reports zero wrench, which counts as its error.
    noise_driven = np.sqrt(np.mean((noisy_est - clean_est) ** 2, axis=0))
    crb = np.array([rel_crb[a] for a in WRENCH_AXES]) * RANGES
    scatter = nominal_est.std(axis=0, ddof=1)
    return {
        "bands": _bands(design),
        "rel_crb_by_harmonics": _bound_by_harmonics(design, noise, estimator),
        "noisy": {**_errors(noisy_est, truth), "status": _statuses(noisy_status)},
        "noise_free": {**_errors(clean_est, truth), "status": _statuses(clean_status)},
        "noise_driven": {
            "rms": _per_axis(noise_driven),
            "rel_rms": _per_axis(noise_driven / RANGES),
            "worst": _worst(noise_driven / RANGES),
        },
        "nominal": {
            "std": _per_axis(scatter),
            "rel_std": _per_axis(scatter / RANGES),
            "worst": _worst(scatter / RANGES),
            "std_over_crb": _per_axis(scatter / crb, 3),
            "bias": _per_axis(nominal_est.mean(axis=0) - np.asarray(nominal[0], np.float64)),
            "noise_free_error": _per_axis(floor_at_nominal),
            "status": _statuses(nominal_status),
        },
        "seconds": round(time.perf_counter() - start, 1),
    }


def _pixel_check(design, nominal, repeats: int, noise: HighFidelity, model_shape) -> dict:
    """The nominal load's noisy repeats through the efficient estimator: band inversion, then
    `refine_in_pixels`, on frames rendered on the fit's own mechanics grid (`PIXEL_MECHANICS`;
    see `crb_vs_scatter.py`, where this estimator's scatter meets the bound within 8%)."""
    start = time.perf_counter()
    wrench, contact = jnp.asarray(nominal[0]), Contact(*nominal[1:])
    truth = np.asarray(nominal[0], np.float64)
    render = lambda w, c: render_frame(design, w, c, mechanics_shape=PIXEL_MECHANICS)
    inverter = Inverter(design, reference=render(jnp.zeros(6), Contact()), model_shape=model_shape)
    clean = render(wrench, contact)
    camera = jax.jit(lambda key: camera_noise(key, clean, noise))
    bound = cramer_rao(design, wrench, contact, noise, mechanics_shape=PIXEL_MECHANICS)
    crb = np.array([bound["std"][a] for a in WRENCH_AXES], np.float64)
    fits, converged = [], 0
    for i in range(repeats):
        frame = camera(jax.random.PRNGKey(10_000 + i))
        fit = refine_in_pixels(design, frame, invert(inverter, frame), noise, mechanics_shape=PIXEL_MECHANICS)
        if bool(fit.converged):
            converged += 1
            fits.append(np.asarray(fit.wrench, np.float64))
    estimates = np.array(fits)
    scatter = estimates.std(axis=0, ddof=1)
    return {
        "frames": repeats,
        "converged": converged,
        "std": _per_axis(scatter),
        "rel_std": _per_axis(scatter / RANGES),
        "worst": _worst(scatter / RANGES),
        "std_over_crb": _per_axis(scatter / crb, 3),
        "bias_over_std": _per_axis((estimates.mean(axis=0) - truth) / scatter, 3),
        "seconds": round(time.perf_counter() - start, 1),
    }


def _ratios(optimum: dict, mid: dict) -> dict[str, float]:
    return {a: round(optimum[a] / mid[a], 3) for a in WRENCH_AXES}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--layout", default="crossed", choices=("crossed", "lines"))
    parser.add_argument("--steps", type=int, default=300, help="optimiser steps (the CLI's default)")
    parser.add_argument("--loads", type=int, default=40, help="mixed loads in contact")
    parser.add_argument("--repeats", type=int, default=100, help="noisy frames of the nominal load")
    parser.add_argument(
        "--estimator",
        default="bands",
        choices=("bands", "pixels"),
        help="whose bound the search minimises (the CLI's default: the band inversion's)",
    )
    parser.add_argument("--seed", type=int, default=11, help="draws the mixed loads")
    parser.add_argument(
        "--max-phase-range", type=float, default=0.0, help="the search's fringe phase limit, rad (0: none)"
    )
    parser.add_argument(
        "--pixel-repeats", type=int, default=0, help="noisy nominal frames through the pixel refinement (0: skip)"
    )
    parser.add_argument(
        "--model-shape", type=int, default=None, help="the Inverter's model grid (square); default model_grid_for"
    )
    args = parser.parse_args(argv)

    start = time.perf_counter()
    mid = mj.preset("mid", layout=args.layout)
    optimum, report = optimise_design(
        mid,
        steps=args.steps,
        estimator=args.estimator,
        max_phase_range=None if args.max_phase_range <= 0 else args.max_phase_range,
        progress=True,
    )

    # The first frames of a `mixed` schedule are unloaded (a session's reference frames).
    schedule = load_schedule("mixed", args.loads + 8, seed=args.seed)
    keep = np.flatnonzero(schedule.contact)[: args.loads]
    loads = [(schedule.wrench[i], schedule.x0[i], schedule.y0[i], schedule.radius[i]) for i in keep]
    wrench, contact = nominal_load()
    nominal = (wrench, contact.x0, contact.y0, contact.radius)
    noise = HighFidelity()
    checks = {
        name: _check(
            design,
            loads,
            nominal,
            args.repeats,
            noise,
            report[key]["rel_crb"],
            None if args.model_shape is None else (args.model_shape,) * 2,
            args.estimator,
        )
        for name, design, key in (("mid", mid, "start"), ("optimum", optimum, "optimum"))
    }

    if args.pixel_repeats:
        for name, design in (("mid", mid), ("optimum", optimum)):
            checks[name]["pixel"] = _pixel_check(
                design,
                nominal,
                args.pixel_repeats,
                noise,
                None if args.model_shape is None else (args.model_shape,) * 2,
            )
    mid_check, opt_check = checks["mid"], checks["optimum"]
    comparison = {
        "rel_crb": _ratios(report["optimum"]["rel_crb"], report["start"]["rel_crb"]),
        "noisy_rmse": _ratios(opt_check["noisy"]["rmse"], mid_check["noisy"]["rmse"]),
        "noise_driven_rms": _ratios(opt_check["noise_driven"]["rms"], mid_check["noise_driven"]["rms"]),
        "noise_free_rmse": _ratios(opt_check["noise_free"]["rmse"], mid_check["noise_free"]["rmse"]),
        "nominal_std": _ratios(opt_check["nominal"]["std"], mid_check["nominal"]["std"]),
    }
    if args.pixel_repeats:
        comparison["pixel_std"] = _ratios(opt_check["pixel"]["std"], mid_check["pixel"]["std"])
        # A standard deviation from n frames is uncertain by 1/sqrt(2 (n - 1)) of itself; a
        # ratio of two independent ones by sqrt(2) times that.
        comparison["pixel_std_ratio_standard_error"] = round(1 / math.sqrt(args.pixel_repeats - 1), 3)
    worst = lambda case: opt_check[case]["worst"]["value"] / mid_check[case]["worst"]["value"]
    comparison["worst_axis"] = {
        "rel_crb": round(report["optimum"]["worst_rel_crb"] / report["start"]["worst_rel_crb"], 3),
        **{
            case: round(worst(case), 3)
            for case in ("noisy", "noise_driven", "noise_free", "nominal") + (("pixel",) if args.pixel_repeats else ())
        },
        **{
            f"rel_crb_{h}_harmonics": round(
                opt_check["rel_crb_by_harmonics"][str(h)]["worst"]["value"]
                / mid_check["rel_crb_by_harmonics"][str(h)]["worst"]["value"],
                3,
            )
            for h in HARMONICS
        },
    }
    result = {
        "layout": args.layout,
        "loads": len(loads),
        "repeats": args.repeats,
        "inverter_model_shape": {name: list(mj.model_grid_for(d)) for name, d in (("mid", mid), ("optimum", optimum))}
        if args.model_shape is None
        else args.model_shape,
        "noise": "model frames + shot noise (4000 e- full well), 4 e- read noise, 8 bit",
        "optimisation": {
            "steps": report["steps"],
            "feasible": report["feasible"],
            "limits": report["limits"],
            "objective_first_last": [round(report["history"][0], 4), round(report["history"][-1], 4)],
            "start": report["start"],
            "optimum": report["optimum"],
            "seconds": round(report["seconds"], 1),
        },
        "check": checks,
        "optimum_over_mid": comparison,
        "seconds": round(time.perf_counter() - start, 1),
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for key, ratios in comparison.items():
            print(f"optimum / mid {key:18s} {ratios}")
        print(f"seconds {result['seconds']}")


if __name__ == "__main__":
    main()
