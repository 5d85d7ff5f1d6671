"""Simulated units, load protocols and datasets.

A simulated unit is a nominal design plus fabrication deviations (pitch, angle,
separation, stiffness, grating registration, optics); datasets record the nominal
device and, apart from it, the true one. Load protocols follow the paper's
calibration (isolated axes), random mixed loads, a manipulation-like sequence, no
contact, contacts of every shape of the indenter library (`shapes`: spheres, flat and
square punches, rings, lines, two fingertips, each solved through its own mechanics), or no
contact with objects in view above the pad (`vision`: colour see-through frames and their
ground truth).
"""

import dataclasses
import math
from pathlib import Path
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from .._conventions import PAPER_RANGES
from ..physics import (
    Contact,
    Device,
    device_to_json,
    HighFidelity,
    render_deformed,
    render_deformed_high,
    render_frame,
    render_frame_high,
)
from ._contacts import CONTACT_FAMILIES, contact_summary, indenter_deformation, IndenterFrame, shape_schedule
from ._scene import render_scene, SCENE_KINDS, scene_schedule, scene_summary


Protocol = Literal["paper", "mixed", "sequence", "none", "shapes", "vision"]
# The protocols of `load_schedule`: one Hertz contact per frame.
PROTOCOLS = ("paper", "mixed", "sequence", "none")


@dataclasses.dataclass(frozen=True)
class Deviations:
    """Bounds of the uniform fabrication deviations of a unit from its nominal design."""

    pitch: float = 0.02  # relative
    angle_deg: float = 0.5
    separation: float = 0.05  # relative
    stiffness: float = 0.30  # relative
    optics: float = 0.10  # relative, gain and background


def perturb_device(key, nominal: Device, deviations: Deviations = Deviations()) -> Device:
    """A unit drawn around `nominal`: every deviation uniform within `deviations`.

    Draws whose moiré period leaves [0.5x, 2.5x] nominal are redrawn, so that the
    fringes stay in the band a real unit of this design would be built for.
    """
    nominal_period = float(2 * jnp.pi / jnp.linalg.norm(nominal.moire_wavevectors()[0]))
    for _ in range(100):
        key, sub = jr.split(key)
        u = np.asarray(jr.uniform(sub, (12,), minval=-1.0, maxval=1.0))
        phases = np.asarray(jr.uniform(jr.fold_in(sub, 1), (2, nominal.n_sets), maxval=2 * math.pi))
        dv = deviations
        optics = eqx.tree_at(
            lambda o: (o.gain, o.background, o.phase1, o.phase2),
            nominal.optics,
            (
                nominal.optics.gain * (1 + dv.optics * u[8]),
                nominal.optics.background * (1 + dv.optics / 2 * u[9]),
                jnp.asarray(phases[0]),
                jnp.asarray(phases[1]),
            ),
        )
        elastomer = eqx.tree_at(lambda e: e.E, nominal.elastomer, nominal.elastomer.E * (1 + dv.stiffness * u[6]))
        a = nominal.a * (1 + dv.separation * u[5])
        elastomer = eqx.tree_at(lambda e: e.thickness, elastomer, jnp.minimum(elastomer.thickness, a))
        unit = dataclasses.replace(
            nominal,
            p1=nominal.p1 * (1 + dv.pitch * u[0]),
            p2=nominal.p2 * (1 + dv.pitch * u[1]),
            alpha1=nominal.alpha1 + math.radians(dv.angle_deg) * u[2],
            alpha2=nominal.alpha2 + math.radians(dv.angle_deg) * u[3],
            a=a,
            elastomer=elastomer,
            optics=optics,
        )
        period = float(2 * jnp.pi / jnp.linalg.norm(unit.moire_wavevectors(), axis=-1).min())
        if 0.5 * nominal_period <= period <= 2.5 * nominal_period:
            return unit
    raise ValueError("could not draw a unit with a usable moire period; reduce the deviations")


@dataclasses.dataclass
class LoadSchedule:
    """Wrenches (N, N*m), contact latents and flags of a sequence of frames."""

    wrench: np.ndarray  # (n, 6)
    x0: np.ndarray
    y0: np.ndarray
    radius: np.ndarray
    contact: np.ndarray  # (n,) bool
    t: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.wrench)

    def contact_at(self, i: int) -> Contact:
        return Contact(x0=float(self.x0[i]), y0=float(self.y0[i]), radius=float(self.radius[i]))


def _centred_moments(fz, x0, y0):
    # Tx = y0 Fz and Ty = -x0 Fz for pressure centred on the contact (N*mm -> N*m).
    return y0 * fz / 1000.0, -x0 * fz / 1000.0


