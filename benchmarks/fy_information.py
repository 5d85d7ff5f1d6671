r"""Where the shear along line gratings goes: `python benchmarks/fy_information.py --json`.

On the Mid design with line gratings (both gratings' lines along y, so the fringes see only
the displacement across them), compares the single-frame standard deviation of every wrench
axis, as a share of its range, that three estimators can reach at the camera noise of the
observability table (4000 e- full well, 4 e- read noise, 8 bit):

- `pixels`: the Cramér–Rao bound of an estimator reading every pixel
  ([`cramer_rao`][moirejax.cramer_rao]);
- `bands`: the bound of one reading the moiré bands and the brightness only;
- `inversion`: the covariance of the inversion's own estimator, from the observables it
  actually reads (the fringe phase in the moiré and carrier bands, 32 x 32 coarse grid,
  [`Inverter.phase_only`][moirejax.Inverter.phase_only]), its least-squares step
  $A = (J^\top J)^{-1} J^\top$ applied to pixel noise: $\mathrm{cov} = \sigma^2 G G^\top$ with
  $G$ the gradient of $A\,r$ with respect to every pixel, exactly (one vector-Jacobian
  product per unknown through the demodulator), data only, no priors;

each with the contact centre and radius estimated alongside (`free`) or known (`fixed`),
and the correlation of the inversion's Fy with every other unknown. `--carriers 0` reads
the moiré bands alone, `--crop N` demodulates on an N x N coarse grid (a wider carrier band).

What the numbers say (docs/results.md, "frames moirejax did not render"): the inversion's
observables hold Fy to within 2x of the whole-frame bound, so Fy's scatter on the independent
renderer's frames is the model misfit of those frames (about ten times the camera noise)
meeting an axis with six times less information than Fx, not information the inversion
throws away.
"""

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj
from moirejax import Contact, HighFidelity, LoadState, pixel_noise_variance, render_frame


AXES = mj.WRENCH_AXES
UNKNOWNS = (*AXES, "x0", "y0", "log_radius")
LOADS = {
    "centred": ((0.0, 0.0, 0.6, 0.0, 0.0, 0.0), (0.0, 0.0, 3.5)),
    "off_centre": ((0.1, 0.1, 0.8, 0.8 * 1.5e-3, 0.8 * 1.0e-3, 0.002), (-1.0, 1.5, 3.0)),
}


def bound(information: np.ndarray, keep: int) -> np.ndarray:
    """Standard deviations of the first six parameters with the first `keep` estimated."""
    return np.sqrt(np.diag(np.linalg.pinv(information[:keep, :keep])))[:6]


def inversion_covariance(inverter: mj.Inverter, frame, state: LoadState, variance: float, keep: int):
    """Covariance (solver coordinates: wrench over its range, mm, log mm) of one least-squares
    step of the inverter's residual at `state`, under white pixel noise of `variance`."""
    y = state.vector()
    observed = inverter.observe(frame)
    jacobian = np.asarray(inverter._data_jacobian(y, observed), np.float64)[:, :keep]
    step = jnp.asarray(np.linalg.pinv(jacobian.T @ jacobian) @ jacobian.T, frame.dtype)
    # The residual is linear in the observed bands (the contact light held at the device's).
    _, vjp = jax.vjp(lambda f: step @ inverter._data_residuals(y, inverter.observe(f)), frame)
    gradients = np.stack([np.asarray(vjp(row)[0], np.float64).ravel() for row in jnp.eye(keep, dtype=frame.dtype)])
    return gradients @ gradients.T * variance


def report(load: str, crop: int, carriers: bool, mechanics: tuple[int, int]) -> dict:
    device = mj.preset("mid", layout="lines", duty1=0.5, duty2=0.5)
    wrench, (x0, y0, radius) = LOADS[load]
    wrench = jnp.asarray(wrench, jnp.float32)
    contact = Contact(x0=jnp.float32(x0), y0=jnp.float32(y0), radius=jnp.float32(radius))
    frame = render_frame(device, wrench, contact, mechanics_shape=mechanics)
    reference = render_frame(device, jnp.zeros(6, jnp.float32), contact, mechanics_shape=mechanics)
    variance = float(jnp.mean(pixel_noise_variance(frame, HighFidelity())))
    out: dict = {"load": load, "crop": crop, "carriers": carriers, "mechanics": list(mechanics)}
    for estimator in ("pixels", "bands"):
        # In units of each axis' range (contact latents in mm).
        scale = np.concatenate([[mj.PAPER_RANGES[a] for a in AXES], np.ones(3)])
        information = np.asarray(
            mj.fisher_information(
                device, wrench, contact, HighFidelity(), mechanics_shape=mechanics, estimator=estimator
            ),
            np.float64,
        ) * np.outer(scale, scale)
        out[f"{estimator}_free"] = bound(information, 9)
        out[f"{estimator}_fixed"] = bound(information, 6)
    inverter = mj.Inverter(
        device, np.asarray(reference), crop_shape=(crop, crop), model_shape=mechanics, carriers=carriers
    ).phase_only(1.0)
    state = LoadState.from_load(wrench, contact)
    for name, keep in (("inversion_free", 9), ("inversion_fixed", 6)):
        covariance = inversion_covariance(inverter, frame, state, variance, keep)
        out[name] = np.sqrt(np.diag(covariance))[:6]
        if keep == 9:
            sd = np.sqrt(np.diag(covariance))
            out["inversion_fy_correlation"] = dict(zip(UNKNOWNS, np.round(covariance[1] / (sd[1] * sd), 3).tolist()))
    for key, value in list(out.items()):
        if isinstance(value, np.ndarray):
            out[key] = dict(zip(AXES, np.round(value, 5).tolist()))
    out["share_of_range"] = "standard deviations over the paper's range of each axis"
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--load", choices=sorted(LOADS), default="centred")
    parser.add_argument("--crop", type=int, default=32)
    parser.add_argument("--carriers", type=int, default=1)
    parser.add_argument("--mechanics", type=int, default=96)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    start = time.perf_counter()
    out = report(args.load, args.crop, bool(args.carriers), (args.mechanics, args.mechanics))
    out["seconds"] = round(time.perf_counter() - start, 1)
    print(json.dumps(out, indent=None if args.json else 1))


if __name__ == "__main__":
    main()
