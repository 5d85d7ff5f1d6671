"""Cramér–Rao bound against the inversions' actual scatter: `python benchmarks/crb_vs_scatter.py --json`.

Renders one `model`-fidelity frame of the Mid design at the nominal observability load,
draws `--frames` noisy copies with the camera noise model the bound assumes (shot noise at
4000 e- full well, 4 e- read noise, 8-bit quantisation), and estimates the wrench of each
twice: by the band inversion (Levenberg–Marquardt from a cold start, [`invert`][moirejax.invert])
and by its refinement in pixels ([`refine_in_pixels`][], a maximum-likelihood fit of the
whole frame started from the band estimate). Per axis and estimator: the empirical
standard deviation and bias, the mean standard error the estimator reports, and whether
the scatter agrees within 20%, where the estimator is unbiased, with that estimator's own
bound: the band bound (`cramer_rao(..., estimator="bands")`, the information in the
Fourier bins the band inversion reads) for the band inversion, the whole-frame bound for
the pixel fit. The band inversion's scatter over the whole-frame bound is reported too:
what reading the bands only costs (the carriers and their harmonics carry information it
leaves). The band inversion also has weak priors (centre of pressure near the contact
centre, a typical radius), so it may scatter a little less than its bound on the tilts.

The frames, the bound, the pixel fit and the band inversion share one mechanics grid
(`--mechanics`, by default the inversion's own, `model_grid_for`: 96 x 96 on Mid): a frame
rendered on 128 x 128 and fitted on 64 x 64 differs from the model by a few percent of
the pixel noise over the whole contact, which biases a fit of every pixel by about 7
standard errors in Fz; frames on 64 x 64 read by the band inversion on 96 x 96 biased
its Fz by 4.6 standard errors of the mean.

"Unbiased" means no bias these frames can detect: |bias| below three standard errors of
the mean (3 std / sqrt(frames), 0.21 std for 200 frames, when a bias would add at most 2%
to the RMS error). The scatter itself is uncertain by 1/sqrt(2 (frames - 1)) of itself
(5% for 200 frames), so the 20% test means something only for a hundred frames or more.
"""

import argparse
import json
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj
from moirejax import (
    camera_noise,
    Contact,
    cramer_rao,
    HighFidelity,
    invert,
    Inverter,
    nominal_load,
    refine_in_pixels,
    render_frame,
)


AXES = mj.WRENCH_AXES
AGREEMENT = 0.2


def _per_axis(values) -> dict[str, float]:
    return {a: float(v) for a, v in zip(AXES, values)}


