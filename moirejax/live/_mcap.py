"""A live-pipeline sink that records to MCAP with ROS 2 message encodings.

MCAP is the container `ros2 bag` records to by default and Foxglove opens directly. The
messages inside are serialised in CDR against ROS 2 message definitions that this module
carries as text, so a recording made here plays back in ROS 2 tools although neither ROS
nor its Python bindings are installed: only the `mcap` and `mcap-ros2-support` packages
(the `ros` extra).

Topics, under a prefix (default `/moirejax`):

| topic | type | when |
|---|---|---|
| `{prefix}/record` | `std_msgs/msg/String` | every record, holding its JSON line |
| `{prefix}/wrench` | `geometry_msgs/msg/WrenchStamped` | records that carry a finite wrench |
| `{prefix}/image` | `sensor_msgs/msg/CompressedImage` | `McapSink.emit_image` (JPEG or PNG) |
| `{prefix}/pressure` | `sensor_msgs/msg/Image` (`32FC1`, Pa) | `McapSink.emit_pressure` |

The JSON on `{prefix}/record` is the same line the other sinks send, so status records,
the covariance and the latency survive even though ROS has no message for them.

[`record_inversion`][] hands the same sink a recording that `moirejax invert` has already
inverted, so that an offline run gives the file a live run gives.

The file is written under a temporary name (`path + ".part"`) and moved onto `path` only
when the sink is closed. A run that is killed therefore never leaves a truncated file
at `path`; what it leaves is the `.part` file, whose complete chunks `mcap recover`
can salvage. A run that fails or is interrupted deletes it with
[`abort`][McapSink.abort].
"""

import math
import os
import threading
import time
from collections.abc import Callable, Collection, Iterator
from pathlib import Path
from typing import Any

import cv2
import jax
import numpy as np

from .._conventions import PA_PER_MPA, WRENCH_AXES, WRENCH_CONVENTION
from ..data import Dataset
from ..inverse import (
    check_source,
    map_grid,
    patch_tractions,
    patches_area_mm2,
    read_wrench_csv,
    row_number,
    row_patches,
    stack_patches,
)
from ..physics import Device
from ._records import LOAD_STATUSES, RecordStream
from ._run import PRESSURE_SHAPE
from ._sinks import _CountingSink, make_record, Sink, WrenchRecord
from ._types import Real


_SEPARATOR = "=" * 80 + "\n"


def _concat_msgdefs(main: str, *dependencies: tuple[str, str]) -> str:
    # A schema is the main definition followed by each type it uses, each introduced by a
    # separator line and a `MSG: pkg/Name` line: the layout rosbag2 writes and mcap_ros2 parses.
    parts = [main]
    for name, text in dependencies:
        parts.append(f"{_SEPARATOR}MSG: {name}\n{text}")
    return "".join(parts)


_TIME_MSG = "int32 sec\nuint32 nanosec\n"
_HEADER_MSG = "builtin_interfaces/Time stamp\nstring frame_id\n"
_VECTOR3_MSG = "float64 x\nfloat64 y\nfloat64 z\n"
_WRENCH_MSG = "geometry_msgs/Vector3 force\ngeometry_msgs/Vector3 torque\n"

STRING_MSGDEF = "string data\n"
"""ROS 2 definition of `std_msgs/msg/String`."""

WRENCH_STAMPED_MSGDEF = _concat_msgdefs(
    "std_msgs/Header header\ngeometry_msgs/Wrench wrench\n",
    ("std_msgs/Header", _HEADER_MSG),
    ("builtin_interfaces/Time", _TIME_MSG),
    ("geometry_msgs/Wrench", _WRENCH_MSG),
    ("geometry_msgs/Vector3", _VECTOR3_MSG),
)
"""ROS 2 definition of `geometry_msgs/msg/WrenchStamped`, with the types it uses appended."""

COMPRESSED_IMAGE_MSGDEF = _concat_msgdefs(
    "std_msgs/Header header\nstring format\nuint8[] data\n",
    ("std_msgs/Header", _HEADER_MSG),
    ("builtin_interfaces/Time", _TIME_MSG),
)
"""ROS 2 definition of `sensor_msgs/msg/CompressedImage`, with the types it uses appended."""

IMAGE_MSGDEF = _concat_msgdefs(
    "std_msgs/Header header\n"
    "uint32 height\n"
    "uint32 width\n"
    "string encoding\n"
    "uint8 is_bigendian\n"
    "uint32 step\n"
    "uint8[] data\n",
    ("std_msgs/Header", _HEADER_MSG),
    ("builtin_interfaces/Time", _TIME_MSG),
)
"""ROS 2 definition of `sensor_msgs/msg/Image`, with the types it uses appended."""

