"""Frame sources for the live pipeline: cameras and streams, video files, image folders, callables.

Every source runs one capture thread and hands out [`Frame`][]s and [`SourceEvent`][]s
through `get()` or iteration. Live sources (cameras, URLs, GStreamer pipelines) use a
one-slot buffer that the newest frame overwrites, so a slow consumer always gets the
latest frame and the skipped ones are counted in `dropped`; nothing queues up. Files and
folders are delivered in order, every frame, with the capture thread waiting for the
consumer. A live source that stops delivering frames is reopened with exponential
backoff a bounded number of times; undecodable frames become `"corrupt_frame"` events,
never exceptions. The last item of every stream is a final event saying why it ended.

It is one module because most of its length is the capture thread, buffer and reconnect
logic of `AbstractFrameSource` that every source shares.
"""

import abc
import collections
import dataclasses
import math
import os
import re
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..data import IMAGE_SUFFIXES
from ._types import Real


# Status codes of source events.
CORRUPT_FRAME = "corrupt_frame"
RECONNECTING = "reconnecting"
RECONNECTED = "reconnected"
END_OF_STREAM = "end_of_stream"
TRUNCATED = "truncated"
SOURCE_LOST = "source_lost"
OPEN_FAILED = "open_failed"
SOURCE_ERROR = "source_error"
CLOSED = "closed"


# Events pile up only if the consumer stalls while a live source keeps failing; past this
# many pending events the oldest are discarded (and counted) so memory stays bounded.
_MAX_PENDING_EVENTS = 64


@dataclasses.dataclass(frozen=True)
class Frame:
    """One captured frame.

    **Fields:**

    - `index`: position of the frame in the source (0-based; files and folders count
        every frame, corrupt ones included, so the index names the file/frame).
    - `stamp`: `time.monotonic()` right after the grab (s).
    - `gray`: float32 grayscale in [0, 1], shape `(h, w)`.
    - `color`: the uint8 BGR frame `(h, w, 3)` when the source delivers colour, else `None`.
    """

    index: int
    stamp: float
    gray: np.ndarray
    color: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class SourceEvent:
    """Something that happened to the source instead of a frame.

    **Fields:**

    - `index`: index of the frame the event concerns (or of the next frame expected).
    - `stamp`: `time.monotonic()` when it happened (s).
    - `status`: a status code (`"corrupt_frame"`, `"reconnecting"`, `"reconnected"`,
        `"end_of_stream"`, `"truncated"`, `"source_lost"`, `"open_failed"`,
        `"source_error"`, `"closed"`).
    - `message`: human-readable detail.
    - `final`: `True` for the last item of the stream.
    """

    index: int
    stamp: float
    status: str
    message: str
    final: bool = False


@dataclasses.dataclass(frozen=True)
class Reconnect:
    """Exponential backoff for reopening a live source that stopped delivering frames.

    Attempt `n` (1-based) waits `min(initial_delay_s * factor**(n-1), max_delay_s)`;
    after `max_attempts` consecutive failures the stream ends with `"source_lost"`.
    The count resets at the first good frame.
    """

    max_attempts: int = 5
    initial_delay_s: Real = 0.1
    max_delay_s: Real = 2.0
    factor: Real = 2.0

    def __post_init__(self):
        if self.max_attempts < 0 or self.initial_delay_s < 0 or self.factor < 1:
            raise ValueError(f"invalid reconnection policy {self}")

    def delay(self, attempt: int) -> float:
        """Seconds to wait before reconnection attempt `attempt` (1-based)."""
        return min(self.initial_delay_s * self.factor ** (attempt - 1), self.max_delay_s)


class CorruptFrameError(Exception):
    """Raised by a source's `_read` for a frame that cannot be decoded."""


class EndOfStreamError(Exception):
    """Raised by a source's `_read` when a finite source has no more frames."""

    def __init__(self, status: str = END_OF_STREAM, message: str = "end of stream"):
        super().__init__(message)
        self.status = status
        self.message = message


