"""Several sensors in one process: one thread per sensor, one stream of records, and the
wrench of a gripper's fingers together in the gripper's frame.

A parallel gripper with a sensor in each finger reads two wrenches, each in its own pad's
frame ([`WRENCH_CONVENTION`][moirejax.WRENCH_CONVENTION]: x along the image columns, y
image up, z into the pad). [`SensorGroup`][] runs one [`SensorHandle`][] per sensor, each on
its own thread with its own unit, calibration and reference, and merges their records into
one stream in the order they arrive, each record naming its sensor by `sensor_id`.

**The grip wrench.** Given where each pad sits on the gripper (a [`Mount`][]: the rotation
$R$ that takes pad axes to gripper axes and the pad origin $t$ in the gripper frame, in
metres), the wrench that the held object puts on the gripper is the sum of the pads'
wrenches moved into the gripper frame,

$$F_g = \\sum_s R_s F_s, \\qquad T_g = \\sum_s \\left(R_s T_s + t_s \\times R_s F_s\\right),$$

that is $w_g = \\sum_s A_s w_s$ with the 6×6 wrench adjoint
$A = \\begin{pmatrix} R & 0 \\\\ [t]_\\times R & R \\end{pmatrix}$. The sensors' errors are
independent, so the covariance is $\\Sigma_g = \\sum_s A_s \\Sigma_s A_s^\\top$. A pad not in
contact adds nothing, and nothing to the covariance; a pad whose newest record has no
wrench to believe (an unexplained fringe field, a bad frame, a lost camera) makes the grip
wrench unavailable, and the record says which pad. Opposed pads pressing equally cancel in
$F_g$: what is left is the weight and the pull of the object, and the moments of where it
is held.
"""

import collections
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import equinox as eqx
import numpy as np
from jaxtyping import Float

from ..physics import Device
from ._camera import AbstractFrameSource
from ._handle import call_each, SensorHandle
from ._pipeline import NO_CONTACT, VISION_ERROR
from ._records import LOAD_STATUSES
from ._sinks import make_record, Sink, WrenchRecord
from ._types import Real


logger = logging.getLogger("moirejax.live")

GRIP_UNAVAILABLE = "unavailable"
"""Status of a grip record when a mounted sensor's newest record has no wrench to believe."""

# Statuses of an untouched sensor: the gate says nothing presses it, so it adds no load.
_UNTOUCHED_STATUSES = (NO_CONTACT, VISION_ERROR)

# A rotation and a translation as the caller has them: nested sequences or arrays.
Matrix3 = Sequence[Sequence[Real]] | np.ndarray
Vector3 = Sequence[Real] | np.ndarray

# How far from orthonormal (largest entry of R^T R - I) a mount's rotation may be.
_ROTATION_TOLERANCE = 1e-6


def _rotation_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll): roll about x, then pitch about y, then yaw about z,
    all about the fixed gripper axes (the URDF and ROS convention)."""
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def _cross_matrix(t: np.ndarray) -> np.ndarray:
    """[t]x, the matrix with [t]x v = t x v."""
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


class Mount(eqx.Module):
    """Where a sensor's pad sits on the gripper: the pose of the pad's wrench frame in the
    gripper frame, $p_g = R\\,p_s + t$.

    **Arguments:**

    - `rotation`: the 3×3 rotation $R$ whose columns are the pad's x, y and z axes in
        gripper axes (a proper rotation: orthonormal, determinant +1).
    - `translation`: the pad's origin (the image centre on the contact surface) in the
        gripper frame, metres.

    [`from_rpy`][Mount.from_rpy] builds one from roll, pitch and yaw.

    **Raises:** `ValueError` for a rotation that is not one (scaled, sheared, a reflection)
    or a translation that is not three finite numbers.
    """

    rotation: Float[np.ndarray, "3 3"]
    translation: Float[np.ndarray, "3"]

    def __init__(self, rotation: Matrix3, translation: Vector3 = (0.0, 0.0, 0.0)):
        rotation = np.asarray(rotation, np.float64)
        translation = np.asarray(translation, np.float64)
        if rotation.shape != (3, 3) or translation.shape != (3,):
            raise ValueError(
                f"a mount needs a 3x3 rotation and 3 translations, got {rotation.shape}, {translation.shape}"
            )
        self.rotation = rotation
        self.translation = translation

    def __check_init__(self):
        if not (np.all(np.isfinite(self.rotation)) and np.all(np.isfinite(self.translation))):
            raise ValueError("a mount's rotation and translation must be finite")
        error = float(np.max(np.abs(self.rotation.T @ self.rotation - np.eye(3))))
        if error > _ROTATION_TOLERANCE:
            raise ValueError(f"a mount's rotation must be orthonormal (R^T R differs from I by {error:.2g})")
        if np.linalg.det(self.rotation) < 0:
            raise ValueError("a mount's rotation is a reflection (determinant -1): the pad's axes must be right-handed")

    @classmethod
    def from_rpy(cls, translation: Vector3, roll: Real, pitch: Real, yaw: Real) -> "Mount":
        """The mount at `translation` (m) turned by `roll`, `pitch`, `yaw` (radians):
        $R = R_z(\\text{yaw})\\,R_y(\\text{pitch})\\,R_x(\\text{roll})$ about the fixed gripper
        axes, as a URDF joint's `rpy`."""
        return cls(_rotation_from_rpy(float(roll), float(pitch), float(yaw)), translation)

    @property
    def adjoint(self) -> Float[np.ndarray, "6 6"]:
        """The 6×6 matrix that moves a pad wrench `[fx, fy, fz, tx, ty, tz]` into the gripper
        frame: `[[R, 0], [[t]x R, R]]`."""
        r = self.rotation
        return np.block([[r, np.zeros((3, 3))], [_cross_matrix(self.translation) @ r, r]])