_MSGDEFS = {
    "std_msgs/msg/String": STRING_MSGDEF,
    "geometry_msgs/msg/WrenchStamped": WRENCH_STAMPED_MSGDEF,
    "sensor_msgs/msg/CompressedImage": COMPRESSED_IMAGE_MSGDEF,
    "sensor_msgs/msg/Image": IMAGE_MSGDEF,
}

_IMAGE_FORMATS = ("jpeg", "png")


def _stamp_ns(stamp: Any) -> int | None:
    """Unix seconds to integer nanoseconds, or None if the stamp is missing, not finite or negative."""
    try:
        seconds = float(stamp)
    except (TypeError, ValueError):
        return None
    if not math.isfinite(seconds) or seconds < 0:
        return None
    # Split before scaling: the whole seconds and the fraction are each exact in float64,
    # so the nanoseconds are the fraction's own rounding, not that of a 1e18-sized product.
    whole = math.floor(seconds)
    return whole * 1_000_000_000 + round((seconds - whole) * 1e9)


def _as_uint8(image: np.ndarray) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim == 3:
        arr = arr[..., :3]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
        raise ValueError(f"image must be (h, w) gray or (h, w, 3) BGR, got shape {np.shape(image)}")
    if arr.dtype != np.uint8:
        arr = (np.clip(np.nan_to_num(arr.astype(np.float32)), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(arr)


WRENCH_STATUSES = (*LOAD_STATUSES, "no_contact")
"""The statuses whose wrench an MCAP file publishes as a WrenchStamped: load estimates and
the zero of an untouched frame. The others (no wrench, or one the inversion does not
believe) are records with their status only."""


class McapSink(_CountingSink):
    """Records to an MCAP file with ROS 2 (CDR) messages, for Foxglove and `ros2 bag`.

    See the module docstring for the topics. A `WrenchStamped` carries the record's wrench
    in the project's convention (`docs/conventions.md`): forces in N and torques in N·m,
    x along the image columns to the right, y up the image (row 0 is the top), z into the
    sensor surface (pressing is +Fz), torques about the image centre on the contact
    surface. The convention is also stored word for word in the file's `moirejax`
    metadata record. Header stamps, and the MCAP log and publish times, are the record's
    `stamp` (its frame's grab time); a record without a usable stamp gets the time it is
    written.

    Like the other sinks, writing never raises: failures are counted in
    `stats["errors"]` and logged once. `stats["sent"]` counts records, `stats["images"]`
    and `stats["pressure_maps"]` the frames written by [`emit_image`][McapSink.emit_image]
    and [`emit_pressure`][McapSink.emit_pressure]. The methods may be called from
    different threads.

    The file only appears at `path` once [`close`][McapSink.close] has finished it; until
    then it is `path + ".part"`.

    **Arguments:**

    - `path`: the MCAP file to write (`.mcap`). An existing file there is replaced at
        close.
    - `topic_prefix`: namespace of the topics.
    - `images`: whether [`emit_image`][McapSink.emit_image] writes anything.
    - `image_format`: `"jpeg"` or `"png"` (lossless, larger).
    - `jpeg_quality`: 0 to 100.
    - `wrench_statuses`: the record statuses whose wrench goes on `{prefix}/wrench`
        (e.g. [`WRENCH_STATUSES`][moirejax.live.WRENCH_STATUSES], what `invert --mcap`
        publishes); default every record with a finite wrench. A record of another status
        is written on `{prefix}/record` only, so that a subscriber to the wrench never takes
        a frame the inversion did not believe (`"unexplained"`) for a reading.

    **Raises:** `ImportError` without the `ros` extra; `ValueError` for a bad option or a
    missing folder; `OSError` if the folder is not writable; `FileExistsError` if a
    `.part` file from an earlier run is in the way (recover or delete it first).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        topic_prefix: str = "/moirejax",
        images: bool = True,
        image_format: str = "jpeg",
        jpeg_quality: int = 90,
        wrench_statuses: Collection[str] | None = None,
    ):
        super().__init__()
        self.stats.update(images=0, pressure_maps=0)
        try:
            from mcap_ros2.writer import Writer
        except ImportError as e:
            raise ImportError("McapSink needs the `ros` extra: pip install 'moirejax[ros]'") from e
        if image_format not in _IMAGE_FORMATS:
            raise ValueError(f"image_format must be one of {_IMAGE_FORMATS}, got {image_format!r}")
        if not 0 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in [0, 100], got {jpeg_quality}")
        self.path = os.fspath(path)
        self.part_path = self.path + ".part"
        self.topic_prefix = "/" + topic_prefix.strip("/") if topic_prefix.strip("/") else ""
        self.images = images
        self.image_format = image_format
        self.jpeg_quality = int(jpeg_quality)
        self.wrench_statuses = None if wrench_statuses is None else frozenset(wrench_statuses)

        folder = os.path.dirname(os.path.abspath(self.path))
        if not os.path.isdir(folder):
            raise ValueError(f"cannot record to {self.path}: folder {folder} does not exist or is not a folder")
        if os.path.isdir(self.path):
            raise ValueError(f"cannot record to {self.path}: it is a directory")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError(f"cannot record to {self.path}: folder {folder} is not writable")
        try:
            # "x": never truncate a `.part` an interrupted run left behind, nor one another
            # sink is writing right now.
            self._stream: Any = open(self.part_path, "xb")
        except FileExistsError as e:
            raise FileExistsError(
                f"cannot record to {self.path}: {self.part_path} exists (left by an interrupted run? "
                "salvage it with `mcap recover` or delete it)"
            ) from e
        except OSError as e:
            raise OSError(f"cannot record to {self.path}: {e.strerror or e}") from e
        try:
            self._writer: Any = Writer(self._stream)
            self._writer.add_metadata("moirejax", {"wrench_convention": WRENCH_CONVENTION})
            # The magic, header and metadata on disk now: a `.part` is a recognisable MCAP
            # file from the start. Messages follow a chunk (1 MiB) at a time.
            self._stream.flush()
        except Exception:
            self._stream.close()
            os.remove(self.part_path)
            raise
        self._schemas: dict[str, Any] = {}
        self._lock = threading.Lock()

    # -- writing ----------------------------------------------------------------------

    def _write(self, topic: str, datatype: str, message: dict[str, Any], log_time: int) -> None:
        # Call with the lock held and the writer open.
        schema = self._schemas.get(datatype)
        if schema is None:
            schema = self._schemas[datatype] = self._writer.register_msgdef(datatype, _MSGDEFS[datatype])
        self._writer.write_message(self.topic_prefix + topic, schema, message, log_time=log_time, publish_time=log_time)

    def _header(self, record: WrenchRecord) -> tuple[dict[str, Any], int]:
        ns = _stamp_ns(record.stamp)
        if ns is None:
            ns = time.time_ns()
        sec, nanosec = divmod(ns, 1_000_000_000)
        return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": record.frame_id}, ns

    def _guarded(self, write: Callable[[], None]) -> None:
        """Run `write` under the lock; a closed sink or a failure is counted, never raised."""
        with self._lock:
            if self._writer is None:
                self._failed("errors", ValueError("sink is closed"))
                return
            try:
                write()
            except Exception as e:
                self._failed("errors", e)

    def emit(self, record: WrenchRecord) -> None:
        """Write a record: its JSON on `{prefix}/record`, its wrench (if any) on `{prefix}/wrench`.

        **Arguments:**

        - `record`: the record; a wrench is written when `force` and `torque` are both
            present and finite (and its status is one of `wrench_statuses`, if given).
        """

        def write() -> None:
            header, ns = self._header(record)
            self._write("/record", "std_msgs/msg/String", {"data": record.to_json()}, ns)
            believed = self.wrench_statuses is None or record.status in self.wrench_statuses
            if believed and record.force is not None and record.torque is not None:
                force = [float(v) for v in record.force]
                torque = [float(v) for v in record.torque]
                if all(math.isfinite(v) for v in force + torque):
                    wrench = {
                        "force": dict(zip("xyz", force)),
                        "torque": dict(zip("xyz", torque)),
                    }
                    self._write("/wrench", "geometry_msgs/msg/WrenchStamped", {"header": header, "wrench": wrench}, ns)
            self.stats["sent"] += 1

        self._guarded(write)

    def emit_image(self, image: np.ndarray, record: WrenchRecord) -> None:
        """Write a camera frame on `{prefix}/image` as JPEG or PNG (nothing if `images=False`).

        **Arguments:**

        - `image`: `(h, w)` gray or `(h, w, 3)` BGR, `uint8` or float in [0, 1].
        - `record`: the frame's record, for the stamp and frame id.
        """
        if not self.images:
            return

        def write() -> None:
            header, ns = self._header(record)
            if self.image_format == "jpeg":
                params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality]
            else:
                params = []
            ok, encoded = cv2.imencode(
                "." + ("jpg" if self.image_format == "jpeg" else "png"), _as_uint8(image), params
            )
            if not ok:
                raise ValueError(f"cv2.imencode could not encode a {np.shape(image)} frame as {self.image_format}")
            message = {"header": header, "format": self.image_format, "data": encoded.tobytes()}
            self._write("/image", "sensor_msgs/msg/CompressedImage", message, ns)
            self.stats["images"] += 1

        self._guarded(write)

    def emit_pressure(self, pressure: np.ndarray, record: WrenchRecord) -> None:
        """Write a pressure map on `{prefix}/pressure` as a `32FC1` image in Pa.

        **Arguments:**

        - `pressure`: `(h, w)` pressure in Pa on the rectified image grid, row 0 at the top.
        - `record`: the frame's record, for the stamp and frame id.
        """

        def write() -> None:
            header, ns = self._header(record)
            arr = np.ascontiguousarray(np.asarray(pressure), dtype="<f4")
            if arr.ndim != 2:
                raise ValueError(f"pressure map must be 2-D, got shape {arr.shape}")
            h, w = arr.shape
            message = {
                "header": header,
                "height": h,
                "width": w,
                "encoding": "32FC1",
                "is_bigendian": 0,
                "step": 4 * w,
                "data": arr.tobytes(),
            }
            self._write("/pressure", "sensor_msgs/msg/Image", message, ns)
            self.stats["pressure_maps"] += 1

        self._guarded(write)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record (string keys and values) to the file, e.g. where its data came from."""
        self._guarded(lambda: self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()}))

    def abort(self) -> None:
        """Stop recording and delete the unfinished `path + ".part"`: nothing appears at
        `path`. For a run that fails or is interrupted; idempotent, and nothing once
        [`close`][McapSink.close] has finished the file."""
        with self._lock:
            writer, self._writer = self._writer, None
            if writer is None:
                return
            self._stream.close()
            try:
                os.remove(self.part_path)
            except FileNotFoundError:
                pass

    def close(self) -> None:
        """Finish the MCAP file and move it from `path + ".part"` onto `path`; idempotent.

        **Raises:** `OSError` if the file cannot be finished or moved; the `.part` file is
        then left in place and the sink is closed all the same.
        """
        with self._lock:
            writer, self._writer = self._writer, None
            if writer is None:
                return
            try:
                writer.finish()
            finally:
                self._stream.close()
            os.replace(self.part_path, self.path)