def to_frame(image: Any, index: int, stamp: Real) -> Frame:
    """Convert a decoded image (gray or BGR/BGRA; uint8, uint16, bool or float in [0, 1]).

    **Raises:** `CorruptFrameError` for empty, non-finite or unsupported arrays.
    """
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.size == 0 or not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] in (3, 4))):
        raise CorruptFrameError(f"frame {index}: unsupported shape {arr.shape}")
    if arr.dtype == np.uint8:
        unit = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        unit = arr.astype(np.float32) / 65535.0
    elif arr.dtype == np.bool_:
        unit = arr.astype(np.float32)
    elif np.issubdtype(arr.dtype, np.floating):
        unit = arr.astype(np.float32)
        if not np.all(np.isfinite(unit)):
            raise CorruptFrameError(f"frame {index}: non-finite pixel values")
        unit = np.clip(unit, 0.0, 1.0)
    else:
        raise CorruptFrameError(f"frame {index}: unsupported dtype {arr.dtype}")
    if unit.ndim == 2:
        return Frame(index, float(stamp), np.ascontiguousarray(unit), None)
    bgr = np.ascontiguousarray(unit[..., :3])
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    if arr.dtype == np.uint8:
        color = np.ascontiguousarray(arr[..., :3])
    else:
        color = (bgr * 255.0 + 0.5).astype(np.uint8)
    return Frame(index, float(stamp), gray, color)


