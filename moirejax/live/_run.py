"""The live sensor end to end: the inversion as `process_tactile`, a simulated sensor, and `run_live`.

[`run_live`][] builds everything [`run_pipeline`][] needs from a device and a source
spec: the frame source (a camera index, a video file or URL, a folder of images, or
`"sim"` for a simulated sensor with no hardware), the no-contact reference of the unit,
the [`Inverter`][moirejax.inverse._inversion.Inverter] wrapped by [`make_tactile_processor`][],
the [`GateER`][] contact gate on the device's upper-grating carriers, and the
vision-mode colour probe behind a moiré notch filter.

It is one module because it is the wiring of the live sensor: each part is a few dozen
lines, and split they would spread one assembly over several files.
"""

import logging
import math
import os
import threading
import time
import urllib.parse
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import jax
import jax.random as jr
import numpy as np

from .._conventions import PA_PER_MPA
from .._fileio import DataError
from ..calibration import ResidualHead
from ..inverse import frame_tracker, Inverter, Status, TRACTION_MAP_SHAPE
from ..physics import Contact, Device, surface_grid, surface_tractions
from ..simulate import load_schedule, LoadSchedule, scene_reflectance, SceneObject, Simulator
from ._camera import (
    AbstractFrameSource,
    CallableSource,
    CLOSED,
    END_OF_STREAM,
    EndOfStreamError,
    find_camera,
    FolderSource,
    Frame,
    OPEN_FAILED,
    Reconnect,
    SOURCE_ERROR,
    SOURCE_LOST,
    SourceEvent,
    to_frame,
    VideoSource,
)
from ._gate import GateER
from ._pipeline import LiveSummary, run_pipeline
from ._records import RecordStream
from ._rectify import load_rectification, Rectification
from ._sinks import FileSink, Sink, StreamSink, StripChart, UdpSink, VideoRecorder
from ._types import Real
from ._vision import ColourProbe, MoireNotch


logger = logging.getLogger("moirejax.live")

# `fn(i) -> (wrench, contact)` for frame i, or `None` once the script is over.
LoadScript = Callable[[int], tuple[Any, Contact] | None]
TactileOutput = tuple[np.ndarray, np.ndarray | None, str, str, dict[str, Any]]

# The grid of the pressure map drawn for sinks that take one: the traction maps' own.
PRESSURE_SHAPE = TRACTION_MAP_SHAPE


