"""Outputs of the live pipeline: wrench records as JSON lines (stdout, file, UDP), an annotated video, a strip chart.

Every sink has `emit(record)` and `close()` and never raises on I/O trouble while
emitting: failures are counted in `stats` (and logged once), so a closed pipe, a full
disk or a UDP port nobody listens on cannot stop the sensor loop.

A record is one JSON object per line:
`{"stamp": s, "frame": int, "mode": "vision"|"tactile", "status": str, "force": [fx, fy, fz] | null,
"torque": [tx, ty, tz] | null, "covariance": 6x6 | null, "latency_ms": float, "message": str, ...}`
with forces in N, torques in N*m (wrench convention of `docs/conventions.md`) and the
covariance over `[fx, fy, fz, tx, ty, tz]` in those units. Records of version 2 add what an
F/T driver's records carry: `sensor_id`, `frame_id` (the ROS frame name), `seq`,
`monotonic`, `in_contact`, `out_of_range`, `centre_of_pressure_mm`, `contact_area_mm2`,
`filtered` and `version` (`data_schema/live_record.schema.json`; version-1 records, without
them, still validate).
"""

import dataclasses
import errno
import json
import logging
import math
import os
import socket
import sys
import time
from collections import deque
from typing import Any, IO, Protocol, runtime_checkable

import cv2
import numpy as np

from .._fileio import atomic_write_text, OutputError
from ._ft import AbstractForceTorqueSource, ForceTorqueLog
from ._types import Real


logger = logging.getLogger("moirejax.live")


RECORD_VERSION = 2
"""Version of the live record's fields (`data_schema/live_record.schema.json`)."""


@dataclasses.dataclass(frozen=True)
class WrenchRecord:
    """One output record; see the module docstring for the fields and units.

    `stamp` is the frame's grab time in Unix seconds (`monotonic` the same instant on the
    monotonic clock); `latency_ms` runs from grab to emit. `seq` counts the records of a
    stream from 0 (`frame` is the source's frame index, whose gaps are dropped frames).
    `in_contact` is true for a tactile-mode frame the inversion found touched (`converged`,
    `max_steps`, or `unexplained`, whose wrench is not believed); `out_of_range` flags each
    axis whose magnitude exceeds the unit's calibrated range; `centre_of_pressure_mm` is
    `(-ty / fz, tx / fz)` on the contact surface (mm), given while the normal force is
    resolved; `contact_area_mm2` is the fitted contact patch's area; `filtered` says the
    wrench went through a filter (e.g. [`WrenchFilter`][]). `skew_ms`, on a record that
    combines several sensors (a grip record of [`SensorGroup`][]), is the spread of their
    capture times, and is written only when set. `pressure` is the record's
    pressure map in Pa (rows top to bottom, not written to JSON), for sinks that draw it.
    """

    stamp: float
    frame: int
    mode: str
    status: str
    force: tuple[float, float, float] | None
    torque: tuple[float, float, float] | None
    covariance: tuple[tuple[float, ...], ...] | None
    latency_ms: float
    message: str = ""
    sensor_id: str = "moirejax"
    frame_id: str = "moirejax_sensor"
    seq: int = 0
    monotonic: float | None = None
    in_contact: bool = False
    out_of_range: tuple[bool, ...] | None = None
    centre_of_pressure_mm: tuple[float, float] | None = None
    contact_area_mm2: float | None = None
    filtered: bool = False
    skew_ms: float | None = None
    pressure: np.ndarray | None = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def wrench(self) -> np.ndarray | None:
        """`[fx, fy, fz, tx, ty, tz]` (N, N*m), or `None` for a record without a wrench."""
        if self.force is None or self.torque is None:
            return None
        return np.asarray(self.force + self.torque, np.float64)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (non-finite numbers become `null`)."""

        def clean(value):
            if value is None:
                return None
            if isinstance(value, tuple | list):
                return [clean(v) for v in value]
            value = float(value)
            return value if math.isfinite(value) else None

        fields = {
            "version": RECORD_VERSION,
            "sensor_id": self.sensor_id,
            "frame_id": self.frame_id,
            "seq": int(self.seq),
            "stamp": clean(self.stamp),
            "monotonic": clean(self.monotonic),
            "frame": int(self.frame),
            "mode": self.mode,
            "status": self.status,
            "in_contact": bool(self.in_contact),
            "force": clean(self.force),
            "torque": clean(self.torque),
            "covariance": clean(self.covariance),
            "out_of_range": None if self.out_of_range is None else [bool(v) for v in self.out_of_range],
            "centre_of_pressure_mm": clean(self.centre_of_pressure_mm),
            "contact_area_mm2": clean(self.contact_area_mm2),
            "filtered": bool(self.filtered),
            "latency_ms": clean(self.latency_ms),
            "message": self.message,
        }
        if self.skew_ms is not None:
            fields["skew_ms"] = clean(self.skew_ms)
        return fields

    def to_json(self) -> str:
        """The record as one line of compact JSON (no trailing newline)."""
        return json.dumps(self.to_dict(), separators=(",", ":"), allow_nan=False)


def make_record(
    *,
    stamp: Real,
    frame: int,
    mode: str,
    status: str,
    wrench: np.ndarray | None = None,
    covariance: np.ndarray | None = None,
    latency_ms: Real = 0.0,
    message: str = "",
    **fields: Any,
) -> WrenchRecord:
    """Build a [`WrenchRecord`][] from a 6-vector `[fx, fy, fz, tx, ty, tz]` and a 6x6
    covariance; further keyword arguments set the record's other fields."""
    force = torque = cov = None
    if wrench is not None:
        w = [float(v) for v in np.asarray(wrench, dtype=np.float64).reshape(6)]
        force, torque = (w[0], w[1], w[2]), (w[3], w[4], w[5])
    if covariance is not None:
        cov = tuple(tuple(float(v) for v in row) for row in np.asarray(covariance, dtype=np.float64).reshape(6, 6))
    return WrenchRecord(
        float(stamp), int(frame), mode, status, force, torque, cov, float(latency_ms), message, **fields
    )


