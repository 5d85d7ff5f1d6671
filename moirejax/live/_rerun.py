"""The live stream in the Rerun viewer: frames, pressure maps, the wrench and the gate's mode.

Rerun is a viewer many robotics labs already keep open beside their robot. `rerun-sdk` is
an optional extra (`pip install "moirejax[viewer]"`), imported only when a [`RerunSink`][]
is made.
"""

import importlib
import os
from typing import Any

import numpy as np

from .._conventions import WRENCH_AXES
from ._sinks import _CountingSink, WrenchRecord


# The modes as numbers on a time series: vision 0, tactile 1.
_MODE_LEVEL = {"vision": 0.0, "tactile": 1.0}


class RerunSink(_CountingSink):
    """Log each record to Rerun: `{prefix}/wrench/{fx..tz}` (N, N·m) and `{prefix}/mode`
    (0 vision, 1 tactile) as time series, the status as a text log, and, where the pipeline
    hands them over, the frame (`{prefix}/frame`) and the pressure map (`{prefix}/pressure`,
    Pa). Every entry is on two timelines: `stamp` (the capture time) and `frame` (the index).

    **Arguments:**

    - `save`: write an `.rrd` file there, for the viewer to open later.
    - `connect`: stream to a running viewer at this address (`rerun+http://HOST:PORT/proxy`;
        `""` for Rerun's default, the viewer on this machine).
    - `spawn`: start a viewer and stream to it.
    - `prefix`: the entity path the sensor's data go under (one per sensor).
    - `application_id`: the recording's application name in the viewer.

    Exactly one of `save`, `connect` and `spawn` is given. Logging failures are counted in
    `stats["errors"]`; the stream goes on.
    """

    def __init__(
        self,
        *,
        save: str | os.PathLike | None = None,
        connect: str | None = None,
        spawn: bool = False,
        prefix: str = "moirejax",
        application_id: str = "moirejax",
    ):
        super().__init__()
        if sum((save is not None, connect is not None, spawn)) != 1:
            raise ValueError("give exactly one of save, connect and spawn")
        try:
            # Resolved at run time: the extra is optional, and type checkers need not have it.
            rr = importlib.import_module("rerun")
        except ImportError as e:
            raise ImportError('the Rerun sink needs rerun-sdk: pip install "moirejax[viewer]"') from e
        self._rr = rr
        self.prefix = prefix.strip("/")
        self._stream = rr.RecordingStream(application_id=application_id)
        if save is not None:
            self._stream.save(os.fspath(save))
        elif spawn:
            self._stream.spawn()
        else:
            self._stream.connect_grpc(connect or None)
        self._closed = False

    def _at(self, record: WrenchRecord) -> None:
        self._stream.set_time("stamp", timestamp=record.stamp)
        self._stream.set_time("frame", sequence=record.frame)

    def _log(self, path: str, entity: Any) -> None:
        self._stream.log(f"{self.prefix}/{path}", entity)

    def emit(self, record: WrenchRecord) -> None:
        if self._closed:
            self._failed("errors", ValueError("sink is closed"))
            return
        rr = self._rr
        try:
            self._at(record)
            wrench = record.wrench
            if wrench is not None:
                for axis, value in zip(WRENCH_AXES, np.asarray(wrench, np.float64)):
                    self._log(f"wrench/{axis}", rr.Scalars(float(value)))
            self._log("mode", rr.Scalars(_MODE_LEVEL.get(record.mode, float("nan"))))
            self._log("status", rr.TextLog(f"{record.status}: {record.message}" if record.message else record.status))
            self.stats["sent"] += 1
        except Exception as e:  # a viewer gone away must not stop the sensor loop
            self._failed("errors", e)

    def emit_image(self, image: np.ndarray, record: WrenchRecord) -> None:
        """Log the frame: gray, or BGR as the cameras deliver it (shown as RGB)."""

        def entity():
            arr = np.asarray(image)
            if arr.ndim == 3:
                arr = arr[..., 2::-1]  # BGR to RGB
            if arr.dtype != np.uint8:
                arr = (np.clip(arr.astype(np.float32), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
            return self._rr.Image(np.ascontiguousarray(arr))

        self._log_at(record, "frame", entity)

    def emit_pressure(self, pressure: np.ndarray, record: WrenchRecord) -> None:
        """Log the pressure map (Pa, the rectified image grid, row 0 at the top)."""
        self._log_at(
            record, "pressure", lambda: self._rr.Tensor(np.asarray(pressure, np.float32), dim_names=("row", "col"))
        )

    def _log_at(self, record: WrenchRecord, path: str, entity) -> None:
        """Log `entity()` at `path` on the record's timelines; a failure is counted."""
        if self._closed:
            return
        try:
            self._at(record)
            self._log(path, entity())
        except Exception as e:  # a viewer gone away must not stop the sensor loop
            self._failed("errors", e)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._stream.flush()
                self._stream.disconnect()
            except Exception as e:
                self._failed("errors", e)