class TactileProcessor:
    """`process_tactile` for [`run_pipeline`][]: one step of [`frame_tracker`][] per frame.

    Made by [`make_tactile_processor`][]. Each call returns `(wrench, covariance, status,
    message, extras)` with `status` the lower-case [`Status`][] name (`"converged"`,
    `"max_steps"`, `"unexplained"`, `"no_contact"`, `"bad_frame"`, `"nonfinite"`, `"wrong_size"`)
    and `extras` the fitted contact patch's area (`contact_area_mm2`) and, with
    `pressure_shape`, its pressure map in Pa (`pressure`, [`surface_tractions`][] of the
    estimate on a grid of that shape over the field).
    With a calibration's `head` ([`ResidualHead`][]), a frame's wrench is the corrected one
    and its covariance is widened by the head's residual, as `invert` reports them; the
    pressure map is drawn from the corrected wrench, so map and wrench agree.
    The solver continues from the previous frame's solution and Jacobian while frames converge; any
    other outcome resets it to a cold start, so one bad frame cannot drag the next ones
    off. Frames are cast to the device's dtype, so every call hits the one compiled
    step ([`frame_tracker`][]). [`rebind`][TactileProcessor.rebind] swaps in an inverter on
    a new reference (a tare) between two frames, from any thread.
    """

    def __init__(
        self,
        inverter: Inverter,
        warmup_frame: np.ndarray | None = None,
        pressure_shape: tuple[int, int] | None = None,
        head: ResidualHead | None = None,
    ):
        device = inverter.device
        self.inverter = inverter
        self.head = head
        self.step = frame_tracker(inverter)
        self.shape = (device.height, device.width)
        self.dtype = np.dtype(device.p1.dtype)
        self.cold_track = inverter.cold_track()
        self.track = self.cold_track
        self._lock = threading.Lock()
        self._pressure = None
        if pressure_shape is not None:
            grid = surface_grid(pressure_shape, device.px_per_mm, self.shape, device.a, device.Z)
            self._pressure = jax.jit(lambda wrench, contact: surface_tractions(wrench, contact, grid)[2] * PA_PER_MPA)
        # Compile now, not on the first contact: a 512x512 solve compiles for tens of
        # seconds on a laptop CPU. Any frame of the right size compiles the same program.
        frame = np.full(self.shape, 0.5, self.dtype) if warmup_frame is None else warmup_frame
        self(frame)
        self.reset()

    def reset(self) -> None:
        """Forget the warm start (the next frame is solved from a cold start)."""
        with self._lock:
            self.track = self.cold_track

    def rebind(self, inverter: Inverter) -> None:
        """Invert the next frames with `inverter` (the same unit on a new reference), cold.

        The compiled step is reused when `inverter` shares this one's layout
        ([`FrameTracker.with_inverter`][moirejax.FrameTracker.with_inverter]).
        """
        step = self.step.with_inverter(inverter)
        cold = inverter.cold_track()
        with self._lock:
            self.inverter, self.step, self.cold_track, self.track = inverter, step, cold, cold

    def __call__(self, gray: np.ndarray) -> TactileOutput:
        frame = np.asarray(gray, dtype=self.dtype)
        if frame.shape != self.shape:
            self.reset()
            status = Status.WRONG_SIZE
            message = f"{status.message} (frame {frame.shape}, device {self.shape}; rectify the camera frames)"
            return np.full(6, np.nan), None, status.name.lower(), message, {}
        with self._lock:
            estimate, self.track = self.step(frame, self.track)
        status = Status(int(estimate.status))
        contact = estimate.contact
        radius = float(contact.radius)
        wrench = np.asarray(estimate.wrench, np.float64)
        covariance = np.asarray(estimate.covariance, np.float64)
        # Every finite estimate of a contact, as `invert` corrects its rows.
        if self.head is not None and status != Status.NO_CONTACT and np.all(np.isfinite(wrench)):
            position = [np.asarray(v, np.float64).reshape(1) for v in (contact.x0, contact.y0, contact.radius)]
            wrench = self.head.correct(wrench[None], *position)[0]
            covariance = self.head.corrected_covariance(covariance)
        extras: dict[str, Any] = {"contact_area_mm2": math.pi * radius**2 if status in _WITH_WRENCH else None}
        if self._pressure is not None and status in _WITH_WRENCH:
            extras["pressure"] = np.asarray(self._pressure(wrench.astype(self.dtype), contact), np.float32)
        return (
            wrench,
            covariance,
            status.name.lower(),
            status.message,
            extras,
        )


# The statuses whose estimate carries a load (the wrench of the others is not one).
_WITH_WRENCH = (Status.CONVERGED, Status.MAX_STEPS)


def make_tactile_processor(
    inverter: Inverter,
    warmup_frame: np.ndarray | None = None,
    pressure_shape: tuple[int, int] | None = None,
    head: ResidualHead | None = None,
) -> TactileProcessor:
    """Adapt a [`frame_tracker`][] step to `process_tactile` of [`run_pipeline`][].

    **Arguments:**

    - `inverter`: the unit's [`Inverter`][moirejax.inverse._inversion.Inverter].
    - `warmup_frame`: a frame of the device's size to compile with (e.g. the reference);
        default a uniform gray frame.
    - `pressure_shape`: also return each frame's pressure map on a grid of this shape.
    - `head`: the calibration's [`ResidualHead`][] (from [`load_calibrated`][]), applied to
        every frame's wrench and covariance; `None` reads the physics alone.

    **Returns:** a [`TactileProcessor`][]: `fn(gray) -> (wrench, covariance, status, message)`,
    already compiled.
    """
    return TactileProcessor(inverter, warmup_frame, pressure_shape, head)


def make_gate(device: Device, **kwargs: Any) -> GateER:
    """A [`GateER`][] for rectified frames of `device`: its upper-grating carriers, moiré and black level.

    The threshold follows the noise floor the gate measures; keyword arguments go to
    [`GateER`][].
    """
    kwargs.setdefault("black_level", float(device.optics.offset))
    return GateER(
        carrier_wavevectors=np.asarray(device.apparent_upper_wavevectors(), np.float64),
        moire_wavevectors=np.asarray(device.moire_wavevectors(), np.float64),
        px_per_mm=float(device.px_per_mm),
        **kwargs,
    )


