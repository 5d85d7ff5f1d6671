r"""The paper's incremental cap-removal cycle, closed on the inverted wrench of a simulated sensor.

A simulated "robot" presses the sensor onto a bottle cap and turns it; each cycle:

1. **approach** in vision mode: while the cap is in view off the sensor's axis, move
   sideways onto it ([`locate`][moirejax.live.locate] on the see-through frame, at the
   height the robot is above it), then descend until the gate reports contact;
2. **press** to a target normal force, a proportional law on the *estimated* $F_z$;
3. **twist**, holding $F_z$, while watching the estimated $T_z$ rise; when it stops rising
   the cap has broken free (it slips in its thread) and the cycle's turn is done;
4. **release**, lifting until the gate is back in vision mode;
5. **return**, turning back in the air, ready to regrip.

The plant is linear: $F_z = k_z d$ for an indentation $d > 0$, and the grip winds a
torsional spring, $T_z = k_t (\theta - \theta_g)$, saturating at the cap's breakaway
torque $T_s$, beyond which the cap turns with the sensor (the "slip" that ends a twist),
or at the torque the pad's friction holds, $\mu_t F_z$, if that is lower (the pad then
slips on the cap, as it does while releasing).
The sensor renders every step from the true load; the controller sees only the gate's
mode and the inversion's estimate (one frame behind the command, as with a real camera).

Targets stay inside the simulator's calibrated range ($F_z \le 1.2$ N, $|T_z| \le 0.008$
N·m): 1 N and a breakaway torque of 0.006 N·m. The paper's demonstration pressed with
about 6 N and turned with 0.024 N·m, far outside its own calibrated range (1.2 N,
0.008 N·m), so those numbers are not reproduced here.
"""

import dataclasses
import math
import os

import cv2
import numpy as np

from .._conventions import PAPER_RANGES
from ..inverse import Inverter
from ..physics import Contact, Device
from ..simulate import scene_disc, SceneObject
from ._run import make_gate, make_tactile_processor, SimulatedSensor
from ._types import Real
from ._vision import locate, SeeThrough


# Vision-mode frames of the approach averaged into the reference of a visible cap's press.
_REFERENCE_FRAMES = 3

PHASES = ("approach", "press", "twist", "release", "return", "done")
_PHASE_COLOURS = {
    "approach": "#dbe9f6",
    "press": "#fde2c8",
    "twist": "#d9f0d3",
    "release": "#f3d7ea",
    "return": "#eeeeee",
}


