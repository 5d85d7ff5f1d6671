"""Accuracy on indenters other than a sphere: flat punches, rings, lines, square punches, two fingertips.

    python benchmarks/contact_shapes.py [--frames 20] [--layout crossed] [--fidelity high] [--max-force 1.2] [--json]

The inversion reads one round patch per frame (or two), whose pressure lies between a
sphere's and a flat punch's. This renders loads of each contact family of
`moirejax.random_indenters` (inside the paper's calibrated ranges, or grasp loads up to
`--max-force` newtons) through the simulator's
own mechanics of that indenter, with the `high`-fidelity camera (binary gratings, PSF,
distortion, grating phase errors, noise, 8 bits) or the `model` one, and inverts every frame
cold with the nominal Mid design and a reference frame of the same unit. The sphere family is
the one the inversion describes; the others measure what its contact model costs. Prints R²,
RMSE over each axis' range and the status counts per family, with the time per frame.
"""

import argparse
import json
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj


FAMILIES = (*mj.CONTACT_SHAPES, "two")
SCALE = np.array([mj.PAPER_RANGES[axis] for axis in mj.WRENCH_AXES])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20, help="loads per family")
    parser.add_argument("--layout", default="crossed", choices=["crossed", "lines"])
    parser.add_argument("--fidelity", default="high", choices=["high", "model"])
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-force", type=float, default=mj.PAPER_RANGES["fz"], help="largest normal force (N)")
    parser.add_argument("--no-carriers", action="store_true", help="invert on the moiré bands alone")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    device = mj.preset("mid", layout=args.layout)
    simulator = mj.Simulator(device, fidelity=args.fidelity, fabrication_key=jax.random.PRNGKey(1))
    render = eqx.filter_jit(simulator.deformed_frame)
    at_rest = mj.indenter_deformation(device, [])
    reference = np.mean([np.asarray(render(jax.random.PRNGKey(10_000 + k), at_rest)) for k in range(4)], axis=0)
    inverter = mj.Inverter(device, reference, carriers=False if args.no_carriers else None)
    report = {
        "layout": args.layout,
        "fidelity": args.fidelity,
        "max_force": args.max_force,
        "frames_per_family": args.frames,
        "families": {},
    }
    rng = np.random.default_rng(args.seed)
    shear, twist = mj.grasp_limits(args.max_force)
    # The drawn loads' limits (contacts within 4 mm of the centre), at least the paper's ranges.
    limits = np.maximum(SCALE, [shear, shear, args.max_force, 4e-3 * args.max_force, 4e-3 * args.max_force, twist])
    for family in args.families.split(","):
        truth, estimate, sigma, status, seconds, angle_errors = [], [], [], [], [], []
        for i in range(args.frames):
            indenters = mj.random_indenters(rng, family, args.max_force)
            state = mj.indenter_deformation(device, indenters)
            frame = render(jax.random.PRNGKey(i), state)
            start = time.perf_counter()
            result = mj.invert(inverter, jnp.asarray(frame))
            jax.block_until_ready(result.wrench)
            seconds.append(time.perf_counter() - start)
            truth.append(np.asarray(state.wrench))
            estimate.append(np.nan_to_num(np.asarray(result.wrench)))
            sigma.append(np.asarray(result.sigma))
            status.append(mj.Status(int(result.status)).name.lower())
            if family == "line" and int(result.contacts) == 1:
                # How far the patch's long axis is from the edge's direction (lines have no sense).
                off = float(result.contact.long_axis_angle) - float(indenters[0].angle)
                angle_errors.append(abs((off + np.pi / 2) % np.pi - np.pi / 2))
        truth, estimate, sigma = np.array(truth), np.array(estimate), np.array(sigma)
        r2 = 1 - ((estimate - truth) ** 2).sum(0) / ((truth - truth.mean(0)) ** 2).sum(0)
        rmse = np.sqrt(((estimate - truth) ** 2).mean(0)) / SCALE
        # Every frame without a believed wrench (a refused frame's is NaN, counted as zero above).
        flagged = ~np.isin(status, ["converged"])
        report["families"][family] = {
            "r2": dict(zip(mj.WRENCH_AXES, np.round(r2, 4).tolist())),
            "rmse_over_range": dict(zip(mj.WRENCH_AXES, np.round(rmse, 4).tolist())),
            "status": {s: status.count(s) for s in sorted(set(status))},
            # How far off the frames were that the inversion did not flag (converged), in ranges.
            "worst_unflagged_error_over_range": float(np.max(np.abs(estimate - truth)[~flagged] / SCALE, initial=0.0)),
            # The same over the drawn loads' limits (at 10 N: 1 N shear, 10 N, 0.04 N*m tilt, 0.035 N*m twist).
            "worst_unflagged_error_over_limits": float(
                np.max(np.abs(estimate - truth)[~flagged] / limits, initial=0.0)
            ),
            # Converged frames with an axis off by more than three of its standard errors:
            # wrong beyond what the estimate itself says.
            "unflagged_beyond_3_sigma": int(np.sum(np.any(np.abs(estimate - truth) > 3 * sigma, axis=1) & ~flagged)),
            "median_s": float(np.median(seconds)),
        }
        if angle_errors:
            # Lines read with one patch: its long axis against the edge's direction.
            report["families"][family]["one_patch_frames"] = len(angle_errors)
            report["families"][family]["median_axis_error_deg"] = round(float(np.degrees(np.median(angle_errors))), 1)
        if not args.json:
            print(family, json.dumps(report["families"][family]), flush=True)
    if args.json:
        print(json.dumps(report))


if __name__ == "__main__":
    main()