@runtime_checkable
class Sink(Protocol):
    """Anything the pipeline can hand records to."""

    def emit(self, record: WrenchRecord) -> None: ...

    def close(self) -> None: ...


class _CountingSink:
    def __init__(self):
        self.stats: dict[str, int] = {"sent": 0, "errors": 0}
        self._warned: set[str] = set()

    def _failed(self, kind: str, error: BaseException) -> None:
        self.stats[kind] = self.stats.get(kind, 0) + 1
        if kind not in self._warned:
            self._warned.add(kind)
            logger.warning("%s: %s (%s); further ones are only counted", type(self).__name__, kind, error)

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


@runtime_checkable
class TextStream(Protocol):
    """A writable text stream (`sys.stdout`, an open text file, `io.StringIO`)."""

    def write(self, text: str, /) -> int: ...

    def flush(self) -> None: ...


class StreamSink(_CountingSink):
    """JSON lines to a text stream (default: the current `sys.stdout`), flushed after every record."""

    def __init__(self, stream: TextStream | None = None):
        super().__init__()
        self.stream = stream

    def emit(self, record: WrenchRecord) -> None:
        stream = self.stream if self.stream is not None else sys.stdout
        try:
            stream.write(record.to_json() + "\n")
            stream.flush()
            self.stats["sent"] += 1
        except (OSError, ValueError) as e:  # broken pipe, closed stream
            self._failed("errors", e)

    def close(self) -> None:
        try:
            (self.stream if self.stream is not None else sys.stdout).flush()
        except (OSError, ValueError):
            pass


