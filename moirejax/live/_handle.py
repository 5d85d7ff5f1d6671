"""The sensor as an object in the caller's process: the newest record at any time, the stream of
records, callbacks, a tare, and drift compensation.

A robot's control loop cannot wait on a camera: [`SensorHandle`][] runs the live loop
([`run_pipeline`][]) on a background thread that owns the camera, and the caller reads
[`latest`][SensorHandle.latest] (never blocked for longer than a lock), iterates over the
records, or registers callbacks.

**Tare.** The wrench is measured against the unit's no-contact reference frame. When the
untouched sensor drifts (temperature moves the gratings, the light ages, the elastomer
creeps), the fringes of the untouched sensor move and the old reference reads the drift
as a load. [`tare`][SensorHandle.tare] takes a new reference from the next untouched frames
and swaps it into the inversion between two frames, reusing the compiled solver; it
refuses while the gate says the sensor is touched.

**Drift compensation.** Optionally the reference also follows slow drift on its own:
while the gate reports no contact, the untouched frames are averaged with an exponential
weight (`drift_rate` per frame), and every `drift_every` untouched frames the average
becomes the reference. It is bounded: once the average has moved more than `max_drift`
(RMS, in frame units) from the reference of the last tare it stops following, logs a
warning and sets [`drift_limited`][SensorHandle.drift_limited] (a change that large is a
damaged or moved sensor, or a lasting contact, not drift; tare to accept it).
"""

import collections
import concurrent.futures
import logging
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from ..calibration import ResidualHead
from ..inverse import Inverter
from ..physics import Device
from ._camera import AbstractFrameSource, Frame
from ._pipeline import LiveSummary, run_pipeline
from ._records import RecordStream, WrenchFilter
from ._rectify import load_rectification, Rectification
from ._run import (
    _is_sim,
    _load_reference,
    capture_reference,
    make_colour_probe,
    make_gate,
    make_tactile_processor,
    open_source,
    PRESSURE_SHAPE,
    SimulatedSensor,
)
from ._sinks import Sink, WrenchRecord
from ._types import Real


logger = logging.getLogger("moirejax.live")

RecordCallback = Callable[[WrenchRecord], None]


def call_each(callbacks: Sequence[RecordCallback], record: WrenchRecord, failed: int) -> int:
    """Give `record` to every callback; a callback that raises does not stop the others or
    the stream. Returns `failed` plus this record's failures; the first ever is logged."""
    for callback in callbacks:
        try:
            callback(record)
        except Exception as e:
            failed += 1
            if failed == 1:
                logger.warning("a record callback failed: %s: %s (further failures are counted)", type(e).__name__, e)
    return failed