def _reads(record: WrenchRecord) -> bool:
    """Whether `record` carries a wrench to believe: in contact, converged or out of steps."""
    return record.in_contact and record.status in LOAD_STATUSES and record.wrench is not None


def grip_wrench(
    records: Mapping[str, WrenchRecord],
    mounts: Mapping[str, Mount],
    *,
    sensor_id: str = "grip",
    frame_id: str = "gripper",
    seq: int = 0,
) -> WrenchRecord:
    """The wrench of the mounted pads together, in the gripper frame (see the module docstring).

    **Arguments:**

    - `records`: the newest record of each sensor, by sensor name.
    - `mounts`: where each sensor sits on the gripper, by the same names; the grip wrench
        sums the sensors named here.
    - `sensor_id`, `frame_id`, `seq`: the grip record's names and sequence number.

    **Returns:** a [`WrenchRecord`][] in the gripper frame, stamped with the newest
    contributing capture, `skew_ms` the spread of the contributing captures and
    `latency_ms` the newest one's. Its status is `"converged"` (or `"max_steps"` when a
    pad's solve ran out of steps) with a wrench, `"no_contact"` with a zero wrench when no
    pad is touched, or `"unavailable"` with no wrench when a pad's record cannot be read
    (no record yet, an unexplained or bad frame, a source event), the message naming it.
    The covariance is `None` when a touched pad's record has none.
    """
    present = {name: records[name] for name in mounts if name in records}
    missing = [name for name in mounts if name not in records]
    unreadable = [
        f"{name}: {r.status}" + (f" ({r.message})" if r.message else "")
        for name, r in present.items()
        if not (_reads(r) or (not r.in_contact and r.status in _UNTOUCHED_STATUSES))
    ]
    problems = [f"{name}: no record yet" for name in missing] + unreadable
    clocks = [r.monotonic for r in present.values()]
    times = clocks if present and all(c is not None for c in clocks) else [r.stamp for r in present.values()]
    newest = max(present.values(), key=lambda r: r.stamp) if present else None
    common: dict[str, Any] = dict(
        stamp=newest.stamp if newest else math.nan,
        frame=seq,
        latency_ms=newest.latency_ms if newest else math.nan,
        sensor_id=sensor_id,
        frame_id=frame_id,
        seq=seq,
        monotonic=newest.monotonic if newest else None,
        skew_ms=(max(times) - min(times)) * 1e3 if times else None,
        filtered=any(r.filtered for r in present.values()),
    )
    if problems:
        mode = "tactile" if any(r.mode == "tactile" for r in present.values()) else "vision"
        message = "no grip wrench: " + "; ".join(problems)
        return make_record(mode=mode, status=GRIP_UNAVAILABLE, message=message, **common)
    wrench, covariance = np.zeros(6), np.zeros((6, 6))
    touched = [name for name, r in present.items() if _reads(r)]
    for name in touched:
        r, adjoint = present[name], mounts[name].adjoint
        wrench = wrench + adjoint @ r.wrench
        if covariance is not None and r.covariance is not None:
            covariance = covariance + adjoint @ np.asarray(r.covariance, np.float64) @ adjoint.T
        else:
            covariance = None
    if not touched:
        return make_record(mode="vision", status=NO_CONTACT, wrench=wrench, covariance=covariance, **common)
    status = "max_steps" if any(present[name].status == "max_steps" for name in touched) else "converged"
    return make_record(
        mode="tactile",
        status=status,
        wrench=wrench,
        covariance=covariance,
        in_contact=True,
        message="pads in contact: " + ", ".join(touched),
        **common,
    )