class AbstractFrameSource(abc.ABC):
    """A frame source with a capture thread. Subclasses implement `_open`, `_read`, `_release`.

    Use as a context manager (`with source:`) or call `start()` / `close()`; iterate to
    get [`Frame`][]s and [`SourceEvent`][]s until the final event, or poll `get(timeout)`.

    **Arguments (common to all sources):**

    - `latest`: `True` for latest-frame delivery (one overwritten slot, drops counted),
        `False` for in-order delivery of every frame; `None` picks latest-frame for live
        sources and in-order for files.
    - `reconnect`: the [`Reconnect`][] policy for live sources.
    - `queue_size`: how many frames the in-order mode may read ahead.
    """

    live: bool = False

    def __init__(self, *, latest: bool | None = None, reconnect: Reconnect = Reconnect(), queue_size: int = 4):
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self._latest_arg = latest
        self.reconnect = reconnect
        self._queue_size = queue_size
        self._items: collections.deque[Frame | SourceEvent] = collections.deque()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._finished = False  # the final event has been queued
        self._exhausted = False  # the final event has been handed out
        self._dropped = 0
        self._events_dropped = 0
        self._delivered = 0

    # -- subclass interface -------------------------------------------------------------

    @abc.abstractmethod
    def _open(self) -> None:
        """Open the underlying device/file; raise `OSError` if it cannot be opened."""

    @abc.abstractmethod
    def _read(self, index: int) -> tuple[Any, float] | None:
        """Return `(image, grab_stamp)`, or `None` when a live source has no frame.

        Raise `CorruptFrameError` for an undecodable frame and `EndOfStreamError` at the end.
        """

    @abc.abstractmethod
    def _release(self) -> None:
        """Release the underlying device/file (called from the capture thread)."""

    # -- public interface ---------------------------------------------------------------

    @property
    def latest(self) -> bool:
        """Whether this source delivers the latest frame only (see the class docstring)."""
        return self.live if self._latest_arg is None else self._latest_arg

    @property
    def dropped(self) -> int:
        """Frames overwritten in the one-slot buffer before the consumer took them."""
        return self._dropped

    @property
    def events_dropped(self) -> int:
        """Events discarded because more than 64 were pending (consumer stalled)."""
        return self._events_dropped

    @property
    def delivered(self) -> int:
        """Frames handed to the consumer so far."""
        return self._delivered

    def start(self) -> "AbstractFrameSource":
        """Start the capture thread (idempotent). Returns `self`."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"{type(self).__name__}-capture", daemon=True)
            self._thread.start()
        return self

    def get(self, timeout: Real | None = None) -> Frame | SourceEvent | None:
        """The next frame or event; `None` on timeout or once the final event was handed out."""
        self.start()
        with self._cond:
            if not self._cond.wait_for(lambda: self._items or self._exhausted, timeout):
                return None
            if not self._items:
                return None
            item = self._items.popleft()
            self._cond.notify_all()
            if isinstance(item, Frame):
                self._delivered += 1
            elif item.final:
                self._exhausted = True
            return item

    def __iter__(self) -> Iterator[Frame | SourceEvent]:
        while True:
            item = self.get(timeout=None)
            if item is None:
                return
            yield item
            if isinstance(item, SourceEvent) and item.final:
                return

    def close(self, timeout: Real = 2.0) -> None:
        """Stop the capture thread and release the source.

        A thread blocked inside a driver call is abandoned after `timeout` seconds (it is
        a daemon thread and releases the source when the call returns).
        """
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def __enter__(self) -> "AbstractFrameSource":
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- capture thread -----------------------------------------------------------------

    def _put(self, item: Frame | SourceEvent) -> None:
        with self._cond:
            if isinstance(item, SourceEvent) and item.final:
                # Always accepted, even over a full queue, so a consumer never waits forever.
                self._items.append(item)
                self._finished = True
            elif isinstance(item, Frame) and self.latest:
                for pending in [x for x in self._items if isinstance(x, Frame)]:
                    self._items.remove(pending)
                    self._dropped += 1
                self._items.append(item)
            else:
                if self.latest:
                    while sum(isinstance(x, SourceEvent) for x in self._items) >= _MAX_PENDING_EVENTS:
                        oldest = next(x for x in self._items if isinstance(x, SourceEvent))
                        self._items.remove(oldest)
                        self._events_dropped += 1
                else:
                    self._cond.wait_for(lambda: len(self._items) < self._queue_size or self._stop.is_set())
                    if self._stop.is_set():
                        return
                self._items.append(item)
            self._cond.notify_all()

    def _event(self, index: int, status: str, message: str, final: bool = False) -> None:
        self._put(SourceEvent(index, time.monotonic(), status, message, final))

    def _backoff(self, index: int, failures: int, reason: str) -> bool:
        """Announce and wait for a reconnection attempt; `False` when attempts are exhausted."""
        policy = self.reconnect
        if failures > policy.max_attempts:
            self._event(
                index, SOURCE_LOST, f"gave up after {policy.max_attempts} reconnection attempts: {reason}", True
            )
            return False
        delay = policy.delay(failures)
        self._event(index, RECONNECTING, f"attempt {failures}/{policy.max_attempts} in {delay:.3g} s: {reason}")
        return not self._stop.wait(delay)

    def _run(self) -> None:
        index = 0
        failures = 0  # consecutive failures since the last good frame
        is_open = False
        try:
            while not self._stop.is_set():
                if not is_open:
                    try:
                        self._open()
                        is_open = True
                    except OSError as e:
                        if not self.live:
                            self._event(index, OPEN_FAILED, str(e), True)
                            return
                        failures += 1
                        if not self._backoff(index, failures, f"cannot open: {e}"):
                            return
                        continue
                try:
                    got = self._read(index)
                except EndOfStreamError as e:
                    self._event(index, e.status, e.message, True)
                    return
                except CorruptFrameError as e:
                    self._event(index, CORRUPT_FRAME, str(e))
                    index += 1
                    continue
                if got is None:
                    self._release()
                    is_open = False
                    failures += 1
                    if not self._backoff(index, failures, "no frame from source"):
                        return
                    continue
                try:
                    frame = to_frame(got[0], index, got[1])
                except CorruptFrameError as e:
                    self._event(index, CORRUPT_FRAME, str(e))
                    index += 1
                    continue
                if failures:
                    self._event(index, RECONNECTED, f"frames again after {failures} failed attempt(s)")
                    failures = 0
                self._put(frame)
                index += 1
        except Exception as e:  # a driver or callback bug must end the stream, not hang the consumer
            self._event(index, SOURCE_ERROR, f"{type(e).__name__}: {e}", True)
        finally:
            if is_open:
                try:
                    self._release()
                except Exception:
                    pass
            if not self._finished:
                self._event(index, CLOSED, "source closed", True)


def _is_device(spec: int | str) -> bool:
    return isinstance(spec, int) or (isinstance(spec, str) and spec.isdigit())


class VideoSource(AbstractFrameSource):
    """An OpenCV `VideoCapture`: camera index, video file, stream URL or GStreamer pipeline.

    **Arguments:**

    - `spec`: a device index (`0` or `"0"`), a file path, a URL (`rtsp://...`), or a
        GStreamer pipeline string (contains `!`; ends in `appsink`).
    - `api`: OpenCV capture API (`cv2.CAP_*`); default chooses automatically
        (`cv2.CAP_GSTREAMER` for pipeline strings).
    - `live`: whether the source is live; default: devices, URLs and pipelines are live,
        files are not. A live source that stops delivering frames is reconnected; a file
        that stops ends the stream (`"truncated"` if it ended before its frame count).
    - `properties`: `cv2.CAP_PROP_*` values to set after opening (e.g. frame size, fps).
    - `timeout_ms`: open/read timeout passed to backends that honour it (FFmpeg).
    - `replay_fps`: deliver a file's frames at this rate, as a camera would (each frame
        grabbed at its due time, latest-frame delivery unless `latest` says otherwise):
        to replay a recording in real time and measure latency as a camera would see it.
    - `latest`, `reconnect`, `queue_size`: see [`AbstractFrameSource`][].
    """

    def __init__(
        self,
        spec: int | str | os.PathLike,
        *,
        api: int | None = None,
        live: bool | None = None,
        properties: Mapping[int, Real] | None = None,
        timeout_ms: int = 5000,
        replay_fps: Real | None = None,
        latest: bool | None = None,
        reconnect: Reconnect = Reconnect(),
        queue_size: int = 4,
    ):
        if replay_fps is not None and not replay_fps > 0:
            raise ValueError(f"replay_fps must be positive, got {replay_fps}")
        if replay_fps is not None and latest is None:
            latest = True
        super().__init__(latest=latest, reconnect=reconnect, queue_size=queue_size)
        self.replay_fps = replay_fps
        self._started_at: float | None = None
        if isinstance(spec, os.PathLike):
            spec = os.fspath(spec)
        self.spec: int | str = int(spec) if _is_device(spec) else spec
        is_pipeline = isinstance(self.spec, str) and "!" in self.spec
        if api is None:
            api = cv2.CAP_GSTREAMER if is_pipeline else cv2.CAP_ANY
        self.api = api
        if live is None:
            live = _is_device(self.spec) or is_pipeline or "://" in str(self.spec)
        self.live = live
        self.properties = dict(properties or {})
        self.timeout_ms = timeout_ms
        self._cap: Any = None
        self._frame_count = 0

    def _open(self) -> None:
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, self.timeout_ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, self.timeout_ms]
        cap = cv2.VideoCapture(self.spec, self.api, params)
        if not cap.isOpened():
            cap.release()
            raise OSError(f"cv2.VideoCapture cannot open {self.spec!r}")
        for prop, value in self.properties.items():
            cap.set(prop, value)
        self._cap = cap
        count = cap.get(cv2.CAP_PROP_FRAME_COUNT)
        self._frame_count = int(count) if math.isfinite(count) and count > 0 else 0
        self._started_at = None

    def _read(self, index: int) -> tuple[Any, float] | None:
        # A replay's clock starts at the first frame's grab, as a camera's does: anchored at
        # the open instead, a slow first decode makes the next frames overdue and bunched.
        if self.replay_fps is not None and self._started_at is not None:
            due = self._started_at + index / float(self.replay_fps)
            if (wait := due - time.monotonic()) > 0:
                self._stop.wait(wait)
        if not self._cap.grab():
            if self.live:
                return None
            position = int(self._cap.get(cv2.CAP_PROP_POS_FRAMES))
            if self._frame_count and position < self._frame_count:
                raise EndOfStreamError(
                    TRUNCATED, f"{self.spec}: stream ended at frame {position} of {self._frame_count}"
                )
            raise EndOfStreamError(END_OF_STREAM, f"{self.spec}: end of video after {index} frames")
        stamp = time.monotonic()
        if self._started_at is None:
            self._started_at = stamp - index / float(self.replay_fps or 1.0)
        ok, image = self._cap.retrieve()
        if not ok or image is None:
            raise CorruptFrameError(f"{self.spec}: frame {index} could not be decoded")
        return image, stamp

    def _release(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def _natural_key(path: Path) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


class FolderSource(AbstractFrameSource):
    """Image files in a folder, in natural sort order (`frame2` before `frame10`), delivered in order.

    Files that cannot be decoded become `"corrupt_frame"` events naming the file.

    **Arguments:**

    - `folder`: the directory.
    - `suffixes`: file suffixes to include (case-insensitive).
    - `latest`, `queue_size`: see [`AbstractFrameSource`][].
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        *,
        suffixes: tuple[str, ...] = IMAGE_SUFFIXES,
        latest: bool | None = None,
        queue_size: int = 4,
    ):
        super().__init__(latest=latest, queue_size=queue_size)
        self.folder = Path(folder)
        self.suffixes = tuple(s.lower() for s in suffixes)
        self.files: list[Path] = []

    def _open(self) -> None:
        if not self.folder.is_dir():
            raise OSError(f"{self.folder}: not a directory")
        files = [p for p in self.folder.iterdir() if p.is_file() and p.suffix.lower() in self.suffixes]
        self.files = sorted(files, key=_natural_key)

    def _read(self, index: int) -> tuple[Any, float] | None:
        if index >= len(self.files):
            raise EndOfStreamError(END_OF_STREAM, f"{self.folder}: end of folder after {index} files")
        path = self.files[index]
        try:
            data = np.fromfile(path, dtype=np.uint8)
        except OSError as e:
            raise CorruptFrameError(f"{path}: cannot read ({e})") from None
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if image is None:
            raise CorruptFrameError(f"{path}: cannot decode image")
        return image, time.monotonic()

    def _release(self) -> None:
        pass


