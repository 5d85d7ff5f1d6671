"""The live loop: frames in, gated wrench records out, never stopped by one bad frame.

For every frame: rectify, gate (vision/tactile), and in tactile mode call the
user-supplied `process_tactile(frame) -> (wrench6, cov6x6 | None, status, message[, extras])`
(the inversion; `extras` may give the record's `contact_area_mm2` and `pressure` map); in vision mode the wrench is zero and an optional vision hook may
describe the scene. Source events (corrupt frames, reconnections, the end of the stream)
and any exception on the way become status records, in order with the frame records.
The loop ends at the end of the source, after `max_frames`, when a `stop` event is set,
or on SIGINT when run from the main thread (a second SIGINT raises `KeyboardInterrupt`
at once, for a hung `process_tactile`).
"""

import contextlib
import dataclasses
import logging
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from ._camera import AbstractFrameSource, Frame, SourceEvent
from ._gate import GateER
from ._records import RecordStream
from ._rectify import Rectification
from ._sinks import make_record, Sink, VideoRecorder, WrenchRecord


logger = logging.getLogger("moirejax.live")

ProcessTactile = Callable[[np.ndarray], tuple[Any, Any, str, str]]
VisionHook = Callable[[Frame], str | None]

# Status codes the pipeline itself emits (source events add theirs, process_tactile its own).
NO_CONTACT = "no_contact"
PROCESS_ERROR = "process_error"
BAD_OUTPUT = "bad_output"
RECTIFY_ERROR = "rectify_error"
GATE_ERROR = "gate_error"
VISION_ERROR = "vision_error"
INTERRUPTED = "interrupted"
MAX_FRAMES = "max_frames"


@dataclasses.dataclass(frozen=True)
class LiveSummary:
    """What a [`run_pipeline`][] run did.

    **Fields:**

    - `frames`: frames processed.
    - `dropped`: frames the source overwrote before they were taken (latest-frame mode).
    - `records`: records emitted (frames and status events).
    - `latency_ms_median`, `latency_ms_p90`: grab-to-emit latency of frame records (ms).
    - `fps`: frames processed per second of loop time.
    - `mode_switches`: gate switches between vision and tactile mode.
    - `status_counts`: number of records per status code.
    - `stopped_by`: `"max_frames"`, `"interrupted"`, or the source's final status.
    - `output_errors`: exceptions raised by sinks or the video recorder (logged, skipped).
    - `elapsed_s`: wall time of the loop.
    """

    frames: int
    dropped: int
    records: int
    latency_ms_median: float
    latency_ms_p90: float
    fps: float
    mode_switches: int
    status_counts: dict[str, int]
    stopped_by: str
    output_errors: int
    elapsed_s: float


@contextlib.contextmanager
def _stop_on_sigint(stop: threading.Event) -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


_EXTRAS = frozenset({"contact_area_mm2", "pressure"})


def _check_output(output: Any) -> tuple[np.ndarray, np.ndarray | None, str, str, dict[str, Any]]:
    """Validate what `process_tactile` returned; raises `ValueError` naming the problem."""
    if not isinstance(output, tuple | list) or len(output) not in (4, 5):
        raise ValueError(f"expected (wrench, covariance, status, message[, extras]), got {type(output).__name__}")
    wrench, covariance, status, message = output[:4]
    extras = dict(output[4]) if len(output) == 5 and output[4] is not None else {}
    if not set(extras) <= _EXTRAS:
        raise ValueError(f"unknown extras {sorted(set(extras) - _EXTRAS)}; known: {sorted(_EXTRAS)}")
    wrench = np.asarray(wrench, dtype=np.float64)
    if wrench.shape != (6,):
        raise ValueError(f"wrench must have shape (6,), got {wrench.shape}")
    if covariance is not None:
        covariance = np.asarray(covariance, dtype=np.float64)
        if covariance.shape != (6, 6):
            raise ValueError(f"covariance must have shape (6, 6), got {covariance.shape}")
    return wrench, covariance, str(status), str(message), extras