RecordCallback = Callable[[WrenchRecord], None]


class SensorGroup:
    """Several [`SensorHandle`][]s as one sensor: a merged record stream and the grip wrench.

    Made by [`open_sensors`][]. Each handle keeps its own thread, unit, reference and
    `sensor_id`; the group sees every record as its sensor's thread delivers it and hands
    the records on one at a time, in arrival order: to its `sinks`, to the callbacks of
    [`on_record`][SensorGroup.on_record] and to iterators. With `mounts`, every record of a
    mounted sensor (once each mounted sensor has one) is followed by a grip record
    ([`grip_wrench`][] of the mounted sensors' newest records) named `grip_id` in the frame
    `grip_frame`, whose `latency_ms` runs from the newest capture to its delivery.

    **Arguments:**

    - `handles`: the sensors by name, not yet started (each name must be its handle's
        `sensor_id`).
    - `mounts`: where some or all of them sit on the gripper, by name; `None` for no grip
        records.
    - `grip_id`, `grip_frame`: the grip records' sensor name and frame name.
    - `sinks`: further sinks that get every record, one record at a time (not closed here).
    - `history`: records kept for iterators that fall behind.

    **Raises:** `ValueError` for no handles, a name that is not its handle's `sensor_id`,
    a handle already running, a mount for an unknown sensor, or a `grip_id` that names a
    sensor.
    """

    def __init__(
        self,
        handles: Mapping[str, SensorHandle],
        mounts: Mapping[str, Mount] | None = None,
        *,
        grip_id: str = "grip",
        grip_frame: str = "gripper",
        sinks: Sequence[Sink] = (),
        history: int = 4096,
    ):
        if not handles:
            raise ValueError("a sensor group needs at least one sensor")
        for name, handle in handles.items():
            if handle.sensor_id != name:
                raise ValueError(f"sensor {name!r}: its handle's sensor_id is {handle.sensor_id!r}")
            if handle.running:
                raise ValueError(f"sensor {name!r} is already running: the group starts its sensors")
        mounts = dict(mounts or {})
        unknown = sorted(set(mounts) - set(handles))
        if unknown:
            raise ValueError(f"a mount for an unknown sensor: {', '.join(unknown)} (sensors: {', '.join(handles)})")
        if mounts and grip_id in handles:
            raise ValueError(f"grip_id {grip_id!r} is the name of a sensor")
        if history < 1:
            raise ValueError(f"history must be >= 1, got {history}")
        self.handles = dict(handles)
        self.mounts = mounts
        self.grip_id = str(grip_id)
        self.grip_frame = str(grip_frame)
        self._sinks = list(sinks)
        # One record at a time through sinks and callbacks, whichever thread it comes from.
        self._delivery = threading.Lock()
        self._cond = threading.Condition()
        self._latest: dict[str, WrenchRecord] = {}
        self._history: collections.deque[tuple[int, WrenchRecord]] = collections.deque(maxlen=history)
        self._count = 0
        self._grip_seq = 0
        self._callbacks: list[RecordCallback] = []
        self._callback_errors = 0
        self._output_errors = 0
        for handle in self.handles.values():
            handle.on_record(self._arrive)

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> "SensorGroup":
        """Start every sensor's thread (once)."""
        for handle in self.handles.values():
            handle.start()
        return self

    def close(self, timeout: Real = 10.0) -> None:
        """Stop every sensor and wait for each (at most `timeout` s apiece). Idempotent."""
        for handle in self.handles.values():
            handle.close(timeout)

    def join(self, timeout: Real | None = None) -> bool:
        """Wait until every sensor's loop has ended (at most `timeout` s); whether they have."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.running:
            if deadline is not None and time.monotonic() >= deadline:
                return False
            with self._cond:
                self._cond.wait(0.05)
        return True

    def __enter__(self) -> "SensorGroup":
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.close()

    @property
    def running(self) -> bool:
        """Whether any sensor's loop is running."""
        return any(handle.running for handle in self.handles.values())

    @property
    def errors(self) -> dict[str, BaseException]:
        """The exception that ended each sensor's loop, for those a failure ended."""
        return {name: h.error for name, h in self.handles.items() if h.error is not None}

    @property
    def callback_errors(self) -> int:
        """How many callback calls raised."""
        return self._callback_errors

    @property
    def output_errors(self) -> int:
        """How many times a sink raised."""
        return self._output_errors

    # -- reading -------------------------------------------------------------------------

    def latest(self) -> dict[str, WrenchRecord]:
        """The newest record of each sensor (and of the grip), by `sensor_id`; never waits."""
        with self._cond:
            return dict(self._latest)

    def __iter__(self) -> Iterator[WrenchRecord]:
        """Every record from now on (from the call of `iter`), of every sensor and the grip,
        in arrival order, until every sensor's stream has ended or the group closes. An
        iterator more than `history` records behind skips the oldest ones."""
        with self._cond:
            return self._records_from(self._count)

    def _records_from(self, next_count: int) -> Iterator[WrenchRecord]:
        while True:
            done = not self.running  # before the records: a loop delivers all it has before it ends
            with self._cond:
                self._cond.wait_for(lambda wanted=next_count: self._count > wanted, 0.05)
                pending = [(n, r) for n, r in self._history if n >= next_count]
            for n, record in pending:
                next_count = n + 1
                yield record
            if done and not pending:
                return

    def on_record(self, callback: RecordCallback) -> None:
        """Call `callback(record)` for every record of every sensor and the grip, one at a
        time, on the thread of the sensor that delivered it. It must return quickly; its
        exceptions are logged and counted, never raised into the loops."""
        with self._cond:
            self._callbacks.append(callback)

    # -- delivery ------------------------------------------------------------------------

    def _arrive(self, record: WrenchRecord) -> None:
        with self._delivery:
            self._publish(record)
            if record.sensor_id not in self.mounts:
                return
            with self._cond:
                newest = {name: self._latest[name] for name in self.mounts if name in self._latest}
            if len(newest) < len(self.mounts):
                return
            grip = grip_wrench(
                newest, self.mounts, sensor_id=self.grip_id, frame_id=self.grip_frame, seq=self._grip_seq
            )
            self._grip_seq += 1
            if grip.monotonic is not None:
                grip = dataclasses.replace(grip, latency_ms=(time.monotonic() - grip.monotonic) * 1e3)
            self._publish(grip)

    def _publish(self, record: WrenchRecord) -> None:
        with self._cond:
            self._latest[record.sensor_id] = record
            self._history.append((self._count, record))
            self._count += 1
            callbacks = list(self._callbacks)
            self._cond.notify_all()
        for sink in self._sinks:
            try:
                sink.emit(record)
                if record.pressure is not None and hasattr(sink, "emit_pressure"):
                    sink.emit_pressure(record.pressure, record)
            except Exception as e:
                self._output_errors += 1
                logger.warning("sink %s failed: %s", type(sink).__name__, e)
        self._callback_errors = call_each(callbacks, record, self._callback_errors)