class CallableSource(AbstractFrameSource):
    """Frames from a function `fn(i) -> image or None` (e.g. a simulated sensor).

    `fn` may return a gray or BGR array (uint8, uint16, or float in [0, 1]; JAX arrays
    are converted). An exception from `fn` becomes a `"corrupt_frame"` event for that index.
    `None` ends a non-live source; for a live source it means "no frame available" and
    triggers reconnection with backoff (`fn` is called again with the same index).

    **Arguments:**

    - `fn`: the frame function.
    - `live`: whether to treat it as a live camera (latest-frame delivery, reconnection).
    - `latest`, `reconnect`, `queue_size`: see [`AbstractFrameSource`][].
    """

    def __init__(
        self,
        fn: Callable[[int], Any],
        *,
        live: bool = False,
        latest: bool | None = None,
        reconnect: Reconnect = Reconnect(),
        queue_size: int = 4,
    ):
        super().__init__(latest=latest, reconnect=reconnect, queue_size=queue_size)
        self.fn = fn
        self.live = live

    def _open(self) -> None:
        pass

    def _read(self, index: int) -> tuple[Any, float] | None:
        try:
            image = self.fn(index)
        except Exception as e:
            raise CorruptFrameError(f"frame {index}: {type(e).__name__}: {e}") from None
        stamp = time.monotonic()
        if image is None:
            if self.live:
                return None
            raise EndOfStreamError(END_OF_STREAM, f"end of stream after {index} frames")
        return image, stamp

    def _release(self) -> None:
        pass