def load_schedule(protocol: str, n: int, seed: int = 0) -> LoadSchedule:
    """The loads of `n` frames of `protocol` (`paper`, `mixed`, `sequence` or `none`)."""
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; choose from {', '.join(PROTOCOLS)}")
    if n < 1:
        raise ValueError(f"need at least one frame, got n={n}")
    rng = np.random.default_rng(seed)
    wrench = np.zeros((n, 6))
    x0, y0 = np.zeros(n), np.zeros(n)
    radius = np.full(n, 3.0)
    contact = np.ones(n, dtype=bool)
    t = None
    if protocol == "none":
        contact[:] = False
    elif protocol == "paper":
        # Isolated axes as in the paper: (i) centre presses, (ii) shear under preload,
        # (iii) twist about the centre under preload, (iv) off-centre presses.
        group = np.arange(n) % 4
        for i in range(n):
            radius[i] = rng.uniform(2.5, 4.5)
            if group[i] == 0:
                wrench[i, 2] = rng.uniform(0.05, 1.2)
            elif group[i] == 1:
                wrench[i, 2] = rng.uniform(0.3, 0.8)
                axis = rng.integers(2)
                wrench[i, axis] = rng.uniform(-0.2, 0.2)
            elif group[i] == 2:
                wrench[i, 2] = rng.uniform(0.5, 1.0)
                radius[i] = rng.uniform(4.0, 5.5)
                wrench[i, 5] = rng.uniform(-0.008, 0.008)
            else:
                fz = rng.uniform(0.3, 1.2)
                reach = min(10.0, 12.0 / fz)
                x0[i], y0[i] = rng.uniform(-reach, reach, 2)
                wrench[i, 2] = fz
                wrench[i, 3], wrench[i, 4] = _centred_moments(fz, x0[i], y0[i])
    elif protocol == "mixed":
        for i in range(n):
            fz = rng.uniform(0.2, 1.2)
            radius[i] = rng.uniform(2.5, 5.0)
            reach = min(7.0, 10.0 / fz)
            x0[i], y0[i] = rng.uniform(-reach, reach, 2)
            fx, fy = rng.uniform(-0.2, 0.2, 2)
            tx, ty = _centred_moments(fz, x0[i], y0[i])
            # Moments about the origin: shear at an off-centre contact adds to Tz.
            tz = rng.uniform(-0.006, 0.006) + (x0[i] * fy - y0[i] * fx) / 1000.0
            wrench[i] = [fx, fy, fz, tx, ty, tz]
    else:  # sequence: approach, press, twist, slide, release, at 60 Hz
        t = np.arange(n) / 60.0
        phase = np.linspace(0, 1, n)
        for i, s in enumerate(phase):
            radius[i] = 4.0
            if s < 0.1 or s > 0.9:
                contact[i] = False
                continue
            ramp = min(1.0, (s - 0.1) / 0.1, (0.9 - s) / 0.1)
            wrench[i, 2] = 1.0 * ramp
            if 0.3 <= s < 0.5:
                wrench[i, 5] = 0.006 * math.sin(math.pi * (s - 0.3) / 0.2)
            if 0.5 <= s < 0.75:
                wrench[i, 0] = 0.15 * math.sin(math.pi * (s - 0.5) / 0.25)
    if protocol in ("paper", "mixed") and n >= 8:
        # A session starts unloaded: these frames give the unit's no-contact reference.
        contact[: max(2, min(8, n // 50))] = False
    wrench[~contact] = 0.0
    return LoadSchedule(wrench=wrench, x0=x0, y0=y0, radius=radius, contact=contact, t=t)


class Simulator(eqx.Module):
    """Renders frames of one unit, jit-compiled once for all frames.

    **Arguments:**

    - `device`: the unit's true parameters.
    - `fidelity`: `"model"` or `"high"`.
    - `high`: the [`HighFidelity`][] non-idealities (used for `"high"`).
    - `fabrication_key`: fixes the unit's grating phase error.
    """

    device: Device
    fidelity: str = eqx.field(static=True, default="high")
    high: HighFidelity = HighFidelity()
    fabrication_key: jax.Array = eqx.field(default_factory=lambda: jr.PRNGKey(7))

    def __check_init__(self):
        if self.fidelity not in ("model", "high"):
            raise ValueError(f"fidelity must be 'model' or 'high', got {self.fidelity!r}")

    def frame(self, key, wrench, contact: Contact) -> jax.Array:
        """One frame in [0, 1]; `model` frames are noise-free and unquantised."""
        wrench = jnp.asarray(wrench, dtype=float)
        if self.fidelity == "model":
            return jnp.clip(render_frame(self.device, wrench, contact), 0.0, 1.0)
        return render_frame_high(key, self.device, wrench, contact, self.high, fabrication_key=self.fabrication_key)

    def deformed_frame(self, key, deformation: IndenterFrame) -> jax.Array:
        """One frame in [0, 1] of any solved deformation (indenters of other shapes, a
        traction map); its mechanics grid covers the image."""
        if self.fidelity == "model":
            shape = (self.device.height, self.device.width)
            resize = lambda f: jax.image.resize(f, (*f.shape[:-2], *shape), method="cubic")
            frame = render_deformed(self.device, resize(deformation.displacement), resize(deformation.light))
            return jnp.clip(frame, 0.0, 1.0)
        return render_deformed_high(
            key,
            self.device,
            deformation.displacement,
            deformation.light,
            self.high,
            fabrication_key=self.fabrication_key,
        )


def simulate_dataset(
    out: str | Path,
    nominal: Device,
    protocol: str,
    n: int,
    *,
    seed: int = 0,
    fidelity: str = "high",
    unit: Device | None = None,
    progress: bool = True,
    overwrite: bool = False,
    max_force: float | None = None,
) -> Path:
    """Simulate `n` frames of `protocol` for a unit of design `nominal` into a dataset folder.

    With `fidelity="high"` and no `unit` given, the unit deviates from `nominal` by
    [`perturb_device`][] with `seed`; the manifest records the nominal device and the true
    one apart. A contact sheet PNG of sample frames is written beside the dataset, and a
    `sequence` protocol also writes an MP4.

    The `shapes` protocol mixes the contact families of [`shape_schedule`][moirejax.shape_schedule]
    with normal forces up to `max_force` (default the paper's 1.2 N; grasps go to 10 N), each
    frame's wrench the resultant of its traction field; its latent columns are the centre
    of pressure (`x0`, `y0`), the contact `area` (mm²), the `radius` of a disc of that area and
    the `family` (its index in [`CONTACT_FAMILIES`][moirejax.CONTACT_FAMILIES]).

    The `vision` protocol has no contact: each frame sees one object of
    [`scene_schedule`][moirejax.scene_schedule] (discs, rings, rectangles and the shipped
    textures at 0-30 mm above the pad), or none, through the sensor by
    [`render_scene`][moirejax.render_scene]. Its frames are colour (BGR PNGs), and each comes
    with its ground truth: the grating-free view as a 16-bit PNG under `grating_free/`, and the
    object's [`scene_summary`][moirejax.scene_summary] in the latent columns (`kind`, its
    index in the manifest's `metadata.scene_kinds`; `x`, `y`, `yaw_deg`, `height`, `length`,
    `width`; `r`, `g`, `b`). `fidelity="model"` renders them without camera noise, in 16 bits.
    """
    from tqdm.auto import tqdm

    from ..data import DatasetWriter

    if unit is None:
        unit = perturb_device(jr.PRNGKey(seed), nominal) if fidelity == "high" else nominal
    if max_force is not None and protocol != "shapes":
        raise ValueError(f"max_force applies to the shapes protocol only, not {protocol!r}")
    simulator = Simulator(unit, fidelity=fidelity, fabrication_key=jr.PRNGKey(seed + 1000))
    if protocol == "vision":
        return _simulate_vision(out, nominal, unit, simulator, n, seed, progress=progress, overwrite=overwrite)
    if protocol == "shapes":
        contacts = shape_schedule(n, seed, PAPER_RANGES["fz"] if max_force is None else max_force)
        schedule = LoadSchedule(
            wrench=np.zeros((n, 6)),
            x0=np.full(n, np.nan),
            y0=np.full(n, np.nan),
            radius=np.full(n, np.nan),
            contact=np.array([c is not None for c in contacts]),
        )
    else:
        contacts = None
        schedule = load_schedule(protocol, n, seed)
    render_deformation = eqx.filter_jit(simulator.deformed_frame)
    at_rest = None
    out = Path(out)
    key = jr.PRNGKey(seed + 2000)
    samples = []
    sample_at = set(np.linspace(0, n - 1, min(n, 12)).astype(int).tolist())
    video = None
    with DatasetWriter(
        out,
        device=device_to_json(nominal),
        true_device=device_to_json(unit),
        frame_shape=(nominal.height, nominal.width),
        source=f"moirejax simulate ({fidelity} fidelity)",
        protocol=protocol,
        fidelity=fidelity,
        seed=seed,
        fps=60.0 if protocol == "sequence" else None,
        overwrite=overwrite,
    ) as writer:
        for i in tqdm(range(n), desc=f"simulate {protocol}", disable=not progress, unit="frame"):
            if contacts is None:
                frame = np.asarray(simulator.frame(jr.fold_in(key, i), schedule.wrench[i], schedule.contact_at(i)))
                latent = {"x0": schedule.x0[i], "y0": schedule.y0[i], "radius": schedule.radius[i]}
            else:
                contact = contacts[i]
                if contact is None:
                    if at_rest is None:
                        at_rest = indenter_deformation(unit, [])
                    deformation, family = at_rest, math.nan
                else:
                    deformation = indenter_deformation(unit, contact[1])
                    family = float(CONTACT_FAMILIES.index(contact[0]))
                frame = np.asarray(render_deformation(jr.fold_in(key, i), deformation))
                schedule.wrench[i] = np.asarray(deformation.wrench) if contact is not None else 0.0
                latent = {**contact_summary(deformation), "family": family}
                schedule.x0[i], schedule.y0[i], schedule.radius[i] = latent["x0"], latent["y0"], latent["radius"]
            writer.add(
                frame,
                schedule.wrench[i],
                t=None if schedule.t is None else float(schedule.t[i]),
                contact=bool(schedule.contact[i]),
                latent=latent,
            )
            if i in sample_at:
                samples.append((i, frame))
            if protocol == "sequence":
                video = _append_video(video, out.with_suffix(".mp4"), frame)
    if video is not None:
        video.release()
    write_contact_sheet(out.with_name(out.name + "_contact_sheet.png"), samples, schedule)
    return out


def _simulate_vision(
    out: str | Path,
    nominal: Device,
    unit: Device,
    simulator: Simulator,
    n: int,
    seed: int,
    *,
    progress: bool,
    overwrite: bool,
) -> Path:
    """The `vision` protocol of [`simulate_dataset`][]: see-through frames of a scene schedule."""
    from tqdm.auto import tqdm

    from ..data import DatasetWriter

    scenes = scene_schedule(unit, n, seed)
    camera = simulator.high
    if simulator.fidelity == "model":
        # A camera without noise, quantised finely enough to keep the render.
        camera = dataclasses.replace(camera, full_well=1e12, read_noise=0.0, bit_depth=16)
    key = jr.PRNGKey(seed + 2000)
    out = Path(out)
    samples, titles = [], []
    sample_at = set(np.linspace(0, n - 1, min(n, 12)).astype(int).tolist())
    with DatasetWriter(
        out,
        device=device_to_json(nominal),
        true_device=device_to_json(unit),
        frame_shape=(nominal.height, nominal.width),
        bit_depth=8 if simulator.fidelity == "high" else 16,
        source=f"moirejax simulate ({simulator.fidelity} fidelity)",
        protocol="vision",
        fidelity=simulator.fidelity,
        seed=seed,
        metadata={"scene_kinds": list(SCENE_KINDS)},
        images=("grating_free",),
        overwrite=overwrite,
    ) as writer:
        for i in tqdm(range(n), desc="simulate vision", disable=not progress, unit="frame"):
            entry = scenes[i]
            seen = render_scene(jr.fold_in(key, i), unit, None if entry is None else entry[1], camera)
            frame = np.clip(np.asarray(seen.frame), 0.0, 1.0)
            writer.add(
                frame,
                np.zeros(6),
                contact=False,
                latent=scene_summary(entry),
                images={"grating_free": np.clip(np.asarray(seen.grating_free), 0.0, 1.0)},
            )
            if i in sample_at:
                samples.append((i, frame))
                titles.append(
                    "empty"
                    if entry is None
                    else f"#{i} {entry[0]} at ({float(entry[1].x):+.1f}, {float(entry[1].y):+.1f}) mm, "
                    f"{float(entry[1].height):.0f} mm up"
                )
    write_contact_sheet(out.with_name(out.name + "_contact_sheet.png"), samples, titles=titles)
    return out


def _append_video(video, path: Path, frame: np.ndarray):
    import cv2

    image = (np.clip(frame, 0, 1) * 255).astype(np.uint8)
    if video is None:
        video = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 60.0, image.shape[::-1], False)
    video.write(image)
    return video


def write_contact_sheet(
    path: Path,
    samples: list[tuple[int, np.ndarray]],
    schedule: LoadSchedule | None = None,
    *,
    titles: list[str] | None = None,
) -> None:
    """A grid of sample frames (gray, or BGR colour), each titled with its wrench from
    `schedule`, or with its entry of `titles`."""
    from .._plotting import pyplot, save_figure

    plt = pyplot()
    cols = min(4, len(samples))
    rows = math.ceil(len(samples) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.4 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for k, (ax, (i, frame)) in enumerate(zip(axes.flat, samples)):
        if frame.ndim == 3:
            ax.imshow(frame[..., ::-1])
        else:
            ax.imshow(frame, cmap="gray", vmin=0, vmax=1)
        if titles is not None or schedule is None:
            ax.set_title(titles[k] if titles is not None else f"#{i}", fontsize=7)
            continue
        w = schedule.wrench[i]
        ax.set_title(
            f"#{i} F=({w[0]:+.2f},{w[1]:+.2f},{w[2]:.2f}) N\nT=({w[3] * 1e3:+.1f},{w[4] * 1e3:+.1f},{w[5] * 1e3:+.1f}) mN·m",
            fontsize=7,
        )
    fig.tight_layout()
    save_figure(fig, path)