class SensorHandle:
    """A live sensor running on a background thread; made by [`open_sensor`][].

    **Arguments:**

    - `device`: the unit (nominal or calibrated).
    - `source`: `"sim"`, a camera index, a video file, a stream URL, a folder of images
        (see [`open_source`][]), or an [`AbstractFrameSource`][].
    - `reference`: the no-contact frame (array or image file). Default: for `"sim"` a
        rendered one; for a source spec the mean of its first `reference_frames` frames
        (untouched while the handle opens); required for a source object.
    - `rectification`: a [`Rectification`][] or its JSON file, applied to every frame.
    - `sensor`: the [`SimulatedSensor`][] behind `"sim"` (default: the default script).
    - `sinks`: further sinks that get every record (not closed here).
    - `sensor_id`, `frame_id`: the records' sensor name and ROS frame name.
    - `filter`: a [`WrenchFilter`][] for in-contact wrenches, or `None`.
    - `drift_compensation`, `drift_rate`, `drift_every`, `max_drift`: see the module
        docstring.
    - `history`: records kept for iterators that fall behind.
    - `max_frames`: stop after this many frames.
    - `vision`: name the colour seen through the sensor in vision mode.
    - `reference_frames`: frames averaged into a captured reference.
    - `head`: the calibration's [`ResidualHead`][] ([`load_calibrated`][] returns it with
        the device), applied to every wrench and covariance.

    The handle starts when made by [`open_sensor`][] (or on [`start`][SensorHandle.start]);
    leave it with [`close`][SensorHandle.close] or a `with` block.
    """

    def __init__(
        self,
        device: Device,
        source: str | AbstractFrameSource = "sim",
        *,
        reference: np.ndarray | str | os.PathLike | None = None,
        rectification: Rectification | str | os.PathLike | None = None,
        sensor: SimulatedSensor | None = None,
        sinks: Sequence[Sink] = (),
        sensor_id: str = "moirejax",
        frame_id: str = "moirejax_sensor",
        filter: WrenchFilter | None = None,
        drift_compensation: bool = False,
        drift_rate: Real = 0.02,
        drift_every: int = 300,
        max_drift: Real = 0.02,
        history: int = 1024,
        max_frames: int | None = None,
        vision: bool = True,
        reference_frames: int = 5,
        head: ResidualHead | None = None,
    ):
        if not 0 < drift_rate <= 1 or drift_every < 1 or not max_drift > 0 or history < 1:
            raise ValueError("need 0 < drift_rate <= 1, drift_every >= 1, max_drift > 0 and history >= 1")
        if isinstance(rectification, str | os.PathLike):
            rectification = load_rectification(rectification)
        shape = (device.height, device.width)
        if isinstance(source, AbstractFrameSource):
            if reference is None:
                raise ValueError("a source object needs reference= (the unit's no-contact frame)")
            self._source = source
        elif _is_sim(source):
            sensor = sensor if sensor is not None else SimulatedSensor(device, n_frames=max_frames or 240)
            self._source = sensor.source()
            reference = sensor.reference_frame() if reference is None else reference
        else:
            self._source = open_source(source)
            if reference is None:
                reference = capture_reference(open_source(source), frames=reference_frames, rectification=rectification)
                if reference is None:
                    raise ValueError(f"{source}: no untouched frame to take the reference from; pass reference=")
        reference = np.asarray(_load_reference(reference), np.float64)
        if reference.shape != shape:
            raise ValueError(f"reference frame is {reference.shape}, device expects {shape}; rectify the frames")
        first = Inverter(device, reference=reference)
        # Later references keep the geometry and the grating registration this one found,
        # so that the compiled solver carries over (FrameTracker.with_inverter).
        self._device = first.device
        self._processor = make_tactile_processor(first, reference, pressure_shape=PRESSURE_SHAPE, head=head)
        self._gate = make_gate(device)
        self._probe = make_colour_probe(device) if vision else None
        self._rectification = rectification
        self._records = RecordStream(sensor_id=sensor_id, frame_id=frame_id, filter=filter)
        self._sinks = list(sinks)
        self._max_frames = max_frames
        self._drift = dict(on=bool(drift_compensation), rate=float(drift_rate), every=int(drift_every))
        self._max_drift = float(max_drift)

        self._lock = threading.Condition()
        self._latest: WrenchRecord | None = None
        self._history: collections.deque[WrenchRecord] = collections.deque(maxlen=history)
        self._callbacks: list[RecordCallback] = []
        self._callback_errors = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._summary: LiveSummary | None = None
        self._error: BaseException | None = None
        self._finished = False

        self._tared_reference = reference
        self._applied_reference = reference
        self._mean = reference.copy()  # the drift average, in frame units
        self._quiet = 0
        self._drift_limited = False
        self._tare_frames: list[np.ndarray] | None = None
        self._tare_wanted = 0
        self._tare_done = threading.Event()
        self._tare_failed: str | None = None
        self._worker = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="moirejax-reference")
        self._pending: concurrent.futures.Future | None = None

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> "SensorHandle":
        """Start the background thread (once)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="moirejax-sensor", daemon=True)
            self._thread.start()
        return self

    def close(self, timeout: Real = 10.0) -> None:
        """Stop the loop and wait for it (at most `timeout` s). Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self._worker.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> "SensorHandle":
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.close()

    def _run(self) -> None:
        try:
            self._summary = run_pipeline(
                self._source,
                self._on_touched,
                [_Collector(self), *self._sinks],
                self._gate,
                max_frames=self._max_frames,
                rectification=self._rectification,
                vision=self._on_untouched,
                stop=self._stop,
                records=self._records,
            )
        except BaseException as e:  # the caller learns of it from `error`, never from a dead thread
            self._error = e
            logger.error("the sensor loop failed: %s: %s", type(e).__name__, e)
        finally:
            with self._lock:
                self._finished = True
                self._lock.notify_all()
            self._tare_done.set()

    # -- reading -------------------------------------------------------------------------

    def latest(self) -> WrenchRecord | None:
        """The newest record, or `None` before the first; never waits for a frame."""
        with self._lock:
            return self._latest

    def wait(self, timeout: Real | None = None) -> WrenchRecord | None:
        """The next record after the current newest one (`None` at `timeout` or the stream's end)."""
        with self._lock:
            seen = self._latest.seq if self._latest is not None else -1
            self._lock.wait_for(
                lambda: self._finished or (self._latest is not None and self._latest.seq > seen), timeout
            )
            return self._latest if self._latest is not None and self._latest.seq > seen else None

    def __iter__(self) -> Iterator[WrenchRecord]:
        """Every record from now on, in order, until the stream ends or the handle closes.

        An iterator that falls more than `history` records behind skips the oldest ones
        (their `seq` shows the gap).
        """
        with self._lock:
            next_seq = self._latest.seq + 1 if self._latest is not None else 0
        while True:
            with self._lock:
                self._lock.wait_for(
                    lambda wanted=next_seq: self._finished or (self._latest is not None and self._latest.seq >= wanted),
                    0.5,
                )
                pending = [r for r in self._history if r.seq >= next_seq]
                done = self._finished
            for record in pending:
                next_seq = record.seq + 1
                yield record
            if done and not pending:
                return

    def on_record(self, callback: RecordCallback) -> None:
        """Call `callback(record)` on the sensor thread for every record. It must return
        quickly; its exceptions are logged and counted, never raised into the loop."""
        with self._lock:
            self._callbacks.append(callback)

    def _deliver(self, record: WrenchRecord) -> None:
        with self._lock:
            self._latest = record
            self._history.append(record)
            callbacks = list(self._callbacks)
            self._lock.notify_all()
        self._callback_errors = call_each(callbacks, record, self._callback_errors)

    # -- state ---------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        """Whether the loop is running."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def summary(self) -> LiveSummary | None:
        """The [`LiveSummary`][] once the loop has ended."""
        return self._summary

    @property
    def error(self) -> BaseException | None:
        """The exception that ended the loop, if one did."""
        return self._error

    @property
    def sensor_id(self) -> str:
        """The records' sensor name."""
        return self._records.sensor_id

    @property
    def frame_id(self) -> str:
        """The records' ROS frame name."""
        return self._records.frame_id

    @property
    def callback_errors(self) -> int:
        """How many callback calls raised."""
        return self._callback_errors

    @property
    def mode(self) -> str:
        """The gate's current mode, `"vision"` (untouched) or `"tactile"`."""
        return self._gate.mode

    @property
    def reference(self) -> np.ndarray:
        """The no-contact reference the inversion uses now (frame units)."""
        return self._applied_reference

    @property
    def drift(self) -> float:
        """RMS change (frame units) of the untouched sensor since the last tare."""
        return float(np.sqrt(np.mean((self._mean - self._tared_reference) ** 2)))

    @property
    def drift_limited(self) -> bool:
        """Whether drift compensation stopped at `max_drift` (tare to accept the change)."""
        return self._drift_limited

    @property
    def bias(self) -> np.ndarray:
        """The wrench subtracted from in-contact wrenches (see [`set_bias`][SensorHandle.set_bias])."""
        return self._records.bias

    def set_bias(self, bias: np.ndarray) -> None:
        """Subtract `bias` (`[fx, fy, fz, tx, ty, tz]`, N and N*m) from in-contact wrenches,
        e.g. the weight of a fingertip pad the sensor carries; [`tare`][SensorHandle.tare] clears it."""
        self._records.set_bias(bias)

    # -- tare and drift ------------------------------------------------------------------

    def tare(self, frames: int = 10, timeout: Real = 30.0) -> np.ndarray:
        """Take a new no-contact reference from the next `frames` untouched frames and
        invert the following frames against it; clears the bias and the filter.

        **Returns:** the new reference frame.

        **Raises:** `RuntimeError` while the sensor is touched (or when it is touched
        before enough frames are taken), or when the loop is not running; `TimeoutError`
        when `frames` untouched frames do not arrive within `timeout` s.
        """
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        if not self.running:
            raise RuntimeError("the sensor loop is not running: start the handle first")
        if self._gate.mode == "tactile":
            raise RuntimeError("the sensor is in contact: release it before a tare")
        self._tare_done.clear()
        self._tare_failed = None
        with self._lock:
            self._tare_frames, self._tare_wanted = [], int(frames)
        if not self._tare_done.wait(timeout):
            with self._lock:
                self._tare_frames = None
            raise TimeoutError(f"no {frames} untouched frames within {timeout} s")
        with self._lock:
            taken, self._tare_frames = self._tare_frames, None
        if self._tare_failed is not None:
            raise RuntimeError(self._tare_failed)
        if not taken or len(taken) < frames:
            raise RuntimeError("the sensor loop ended before the tare's frames were taken")
        reference = np.mean(np.stack(taken), axis=0, dtype=np.float64)
        # On the worker, after any drift update already queued: one reference at a time.
        self._worker.submit(self._apply_reference, reference).result()
        self._tared_reference = reference
        self._mean = reference.copy()
        self._quiet = 0
        self._drift_limited = False
        self._records.set_bias(np.zeros(6))
        if self._records.filter is not None:
            self._records.filter.reset()
        return reference

    def _apply_reference(self, reference: np.ndarray) -> None:
        inverter = Inverter(self._device, reference=reference, match_reference=False, register_gratings=True)
        self._processor.rebind(inverter)
        self._applied_reference = reference

    def _on_touched(self, gray: np.ndarray):
        """The tactile-mode step: the inversion; a touch ends a tare that is taking frames."""
        with self._lock:
            if self._tare_frames is not None and len(self._tare_frames) < self._tare_wanted:
                self._tare_failed = "the sensor was touched while the tare took its frames"
                self._tare_done.set()
        return self._processor(gray)

    def _on_untouched(self, frame: Frame) -> str | None:
        """The vision-mode hook: frames for a tare, the drift average, the colour probe."""
        gray = frame.gray  # float32; the averages below are float64
        with self._lock:
            if self._tare_frames is not None and len(self._tare_frames) < self._tare_wanted:
                self._tare_frames.append(gray)
                if len(self._tare_frames) == self._tare_wanted:
                    self._tare_done.set()
            taring = self._tare_frames is not None
        if self._drift["on"] and gray.shape == self._mean.shape and not (self._drift_limited or taring):
            self._follow_drift(gray)
        return self._probe(frame) if self._probe is not None else None

    def _follow_drift(self, gray: np.ndarray) -> None:
        self._mean += self._drift["rate"] * (gray - self._mean)
        self._quiet += 1
        if self._quiet % self._drift["every"]:
            return
        if self.drift > self._max_drift:
            self._drift_limited = True
            logger.warning(
                "the untouched sensor has changed by %.3f RMS since the last tare (max_drift %.3f): "
                "drift compensation stops; tare to accept the change",
                self.drift,
                self._max_drift,
            )
            return
        if self._pending is None or self._pending.done():
            self._pending = self._worker.submit(self._apply_reference, self._mean.copy())


class _Collector:
    """The handle's own sink: keeps the newest record and the history, runs the callbacks."""

    def __init__(self, handle: SensorHandle):
        self.handle = handle

    def emit(self, record: WrenchRecord) -> None:
        self.handle._deliver(record)

    def close(self) -> None:
        pass


def open_sensor(device: Device, source: str | AbstractFrameSource = "sim", **kwargs: Any) -> SensorHandle:
    """Open a live sensor in this process: `with open_sensor(device, "0") as s: s.latest()`.

    Builds the inversion (compiling it, tens of seconds at 512 × 512 on a laptop CPU) and
    starts the background thread; keyword arguments go to [`SensorHandle`][].
    """
    return SensorHandle(device, source, **kwargs).start()
