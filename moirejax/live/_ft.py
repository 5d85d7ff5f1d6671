"""A reference force/torque sensor read beside the camera, for capturing calibration sessions.

The paper calibrates a unit against a commercial six-axis F/T sensor recorded at the same
time as the camera. [`RecordingSink`][] writes the camera's frames with their capture
times; given a force/torque source it also writes the F/T readings, each with its time, to
`ft.csv` in the same folder, the log that `moirejax import --ft FOLDER/ft.csv --align`
aligns to the frames (the clock offset estimated from the data, so a driver on its own
clock works too).

Two sources, behind one interface ([`AbstractForceTorqueSource`][]):

- [`UdpForceTorqueSource`][]: datagrams of text lines from any driver or bridge
  (a ROS 2 node, a vendor SDK script, a Bota or rokubimini driver): `t,fx,fy,fz,tx,ty,tz`,
  `fx,fy,fz,tx,ty,tz` (stamped on arrival) or a JSON object with `t` (optional) and
  `wrench` or `force` and `torque`.
- [`NetFTSource`][]: an ATI Net F/T box, through its raw data transfer protocol (RDT: UDP
  port 49152, one 36-byte sample per datagram). The protocol is two fixed-size structs,
  so the adapter speaks it directly rather than through a compiled client. Readings are
  stamped on arrival (RDT carries no time).

Readings are wrenches in N and N·m in moirejax's convention
([`WRENCH_CONVENTION`][moirejax.WRENCH_CONVENTION]); a sensor mounted another way is
mapped by `to_sensor`, a 6 × 6 matrix applied to each reading (for a rotation R of the F/T
frame into the sensor's, `[[R, 0], [0, R]]`, with the lever arm's cross product in the
lower-left block when the origins differ). A malformed datagram or a faulted sample is
counted in `stats`, never raised: the camera must not stop because the F/T stream
hiccups.
"""

import abc
import json
import logging
import math
import os
import re
import socket
import struct
import threading
import time
import urllib.request
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from .._conventions import WRENCH_AXES
from .._fileio import OutputError


logger = logging.getLogger("moirejax.live")

ReadingCallback = Callable[[float, np.ndarray], None]
"""Receives each reading: its time (s) and its wrench (6 values, N and N·m)."""

# The ATI Net F/T raw data transfer protocol: a request of header, command and sample
# count, and samples of three counters and six counts, all big-endian.
RDT_PORT = 49152
_RDT_HEADER = 0x1234
_RDT_STOP, _RDT_STREAM, _RDT_BIAS = 0x0000, 0x0002, 0x0042
_RDT_REQUEST = struct.Struct(">HHI")
_RDT_SAMPLE = struct.Struct(">III6i")