class FileSink(_CountingSink):
    """JSON lines appended to a file, line-buffered and flushed after every record."""

    def __init__(self, path: str | os.PathLike):
        super().__init__()
        self.path = os.fspath(path)
        self._file: IO[str] | None = open(self.path, "a", buffering=1, encoding="utf-8")

    def emit(self, record: WrenchRecord) -> None:
        if self._file is None:
            self._failed("errors", ValueError("sink is closed"))
            return
        try:
            self._file.write(record.to_json() + "\n")
            self._file.flush()
            self.stats["sent"] += 1
        except OSError as e:
            self._failed("errors", e)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class UdpSink(_CountingSink):
    """One JSON record per datagram to `host:port`, non-blocking.

    The socket is connected so the kernel reports ICMP "port unreachable" back as
    `ECONNREFUSED` on a later send: counted in `stats["refused"]`, never raised. A full
    send buffer counts in `stats["dropped"]`.
    """

    def __init__(self, host: str, port: int):
        super().__init__()
        self.stats.update(refused=0, dropped=0)
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        self.address = address
        self._sock: socket.socket | None = socket.socket(family, kind, proto)
        self._sock.setblocking(False)
        self._sock.connect(address)

    def emit(self, record: WrenchRecord) -> None:
        if self._sock is None:
            self._failed("errors", ValueError("sink is closed"))
            return
        payload = (record.to_json() + "\n").encode("utf-8")
        # A refusal reported for an earlier datagram surfaces on this send; try once more
        # so this record is not lost with it.
        for _ in range(2):
            try:
                self._sock.send(payload)
                self.stats["sent"] += 1
                return
            except ConnectionRefusedError as e:
                self._failed("refused", e)
            except BlockingIOError as e:
                self._failed("dropped", e)
                return
            except OSError as e:
                self._failed("dropped" if e.errno == errno.ENOBUFS else "errors", e)
                return

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class RecordingSink(_CountingSink):
    """The camera's frames with their capture times and the gate's contact flag, as a
    recording that `moirejax import` turns into a dataset: `folder/frames/NNNNNN.png` and
    `folder/frames.csv` with columns `frame,t,contact`.

    This is how a calibration session is captured: record the frames live, log the
    reference force/torque sensor on its own clock, then
    `moirejax import --frames FOLDER/frames --wrench FOLDER/frames.csv --ft FT.csv --align`
    interpolates the log to each frame's time, the clock offset estimated from the data.
    The times are the records' capture stamps (s, the host's wall clock, which a driver on
    the same host shares); `contact` is 1 for a frame the gate put in tactile mode. Frames are written as they come, each PNG complete before its
    name appears (written beside it, then renamed); `frames.csv` is rewritten atomically
    every `index_every` frames and at `close`, so an interrupted session keeps every frame
    the index lists. A frame that cannot be written is counted in `stats["errors"]` and left
    out of the index; the stream goes on.

    **Arguments:**

    - `folder`: a new or empty folder.
    - `bit_depth`: 8 (a camera's own depth: frames in [0, 1] from 8-bit images come back
        exactly) or 16 bits per PNG pixel.
    - `index_every`: frames between rewrites of the index.
    - `compression`: the PNG's zlib level, 0 to 9. 0 (the default) stores the pixels
        unpacked, 0.26 MB a 512 x 512 frame written in about 4 ms, which keeps up with a
        60 fps camera; level 1 made a noisy frame a fifth smaller in four times as long.
    - `ft`: a reference force/torque sensor ([`AbstractForceTorqueSource`][]), read from
        now until `close` into `folder/ft.csv` ([`ForceTorqueLog`][]), the log that
        `import --ft FOLDER/ft.csv --align` aligns to the frames.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        *,
        bit_depth: int = 8,
        index_every: int = 60,
        compression: int = 0,
        ft: AbstractForceTorqueSource | None = None,
    ):
        super().__init__()
        if bit_depth not in (8, 16):
            raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth}")
        if index_every < 1:
            raise ValueError(f"index_every must be at least 1, got {index_every}")
        self.folder = os.fspath(folder)
        self.bit_depth = bit_depth
        self.index_every = index_every
        if not 0 <= compression <= 9:
            raise ValueError(f"compression must be a zlib level 0 to 9, got {compression}")
        self.compression = compression
        frames = os.path.join(self.folder, "frames")
        if os.path.isdir(self.folder) and os.listdir(self.folder):
            raise OutputError(f"{self.folder}: not empty; a recording needs a new folder")
        try:
            os.makedirs(frames, exist_ok=True)
        except OSError as e:
            raise OutputError(f"{frames}: cannot be made ({e.strerror or e})") from e
        self._rows: list[str] = []
        self._closed = False
        self.ft_log = ForceTorqueLog(os.path.join(self.folder, "ft.csv"), ft) if ft is not None else None

    def emit(self, record: WrenchRecord) -> None:
        """Records are not kept: the frames are ([`emit_image`][RecordingSink.emit_image])."""

    def emit_image(self, image: np.ndarray, record: WrenchRecord) -> None:
        """Write the frame of `record`: gray or BGR, uint8 or float in [0, 1]."""
        if self._closed:
            self._failed("errors", ValueError("sink is closed"))
            return
        name = f"{record.frame:06d}.png"
        path = os.path.join(self.folder, "frames", name)
        arr = np.asarray(image)
        if self.bit_depth == 8 and arr.dtype != np.uint8:
            # Rounded to the nearest level and saturated: an 8-bit camera's frame comes back exactly.
            arr = cv2.convertScaleAbs(np.asarray(arr, np.float32), alpha=255.0)
        elif self.bit_depth == 16:
            scale = 65535 / 255 if arr.dtype == np.uint8 else 65535.0
            arr = np.round(np.clip(arr.astype(np.float64) * scale, 0.0, 65535.0)).astype(np.uint16)
        try:
            ok, encoded = cv2.imencode(".png", arr, [cv2.IMWRITE_PNG_COMPRESSION, self.compression])
            if not ok:
                raise ValueError(f"cannot encode a {arr.shape} {arr.dtype} frame as PNG")
            with open(path + ".part", "wb") as f:
                f.write(encoded.tobytes())
            os.replace(path + ".part", path)
        except (OSError, ValueError) as e:
            self._failed("errors", e)
            return
        self._rows.append(f"{name},{record.stamp!r},{int(record.mode == 'tactile')}")
        self.stats["sent"] += 1
        if len(self._rows) % self.index_every == 0:
            self._write_index()

    def _write_index(self) -> None:
        try:
            atomic_write_text(
                os.path.join(self.folder, "frames.csv"), "frame,t,contact\n" + "".join(r + "\n" for r in self._rows)
            )
        except OutputError as e:
            self._failed("errors", e)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if self.ft_log is not None:
                self.ft_log.close()
            self._write_index()


def _as_bgr8(image: np.ndarray) -> np.ndarray:
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = (np.clip(arr.astype(np.float32), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    if arr.ndim == 2:
        arr = cv2.cvtColor(arr, cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(arr[..., :3])


class VideoRecorder:
    """Annotated MP4 (`mp4v`) of the frames: frame index, mode, status and six wrench bars.

    The writer opens on the first frame and takes its size; a panel with the bars is
    added below the image. Bars are scaled so `force_range` N and `torque_range` N*m
    fill half the panel width.

    **Arguments:**

    - `path`: output file (`.mp4`).
    - `fps`: frame rate written into the file.
    - `force_range`, `torque_range`: full-scale values of the bars.
    """

    _PANEL_ROW = 14

    def __init__(
        self, path: str | os.PathLike, fps: Real = 30.0, *, force_range: Real = 1.0, torque_range: Real = 0.01
    ):
        self.path = os.fspath(path)
        self.fps = fps
        self.force_range = force_range
        self.torque_range = torque_range
        self.frames = 0
        self._writer: Any = None
        self._size: tuple[int, int] | None = None

    def write(self, image: np.ndarray, record: WrenchRecord) -> None:
        """Annotate and append one frame (gray or BGR, uint8 or float in [0, 1]).

        **Raises:** `OSError` if the video file cannot be opened; `ValueError` if the frame
        size changes.
        """
        bgr = _as_bgr8(image)
        h, w = bgr.shape[:2]
        panel_h = 8 * self._PANEL_ROW
        if self._writer is None:
            writer = cv2.VideoWriter(self.path, cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h + panel_h))
            if not writer.isOpened():
                raise OSError(f"cv2.VideoWriter cannot open {self.path}")
            self._writer, self._size = writer, (w, h)
        elif (w, h) != self._size:
            raise ValueError(f"frame size {(w, h)} differs from the recording's {self._size}")
        canvas = np.zeros((h + panel_h, w, 3), np.uint8)
        canvas[:h] = bgr
        self._draw_panel(canvas[h:], record)
        self._writer.write(canvas)
        self.frames += 1

    def _draw_panel(self, panel: np.ndarray, record: WrenchRecord) -> None:
        font, row = cv2.FONT_HERSHEY_SIMPLEX, self._PANEL_ROW
        colour = (80, 200, 80) if record.mode == "tactile" else (200, 160, 60)
        header = f"#{record.frame} {record.mode} {record.status}"
        cv2.putText(panel, header, (4, row - 3), font, 0.4, colour, 1, cv2.LINE_AA)
        values = list(record.force or (0.0, 0.0, 0.0)) + list(record.torque or (0.0, 0.0, 0.0))
        labels = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")
        width = panel.shape[1]
        x0, half = width // 2, max(1, width // 2 - 24)
        for k, (label, value) in enumerate(zip(labels, values)):
            y = (k + 1) * row + row // 2
            scale = self.force_range if k < 3 else self.torque_range
            v = float(value) if math.isfinite(float(value)) else 0.0
            length = int(round(np.clip(v / scale, -1.0, 1.0) * half))
            cv2.putText(panel, label, (2, y + 4), font, 0.35, (220, 220, 220), 1, cv2.LINE_AA)
            cv2.line(panel, (x0, y - 4), (x0, y + 4), (120, 120, 120), 1)
            if length:
                cv2.rectangle(panel, (x0, y - 3), (x0 + length, y + 3), (60, 180, 255) if k < 3 else (255, 120, 60), -1)

    def close(self) -> None:
        """Finish the file."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def __enter__(self) -> "VideoRecorder":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


