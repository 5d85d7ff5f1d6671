"""Is the independent renderer's fringe phase a camera's? A registration test of its sampling.

    python benchmarks/peer_aliasing.py [--supersample 4 12] [--json]

Renders, with the independent renderer's own code (`../shared/peer/raycast_sensor.py`), a
0.9 N press of 3 mm radius at the image centre, without noise or vignetting, once with the
renderer's grating registration and once with both gratings moved by a quarter of their
period, at each number of samples a pixel. The fringe-phase change against the unloaded
frame is read by moirejax's demodulator (nominal Mid with line gratings).

Two facts a camera obeys give the test. Moving both gratings by a quarter of their own
period leaves the beat of their fundamentals, and so the moiré band's phase change, as it
was; and a press at the centre of a mirror-symmetric sensor changes the phase by an odd
function of x, whose even part is zero. The report gives, per band and number of samples,
the rms of the phase change's odd part for both registrations (equal for a camera) and
the rms of its even part with the renderer's registration (zero for a camera). Whatever
departs from them is the renderer's point sampling of its binary gratings, which folds
their harmonics into the bands; it shrinks as the samples grow. The even part is what the
inversion reads as a centre of pressure off the centre (a Ty bias).
"""

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import moirejax as mj


PEER = Path(__file__).resolve().parents[2] / "shared" / "peer" / "raycast_sensor.py"


def phase_change(peer, supersample: int, registration: float, inverter_for) -> np.ndarray:
    device = peer.Device(
        supersample=supersample,
        full_well=4e8,
        read_noise=0.0,
        vignette=0.0,
        phase_far=registration,
        phase_near=registration,
    )
    layer = peer.Layer(device)
    zero = np.zeros((layer.n, layer.n))
    rng = np.random.default_rng(0)
    rest = peer.render(device, layer, layer.displace(zero, zero, zero), rng) / 255.0
    tx, ty, p = peer.tractions(peer.Contact(x0=0.0, y0=0.0, radius=3.0, fz=0.9), layer)
    pressed = peer.render(device, layer, layer.displace(tx, ty, p), rng) / 255.0
    inverter = inverter_for(rest)
    observed = inverter.observe(jnp.asarray(pressed, jnp.float32))
    return np.angle(np.asarray(observed.fringe) / np.asarray(inverter.reference.fringe)), np.asarray(
        inverter.fringe_weight
    )


def _rms(field: np.ndarray, inside: np.ndarray) -> float:
    """The spread of a phase-change map over the pixels where its band has weight."""
    return float(field[inside].std())


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--supersample", type=int, nargs="+", default=[4, 12])
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if not PEER.exists():
        parser.error(f"the independent renderer is expected at {PEER}")
    spec = importlib.util.spec_from_file_location("raycast_sensor", PEER)
    peer = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = peer  # its dataclasses look their module up there
    spec.loader.exec_module(peer)

    design = mj.preset("mid", layout="lines", duty1=0.5, duty2=0.5)

    def inverter_for(reference):
        return mj.Inverter(design, reference)

    bands = ["moire", "carrier"]
    report = {"load": "0.9 N press, radius 3 mm, at the image centre; no noise, no vignetting", "rows": []}
    for supersample in args.supersample:
        own, weight = phase_change(peer, supersample, 0.0, inverter_for)
        moved, _ = phase_change(peer, supersample, -0.25, inverter_for)
        for band in range(own.shape[0]):
            inside = weight[band] > 0.3 * weight[band].max()
            even = _rms(0.5 * (own[band] + own[band][:, ::-1]), inside)
            odd_own = _rms(0.5 * (own[band] - own[band][:, ::-1]), inside)
            odd_moved = _rms(0.5 * (moved[band] - moved[band][:, ::-1]), inside)
            report["rows"].append(
                {
                    "samples_a_pixel": supersample,
                    "band": bands[min(band // design.n_sets, 1)],
                    "odd_rms_rad": round(odd_own, 5),
                    "odd_rms_rad_quarter_period_registration": round(odd_moved, 5),
                    "registration_change": round(odd_moved / odd_own - 1, 4),
                    "even_rms_rad": round(even, 5),
                    "even_share_of_odd": round(even / odd_own, 4),
                }
            )
    print(json.dumps(report, indent=None if args.json else 1))


if __name__ == "__main__":
    main()
