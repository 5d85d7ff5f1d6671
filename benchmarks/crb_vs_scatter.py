"""Cramér–Rao bound against the inversion's actual scatter: `python benchmarks/crb_vs_scatter.py --json`.

Renders one `model`-fidelity frame of the Mid design at the nominal observability load,
draws `--frames` noisy copies with the camera noise model the bound assumes (shot noise at
4000 e- full well, 4 e- read noise, 8-bit quantisation), inverts each independently
(Levenberg–Marquardt from a cold start), and compares per axis: the bound, the empirical
standard deviation and bias of the estimates, and the mean standard error the inversion
reports. An efficient, unbiased inversion has scatter/bound near 1; the inversion fits the
demodulated bands only (the carriers and harmonics carry information it leaves), so a
ratio above 1 measures what that choice costs.
"""

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj
from moirejax._contact import Contact
from moirejax._inversion import invert_frame, Inverter
from moirejax._observability import cramer_rao, nominal_load, pixel_noise_variance
from moirejax._render import HighFidelity, render_frame


AXES = ("fx", "fy", "fz", "tx", "ty", "tz")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--layout", default="crossed", choices=("crossed", "lines"))
    args = parser.parse_args(argv)

    device = mj.preset("mid", layout=args.layout)
    wrench, contact = nominal_load(np.float32)
    noise = HighFidelity()
    bound = cramer_rao(device, wrench, contact, noise)
    clean = render_frame(device, wrench, contact)
    std = jnp.sqrt(pixel_noise_variance(clean, noise))
    levels = 2**noise.bit_depth - 1
    inverter = Inverter(device, reference=render_frame(device, jnp.zeros(6), Contact()))

    estimates, reported, statuses = [], [], []
    start = time.perf_counter()
    for i in range(args.frames):
        # Shot and read noise as a Gaussian of the same variance, then 8-bit quantisation.
        draw = clean + std * jax.random.normal(jax.random.PRNGKey(i), clean.shape)
        frame = jnp.round(jnp.clip(draw, 0.0, 1.0) * levels) / levels
        estimate = invert_frame(inverter, frame)
        statuses.append(int(estimate.status))
        estimates.append(np.asarray(estimate.wrench, np.float64))
        reported.append(np.asarray(estimate.sigma, np.float64))
    elapsed = time.perf_counter() - start
    ok = np.isin(statuses, [int(mj.Status.CONVERGED)])
    estimates, reported = np.array(estimates)[ok], np.array(reported)[ok]
    scatter = estimates.std(axis=0, ddof=1)
    bias = estimates.mean(axis=0) - np.asarray(wrench, np.float64)
    crb = np.array([bound["std"][a] for a in AXES], np.float64)
    result = {
        "layout": args.layout,
        "load": {
            "wrench": np.asarray(wrench).tolist(),
            "contact": [float(contact.x0), float(contact.y0), float(contact.radius)],
        },
        "frames": args.frames,
        "converged": int(ok.sum()),
        "crb_std": dict(zip(AXES, crb.tolist())),
        "empirical_std": dict(zip(AXES, scatter.tolist())),
        "scatter_over_crb": dict(zip(AXES, (scatter / crb).round(3).tolist())),
        "bias_over_std": dict(zip(AXES, (bias / scatter).round(3).tolist())),
        "reported_sigma_over_scatter": dict(zip(AXES, (reported.mean(axis=0) / scatter).round(3).tolist())),
        "seconds_per_frame": elapsed / args.frames,
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k:28s} {v}")


if __name__ == "__main__":
    main()