SensorSpec = tuple[Device, str | AbstractFrameSource] | Mapping[str, Any]


def open_sensors(
    specs: Mapping[str, SensorSpec],
    mounts: Mapping[str, Mount] | None = None,
    *,
    grip_id: str = "grip",
    grip_frame: str = "gripper",
    sinks: Sequence[Sink] = (),
    start: bool = True,
    **common: Any,
) -> SensorGroup:
    """Open several live sensors in this process as one [`SensorGroup`][], started.

    `with open_sensors({"left": (unit_a, "0"), "right": (unit_b, "1")}, mounts) as grip:`
    builds each sensor's inversion (one after another, each compiling) and then starts
    them all, so that no record is missed.

    **Arguments:**

    - `specs`: by name, `(device, source)` or a dict of [`SensorHandle`][] arguments
        (`device`, `source`, `reference`, ...) for that sensor alone.
    - `mounts`: by name, the [`Mount`][] of each sensor on the gripper, for grip records.
    - `grip_id`, `grip_frame`, `sinks`: see [`SensorGroup`][].
    - `start`: start the sensors; `False` leaves that to [`start`][SensorGroup.start] (or a
        `with` block), for callbacks and iterators that must see the first records.
    - `common`: [`SensorHandle`][] arguments for every sensor (a spec's own win). Each
        sensor's `sensor_id` is its name and its `frame_id` defaults to `NAME_sensor`.

    **Raises:** `ValueError` for a spec without a device, or as [`SensorGroup`][] does.
    """
    if "sensor_id" in common:
        raise ValueError("open_sensors names each sensor by its key: drop sensor_id")
    handles: dict[str, SensorHandle] = {}
    try:
        for name, spec in specs.items():
            arguments: dict[str, Any] = (
                dict(spec) if isinstance(spec, Mapping) else dict(zip(("device", "source"), spec))
            )
            if "device" not in arguments:
                raise ValueError(f"sensor {name!r}: its spec has no device")
            arguments = {"frame_id": f"{name}_sensor", **common, **arguments, "sensor_id": name}
            device = arguments.pop("device")
            handles[name] = SensorHandle(device, **arguments)
        group = SensorGroup(handles, mounts, grip_id=grip_id, grip_frame=grip_frame, sinks=sinks)
    except BaseException:
        for handle in handles.values():
            handle.close()
        raise
    return group.start() if start else group