@dataclasses.dataclass
class CapRig:
    """The simulated robot and bottle cap (the plant), in sensor coordinates.

    **Fields:**

    - `depth`: commanded indentation of the sensor into the cap (mm; negative: above it).
    - `angle`: commanded rotation of the sensor about its axis (rad).
    - `k_z`: normal stiffness of the pad on the cap (N/mm).
    - `k_t`: torsional stiffness of the grip (N·m/rad).
    - `slip_torque`: the cap's breakaway torque (N·m): $|T_z|$ saturates here and the cap turns.
    - `grip_torque_per_newton`: torque the pad holds on the cap per newton of normal
        force (N·m/N, friction times an effective radius); below `slip_torque / it` newtons
        the pad slips on the cap instead, as when releasing.
    - `radius`: contact radius on the cap (mm).
    - `grip_angle`: the sensor angle at which the grip torque is zero; reset at each new
        contact and dragged along while the cap turns.
    - `cap_angle`: how far the cap has turned (rad).
    - `cap_x`, `cap_y`: where the cap's axis is relative to the sensor's (mm, wrench frame);
        a sideways move of the robot shifts it.
    - `cap_diameter`: the cap's diameter (mm), as the camera sees it through the sensor.
    - `cap_rgb`: its colour (linear RGB, e.g. the paper's green cap `(0.1, 0.7, 0.2)`);
        `None` (the default) for a cap the camera does not see: gray frames, no alignment.
        A visible cap pressed under the pad tints the frames the inversion reads; the press
        is read against the approach's last frames, which show it, but during the twist
        the estimated Fz drifts up to 0.2 N above the true one (the twist moves the fringes
        out to the cap's edge, which the reference shows where it was).
    """

    depth: float = -0.5
    angle: float = 0.0
    k_z: float = 1.0
    k_t: float = 0.03
    slip_torque: float = 0.006
    grip_torque_per_newton: float = 0.008
    radius: float = 4.0
    grip_angle: float = 0.0
    cap_angle: float = 0.0
    cap_x: float = 0.0
    cap_y: float = 0.0
    cap_diameter: float = 14.0
    cap_rgb: tuple[float, float, float] | None = None

    def move(self, dx: Real, dy: Real) -> None:
        """Move the robot sideways by `(dx, dy)` mm in the sensor's frame; the cap, fixed
        in the world, shifts the other way. Nothing moves while the pad grips the cap."""
        if self.depth <= 0:
            self.cap_x -= float(dx)
            self.cap_y -= float(dy)

    def scene(self) -> SceneObject | None:
        """The cap as the camera sees it through the sensor, at the robot's height above it."""
        if self.cap_rgb is None:
            return None
        return scene_disc(self.cap_x, self.cap_y, self.cap_diameter, height=max(-self.depth, 0.0), rgb=self.cap_rgb)

    def command(self, depth: Real, angle: Real) -> None:
        """Move the robot; the cap follows through the grip if in contact."""
        was_touching = self.depth > 0
        self.depth, self.angle = float(depth), float(angle)
        if self.depth <= 0 or not was_touching:
            # A fresh grip (or none): no wind-up.
            self.grip_angle = self.angle
            return
        wind = self.angle - self.grip_angle
        cap_limit = self.slip_torque / self.k_t
        pad_limit = self.grip_torque_per_newton * self.k_z * self.depth / self.k_t
        limit = min(cap_limit, pad_limit)
        if abs(wind) > limit:
            # Past the weaker of the two frictions something turns, keeping the torque at
            # its limit: the cap in its thread, or the pad on the cap (light grip, release).
            turned = wind - math.copysign(limit, wind)
            self.grip_angle += turned
            if cap_limit <= pad_limit:
                self.cap_angle += turned

    def wrench(self) -> np.ndarray:
        """True `[fx, fy, fz, tx, ty, tz]` (N, N·m) on the sensor, moments about its centre."""
        fz = self.k_z * max(self.depth, 0.0)
        tz = self.k_t * (self.angle - self.grip_angle) if fz > 0 else 0.0
        # A press off the axis: Tx = y Fz, Ty = -x Fz (mm to m).
        return np.array([0.0, 0.0, fz, self.cap_y * fz / 1e3, -self.cap_x * fz / 1e3, tz])

    def __call__(self, index: int) -> tuple[np.ndarray, Contact]:
        """The load script of a [`SimulatedSensor`][]: the current load, whatever the frame."""
        return self.wrench(), Contact(self.cap_x, self.cap_y, self.radius)


@dataclasses.dataclass(frozen=True)
class CapController:
    """Settings of the cap-removal state machine.

    **Fields:**

    - `target_fz`: normal force to press to (N); `fz_tolerance`: "reached" band (N).
    - `settle_frames`: consecutive frames within the band before twisting.
    - `press_gain`: indentation step per newton of force error (mm/N); `max_press_step` caps it (mm).
    - `approach_step`, `release_step`: per-frame descent and lift (mm).
    - `lift_to`: height above the cap to lift to before turning back (mm).
    - `twist_step`, `return_step`: per-frame rotation while twisting and turning back (rad).
    - `min_twist_torque`: $T_z$ (N·m) that must be reached before a stall counts as slip.
    - `slip_ratio`: slip when the estimated $T_z$ rises by less than this fraction of its
        largest per-frame rise so far in this twist.
    - `max_twist`: rotation after which a twist ends anyway (rad).
    - `align_tolerance`: during the approach, the cap's located centre must be this close
        to the sensor's axis (mm) before descending; `align_gain` (per frame) and
        `max_align_step` (mm) set the sideways move towards it.
    """

    target_fz: float = 1.0
    fz_tolerance: float = 0.05
    settle_frames: int = 2
    press_gain: float = 0.8
    max_press_step: float = 0.25
    approach_step: float = 0.12
    release_step: float = 0.35
    lift_to: float = 0.3
    twist_step: float = 0.05
    return_step: float = 0.2
    min_twist_torque: float = 0.002
    slip_ratio: float = 0.3
    max_twist: float = 0.6
    align_tolerance: float = 0.3
    align_gain: float = 0.8
    max_align_step: float = 2.0