def make_colour_probe(device: Device, *, harmonics: int = 1) -> ColourProbe:
    """The vision hook: a [`MoireNotch`][] on the moiré and both carrier wavevectors, then a [`ColourProbe`][]."""
    wavevectors = np.concatenate(
        [
            np.asarray(device.moire_wavevectors(), np.float64),
            np.asarray(device.apparent_upper_wavevectors(), np.float64),
            np.asarray(device.reference_wavevectors(), np.float64),
        ]
    )
    notch = MoireNotch(
        (device.height, device.width), wavevectors, px_per_mm=float(device.px_per_mm), harmonics=harmonics
    )
    return ColourProbe(notch)


# ---------------------------------------------------------------------------------------
# The simulated sensor.


def schedule_script(schedule: LoadSchedule) -> LoadScript:
    """A [`LoadSchedule`][moirejax.simulate._simulate.LoadSchedule] as a load script (ends after its last frame)."""

    def script(i: int) -> tuple[np.ndarray, Contact] | None:
        if i >= len(schedule):
            return None
        return schedule.wrench[i], schedule.contact_at(i)

    return script


class _ScriptSource(CallableSource):
    """A [`CallableSource`][] that ends with `"end_of_stream"` when the script does, live or not.

    Not live, it renders on demand: a frame is rendered only once the consumer has taken
    the previous one and asks again, so no frame waits in a queue while the previous one is
    processed and the grab-to-emit latency is the sensor's, not the read-ahead's.
    """

    def __init__(self, sensor: "SimulatedSensor"):
        super().__init__(sensor.paced_frame, live=sensor.live, reconnect=Reconnect(max_attempts=0), queue_size=1)
        self.sensor = sensor
        self._wanted = threading.Event()

    def get(self, timeout: Real | None = None) -> Frame | SourceEvent | None:
        if not self.live:
            with self._cond:
                if not self._items:
                    self._wanted.set()
        item = super().get(timeout)
        if item is not None:
            # A request made while this item was being rendered is already served.
            self._wanted.clear()
        return item

    def _read(self, index: int) -> tuple[Any, float] | None:
        if self.sensor.finished(index):
            raise EndOfStreamError(END_OF_STREAM, f"end of the simulated load script after {index} frames")
        if not self.live:
            while not self._wanted.wait(0.05):
                if self._stop.is_set():
                    raise EndOfStreamError(CLOSED, "source closed")
            self._wanted.clear()
        return super()._read(index)