# --------------------------------------------------------------------------- cameras by name

CAMERAS_EXTRA = "pip install 'moirejax[cameras]'"

# OpenCV's camera backends by their `cv2.CAP_*` id. One device reached through several
# backends (GStreamer and V4L2 on Linux, MSMF and DirectShow on Windows) is listed once,
# under the first of these that reports it: the backend OpenCV itself tries first for a
# camera index on that system.
_BACKEND_NAMES = {
    cv2.CAP_V4L2: "V4L2",
    cv2.CAP_MSMF: "MSMF",
    cv2.CAP_DSHOW: "DSHOW",
    cv2.CAP_AVFOUNDATION: "AVFOUNDATION",
    cv2.CAP_GSTREAMER: "GSTREAMER",
}
_PREFERRED_BACKENDS = tuple(_BACKEND_NAMES)

# Linux names each video device by links that survive a reboot and a change of USB port
# (`by-id`, which holds the serial number) or that name the port (`by-path`).
_PERSISTENT_LINK_FOLDERS = ("/dev/v4l/by-id", "/dev/v4l/by-path")


@dataclasses.dataclass(frozen=True)
class CameraDevice:
    """A camera as the system reports it, from [`list_cameras`][].

    **Fields:**

    - `index`: what `VideoSource`, `cv2.VideoCapture` and `moirejax live --source` take to
        open it: the backend's camera number plus OpenCV's id of the backend (`200` is
        V4L2's camera 0, `1400` Media Foundation's), so that the number names one
        device through one backend.
    - `name`: the device's name (`"HD Pro Webcam C920"`).
    - `backend`: the OpenCV backend it is opened through (`"V4L2"`, `"MSMF"`, ...).
    - `path`: the backend's device path: `/dev/videoN` on Linux, the device instance
        path (with the USB serial number) on Windows, the unique id on macOS; or `None`.
    - `usb_id`: `"VID:PID"` in hexadecimal when the device is on USB, else `None`.
    - `aliases`: other names of the device that survive a reboot, on Linux its
        `/dev/v4l/by-id` link (with the serial number) and `/dev/v4l/by-path` link.
    """

    index: int
    name: str
    backend: str
    path: str | None = None
    usb_id: str | None = None
    aliases: tuple[str, ...] = ()

    def describe(self) -> str:
        """One line naming the camera: `200 'HD Pro Webcam C920' (V4L2, /dev/video0)`."""
        where = ", ".join(x for x in (self.backend, self.path, self.usb_id) if x)
        return f"{self.index} {self.name!r} ({where})"


