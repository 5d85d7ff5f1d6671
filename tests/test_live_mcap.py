"""McapSink: ROS 2 messages in MCAP, read back with an independent reader and by hand from the CDR bytes."""

import dataclasses
import json
import os
import struct
import sys
import threading
import time

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from moirejax._conventions import WRENCH_CONVENTION
from moirejax.live import make_record, McapSink


MCAP_MAGIC = b"\x89MCAP0\r\n"


def record(frame=0, stamp=1700000000.25, status="ok", wrench=(0.01, -0.02, 0.8, 0.001, -0.002, 0.0005), **kw):
    return make_record(
        stamp=stamp,
        frame=frame,
        mode="tactile",
        status=status,
        wrench=None if wrench is None else np.asarray(wrench, dtype=np.float64),
        covariance=None if wrench is None else np.diag(np.arange(1.0, 7.0)) * 1e-4,
        latency_ms=3.5,
        **kw,
    )


class Decoded:
    def __init__(self, schema, channel, message, ros_msg):
        self.schema, self.channel, self.ros_msg = schema, channel, ros_msg
        self.log_time_ns, self.publish_time_ns = message.log_time, message.publish_time


def with_frame_id(rec, frame_id):
    return dataclasses.replace(rec, frame_id=frame_id)


def read(path, topic=None):
    """Decoded messages in file order (what `mcap_ros2.reader.read_ros2_messages` gives, minus its deprecation)."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = None if topic is None else [topic]
        return [Decoded(*item) for item in reader.iter_decoded_messages(topics, log_time_order=False)]


def test_records_and_wrenches_round_trip(tmp_path):
    path = tmp_path / "run.mcap"
    # Force and torque values that are not short decimals: float64 must survive bit for bit.
    w1 = (0.1 + 0.2, -1 / 3, 2.0**-30 + 1.0, 1e-3 / 7, -np.pi * 1e-4, 5e-300)
    recs = [
        record(frame=0, stamp=1700000000.25, wrench=w1),
        record(frame=1, stamp=1700000000.5, status="no_contact", wrench=None),
        record(frame=2, stamp=1700000000.75, status="bad_frame", wrench=None, message="corrupt"),
        record(frame=3, stamp=1700000001.0, wrench=(1.0, 2.0, 3.0, 4.0, 5.0, 6.0)),
        # A wrench with a NaN is not a wrench: JSON (with nulls) only.
        record(frame=4, stamp=1700000001.25, wrench=(np.nan, 0, 1, 0, 0, 0)),
    ]
    with McapSink(path) as sink:
        for r in recs:
            sink.emit(r)
    assert sink.stats == {"sent": 5, "errors": 0, "images": 0, "pressure_maps": 0}

    strings = read(path, "/moirejax/record")
    assert [m.schema.name for m in strings] == ["std_msgs/msg/String"] * 5
    # The JSON line is carried verbatim: nothing the JSON sinks carry is lost.
    assert [m.ros_msg.data for m in strings] == [r.to_json() for r in recs]
    assert json.loads(strings[2].ros_msg.data)["message"] == "corrupt"

    wrenches = read(path, "/moirejax/wrench")
    assert [m.schema.name for m in wrenches] == ["geometry_msgs/msg/WrenchStamped"] * 2
    for m, r in zip(wrenches, [recs[0], recs[3]]):
        w = m.ros_msg.wrench
        assert (w.force.x, w.force.y, w.force.z) == r.force  # exact float64
        assert (w.torque.x, w.torque.y, w.torque.z) == r.torque
        stamp = m.ros_msg.header.stamp
        assert stamp.sec + stamp.nanosec / 4e9 * 4 == r.stamp
        assert m.ros_msg.header.frame_id == "moirejax_sensor"
        assert m.log_time_ns == m.publish_time_ns == stamp.sec * 10**9 + stamp.nanosec
    assert (wrenches[0].ros_msg.header.stamp.sec, wrenches[0].ros_msg.header.stamp.nanosec) == (1700000000, 250000000)
    assert (wrenches[1].ros_msg.header.stamp.sec, wrenches[1].ros_msg.header.stamp.nanosec) == (1700000001, 0)
    # Every message is logged at its record's stamp.
    assert sorted(m.log_time_ns for m in strings) == [1700000000_250000000 + k * 250_000000 for k in range(5)]
    assert {m.channel.topic for m in read(path)} == {"/moirejax/record", "/moirejax/wrench"}


def test_wrench_cdr_layout_by_hand(tmp_path):
    # Decode the bytes without the ROS 2 message parser, against the layout ROS 2 itself
    # gives WrenchStamped: CDR little-endian header, int32 sec, uint32 nanosec, string
    # frame_id (uint32 length with NUL), then six float64 aligned to 8 bytes.
    path = tmp_path / "w.mcap"
    r = with_frame_id(record(stamp=1700000123.5, wrench=(1.5, -2.25, 3.125, -0.5, 0.25, 1e-6)), "pad_7")
    with McapSink(path) as sink:
        sink.emit(r)
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        (channel,) = [c for c in reader.get_summary().channels.values() if c.topic == "/moirejax/wrench"]
        assert channel.message_encoding == "cdr"
        data = next(m for _, c, m in reader.iter_messages() if c.topic == "/moirejax/wrench").data
    assert data[:2] == b"\x00\x01"  # CDR_LE
    body = data[4:]
    sec, nanosec, n = struct.unpack_from("<iII", body, 0)
    assert (sec, nanosec) == (1700000123, 500000000)
    assert body[12 : 12 + n] == b"pad_7\x00"
    start = -(-(12 + n) // 8) * 8
    assert struct.unpack_from("<6d", body, start) == r.force + r.torque
    assert len(body) == start + 48


def test_frame_id_prefix_and_metadata(tmp_path):
    path = tmp_path / "tagged.mcap"
    base = record()
    with McapSink(path, topic_prefix="robot1/moire/") as sink:
        sink.emit(with_frame_id(base, "left_finger"))  # each record's own frame
        sink.emit(with_frame_id(base, "right_finger"))
    wrenches = read(path, "/robot1/moire/wrench")
    assert [m.ros_msg.header.frame_id for m in wrenches] == ["left_finger", "right_finger"]
    assert len(read(path, "/robot1/moire/record")) == 2
    with open(path, "rb") as f:
        (meta,) = [m for m in make_reader(f).iter_metadata() if m.name == "moirejax"]
    assert meta.metadata["wrench_convention"] == WRENCH_CONVENTION


def test_missing_stamp_falls_back_to_now(tmp_path):
    path = tmp_path / "now.mcap"
    before = time.time_ns()
    with McapSink(path) as sink:
        sink.emit(record(stamp=float("nan")))
    after = time.time_ns()
    (m,) = read(path, "/moirejax/wrench")
    stamp_ns = m.ros_msg.header.stamp.sec * 10**9 + m.ros_msg.header.stamp.nanosec
    assert before <= stamp_ns == m.log_time_ns <= after


def gradient_gray(h=48, w=64):
    y, x = np.mgrid[0:h, 0:w]
    return (0.5 + 0.4 * np.sin(x / 9.0) * np.cos(y / 7.0)).astype(np.float32)


def decode(message):
    return cv2.imdecode(np.frombuffer(message.data, np.uint8), cv2.IMREAD_UNCHANGED)


def test_png_images_are_lossless(tmp_path):
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    bgr = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    gray_float = gradient_gray()
    path = tmp_path / "png.mcap"
    with McapSink(path, image_format="png") as sink:
        r = record()
        sink.emit(r)
        sink.emit_image(gray, r)
        sink.emit_image(bgr, r)
        sink.emit_image(gray_float, r)
    assert sink.stats["images"] == 3 and sink.stats["errors"] == 0
    images = read(path, "/moirejax/image")
    assert [m.schema.name for m in images] == ["sensor_msgs/msg/CompressedImage"] * 3
    assert all(m.ros_msg.format == "png" for m in images)
    np.testing.assert_array_equal(decode(images[0].ros_msg), gray)
    np.testing.assert_array_equal(decode(images[1].ros_msg), bgr)  # BGR stays BGR
    # Floats in [0, 1] map onto 0..255 to the nearest level.
    assert np.max(np.abs(decode(images[2].ros_msg).astype(float) - gray_float * 255)) <= 0.5 + 1e-3
    assert images[0].ros_msg.header.stamp.nanosec == 250000000


def test_jpeg_images_within_tolerance(tmp_path):
    gray = gradient_gray()
    bgr = np.stack([gray, 1 - gray, np.full_like(gray, 0.3)], axis=-1)
    path = tmp_path / "jpeg.mcap"
    with McapSink(path, jpeg_quality=95) as sink:
        sink.emit_image(gray, record())
        sink.emit_image(bgr, record())
    images = read(path, "/moirejax/image")
    assert [m.ros_msg.format for m in images] == ["jpeg", "jpeg"]
    assert images[0].ros_msg.data[:2] == b"\xff\xd8"  # JPEG SOI marker
    np.testing.assert_allclose(decode(images[0].ros_msg) / 255.0, gray, atol=4 / 255)
    # Colour JPEG halves the chroma resolution: small on average, larger at a few pixels.
    error = np.abs(decode(images[1].ros_msg) / 255.0 - bgr)
    assert error.mean() < 2 / 255 and error.max() < 0.1


def test_images_off(tmp_path):
    path = tmp_path / "noimg.mcap"
    with McapSink(path, images=False) as sink:
        sink.emit(record())
        sink.emit_image(gradient_gray(), record())
    assert read(path, "/moirejax/image") == [] and sink.stats["images"] == 0


def test_pressure_map_round_trips_as_float32(tmp_path):
    rng = np.random.default_rng(1)
    # An asymmetric map in Pa with a row gradient, so a flip or transpose would show.
    pressure = rng.normal(2e3, 5e2, (48, 64)) + np.arange(48)[:, None] * 100.0
    path = tmp_path / "p.mcap"
    with McapSink(path) as sink:
        sink.emit_pressure(pressure, record(stamp=1700000002.5))
    (m,) = read(path, "/moirejax/pressure")
    msg = m.ros_msg
    assert m.schema.name == "sensor_msgs/msg/Image"
    assert (msg.height, msg.width, msg.encoding, msg.is_bigendian, msg.step) == (48, 64, "32FC1", 0, 256)
    back = np.frombuffer(msg.data, "<f4").reshape(msg.height, msg.width)
    np.testing.assert_array_equal(back, pressure.astype(np.float32))
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1700000002, 500000000)


def test_atomic_rename_on_close(tmp_path):
    path = tmp_path / "run.mcap"
    part = tmp_path / "run.mcap.part"
    path.write_bytes(b"previous recording")
    sink = McapSink(path)
    sink.emit(record())
    # Until close: the old file is untouched and the new one grows under `.part`.
    assert path.read_bytes() == b"previous recording"
    # The header is on disk from the start (the messages follow a chunk at a time).
    assert part.exists() and part.read_bytes().startswith(MCAP_MAGIC)
    sink.close()
    assert not part.exists()
    assert path.read_bytes().startswith(MCAP_MAGIC) and path.read_bytes().endswith(MCAP_MAGIC)
    sink.close()  # idempotent
    assert len(read(path)) == 2

    fresh = tmp_path / "fresh.mcap"
    sink = McapSink(fresh)
    assert not fresh.exists() and (tmp_path / "fresh.mcap.part").exists()
    sink.close()
    assert fresh.exists() and read(fresh) == []


def test_leftover_part_is_not_overwritten(tmp_path):
    path = tmp_path / "run.mcap"
    part = tmp_path / "run.mcap.part"
    part.write_bytes(b"interrupted run")
    with pytest.raises(FileExistsError, match="run.mcap.part"):
        McapSink(path)
    assert part.read_bytes() == b"interrupted run"


def test_bad_folders_are_refused(tmp_path, monkeypatch):
    missing = tmp_path / "no" / "such" / "run.mcap"
    with pytest.raises(ValueError, match=str(missing)) as info:
        McapSink(missing)
    assert "\n" not in str(info.value)
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(ValueError, match="afile"):
        McapSink(afile / "run.mcap")
    with pytest.raises(ValueError, match="directory"):
        McapSink(tmp_path)
    # Not writable (root may write anywhere, so pretend the access check fails).
    monkeypatch.setattr(os, "access", lambda *args, **kwargs: False)
    with pytest.raises(OSError, match="not writable") as info:
        McapSink(tmp_path / "run.mcap")
    assert str(tmp_path / "run.mcap") in str(info.value)
    assert list(tmp_path.iterdir()) == [afile]
    with pytest.raises(ValueError, match="image_format"):
        McapSink(tmp_path / "x.mcap", image_format="bmp")


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root ignores permissions")
def test_read_only_folder_is_refused(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        with pytest.raises(OSError, match="ro"):
            McapSink(folder / "run.mcap")
    finally:
        folder.chmod(0o755)


def test_failures_are_counted_not_raised(tmp_path):
    path = tmp_path / "err.mcap"
    sink = McapSink(path)
    sink.emit_image(np.zeros(5), record())  # not an image
    sink.emit_pressure(np.zeros((2, 3, 4)), record())  # not a map
    sink.emit(record(frame=1))
    assert sink.stats["errors"] == 2 and sink.stats["sent"] == 1
    sink.close()
    sink.emit(record(frame=2))
    sink.emit_image(gradient_gray(), record())
    sink.emit_pressure(np.zeros((4, 4)), record())
    assert sink.stats["errors"] == 5 and sink.stats["sent"] == 1
    assert [json.loads(m.ros_msg.data)["frame"] for m in read(path, "/moirejax/record")] == [1]


def test_threads_share_one_sink(tmp_path):
    path = tmp_path / "threads.mcap"
    with McapSink(path, image_format="png") as sink:

        def work(offset):
            for k in range(100):
                r = record(frame=offset + k, stamp=1700000000.0 + (offset + k) * 1e-3)
                sink.emit(r)
                if k % 10 == 0:
                    sink.emit_image(np.full((8, 8), k, np.uint8), r)

        threads = [threading.Thread(target=work, args=(i * 1000,)) for i in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert sink.stats["errors"] == 0 and sink.stats["sent"] == 300
    frames = sorted(json.loads(m.ros_msg.data)["frame"] for m in read(path, "/moirejax/record"))
    assert frames == sorted(i * 1000 + k for i in range(3) for k in range(100))
    assert len(read(path, "/moirejax/wrench")) == 300 and len(read(path, "/moirejax/image")) == 30


def test_without_the_ros_extra_the_error_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "mcap_ros2.writer", None)
    with pytest.raises(ImportError, match=r"moirejax\[ros\]"):
        McapSink(tmp_path / "x.mcap")
    assert not (tmp_path / "x.mcap.part").exists()