_NON_INTERACTIVE_BACKENDS = {"agg", "cairo", "pdf", "pgf", "ps", "svg", "template"}


def display_available() -> bool:
    """Whether an interactive matplotlib window can be shown (a display and a GUI backend)."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return False
    try:
        import matplotlib
    except ImportError:
        return False
    backend = matplotlib.get_backend().lower()
    return backend not in _NON_INTERACTIVE_BACKENDS and "inline" not in backend


class StripChart:
    """Live plot of the last `window_s` seconds of force and torque; a no-op without a display.

    Redraws at most every `redraw_s` seconds so plotting cannot slow the sensor loop much.
    """

    def __init__(self, window_s: Real = 10.0, *, redraw_s: Real = 0.1):
        self.window_s = window_s
        self.redraw_s = redraw_s
        self.enabled = display_available()
        self._data: deque[tuple[float, tuple[float, ...]]] = deque()
        self._last_draw = 0.0
        self._fig: Any = None
        if self.enabled:
            import matplotlib.pyplot as plt

            plt.ion()
            self._fig, axes = plt.subplots(2, 1, sharex=True, figsize=(6, 4))
            self._lines = [axes[0].plot([], [], label=n)[0] for n in ("Fx", "Fy", "Fz")]
            self._lines += [axes[1].plot([], [], label=n)[0] for n in ("Tx", "Ty", "Tz")]
            axes[0].set_ylabel("force (N)")
            axes[1].set_ylabel("torque (N m)")
            axes[1].set_xlabel("time (s)")
            for ax in axes:
                ax.legend(loc="upper left", fontsize="small")
            self._axes = axes

    def emit(self, record: WrenchRecord) -> None:
        """Add a record (records without a wrench are skipped)."""
        if not self.enabled or record.force is None or record.torque is None:
            return
        self._data.append((record.stamp, tuple(record.force) + tuple(record.torque)))
        while self._data and self._data[-1][0] - self._data[0][0] > self.window_s:
            self._data.popleft()
        now = time.monotonic()
        if now - self._last_draw < self.redraw_s:
            return
        self._last_draw = now
        t = np.array([d[0] for d in self._data]) - self._data[-1][0]
        values = np.array([d[1] for d in self._data])
        for k, line in enumerate(self._lines):
            line.set_data(t, values[:, k])
        for ax in self._axes:
            ax.relim()
            ax.autoscale_view()
        self._fig.canvas.draw_idle()
        self._fig.canvas.flush_events()

    def close(self) -> None:
        if self._fig is not None:
            import matplotlib.pyplot as plt

            plt.close(self._fig)
            self._fig = None
            self.enabled = False