class _StateMachine:
    """Phase logic of [`CapController`][] on (gate mode, estimated wrench)."""

    def __init__(self, settings: CapController, cycles: int):
        self.s = settings
        self.cycles = cycles
        self.cycle = 0
        self.phase = "approach"
        self.settled = 0
        self.twist_start = 0.0
        self.last_tz = 0.0
        self.max_rise = 0.0

    def _enter(self, phase: str) -> None:
        self.phase, self.settled = phase, 0

    def step(
        self, mode: str, wrench: np.ndarray, depth: float, angle: float, cap: tuple[float, float] | None = None
    ) -> tuple[float, float, tuple[float, float]]:
        """New `(depth, angle, (dx, dy))` command from this frame's gate mode, estimate and,
        in vision mode, where the cap was located (`None`: not seen)."""
        depth, angle = self._step(mode, wrench, depth, angle)
        s = self.s
        if self.phase == "approach" and mode == "vision" and cap is not None:
            offset = math.hypot(*cap)
            if offset > s.align_tolerance:
                # Sideways onto the cap before going down: hold the height this frame.
                move = min(s.align_gain * offset, s.max_align_step) / offset
                return depth - s.approach_step, angle, (cap[0] * move, cap[1] * move)
        return depth, angle, (0.0, 0.0)

    def _step(self, mode: str, wrench: np.ndarray, depth: float, angle: float) -> tuple[float, float]:
        s = self.s
        fz, tz = float(wrench[2]), float(wrench[5])
        usable = mode == "tactile" and math.isfinite(fz) and math.isfinite(tz)
        if self.phase == "approach":
            if mode == "tactile":
                self._enter("press")
            else:
                return depth + s.approach_step, angle
        if self.phase == "press":
            if not usable:
                return depth, angle
            error = s.target_fz - fz
            self.settled = self.settled + 1 if abs(error) <= s.fz_tolerance else 0
            if self.settled >= s.settle_frames:
                self._enter("twist")
                self.twist_start, self.last_tz, self.max_rise = angle, tz, 0.0
            else:
                return depth + self._press_step(error), angle
        if self.phase == "twist":
            if not usable:
                return depth, angle
            rise = tz - self.last_tz
            self.last_tz = tz
            self.max_rise = max(self.max_rise, rise)
            slipping = tz > s.min_twist_torque and rise < s.slip_ratio * self.max_rise
            if slipping or angle - self.twist_start >= s.max_twist:
                self._enter("release")
            else:
                return depth + self._press_step(s.target_fz - fz), angle + s.twist_step
        if self.phase == "release":
            if depth > -s.lift_to:
                return max(depth - s.release_step, -s.lift_to), angle
            if mode == "tactile" and depth > -4 * s.lift_to:
                # The gate still sees contact: lift further, within reason.
                return depth - s.release_step, angle
            self._enter("return")
        if self.phase == "return":
            if angle > self.twist_start + 1e-12:
                return depth, max(angle - s.return_step, self.twist_start)
            self.cycle += 1
            self._enter("done" if self.cycle >= self.cycles else "approach")
            if self.phase == "approach":
                return depth + s.approach_step, angle
        return depth, angle

    def _press_step(self, error: float) -> float:
        s = self.s
        return float(np.clip(s.press_gain * error, -s.max_press_step, s.max_press_step))


