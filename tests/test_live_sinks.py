"""Record format and sinks: JSON lines to streams, files and UDP (localhost only), video, strip chart."""

import io
import json
import socket
import sys

import cv2
import numpy as np
import pytest

from moirejax import OutputError
from moirejax.live import FileSink, make_record, RecordingSink, StreamSink, StripChart, UdpSink, VideoRecorder


FIELDS = [
    "version",
    "sensor_id",
    "frame_id",
    "seq",
    "stamp",
    "monotonic",
    "frame",
    "mode",
    "status",
    "in_contact",
    "force",
    "torque",
    "covariance",
    "out_of_range",
    "centre_of_pressure_mm",
    "contact_area_mm2",
    "filtered",
    "latency_ms",
    "message",
]


def sample(frame=7, **kwargs):
    defaults = dict(
        stamp=1700000000.25,
        frame=frame,
        mode="tactile",
        status="ok",
        wrench=np.array([0.01, -0.02, 0.8, 0.001, -0.002, 0.0005]),
        covariance=np.diag(np.full(6, 1e-4)),
        latency_ms=4.5,
    )
    return make_record(**{**defaults, **kwargs})


def test_record_json_format():
    obj = json.loads(sample().to_json())
    assert list(obj) == FIELDS
    assert obj["frame"] == 7 and obj["mode"] == "tactile" and obj["status"] == "ok"
    assert obj["force"] == [0.01, -0.02, 0.8] and obj["torque"] == [0.001, -0.002, 0.0005]
    assert len(obj["covariance"]) == 6 and all(len(row) == 6 for row in obj["covariance"])
    assert obj["covariance"][2][2] == 1e-4 and obj["latency_ms"] == 4.5 and obj["message"] == ""
    # No wrench, no covariance, non-finite numbers: nulls, still valid strict JSON.
    bare = json.loads(make_record(stamp=1.0, frame=3, mode="vision", status="corrupt_frame", message="x").to_json())
    assert bare["force"] is None and bare["torque"] is None and bare["covariance"] is None
    nan = json.loads(sample(wrench=np.array([np.nan, 0, 0, 0, 0, np.inf])).to_json())
    assert nan["force"][0] is None and nan["torque"][2] is None
    assert "\n" not in sample().to_json()


def test_stream_sink_writes_json_lines():
    buffer = io.StringIO()
    sink = StreamSink(buffer)
    for i in range(3):
        sink.emit(sample(frame=i))
    lines = buffer.getvalue().splitlines()
    assert [json.loads(line)["frame"] for line in lines] == [0, 1, 2]
    assert sink.stats["sent"] == 3
    buffer.close()
    sink.emit(sample())  # a closed stream is counted, not raised
    assert sink.stats["errors"] == 1


def test_stream_sink_defaults_to_stdout(capsys):
    StreamSink().emit(sample(frame=42))
    assert json.loads(capsys.readouterr().out)["frame"] == 42
    assert sys.stdout is not None


def test_file_sink_appends_and_flushes(tmp_path):
    path = tmp_path / "wrench.jsonl"
    with FileSink(path) as sink:
        sink.emit(sample(frame=0))
        # Readable before close: line-buffered and flushed.
        assert json.loads(path.read_text().splitlines()[0])["frame"] == 0
    with FileSink(path) as sink:
        sink.emit(sample(frame=1))
    assert [json.loads(line)["frame"] for line in path.read_text().splitlines()] == [0, 1]
    sink.emit(sample())  # after close: counted
    assert sink.stats["errors"] == 1


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_udp_sink_to_closed_port_does_not_raise():
    sink = UdpSink("127.0.0.1", free_udp_port())
    for i in range(20):
        sink.emit(sample(frame=i))
    sink.close()
    counted = sink.stats["sent"] + sink.stats["dropped"] + sink.stats["errors"]
    assert counted == 20
    if sys.platform.startswith("linux"):  # Linux reports ICMP port-unreachable on localhost
        assert sink.stats["refused"] >= 1


def test_udp_sink_delivers_records():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
        receiver.bind(("127.0.0.1", 0))
        receiver.settimeout(5)
        with UdpSink("127.0.0.1", receiver.getsockname()[1]) as sink:
            sink.emit(sample(frame=5))
            sink.emit(sample(frame=6))
            got = [json.loads(receiver.recv(65536))["frame"] for _ in range(2)]
    assert got == [5, 6] and sink.stats["refused"] == 0


def test_video_recorder_writes_annotated_mp4(tmp_path):
    path = tmp_path / "run.mp4"
    with VideoRecorder(path, fps=20) as recorder:
        for i in range(8):
            gray = np.full((60, 80), i / 10, np.float32)
            recorder.write(gray, sample(frame=i, mode="tactile" if i % 2 else "vision"))
        with pytest.raises(ValueError, match="differs"):
            recorder.write(np.zeros((10, 10), np.float32), sample())
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame)
    capture.release()
    assert len(frames) == 8 and frames[0].shape[1] == 80 and frames[0].shape[0] > 60
    # The bar panel below the image is drawn (not black), the Fz bar is to the right of centre.
    panel = frames[3][60:].astype(int)
    assert panel.max() > 100


def test_strip_chart_is_a_no_op_without_display(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    chart = StripChart()
    assert not chart.enabled
    chart.emit(sample())
    chart.close()


def test_recording_sink_keeps_the_frames_exactly_and_what_its_index_lists(tmp_path):
    rng = np.random.default_rng(0)
    gray = (rng.integers(0, 256, (24, 32)) / 255).astype(np.float32)  # an 8-bit camera's frame in [0, 1]
    sink = RecordingSink(tmp_path / "rec", index_every=2)
    for i in range(3):
        sink.emit_image(
            gray, make_record(stamp=100.0 + i / 60, frame=i, mode="tactile" if i else "vision", status="ok")
        )
    # Two frames listed so far (the index is rewritten every second frame), all three on disk.
    assert (tmp_path / "rec" / "frames.csv").read_text().splitlines()[1:] == [
        f"000000.png,{100.0!r},0",
        f"000001.png,{100.0 + 1 / 60!r},1",
    ]
    (tmp_path / "rec" / "frames").rename(tmp_path / "rec" / "gone")  # the disk goes away
    sink.emit_image(gray, make_record(stamp=101.0, frame=3, mode="vision", status="ok"))
    sink.close()
    assert sink.stats == {"sent": 3, "errors": 1}
    rows = (tmp_path / "rec" / "frames.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[3].startswith("000002.png,")
    back = cv2.imread(str(tmp_path / "rec" / "gone" / "000002.png"), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint8 and np.array_equal(back.astype(np.float32) / 255, gray)

    deep = RecordingSink(tmp_path / "deep", bit_depth=16)
    deep.emit_image(gray, make_record(stamp=0.0, frame=0, mode="vision", status="ok"))
    deep.close()
    back = cv2.imread(str(tmp_path / "deep" / "frames" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16 and np.array_equal(back // 257, (gray * 255).round().astype(np.uint16))
    with pytest.raises(OutputError, match="not empty"):
        RecordingSink(tmp_path / "rec")
    with pytest.raises(ValueError, match="bit_depth"):
        RecordingSink(tmp_path / "other", bit_depth=12)