def _summary(
    estimates: np.ndarray, reported: np.ndarray, truth: np.ndarray, crb: np.ndarray, other_crb: dict[str, np.ndarray]
) -> dict:
    """Scatter, bias and reported sigma of one estimator over the frames it solved, against
    its own bound `crb` (and other bounds, reported only)."""
    n = len(estimates)
    if n < 2:
        return {"frames": n}
    scatter = estimates.std(axis=0, ddof=1)
    bias = estimates.mean(axis=0) - truth
    ratio = scatter / crb
    unbiased = np.abs(bias) < 3 * scatter / math.sqrt(n)
    agrees = unbiased & (np.abs(ratio - 1) <= AGREEMENT)
    return {
        "frames": n,
        "empirical_std": _per_axis(scatter),
        "scatter_over_crb": _per_axis(ratio.round(3)),
        **{f"scatter_over_{name}": _per_axis((scatter / other).round(3)) for name, other in other_crb.items()},
        "bias_over_std": _per_axis((bias / scatter).round(3)),
        # Bias in standard errors of the mean: beyond 3, these frames detect it.
        "bias_z": _per_axis((bias / scatter * math.sqrt(n)).round(2)),
        "reported_sigma_over_scatter": _per_axis((reported.mean(axis=0) / scatter).round(3)),
        "unbiased": {a: bool(u) for a, u in zip(AXES, unbiased)},
        "within_20pct_where_unbiased": {a: (bool(g) if u else None) for a, g, u in zip(AXES, agrees, unbiased)},
        "all_unbiased_axes_agree": bool(np.all(agrees[unbiased])),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, default=200, help="noisy frames to invert")
    parser.add_argument("--layout", default="crossed", choices=("crossed", "lines"))
    parser.add_argument(
        "--mechanics",
        type=int,
        default=None,
        help="mechanics grid of frames, bounds and fits (default: model_grid_for)",
    )
    args = parser.parse_args(argv)

    device = mj.preset("mid", layout=args.layout)
    mechanics = mj.model_grid_for(device) if args.mechanics is None else (args.mechanics, args.mechanics)
    wrench, contact = nominal_load(np.float32)
    truth = np.asarray(wrench, np.float64)
    noise = HighFidelity()
    bound = cramer_rao(device, wrench, contact, noise, mechanics_shape=mechanics)
    crb = np.array([bound["std"][a] for a in AXES], np.float64)
    band_bound = cramer_rao(device, wrench, contact, noise, mechanics_shape=mechanics, estimator="bands")
    band_crb = np.array([band_bound["std"][a] for a in AXES], np.float64)
    clean = render_frame(device, wrench, contact, mechanics_shape=mechanics)
    inverter = Inverter(
        device,
        reference=render_frame(device, jnp.zeros(6), Contact(), mechanics_shape=mechanics),
        model_shape=mechanics,
    )
    refine = lambda frame, start: refine_in_pixels(device, frame, start, noise, mechanics_shape=mechanics)

    # The noise-free frame fitted from the truth: a check that the fit reproduces its own
    # model (zero bias), and the bound with the exposure estimated too, as the fit does.
    truth_state = mj.LoadState.from_load(wrench, contact)
    exact = refine(clean, truth_state)
    crb_exposure = np.asarray(exact.sigma, np.float64)
    # Compile both estimators before timing them.
    invert(inverter, clean)
    jax.block_until_ready(refine(clean, truth_state))

    # Shot and read noise as a Gaussian of their variance, then 8-bit quantisation (whose
    # uniform rounding error completes the variance the bound assumes).
    camera = jax.jit(lambda key: camera_noise(key, clean, noise))
    estimates, fits = [], []
    band_seconds = pixel_seconds = 0.0
    for i in range(args.frames):
        frame = camera(jax.random.PRNGKey(i))
        start = time.perf_counter()
        estimates.append(jax.block_until_ready(invert(inverter, frame)))
        band_seconds += time.perf_counter() - start
        start = time.perf_counter()
        fits.append(jax.block_until_ready(refine(frame, estimates[-1])))
        pixel_seconds += time.perf_counter() - start
    band, pixel = (jax.tree_util.tree_map(lambda *x: np.stack(x), *results) for results in (estimates, fits))

    def solved(results):
        ok = results.status == int(mj.Status.CONVERGED)
        return results.wrench[ok].astype(np.float64), results.sigma[ok].astype(np.float64)

    result = {
        "layout": args.layout,
        "load": {
            "wrench": np.asarray(wrench).tolist(),
            "contact": [float(contact.x0), float(contact.y0), float(contact.radius)],
        },
        "mechanics_shape": list(mechanics),
        "frames": args.frames,
        "crb_std": _per_axis(crb),
        "crb_std_exposure_fitted": _per_axis(crb_exposure),
        "band_crb_std": _per_axis(band_crb),
        "noise_free_pixel_fit_error_over_crb": _per_axis(((np.asarray(exact.wrench) - truth) / crb).round(4)),
        "band": {
            "converged": int(np.sum(band.status == int(mj.Status.CONVERGED))),
            **_summary(*solved(band), truth, band_crb, {"whole_frame_crb": crb}),
            "seconds_per_frame": band_seconds / args.frames,
        },
        "pixel": {
            "converged": int(np.sum(pixel.status == int(mj.Status.CONVERGED))),
            # The pixel fit estimates the exposure too, whose bound is a little wider (Fz).
            **_summary(*solved(pixel), truth, crb, {"crb_exposure_fitted": crb_exposure}),
            "mean_chi2_per_dof": float(np.mean(pixel.chi2)),
            "mean_steps": float(np.mean(pixel.steps)),
            "seconds_per_frame": pixel_seconds / args.frames,
        },
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k:36s} {v}")


if __name__ == "__main__":
    main()