# --------------------------------------------------------------------------- inverted recordings


def _frame_stamps(kind: str, source: Path, names: list[str], fps: Real | None) -> tuple[np.ndarray, str]:
    """Each row's stamp (s) and a line saying where the stamps come from."""
    index = np.arange(len(names), dtype=np.float64)
    if fps is not None:
        return index / float(fps), f"frame index / {float(fps):g} fps (given)"
    rate, what = None, ""
    if kind == "dataset":
        dataset = Dataset(source)
        if dataset.t is not None:
            by_name = dict(zip(dataset.frame_names, dataset.t))
            if all(name in by_name for name in names):
                times = np.array([by_name[name] for name in names], np.float64)
                if times.size and times.min() < 0:
                    return times - times.min(), "the dataset's t column, shifted to start at 0"
                return times, "the dataset's t column (s)"
        rate, what = dataset.fps, "the dataset's fps"
    elif kind == "video":
        capture = cv2.VideoCapture(str(source))
        try:
            rate, what = capture.get(cv2.CAP_PROP_FPS), "the video's frame rate"
        finally:
            capture.release()
    if rate is not None and math.isfinite(rate) and rate > 0:
        return index / float(rate), f"frame index / {float(rate):g} fps ({what})"
    return index, "the frame index as seconds: the recording gives no frame rate"