@dataclasses.dataclass(frozen=True)
class Timeline:
    """What a [`run_cap_removal`][] run did, one entry per frame.

    **Fields:**

    - `t`: time (s) at the sensor's frame rate.
    - `mode`: the gate's `"vision"`/`"tactile"`; `phase`: the controller's phase when
        the frame was taken; `status`: the inversion's status (`"no_contact"` in vision mode).
    - `wrench_estimated`: `(n, 6)` inverted wrench (N, N·m), zero in vision mode, NaN
        where the inversion gave none; `wrench_true`: `(n, 6)` the rendered load.
    - `depth` (mm), `angle` (rad), `cap_angle` (rad): the rig's state at each frame.
    - `cap_offset`: `(n, 2)` where the cap's axis was relative to the sensor's (mm), the
        truth; `cap_seen`: `(n, 2)` where [`locate`][moirejax.live.locate] put it in
        vision mode (NaN where it was not seen or not looked for).
    - `target_fz` (N), `cycles` (completed).
    """

    t: np.ndarray
    mode: np.ndarray
    phase: np.ndarray
    status: np.ndarray
    wrench_estimated: np.ndarray
    wrench_true: np.ndarray
    depth: np.ndarray
    angle: np.ndarray
    cap_angle: np.ndarray
    cap_offset: np.ndarray
    cap_seen: np.ndarray
    target_fz: float
    cycles: int

    def phase_spans(self) -> list[tuple[str, int, int]]:
        """Runs of one phase as `(phase, first, last + 1)` frame indices."""
        spans: list[tuple[str, int, int]] = []
        for i, phase in enumerate(self.phase):
            if spans and spans[-1][0] == phase:
                spans[-1] = (phase, spans[-1][1], i + 1)
            else:
                spans.append((str(phase), i, i + 1))
        return spans


def run_cap_removal(
    device: Device,
    cycles: int = 3,
    *,
    inverter: Inverter | None = None,
    controller: CapController = CapController(),
    rig: CapRig | None = None,
    fps: Real = 30.0,
    fidelity: str = "model",
    noise: Real = 0.0,
    max_frames: int = 400,
) -> Timeline:
    """Run `cycles` cap-removal cycles of a simulated robot on a simulated sensor.

    Every step renders the rig's true load, gates the frame and, in tactile mode,
    inverts it; the state machine commands the rig from the gate mode and the *estimate*.
    When the rig's cap is visible (`CapRig.cap_rgb`), frames are colour: in vision mode the
    cap is located on the see-through frame at the robot's height above it, and the
    approach moves sideways onto it before descending, as the paper's robot aligns on the
    cap by its colour; the gate and the inversion read the frames' gray.

    **Arguments:**

    - `device`: the simulated unit (also the inversion's model).
    - `cycles`: how many press-twist-release cycles.
    - `inverter`: an [`Inverter`][moirejax.inverse._inversion.Inverter] to reuse (default: one
        built on the sensor's rendered no-contact frame).
    - `controller`: the [`CapController`][] settings (target force etc.).
    - `rig`: the plant (default [`CapRig`][] with its defaults: 1 N/mm, 0.006 N·m breakaway).
    - `fps`: the sensor's frame rate, which sets the timeline's time axis.
    - `fidelity`, `noise`: rendering of the [`SimulatedSensor`][].
    - `max_frames`: stop after this many frames even if the cycles are not done.

    **Returns:** the [`Timeline`][].
    """
    if cycles < 1:
        raise ValueError(f"need at least one cycle, got {cycles}")
    rig = rig if rig is not None else CapRig()
    if not 0 < controller.target_fz <= PAPER_RANGES["fz"] or not 0 < rig.slip_torque <= PAPER_RANGES["tz"]:
        raise ValueError(
            f"target_fz {controller.target_fz} N and slip_torque {rig.slip_torque} N*m must lie in the calibrated "
            f"range (0, {PAPER_RANGES['fz']}] N and (0, {PAPER_RANGES['tz']}] N*m"
        )
    visible = rig.cap_rgb is not None
    sensor = SimulatedSensor(
        device, rig, fidelity=fidelity, noise=noise, scene=(lambda i: rig.scene()) if visible else None
    )
    reference = sensor.reference_frame()
    if inverter is None:
        inverter = Inverter(device, reference=reference)
    processor = make_tactile_processor(inverter, reference)
    gate = make_gate(device)
    see_through = SeeThrough(np.repeat(reference[..., None], 3, axis=-1), black_level=float(device.optics.offset))
    machine = _StateMachine(controller, cycles)
    untouched: list[np.ndarray] = []  # the approach's last vision-mode frames
    names = ("mode", "phase", "status", "est", "true", "depth", "angle", "cap", "offset", "seen")
    rows: dict[str, list] = {k: [] for k in names}
    for i in range(max_frames):
        if machine.phase == "done":
            break
        frame = sensor.frame(i)
        if frame is None:  # a rig's script has no end; a script that has one stops the run
            break
        gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
        decision = gate.update(gray)
        mode = decision.mode
        cap = None
        if mode == "tactile":
            if decision.switched and visible and untouched:
                # The cap now fills the view under the pad, and the reference frame does not
                # show it: read the contact against the last frames before it, which do.
                reference = np.mean(untouched, axis=0)
                processor.rebind(Inverter(device, reference=reference, match_reference=False, register_gratings=True))
            wrench, _, status, *_ = processor(gray)
        else:
            processor.reset()
            wrench, status = np.zeros(6), "no_contact"
            untouched = [*untouched[-(_REFERENCE_FRAMES - 1) :], gray] if machine.phase == "approach" else []
            if visible and machine.phase == "approach":
                cap = _nearest_object(locate(frame, device, see_through=see_through, height=max(-rig.depth, 0.0)))
        rows["offset"].append((rig.cap_x, rig.cap_y))
        rows["seen"].append(cap if cap is not None else (math.nan, math.nan))
        rows["mode"].append(mode)
        rows["phase"].append(machine.phase)
        rows["status"].append(status)
        rows["est"].append(wrench)
        rows["true"].append(sensor.truth(i))
        rows["depth"].append(rig.depth)
        rows["angle"].append(rig.angle)
        rows["cap"].append(rig.cap_angle)
        depth, angle, (dx, dy) = machine.step(mode, wrench, rig.depth, rig.angle, cap)
        rig.move(dx, dy)
        rig.command(depth, angle)
    n = len(rows["mode"])
    return Timeline(
        t=np.arange(n) / float(fps),
        mode=np.asarray(rows["mode"]),
        phase=np.asarray(rows["phase"]),
        status=np.asarray(rows["status"]),
        wrench_estimated=np.asarray(rows["est"], np.float64).reshape(n, 6),
        wrench_true=np.asarray(rows["true"], np.float64).reshape(n, 6),
        depth=np.asarray(rows["depth"]),
        angle=np.asarray(rows["angle"]),
        cap_angle=np.asarray(rows["cap"]),
        cap_offset=np.asarray(rows["offset"], np.float64).reshape(n, 2),
        cap_seen=np.asarray(rows["seen"], np.float64).reshape(n, 2),
        target_fz=float(controller.target_fz),
        cycles=machine.cycle,
    )


