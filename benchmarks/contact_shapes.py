"""Accuracy on indenters the inversion does not model: flat punches, rings, lines, square punches, two fingertips.

    python benchmarks/contact_shapes.py [--frames 20] [--layout crossed] [--fidelity high] [--json]

The inversion assumes one Hertz patch per frame. This renders loads of each contact family of
`moirejax.random_indenters` (inside the paper's calibrated ranges) through the simulator's
own mechanics of that indenter, with the `high`-fidelity camera (binary gratings, PSF,
distortion, grating phase errors, noise, 8 bits) or the `model` one, and inverts every frame
cold with the nominal Mid design and a reference frame of the same unit. The sphere family is
the one the inversion describes; the others measure what its contact model costs. Prints R²,
RMSE over each axis' range and the status counts per family, with the time per frame.
"""

import argparse
import json
import time

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
    parser.add_argument("--no-carriers", action="store_true", help="invert on the moiré bands alone")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    device = mj.preset("mid", layout=args.layout)
    noise = mj.HighFidelity()

    @jax.jit
    def render(displacement, light, key):
        if args.fidelity == "model":
            shape = (device.height, device.width)
            resize = lambda f: jax.image.resize(f, (*f.shape[:-2], *shape), method="cubic")
            return mj.render_deformed(device, resize(displacement), resize(light))
        return mj.render_deformed_high(key, device, displacement, light, noise, fabrication_key=jax.random.PRNGKey(1))

    at_rest = mj.indenter_deformation(device, [mj.Indenter("sphere", force=(0.0, 0.0, 0.0))])
    reference = np.mean(
        [np.asarray(render(at_rest.displacement, at_rest.light, jax.random.PRNGKey(10_000 + k))) for k in range(4)],
        axis=0,
    )
    inverter = mj.Inverter(device, reference, carriers=False if args.no_carriers else None)
    report = {"layout": args.layout, "fidelity": args.fidelity, "frames_per_family": args.frames, "families": {}}
    rng = np.random.default_rng(args.seed)
    for family in args.families.split(","):
        truth, estimate, status, seconds = [], [], [], []
        for i in range(args.frames):
            state = mj.indenter_deformation(device, mj.random_indenters(rng, family))
            frame = render(state.displacement, state.light, jax.random.PRNGKey(i))
            start = time.perf_counter()
            result = mj.invert(inverter, jnp.asarray(frame))
            jax.block_until_ready(result.wrench)
            seconds.append(time.perf_counter() - start)
            truth.append(np.asarray(state.wrench))
            estimate.append(np.nan_to_num(np.asarray(result.wrench)))
            status.append(mj.Status(int(result.status)).name.lower())
        truth, estimate = np.array(truth), np.array(estimate)
        r2 = 1 - ((estimate - truth) ** 2).sum(0) / ((truth - truth.mean(0)) ** 2).sum(0)
        rmse = np.sqrt(((estimate - truth) ** 2).mean(0)) / SCALE
        report["families"][family] = {
            "r2": dict(zip(mj.WRENCH_AXES, np.round(r2, 4).tolist())),
            "rmse_over_range": dict(zip(mj.WRENCH_AXES, np.round(rmse, 4).tolist())),
            "status": {s: status.count(s) for s in sorted(set(status))},
            "median_s": float(np.median(seconds)),
        }
        if not args.json:
            print(family, json.dumps(report["families"][family]), flush=True)
    if args.json:
        print(json.dumps(report))


if __name__ == "__main__":
    main()