def _frame_images(kind: str, source: Path, names: list[str]) -> Iterator[np.ndarray | None]:
    """Each row's frame as stored (gray or BGR; 16-bit frames scaled to [0, 1]), or `None`."""
    if kind == "video":
        capture = cv2.VideoCapture(str(source))
        try:
            for _ in names:
                ok, image = capture.read()
                yield image if ok else None
        finally:
            capture.release()
        return
    folder = source / "frames" if kind == "dataset" else source
    for name in names:
        image = cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED)
        if image is not None and image.dtype == np.uint16:
            image = image.astype(np.float32) / np.float32(65535.0)
        yield image


def record_inversion(
    sink: Sink,
    source: str | os.PathLike,
    wrench_csv: str | os.PathLike,
    device: Device,
    *,
    records: RecordStream | None = None,
    fps: Real | None = None,
    pressure_shape: tuple[int, int] | None = PRESSURE_SHAPE,
) -> str:
    """Hand an inverted recording to a sink frame by frame, as the live loop hands a camera's.

    `moirejax invert --mcap` writes with it: every row of the wrench CSV that
    `moirejax invert` wrote becomes a record (with
    the row's status and message; a frame without a wrench has `force` and `torque`
    `null`, never zero), completed by `records` (sensor and frame names, sequence,
    `in_contact`, range flags, centre of pressure). A sink with `emit_image` also gets the
    frame, and one with `emit_pressure` the pressure map of each frame whose wrench is a
    load estimate (`converged`, `max_steps`), drawn as the live loop draws it from the
    row's wrench and contact patch (both patches, each with its share of the wrench, for
    a row read with two). The wrench is the CSV's, so the two files agree to
    the digit. The records carry no covariance: the CSV keeps only its square-rooted
    diagonal, the `sigma_*` columns.

    A recording has no capture clock of its own, so the stamps are, in this order of
    preference: the frame index over `fps` when given; a dataset's `t` column (shifted to
    start at 0 if it goes negative); the frame index over the recording's frame rate (a
    dataset's `fps`, a video's); else the frame index as seconds. The returned line says
    which, and a sink with `add_metadata` (an [`McapSink`][]) stores it with the source
    and the CSV in a `moirejax_inversion` metadata record.

    **Arguments:**

    - `sink`: where the records go (not closed here).
    - `source`: the dataset, folder of images or video that was inverted.
    - `wrench_csv`: the CSV `moirejax invert` wrote for it.
    - `device`: the unit, for the pressure maps.
    - `records`: completes each record (default: a [`RecordStream`][] with the default names).
    - `fps`: the frame rate of the stamps, over the recording's own.
    - `pressure_shape`: the grid of the pressure maps; `None` for none (also for a
        device whose image is not square).

    **Returns:** the line saying where the stamps come from.

    **Raises:** [`DataError`][moirejax.DataError] for a source or CSV that cannot be read,
    or a CSV that is not a wrench CSV.
    """
    if fps is not None and not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    path, csv_path = Path(source), Path(wrench_csv)
    kind = check_source(path)
    rows = read_wrench_csv(csv_path)
    names = [row["frame"] for row in rows]
    stamps, stamps_from = _frame_stamps(kind, path, names, fps)
    records = records if records is not None else RecordStream()
    if hasattr(sink, "add_metadata"):
        sink.add_metadata(
            "moirejax_inversion", {"source": str(path), "wrench_csv": str(csv_path), "stamps": stamps_from}
        )
    shape = (device.height, device.width)
    pressure_of = None
    if pressure_shape is not None and shape[0] * pressure_shape[1] == shape[1] * pressure_shape[0]:
        grid = map_grid(device, pressure_shape)
        pressure_of = jax.jit(lambda wrenches, contacts: patch_tractions(wrenches, contacts, grid)[2] * PA_PER_MPA)
    dtype = device.p1.dtype
    for i, (row, image) in enumerate(zip(rows, _frame_images(kind, path, names))):
        line = i + 2  # the header is line 1
        wrench = np.array([row_number(row, axis, csv_path, line) for axis in WRENCH_AXES])
        status = row["status"]
        has_load = status in LOAD_STATUSES and bool(np.all(np.isfinite(wrench)))
        patches = row_patches(row, csv_path, line) if has_load else []
        record = make_record(
            stamp=stamps[i],
            frame=i,
            mode="tactile",
            status=status,
            wrench=None if np.all(np.isnan(wrench)) else wrench,
            latency_ms=math.nan,  # offline: no capture-to-output time
            message=row["message"],
            contact_area_mm2=patches_area_mm2(patches) if has_load else None,
        )
        record = records.finish(record)
        sink.emit(record)
        if image is not None and hasattr(sink, "emit_image"):
            sink.emit_image(image, record)
        if pressure_of is not None and has_load and hasattr(sink, "emit_pressure"):
            sink.emit_pressure(np.asarray(pressure_of(*stack_patches(patches, dtype)), np.float32), record)
    return stamps_from