class AbstractForceTorqueSource(abc.ABC):
    """A force/torque sensor read on a thread of its own.

    [`start`][AbstractForceTorqueSource.start] begins delivering readings to a callback,
    [`close`][AbstractForceTorqueSource.close] stops and joins; `stats` counts `readings`
    and whatever was dropped (`malformed`, `faults`, `callback_errors`).
    """

    def __init__(self, to_sensor: npt.ArrayLike | None = None, clock: Callable[[], float] = time.time):
        matrix = np.eye(6) if to_sensor is None else np.asarray(to_sensor, np.float64)
        if matrix.shape != (6, 6) or not np.all(np.isfinite(matrix)):
            raise ValueError(f"to_sensor must be a finite 6 x 6 matrix, got shape {matrix.shape}")
        self.to_sensor = matrix
        self.clock = clock
        self.stats: dict[str, int] = {"readings": 0, "malformed": 0, "faults": 0, "callback_errors": 0}
        self._deliver: ReadingCallback | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, deliver: ReadingCallback) -> None:
        """Deliver every reading to `deliver(t, wrench)` from the source's thread."""
        if self._thread is not None:
            raise RuntimeError(f"{type(self).__name__} is already started")
        self._deliver = deliver
        self._open()
        self._thread = threading.Thread(target=self._loop, name=f"moirejax-{type(self).__name__}", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 5.0) -> None:
        """Stop reading; the callback gets nothing after this returns."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        self._shut()

    def _emit(self, t: float, wrench: np.ndarray) -> None:
        if not math.isfinite(t) or wrench.shape != (6,) or not np.all(np.isfinite(wrench)):
            self.stats["malformed"] += 1
            return
        self.stats["readings"] += 1
        assert self._deliver is not None
        try:
            self._deliver(t, self.to_sensor @ wrench)
        except Exception as e:  # a failing consumer must not stop the reader
            self.stats["callback_errors"] += 1
            if self.stats["callback_errors"] == 1:
                logger.warning("force/torque callback failed (%s); further failures are only counted", e)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._read()
            except TimeoutError:
                continue
            except OSError as e:
                if self._stop.is_set():
                    return
                self.stats["faults"] += 1
                logger.warning("%s: %s", type(self).__name__, e)
                time.sleep(0.05)

    @abc.abstractmethod
    def _open(self) -> None:
        """Open the connection (called by `start`, before the thread)."""

    @abc.abstractmethod
    def _read(self) -> None:
        """Wait for the next datagram (at most the socket's timeout) and emit its readings."""

    @abc.abstractmethod
    def _shut(self) -> None:
        """Release the connection."""


def _parse_line(line: str) -> tuple[float | None, np.ndarray] | None:
    """`(t or None, wrench)` of one text line, or None when it is not a reading."""
    line = line.strip()
    if not line:
        return None
    if line.startswith("{"):
        obj = json.loads(line)
        if "wrench" in obj:
            wrench = np.asarray(obj["wrench"], np.float64)
        else:
            wrench = np.concatenate([np.asarray(obj["force"], np.float64), np.asarray(obj["torque"], np.float64)])
        t = obj.get("t")
        return (None if t is None else float(t)), wrench.reshape(-1)
    values = [float(v) for v in re.split(r"[,\s]+", line)]
    if len(values) == 7:
        return values[0], np.asarray(values[1:], np.float64)
    if len(values) == 6:
        return None, np.asarray(values, np.float64)
    raise ValueError(f"{len(values)} numbers, expected 6 or 7")


class UdpForceTorqueSource(AbstractForceTorqueSource):
    """Readings sent as UDP datagrams of text lines (see the module docstring).

    A line with seven numbers is `t,fx,fy,fz,tx,ty,tz` with `t` in seconds on the sender's
    clock (any origin: `import --align` finds the offset); six numbers are stamped on
    arrival with the host's wall clock, the clock of the frames' capture stamps.

    **Arguments:**

    - `host`, `port`: where to listen (`port=0` picks a free port: see `address`).
    - `to_sensor`: 6 × 6 map of each reading into the sensor's convention (default identity).
    """

    def __init__(self, host: str = "0.0.0.0", port: int = 0, *, to_sensor: npt.ArrayLike | None = None, **kwargs):
        super().__init__(to_sensor, **kwargs)
        if not 0 <= port <= 65535:
            raise ValueError(f"port must be 0 to 65535, got {port}")
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._socket.bind((host, port))
        except OSError as e:
            self._socket.close()
            raise OSError(f"udp://{host}:{port}: cannot listen for force/torque readings ({e.strerror or e})") from e
        self._socket.settimeout(0.1)
        self.address: tuple[str, int] = self._socket.getsockname()

    def _open(self) -> None:
        pass

    def _read(self) -> None:
        data, _ = self._socket.recvfrom(65536)
        arrival = self.clock()
        for line in data.decode("utf-8", "replace").splitlines():
            try:
                reading = _parse_line(line)
            except (ValueError, KeyError, TypeError):
                self.stats["malformed"] += 1
                continue
            if reading is not None:
                t, wrench = reading
                self._emit(arrival if t is None else t, wrench)

    def _shut(self) -> None:
        self._socket.close()


def netft_counts(host: str, timeout: float = 2.0) -> tuple[float, float]:
    """The counts per N and per N·m of an ATI Net F/T box, read from its configuration
    page (`http://HOST/netftapi2.xml`, fields `cfgcpf` and `cfgcpt`)."""
    url = f"http://{host}/netftapi2.xml"
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            text = response.read().decode("utf-8", "replace")
    except OSError as e:
        raise OSError(
            f"{url}: cannot read the Net F/T's counts per unit ({e}); pass counts_per_force and "
            "counts_per_torque from its configuration page"
        ) from e
    counts = []
    for field in ("cfgcpf", "cfgcpt"):
        match = re.search(rf"<{field}>\s*([0-9.eE+-]+)\s*</{field}>", text)
        if match is None:
            raise ValueError(f"{url}: no <{field}> field; pass counts_per_force and counts_per_torque")
        counts.append(float(match.group(1)))
    return counts[0], counts[1]


class NetFTSource(AbstractForceTorqueSource):
    """An ATI Net F/T box streaming over RDT (UDP), each sample stamped on arrival.

    A sample whose status word is non-zero (a saturated gauge, a fault the box reports) is
    counted in `stats["faults"]` and dropped.

    **Arguments:**

    - `host`: the box's address; `port`: its RDT port (49152).
    - `counts_per_force`, `counts_per_torque`: the box's scale (counts per N and per N·m);
        default: read from its configuration page ([`netft_counts`][]).
    - `bias`: ask the box to zero its readings before streaming (do it unloaded).
    - `to_sensor`: 6 × 6 map of each reading into the sensor's convention (default identity).
    """

    def __init__(
        self,
        host: str,
        port: int = RDT_PORT,
        *,
        counts_per_force: float | None = None,
        counts_per_torque: float | None = None,
        bias: bool = False,
        to_sensor: npt.ArrayLike | None = None,
        **kwargs,
    ):
        super().__init__(to_sensor, **kwargs)
        if (counts_per_force is None) != (counts_per_torque is None):
            raise ValueError("give both counts_per_force and counts_per_torque, or neither")
        if counts_per_force is None or counts_per_torque is None:
            counts_per_force, counts_per_torque = netft_counts(host)
        if not (counts_per_force > 0 and counts_per_torque > 0):
            raise ValueError(f"counts per unit must be positive, got {counts_per_force}, {counts_per_torque}")
        self.host, self.port, self.bias = host, port, bias
        self._scale = np.array([counts_per_force] * 3 + [counts_per_torque] * 3, np.float64)
        self._socket: socket.socket | None = None

    def _send(self, command: int) -> None:
        assert self._socket is not None
        self._socket.send(_RDT_REQUEST.pack(_RDT_HEADER, command, 0))

    def _open(self) -> None:
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._socket.settimeout(0.1)
        self._socket.connect((self.host, self.port))
        if self.bias:
            self._send(_RDT_BIAS)
        self._send(_RDT_STREAM)

    def _read(self) -> None:
        assert self._socket is not None
        data = self._socket.recv(1024)
        arrival = self.clock()
        if len(data) != _RDT_SAMPLE.size:
            self.stats["malformed"] += 1
            return
        _, _, status, *counts = _RDT_SAMPLE.unpack(data)
        if status != 0:
            self.stats["faults"] += 1
            return
        self._emit(arrival, np.asarray(counts, np.float64) / self._scale)

    def _shut(self) -> None:
        if self._socket is not None:
            try:
                self._send(_RDT_STOP)
            except OSError:
                pass
            self._socket.close()
            self._socket = None


def open_ft_source(spec: str) -> AbstractForceTorqueSource:
    """The force/torque source of a command line's `--ft`: `udp://HOST:PORT` listens for
    text readings, `netft://HOST` (optionally `netft://HOST?cpf=N&cpt=N`) reads an ATI Net
    F/T box."""
    match = re.fullmatch(r"udp://([^:/]*):(\d+)", spec)
    if match:
        return UdpForceTorqueSource(match.group(1) or "0.0.0.0", int(match.group(2)))
    match = re.fullmatch(r"netft://([^:/?]+)(?::(\d+))?(?:\?cpf=([0-9.eE+-]+)&cpt=([0-9.eE+-]+))?", spec)
    if match:
        host, port, cpf, cpt = match.groups()
        counts: dict[str, Any] = {}
        if cpf is not None:
            counts = {"counts_per_force": float(cpf), "counts_per_torque": float(cpt)}
        return NetFTSource(host, int(port) if port else RDT_PORT, **counts)
    raise ValueError(f"{spec!r} is not a force/torque source: give udp://HOST:PORT or netft://HOST[?cpf=N&cpt=N]")


class ForceTorqueLog:
    """A force/torque source's readings written to a CSV that `moirejax import --ft` reads:
    a header `t,fx,fy,fz,tx,ty,tz`, then one reading per line.

    Readings arrive on the source's thread and are appended in whole lines every
    `flush_every` seconds and at [`close`][ForceTorqueLog.close], so an interrupted session
    keeps what was flushed. Readings whose time does not follow the previous one (a
    sender's clock stepping back) are counted in `stats["out_of_order"]` and left out, as
    the log's reader needs increasing times.
    """

    def __init__(self, path: str | os.PathLike, source: AbstractForceTorqueSource, *, flush_every: float = 0.25):
        self.path = os.fspath(path)
        self.source = source
        self.flush_every = float(flush_every)
        self.stats: dict[str, int] = {"written": 0, "out_of_order": 0, "errors": 0}
        try:
            self._file = open(self.path, "x", encoding="utf-8", newline="")
        except OSError as e:
            raise OutputError(f"{self.path}: cannot be written ({e.strerror or e})") from e
        self._file.write("t," + ",".join(WRENCH_AXES) + "\n")
        self._file.flush()
        self._lock = threading.Lock()
        self._lines: list[str] = []
        self._last_t = -math.inf
        self._last_flush = time.monotonic()
        self._closed = False
        source.start(self._append)

    def _append(self, t: float, wrench: np.ndarray) -> None:
        with self._lock:
            if self._closed:
                return
            if not t > self._last_t:
                self.stats["out_of_order"] += 1
                return
            self._last_t = t
            self._lines.append(f"{t!r}," + ",".join(repr(float(v)) for v in wrench) + "\n")
            if time.monotonic() - self._last_flush >= self.flush_every:
                self._flush()

    def _flush(self) -> None:
        if self._lines:
            try:
                self._file.write("".join(self._lines))
                self._file.flush()
                self.stats["written"] += len(self._lines)
            except OSError as e:
                self.stats["errors"] += len(self._lines)
                logger.warning("%s: force/torque readings not written (%s)", self.path, e)
            self._lines.clear()
        self._last_flush = time.monotonic()

    def close(self) -> None:
        """Stop the source and write what is left."""
        self.source.close()
        with self._lock:
            if not self._closed:
                self._closed = True
                self._flush()
                self._file.close()