def run_pipeline(
    source: AbstractFrameSource,
    process_tactile: ProcessTactile,
    sinks: Sequence[Sink],
    gate: GateER | None,
    *,
    max_frames: int | None = None,
    rectification: Rectification | None = None,
    vision: VisionHook | None = None,
    record: VideoRecorder | None = None,
    stop: threading.Event | None = None,
    records: RecordStream | None = None,
) -> LiveSummary:
    """Run the live loop until the source ends, `max_frames` frames, SIGINT, or `stop` is set.

    **Arguments:**

    - `source`: a frame source; it is started here and closed on return.
    - `process_tactile`: `fn(gray) -> (wrench, covariance, status, message)` on the
        rectified float32 frame in [0, 1]; `wrench` is `[fx, fy, fz, tx, ty, tz]` in N and
        N*m, `covariance` 6x6 or `None`. Exceptions become `"process_error"` records.
    - `sinks`: receive every record in order (they are not closed here). A sink with an
        `emit_image(image, record)` method also gets each frame (colour if the source has
        it), and one with `emit_pressure(pressure, record)` each record's pressure map.
    - `gate`: the contact gate; `None` treats every frame as tactile.
    - `max_frames`: stop after this many frames.
    - `rectification`: applied to the gray and colour frames first.
    - `vision`: optional `fn(frame) -> message | None` called in vision mode with the
        rectified [`Frame`][]; its message goes into the record.
    - `record`: optional [`VideoRecorder`][] for an annotated video (not closed here).
    - `stop`: an event that ends the loop when set (from another thread).
    - `records`: a [`RecordStream`][] that completes every record (identity, sequence,
        tare bias, range flags, centre of pressure, filter) before the sinks see it.

    **Returns:** a [`LiveSummary`][].
    """
    stop = stop if stop is not None else threading.Event()
    wall_offset = time.time() - time.monotonic()
    statuses: Counter[str] = Counter()
    latencies: list[float] = []
    frames = switches = n_records = output_errors = 0
    next_index = 0  # frame index for the record of an interruption
    stopped_by = INTERRUPTED
    mode = gate.mode if gate is not None else "tactile"
    started = time.monotonic()

    def emit(rec: WrenchRecord, image: np.ndarray | None = None) -> None:
        nonlocal n_records, output_errors
        if records is not None:
            try:
                rec = records.finish(rec, rec.stamp - wall_offset)
            except Exception as e:
                output_errors += 1
                logger.warning("record stream failed: %s", e)
        statuses[rec.status] += 1
        n_records += 1
        for sink in sinks:
            try:
                sink.emit(rec)
                if image is not None and hasattr(sink, "emit_image"):
                    sink.emit_image(image, rec)
                if rec.pressure is not None and hasattr(sink, "emit_pressure"):
                    sink.emit_pressure(rec.pressure, rec)
            except Exception as e:
                output_errors += 1
                logger.warning("sink %s failed: %s", type(sink).__name__, e)
        if record is not None and image is not None:
            try:
                record.write(image, rec)
            except Exception as e:
                output_errors += 1
                logger.warning("video recorder failed: %s", e)

    def status_record(index: int, stamp: float, status: str, message: str) -> WrenchRecord:
        return make_record(
            stamp=stamp + wall_offset,
            frame=index,
            mode=mode,
            status=status,
            latency_ms=(time.monotonic() - stamp) * 1e3,
            message=message,
        )

    with _stop_on_sigint(stop), source:
        while not stop.is_set():
            item = source.get(timeout=0.05)
            if item is None:
                continue
            next_index = item.index + 1
            if isinstance(item, SourceEvent):
                emit(status_record(item.index, item.stamp, item.status, item.message))
                if item.final:
                    stopped_by = item.status
                    break
                continue
            frame: Frame = item
            frames += 1
            try:
                if rectification is not None:
                    color = None if frame.color is None else rectification.apply(frame.color)
                    frame = dataclasses.replace(frame, gray=rectification.apply(frame.gray), color=color)
            except Exception as e:
                emit(status_record(frame.index, frame.stamp, RECTIFY_ERROR, f"{type(e).__name__}: {e}"))
            else:
                try:
                    decision = gate.update(frame.gray) if gate is not None else None
                except Exception as e:
                    emit(status_record(frame.index, frame.stamp, GATE_ERROR, f"{type(e).__name__}: {e}"))
                else:
                    if decision is not None:
                        mode = decision.mode
                        switches += decision.switched
                    rec = _process(frame, mode, process_tactile, vision, wall_offset)
                    latencies.append(rec.latency_ms)
                    emit(rec, frame.color if frame.color is not None else frame.gray)
            if max_frames is not None and frames >= max_frames:
                stopped_by = MAX_FRAMES
                break
        else:
            emit(status_record(next_index, time.monotonic(), INTERRUPTED, "stopped by SIGINT or stop event"))
    elapsed = time.monotonic() - started
    lat = np.asarray(latencies) if latencies else np.full(1, np.nan)
    return LiveSummary(
        frames=frames,
        dropped=source.dropped,
        records=n_records,
        latency_ms_median=float(np.median(lat)),
        latency_ms_p90=float(np.percentile(lat, 90)),
        fps=frames / elapsed if elapsed > 0 else 0.0,
        mode_switches=switches,
        status_counts=dict(statuses),
        stopped_by=stopped_by,
        output_errors=output_errors,
        elapsed_s=elapsed,
    )


def _process(
    frame: Frame, mode: str, process_tactile: ProcessTactile, vision: VisionHook | None, wall_offset: float
) -> WrenchRecord:
    """The record of one gated frame; exceptions become status records."""
    wrench = covariance = None
    extras: dict[str, Any] = {}
    if mode == "tactile":
        try:
            output = process_tactile(frame.gray)
        except Exception as e:
            status, message = PROCESS_ERROR, f"{type(e).__name__}: {e}"
        else:
            try:
                wrench, covariance, status, message, extras = _check_output(output)
            except ValueError as e:
                status, message = BAD_OUTPUT, str(e)
    else:
        wrench, status, message = np.zeros(6), NO_CONTACT, ""
        if vision is not None:
            try:
                message = vision(frame) or ""
            except Exception as e:
                status, message = VISION_ERROR, f"{type(e).__name__}: {e}"
    return make_record(
        stamp=frame.stamp + wall_offset,
        frame=frame.index,
        mode=mode,
        status=status,
        wrench=wrench,
        covariance=covariance,
        latency_ms=(time.monotonic() - frame.stamp) * 1e3,
        message=message,
        **extras,
    )