def _nearest_object(sighting) -> tuple[float, float] | None:
    """Centre (mm) of the located object nearest the sensor's axis, or `None`."""
    if not sighting.objects:
        return None
    nearest = min(sighting.objects, key=lambda o: math.hypot(o.x_mm, o.y_mm))
    return (nearest.x_mm, nearest.y_mm)


def plot_timeline(path: str | os.PathLike, timeline: Timeline) -> None:
    """Write a PNG like the paper's cap-removal timeline: $F_z$ and $T_z$, estimated vs true, phases shaded."""
    from .._plotting import pyplot, save_figure

    plt = pyplot()
    fig, axes = plt.subplots(2, 1, sharex=True, figsize=(9, 4.8))
    t = timeline.t
    dt = float(t[1] - t[0]) if len(t) > 1 else 1.0
    panels = ((2, 1.0, "$F_z$ (N)"), (5, 1e3, "$T_z$ (mN·m)"))
    for ax, (axis, scale, label) in zip(axes, panels):
        for phase, start, stop in timeline.phase_spans():
            if phase in _PHASE_COLOURS:
                ax.axvspan(t[start] - dt / 2, t[stop - 1] + dt / 2, color=_PHASE_COLOURS[phase], lw=0)
        ax.plot(t, timeline.wrench_true[:, axis] * scale, color="k", lw=1.2, label="true")
        ax.plot(t, timeline.wrench_estimated[:, axis] * scale, "o-", color="C3", ms=2.5, lw=0.8, label="estimated")
        ax.set_ylabel(label)
    axes[0].axhline(timeline.target_fz, color="C0", ls="--", lw=0.8, label="target")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in _PHASE_COLOURS.values()]
    outside = dict(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    axes[0].legend(**outside)
    axes[1].legend(handles, list(_PHASE_COLOURS), **outside)
    axes[1].set_xlabel("time (s)")
    turned = math.degrees(float(timeline.cap_angle[-1])) if len(t) else 0.0
    axes[0].set_title(
        f"Incremental cap removal (simulated): {timeline.cycles} cycle(s), cap turned {turned:.1f}°", fontsize=10
    )
    fig.tight_layout()
    save_figure(fig, path)
