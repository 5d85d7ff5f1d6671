"""How fast the contact gate switches between vision and tactile mode, and how often it is fooled.

    python benchmarks/gate_switching.py            # summary
    python benchmarks/gate_switching.py --json     # one JSON object

Scripted 60 fps recordings of a high-fidelity Mid unit (its fabrication errors, PSF,
vignetting, shot and read noise, 8 bits), each frame the tactile frame of its load times
what the camera sees through the sensor (`mj.render_scene`'s grating-free view of the scene
over that of the empty view), under its lighting:

- `press`: a disc held still above the pad, then a press that reaches its load in 6 frames
  (100 ms), holds for half a second and lets go in 3 frames; loads, places, shear and twist
  drawn inside the paper's ranges;
- `approach`: a disc coming down from 30 mm onto the pad over a second, then pressing;
- `lighting`: no contact, the exposure falling by 30% over two seconds while a gradient and a
  slow ripple sweep the field;
- `passing`: no contact, a disc, a ring and a picture sliding across the view 2-10 mm above
  the pad.

The truth is the load: a frame is in contact from the first frame with any normal force to
the last. Reported per press: `onset_frames`, frames from the true onset to the gate's first
tactile frame, and `release_frames`, from the first unloaded frame after a press to the
gate's first vision frame (median and worst); `false_switches_per_1000`, switches to tactile
on unloaded frames per thousand unloaded frames (every script), and the gate's time per
frame against the floor of its first step alone, the area-averaging of the frame to the
gate's working size (`cv2.resize` with `INTER_AREA`), measured on the same frames. A missed press
counts as the length of its contact. The gate is the one `moirejax live` uses
(`mj.live.make_gate`), fed the 8-bit gray frames a camera gives.
"""

import argparse
import json
import time

import cv2
import equinox as eqx
import jax
import jax.random as jr
import numpy as np

import moirejax as mj
from moirejax import live


FPS = 60
RAMP_FRAMES, HOLD_FRAMES, RELEASE_FRAMES = 6, 30, 3


def _gray(bgr: np.ndarray) -> np.ndarray:
    return bgr @ np.array([0.114, 0.587, 0.299])


class Scripts:
    """Renders the frames of every script for one unit."""

    def __init__(self, device: mj.Device, seed: int):
        self.device = device
        self.offset = float(device.optics.offset)
        self.simulator = mj.Simulator(device, "high", fabrication_key=jr.PRNGKey(seed))
        self.tactile = eqx.filter_jit(lambda s, k, w, c: s.frame(k, w, c))
        self.scene = eqx.filter_jit(lambda k, d, o: mj.render_scene(k, d, o).grating_free)
        self.empty = _gray(np.asarray(self.scene(jr.PRNGKey(0), device, None))) - self.offset
        self.key = jr.PRNGKey(seed)

    def _next(self):
        self.key, key = jr.split(self.key)
        return key

    def see_through(self, scene) -> np.ndarray:
        """The scene's share of the light at every pixel: 1 on the backdrop."""
        if scene is None:
            return np.ones_like(self.empty)
        view = _gray(np.asarray(self.scene(self._next(), self.device, scene))) - self.offset
        return view / self.empty

    def frame(self, wrench, contact, scene=None, light=1.0) -> np.ndarray:
        tactile = np.asarray(self.tactile(self.simulator, self._next(), np.asarray(wrench, float), contact))
        frame = self.offset + (tactile - self.offset) * self.see_through(scene) * light
        return np.clip(np.round(frame * 255), 0, 255) / 255


def press_loads(rng, n_quiet: int):
    """One press: (wrench, contact) per frame, and whether each frame is loaded."""
    peak = np.array(
        [
            rng.uniform(-0.15, 0.15),
            rng.uniform(-0.15, 0.15),
            rng.uniform(0.1, 1.2),
            0.0,
            0.0,
            rng.uniform(-0.004, 0.004),
        ]
    )
    contact = mj.Contact(rng.uniform(-4, 4), rng.uniform(-4, 4), rng.uniform(2.0, 4.0))
    scale = np.concatenate(
        [
            np.zeros(n_quiet),
            np.arange(1, RAMP_FRAMES + 1) / RAMP_FRAMES,
            np.ones(HOLD_FRAMES),
            1 - np.arange(1, RELEASE_FRAMES + 1) / RELEASE_FRAMES,
            np.zeros(n_quiet),
        ]
    )
    return [peak * s for s in scale], contact, scale > 0