class SimulatedSensor:
    """Frames of a simulated unit under a load script, for running the live sensor with no hardware.

    **Arguments:**

    - `device`: the simulated unit.
    - `script`: a [`LoadSchedule`][moirejax.simulate._simulate.LoadSchedule], or `fn(i) ->
        (wrench, contact) | None` (e.g. a closed-loop rig that returns its current load);
        default `load_schedule("sequence", n_frames, seed)` (approach, press, twist, slide,
        release).
    - `n_frames`: length of the default script.
    - `fps`: frame rate the source paces itself to; `None` delivers as fast as the
        renderer and the consumer go.
    - `fidelity`: `"model"` (noise-free, fast) or `"high"` (the renderer's camera
        non-idealities and noise).
    - `noise`: standard deviation of extra white pixel noise (frame units, 0..1).
    - `seed`: seeds the default script and the noise.
    - `live`: deliver as a live camera (latest frame only, slow consumers drop frames)
        instead of every frame in order.
    - `scene`: what is above the sensor, seen through it: a [`SceneObject`][moirejax.SceneObject]
        in every frame, or `fn(i) -> SceneObject | None` (an object that comes and goes,
        moves, descends onto the pad); `None` for none. With a scene the frames are colour
        (BGR): the tactile frame's light above the black level times the
        [`scene_reflectance`][moirejax.scene_reflectance] of frame `i`'s object, so that
        vision mode can be exercised live (its gray is the tactile frame where nothing is in
        view).

    The ground truth of frame `i` is `truth(i)` (and `scene_at(i)`); [`source`][SimulatedSensor.source] gives
    the frame source for [`run_pipeline`][].
    """

    def __init__(
        self,
        device: Device,
        script: LoadSchedule | LoadScript | None = None,
        *,
        n_frames: int = 240,
        fps: Real | None = None,
        fidelity: str = "model",
        noise: Real = 0.0,
        seed: int = 0,
        live: bool = False,
        scene: SceneObject | Callable[[int], SceneObject | None] | None = None,
    ):
        if fps is not None and not fps > 0:
            raise ValueError(f"fps must be positive or None, got {fps}")
        if noise < 0:
            raise ValueError(f"noise must be non-negative, got {noise}")
        if script is None:
            script = load_schedule("sequence", n_frames, seed)
        self.device = device
        self.schedule = script if isinstance(script, LoadSchedule) else None
        self.script: LoadScript = schedule_script(script) if isinstance(script, LoadSchedule) else script
        self.simulator = Simulator(device, fidelity=fidelity)
        self.fps = fps
        self.noise = float(noise)
        self.seed = seed
        self.live = live
        self.scene = scene
        self._key = jr.PRNGKey(seed)
        self._truth: dict[int, np.ndarray] = {}
        self._ended_at: int | None = None
        self._t0: float | None = None

    def __len__(self) -> int:
        if self.schedule is None:
            raise TypeError("a closed-loop script has no length")
        return len(self.schedule)

    def scene_at(self, index: int) -> SceneObject | None:
        """The object above the sensor in frame `index`, or `None`."""
        return self.scene(index) if callable(self.scene) else self.scene

    def render(self, wrench: Any, contact: Contact, index: int = 0) -> np.ndarray:
        """One float32 frame in [0, 1] of `wrench` (N, N*m) at `contact`, with the sensor's
        noise: gray `(h, w)`, or BGR `(h, w, 3)` with a scene."""
        key = jr.fold_in(self._key, index)
        frame = np.asarray(self.simulator.frame(key, np.asarray(wrench, np.float64), contact), np.float32)
        if self.noise > 0:
            rng = np.random.default_rng((self.seed, index))
            frame = np.clip(frame + rng.normal(0.0, self.noise, frame.shape).astype(np.float32), 0.0, 1.0)
        if self.scene is None:
            return frame
        black = np.float32(self.device.optics.offset)
        reflectance = np.asarray(scene_reflectance(self.device, self.scene_at(index)), np.float32)
        return np.clip(black + (frame - black)[..., None] * reflectance, 0.0, 1.0)

    def reference_frame(self) -> np.ndarray:
        """A noise-free no-contact frame: the unit's reference for the inversion."""
        frame = self.simulator.frame(self._key, np.zeros(6), Contact())
        return np.asarray(frame, np.float32)

    def frame(self, index: int) -> np.ndarray | None:
        """Frame `index` of the script, or `None` once the script is over."""
        load = self.script(index)
        if load is None:
            self._ended_at = index if self._ended_at is None else min(self._ended_at, index)
            return None
        wrench, contact = load
        self._truth[index] = np.asarray(wrench, np.float64).reshape(6)
        return self.render(wrench, contact, index)

    def paced_frame(self, index: int) -> np.ndarray | None:
        """[`frame`][SimulatedSensor.frame], held back until `index / fps` after frame 0."""
        if self.fps is not None:
            now = time.monotonic()
            if index == 0 or self._t0 is None:
                self._t0 = now
            delay = self._t0 + index / self.fps - now
            if delay > 0:
                time.sleep(delay)
        return self.frame(index)

    def finished(self, index: int) -> bool:
        """Whether the script ended at or before frame `index`."""
        if self.schedule is not None:
            return index >= len(self.schedule)
        return self._ended_at is not None and index >= self._ended_at

    def truth(self, index: int) -> np.ndarray:
        """The true wrench `[fx, fy, fz, tx, ty, tz]` (N, N*m) of frame `index`.

        **Raises:** `KeyError` for a frame of a closed-loop script that was never rendered.
        """
        if self.schedule is not None:
            return np.asarray(self.schedule.wrench[index], np.float64)
        return self._truth[index]

    def source(self) -> CallableSource:
        """A frame source delivering the script's frames (ends with `"end_of_stream"`).

        In order, every frame rendered when the consumer asks for it (at most `fps`);
        `live`: free running at `fps` (or as fast as it renders), the consumer gets the latest.
        """
        self._t0 = None
        self._ended_at = None
        return _ScriptSource(self)


# ---------------------------------------------------------------------------------------
# Sources, sinks, references.


def _is_sim(spec: str) -> bool:
    return spec.strip().lower() == "sim"