def _enumerate_cameras() -> list[Any]:
    """The cameras `cv2-enumerate-cameras` reports, through each backend it supports.

    Each item has `index` (the backend's camera number), `name`, `path`, `vid`, `pid`
    and `backend` (the `cv2.CAP_*` id).
    """
    try:
        import cv2_enumerate_cameras as enumeration  # pyright: ignore[reportMissingImports] (optional extra)
    except ImportError as e:
        raise ImportError(f"finding cameras by name needs the `cameras` extra: {CAMERAS_EXTRA}") from e
    found: list[Any] = []
    for backend in enumeration.supported_backends:
        try:
            found.extend(enumeration.enumerate_cameras(backend))
        except Exception:  # a backend without its driver or service lists no cameras
            continue
    return found


def _persistent_links(path: str | None) -> tuple[str, ...]:
    if not path or not path.startswith("/dev/"):
        return ()
    target = os.path.realpath(path)
    links = []
    for folder in _PERSISTENT_LINK_FOLDERS:
        try:
            names = sorted(os.listdir(folder))
        except OSError:
            continue
        links += [os.path.join(folder, n) for n in names if os.path.realpath(os.path.join(folder, n)) == target]
    return tuple(links)


def list_cameras() -> list[CameraDevice]:
    """The cameras attached to this computer, each once, in the order the system lists them.

    Found with the `cv2-enumerate-cameras` package (the `cameras` extra), which reports
    names, device paths and USB ids but not the resolutions and frame rates a camera
    offers: open it (`cv2.VideoCapture(camera.index)`) to ask for those.

    **Returns:** a list of [`CameraDevice`][].

    **Raises:** `ImportError` without the `cameras` extra, saying how to install it.
    """
    rank = {backend: k for k, backend in enumerate(_PREFERRED_BACKENDS)}
    chosen: dict[Any, Any] = {}
    for info in _enumerate_cameras():
        key = info.path or (info.name, info.index)
        held = chosen.get(key)
        if held is None or rank.get(info.backend, len(rank)) < rank.get(held.backend, len(rank)):
            chosen[key] = info
    cameras = []
    for info in chosen.values():
        backend = int(info.backend)
        name = _BACKEND_NAMES.get(backend) or cv2.videoio_registry.getBackendName(backend)
        usb = f"{info.vid:04X}:{info.pid:04X}" if info.vid is not None and info.pid is not None else None
        index = int(info.index) + (backend if backend != cv2.CAP_ANY else 0)
        cameras.append(CameraDevice(index, str(info.name), name, info.path, usb, _persistent_links(info.path)))
    return cameras


def find_camera(name: str, cameras: list[CameraDevice] | None = None) -> int:
    """The index of the one camera that `name` names, for `VideoSource` or `live --source`.

    Camera indices change when cameras are plugged in another order or the computer
    restarts; a camera's name, serial number and device path do not. A camera whose name
    is `name` (ignoring case) is chosen; otherwise one whose name, device path, USB id
    or persistent link (on Linux `/dev/v4l/by-id/...`, which holds the serial number)
    contains `name`.

    **Arguments:**

    - `name`: a camera name, or part of a name, serial number, path or `VID:PID`.
    - `cameras`: the cameras to choose from; default [`list_cameras`][].

    **Returns:** the camera's [`index`][moirejax.live.CameraDevice].

    **Raises:** `ValueError`, one line listing the cameras found, when no camera or several
    match; `ImportError` without the `cameras` extra.
    """
    cameras = list_cameras() if cameras is None else cameras
    wanted = name.strip().casefold()
    matches = [c for c in cameras if c.name.strip().casefold() == wanted]
    if not matches:
        matches = [
            c
            for c in cameras
            if any(wanted in field.casefold() for field in (c.name, c.path or "", c.usb_id or "", *c.aliases))
        ]
    if len(matches) == 1:
        return matches[0].index
    if not matches:
        found = "; ".join(c.describe() for c in cameras) if cameras else "none"
        raise ValueError(f"{name}: no camera's name, serial, path or USB id contains it; cameras found: {found}")
    listed = "; ".join(c.describe() for c in matches)
    raise ValueError(f"{name}: {len(matches)} cameras match: {listed}; give more of the name, the serial or path")