def switching(tactile: np.ndarray, loaded: np.ndarray):
    """Onset and release delays (frames) of each contact, and false switches on unloaded frames."""
    onsets = np.flatnonzero(np.diff(np.concatenate([[0], loaded.astype(int)])) == 1)
    releases = np.flatnonzero(np.diff(np.concatenate([loaded.astype(int), [0]])) == -1) + 1
    onset_delays, release_delays = [], []
    for on, off in zip(onsets, releases):
        hits = np.flatnonzero(tactile[on:off])
        onset_delays.append(int(hits[0]) if hits.size else int(off - on))
        after = np.flatnonzero(~tactile[off:])
        release_delays.append(int(after[0]) if after.size else int(len(tactile) - off))
    switched_on = np.flatnonzero(np.diff(tactile.astype(int)) == 1) + 1
    false = int(np.sum(~loaded[switched_on]))
    return onset_delays, release_delays, false


def run_script(scripts: Scripts, frames, loaded):
    gate = live.make_gate(scripts.device)
    seconds, floor, modes = [], [], []
    work = (gate.work_size, gate.work_size)
    for f in frames:
        t = time.perf_counter()
        modes.append(gate.update(f).mode == "tactile")
        seconds.append(time.perf_counter() - t)
        t = time.perf_counter()
        cv2.resize(f.astype(np.float32), work, interpolation=cv2.INTER_AREA)
        floor.append(time.perf_counter() - t)
    return switching(np.array(modes), np.asarray(loaded)), seconds, floor


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presses", type=int, default=6, help="press scripts (each about 1.5 s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    device = mj.preset("mid")
    start = time.perf_counter()
    scripts = Scripts(device, args.seed)
    zero, rest = np.zeros(6), mj.Contact()
    render = scripts.frame

    recordings = {}
    for i in range(args.presses):
        loads, contact, loaded = press_loads(rng, 20)
        disc = mj.scene_disc(contact.x0, contact.y0, 12.0, height=0.0, rgb=tuple(rng.uniform(0.1, 0.9, 3)))
        recordings[f"press{i}"] = ([render(w, contact, disc) for w in loads], loaded)
    loads, contact, loaded = press_loads(rng, 0)
    heights = np.linspace(30.0, 0.0, FPS)
    approach = [render(zero, rest, mj.scene_disc(contact.x0, contact.y0, 12.0, height=h)) for h in heights]
    disc = mj.scene_disc(contact.x0, contact.y0, 12.0)
    approach += [render(w, contact, disc) for w in loads] + [render(zero, rest, disc) for _ in range(20)]
    recordings["approach"] = (approach, np.concatenate([np.zeros(FPS, bool), loaded, np.zeros(20, bool)]))
    rows, cols = np.mgrid[0 : device.height, 0 : device.width] / device.height
    lighting = []
    for i in range(2 * FPS):
        s = i / (2 * FPS)
        light = (1 - 0.3 * s) * (1 + 0.2 * s * (cols - 0.5) + 0.05 * np.sin(2 * np.pi * (rows + s)))
        lighting.append(render(zero, rest, None, light))
    recordings["lighting"] = (lighting, np.zeros(len(lighting), bool))
    objects = [
        lambda x: mj.scene_disc(x, 2.0, 10.0, height=2.0, rgb=(0.1, 0.7, 0.2)),
        lambda x: mj.scene_ring(-x, -3.0, 14.0, 8.0, height=5.0, rgb=(0.9, 0.5, 0.1)),
        lambda x: mj.scene_texture("coffee", 20.0, x=x, y=0.0, height=10.0),
    ]
    passing = [render(zero, rest, objects[(i // FPS) % 3](-16.0 + 32.0 * (i % FPS) / FPS)) for i in range(3 * FPS)]
    recordings["passing"] = (passing, np.zeros(len(passing), bool))
    setup_s = time.perf_counter() - start

    onset, release, false, unloaded, gate_s, floor_s = [], [], 0, 0, [], []
    per_script = {}
    for name, (frames, loaded) in recordings.items():
        (on, off, f), seconds, floor = run_script(scripts, frames, loaded)
        onset += on
        release += off
        false += f
        unloaded += int(np.sum(~np.asarray(loaded)))
        gate_s += seconds[1:]
        floor_s += floor[1:]
        per_script[name] = {"onset_frames": on, "release_frames": off, "false_switches": f}
    report = {
        "device": "mid 512x512, high fidelity",
        "fps": FPS,
        "presses": len(onset),
        "onset_frames": {"median": float(np.median(onset)), "max": int(np.max(onset))},
        "release_frames": {"median": float(np.median(release)), "max": int(np.max(release))},
        "false_switches_per_1000": 1000.0 * false / max(unloaded, 1),
        "unloaded_frames": unloaded,
        "per_script": per_script,
        "gate_ms": {"median": float(np.median(gate_s) * 1e3), "p90": float(np.percentile(gate_s, 90) * 1e3)},
        "frames_per_s": float(1 / np.median(gate_s)),
        "floor_area_average_ms": float(np.median(floor_s) * 1e3),
        "setup_s": setup_s,
        "backend": jax.default_backend(),
    }
    print(json.dumps(report, indent=None if args.json else 1))


if __name__ == "__main__":
    main()