def open_source(spec: str, *, replay_fps: float | None = None) -> AbstractFrameSource:
    """A frame source from a spec: a camera index (`"0"`) or name ([`find_camera`][]), a URL
    or GStreamer pipeline, a folder of images, or a video file (played at `replay_fps` if given, else as fast as
    it decodes).

    (`"sim"` is handled by [`run_live`][], which needs the device.)

    **Raises:** `FileNotFoundError` for a path that does not exist.
    """
    if spec.isdigit() or "://" in spec or "!" in spec:
        return VideoSource(spec)
    path = Path(spec)
    if path.is_dir():
        return FolderSource(path)
    if path.is_file():
        return VideoSource(path, replay_fps=replay_fps)
    if "/" not in spec and not path.suffix:
        # A camera's name, serial number or path: its index ([`find_camera`][]).
        try:
            return VideoSource(str(find_camera(spec)))
        except ImportError as e:
            raise FileNotFoundError(f"{spec}: not a camera index, URL, folder or video file; {e}") from None
    raise FileNotFoundError(f"{spec}: not 'sim', a camera index, a URL, a folder or a video file")


def parse_sink(spec: str) -> Sink:
    """A sink from a spec: `"-"` or `"stdout"` (JSON lines to stdout), `"udp://host:port"`,
    or a file path (JSON lines appended).

    **Raises:** `ValueError` for a UDP spec without host or port.
    """
    if spec in ("-", "stdout"):
        return StreamSink()
    if spec.lower().startswith("udp://"):
        parts = urllib.parse.urlsplit(spec)
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None:
            raise ValueError(f"UDP sink {spec!r} needs udp://host:port")
        return UdpSink(parts.hostname, port)
    return FileSink(spec)


def capture_reference(
    source: AbstractFrameSource,
    *,
    frames: int = 5,
    rectification: Rectification | None = None,
    timeout_s: Real = 10.0,
) -> np.ndarray | None:
    """Mean of the first `frames` good frames of `source` (rectified), or `None` if it gives none.

    The sensor must be untouched while they are taken (the same assumption the gate's
    warm-up makes). The source is started and closed here; corrupt frames are skipped.

    **Raises:** `ValueError` if the source fails (cannot be opened, is lost) before its
    first frame, so that a missing camera is reported before the inverter is built.
    """
    grabbed: list[np.ndarray] = []
    deadline = time.monotonic() + timeout_s
    with source:
        while len(grabbed) < frames and time.monotonic() < deadline:
            item = source.get(timeout=0.1)
            if item is None:
                continue
            if isinstance(item, SourceEvent):
                if item.final and not grabbed and item.status in (OPEN_FAILED, SOURCE_LOST, SOURCE_ERROR):
                    raise ValueError(f"no reference frame from the source: {item.status}: {item.message}")
                if item.final:
                    break
                continue
            gray = item.gray if rectification is None else rectification.apply(item.gray)
            if grabbed and gray.shape != grabbed[0].shape:
                continue
            grabbed.append(gray.astype(np.float64))
    return np.mean(grabbed, axis=0) if grabbed else None


def _load_reference(reference: np.ndarray | str | os.PathLike) -> np.ndarray:
    if isinstance(reference, np.ndarray):
        return reference
    data = np.fromfile(os.fspath(reference), dtype=np.uint8)
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise DataError(f"{os.fspath(reference)}: cannot read the reference image")
    return to_frame(image, 0, 0.0).gray


def run_live(
    device: Device,
    source_spec: str,
    *,
    sinks: Sequence[Sink],
    max_frames: int | None = None,
    record: str | os.PathLike | VideoRecorder | None = None,
    plot: bool = False,
    rectification: Rectification | str | os.PathLike | None = None,
    reference: np.ndarray | str | os.PathLike | None = None,
    inverter: Inverter | None = None,
    sensor: SimulatedSensor | None = None,
    vision: bool = True,
    reference_frames: int = 5,
    record_fps: Real = 30.0,
    replay_fps: float | None = None,
    stop: threading.Event | None = None,
    records: RecordStream | None = None,
    head: ResidualHead | None = None,
) -> LiveSummary:
    """Run the live sensor: frames from `source_spec` to wrench records in `sinks`.

    **Arguments:**

    - `device`: the unit (nominal or calibrated); frames must be rectified to its size.
    - `source_spec`: `"sim"` (a [`SimulatedSensor`][] of `device`), a camera index
        (`"0"`), a video file, a stream URL or GStreamer pipeline, or a folder of images.
    - `sinks`: where the records go (not closed here); see [`parse_sink`][].
    - `max_frames`: stop after this many frames. For `"sim"` it is also the length of the
        default load script (an approach, press, twist, slide and release).
    - `record`: path of an annotated MP4 (or a [`VideoRecorder`][], not closed here).
    - `plot`: show a live [`StripChart`][] (a no-op without a display).
    - `rectification`: a [`Rectification`][] or its JSON file, applied to every frame.
    - `reference`: the unit's no-contact frame (array or image file). Default: for `"sim"`
        a rendered no-contact frame; otherwise the mean of the first `reference_frames`
        frames of the source, which must be untouched when it starts (the source is
        opened once for them and again for the run). With no frame, the model's own
        prediction.
    - `inverter`: use this [`Inverter`][moirejax.inverse._inversion.Inverter] (e.g. one already
        compiled) instead of building one; `reference` is then not used.
    - `sensor`: the simulated sensor for `"sim"` (default: one with the default script).
    - `vision`: in vision mode, name the colour seen through the sensor (colour sources).
    - `record_fps`: frame rate written into the recording.
    - `replay_fps`: play a video file at this rate, as a camera would deliver it.
    - `stop`: a `threading.Event` that ends the run when set.
    - `records`: a [`RecordStream`][] completing every record (sensor and ROS frame names,
        range flags, centre of pressure, filter); default one with the default names.
    - `head`: the calibration's [`ResidualHead`][] ([`load_calibrated`][] returns it with
        the device): every wrench and covariance corrected by it, as `invert` does.

    **Returns:** the [`LiveSummary`][]; see [`format_summary`][].

    **Raises:** `FileNotFoundError` for a source path that does not exist; `ValueError`
    for a reference frame of the wrong size, or a source that fails before its first
    frame while the reference is taken.
    """
    if isinstance(rectification, str | os.PathLike):
        rectification = load_rectification(rectification)
    shape = (device.height, device.width)
    if _is_sim(source_spec):
        if sensor is None:
            sensor = SimulatedSensor(device, n_frames=max_frames if max_frames else 240)
        source: AbstractFrameSource = sensor.source()
    else:
        source = open_source(source_spec, replay_fps=replay_fps)

    reference_frame = None
    if inverter is None:
        if reference is not None:
            reference_frame = _load_reference(reference)
        elif sensor is not None:
            reference_frame = sensor.reference_frame()
        else:
            reference_frame = capture_reference(
                open_source(source_spec), frames=reference_frames, rectification=rectification
            )
            if reference_frame is None:
                logger.warning("no reference frame from %s: using the model's own prediction", source_spec)
            elif reference_frame.shape != shape:
                logger.warning(
                    "source frames are %s, the device expects %s: no reference (rectify the camera frames)",
                    reference_frame.shape,
                    shape,
                )
                reference_frame = None
        if reference_frame is not None and reference_frame.shape != shape:
            raise ValueError(f"reference frame is {reference_frame.shape}, device expects {shape}")
        inverter = Inverter(device, reference=reference_frame)
    draws_pressure = any(hasattr(sink, "emit_pressure") for sink in sinks)
    processor = make_tactile_processor(inverter, reference_frame, PRESSURE_SHAPE if draws_pressure else None, head)

    owned: list[Any] = []
    all_sinks = list(sinks)
    if plot:
        chart = StripChart()
        owned.append(chart)
        all_sinks.append(chart)
    recorder = record
    if isinstance(record, str | os.PathLike):
        recorder = VideoRecorder(record, fps=record_fps)
        owned.append(recorder)
    try:
        return run_pipeline(
            source,
            processor,
            all_sinks,
            make_gate(device),
            max_frames=max_frames,
            rectification=rectification,
            vision=make_colour_probe(device) if vision else None,
            record=recorder,
            stop=stop,
            records=records if records is not None else RecordStream(),
        )
    finally:
        for thing in owned:
            thing.close()


def format_summary(summary: LiveSummary) -> str:
    """A one-paragraph human summary of a [`LiveSummary`][]."""

    def ms(x: float) -> str:
        return f"{x:.1f} ms" if math.isfinite(x) else "n/a"

    statuses = ", ".join(f"{name} {count}" for name, count in sorted(summary.status_counts.items()))
    lines = [
        f"frames {summary.frames} (dropped {summary.dropped}), records {summary.records}, "
        f"{summary.fps:.1f} fps over {summary.elapsed_s:.1f} s",
        f"latency median {ms(summary.latency_ms_median)}, p90 {ms(summary.latency_ms_p90)}",
        f"mode switches {summary.mode_switches}; stopped by {summary.stopped_by}",
        f"status: {statuses or 'none'}",
    ]
    if summary.output_errors:
        lines.append(f"output errors: {summary.output_errors}")
    return "\n".join(lines)
