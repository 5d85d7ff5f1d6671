"""The live loop end to end with a simulated sensor and a stub inversion."""

import io
import json
import os
import signal
import threading

import cv2
import numpy as np

from moirejax.live import (
    CallableSource,
    FileSink,
    FolderSource,
    GateER,
    Rectification,
    run_pipeline,
    StreamSink,
    VideoRecorder,
)


H = W = 96
ROWS, COLS = np.mgrid[0:H, 0:W].astype(np.float64)
K1 = 2 * np.pi / 3.0 * np.array([np.cos(0.05), np.sin(0.05)])
K2 = 2 * np.pi / 3.5 * np.array([1.0, 0.0])


def sensor_frame(pressed):
    """Moire of two gratings; `pressed` adds a Gaussian phase bump (a contact)."""
    bump = 1.5 * np.exp(-((COLS - 48) ** 2 + (ROWS - 48) ** 2) / (2 * 8.0**2)) if pressed else 0.0
    a = K1[0] * COLS + K1[1] * ROWS + bump
    b = K2[0] * COLS
    return (0.1 + 0.6 * (1 + np.cos(a)) * (1 + np.cos(b)) / 4).astype(np.float32)


REST, PRESSED = sensor_frame(False), sensor_frame(True)


def simulated(n, contact=range(20, 40)):
    """A finite simulated sensor: `fn(i) -> frame or None`."""
    return lambda i: None if i >= n else (PRESSED if i in contact else REST)


def stub_inversion(gray):
    return np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), np.eye(6) * 1e-4, "ok", ""


def records_of(buffer):
    return [json.loads(line) for line in buffer.getvalue().splitlines()]


def test_gated_run_emits_ordered_records():
    buffer = io.StringIO()
    summary = run_pipeline(CallableSource(simulated(60)), stub_inversion, [StreamSink(buffer)], GateER())
    records = records_of(buffer)
    frames = [r for r in records if r["status"] != "end_of_stream"]
    assert [r["frame"] for r in frames] == list(range(60))
    assert [r["mode"] for r in frames] == ["vision"] * 20 + ["tactile"] * 20 + ["vision"] * 20
    assert frames[25]["force"] == [0.0, 0.0, 1.0] and frames[25]["covariance"][0][0] == 1e-4
    assert frames[5]["status"] == "no_contact" and frames[5]["force"] == [0.0, 0.0, 0.0]
    assert frames[5]["covariance"] is None
    assert records[-1]["status"] == "end_of_stream"
    assert all(r["latency_ms"] >= 0 for r in records)
    assert all(b["stamp"] >= a["stamp"] for a, b in zip(frames, frames[1:]))
    assert summary.frames == 60 and summary.dropped == 0 and summary.records == 61
    assert summary.mode_switches == 2 and summary.stopped_by == "end_of_stream"
    assert summary.status_counts == {"no_contact": 40, "ok": 20, "end_of_stream": 1}
    assert np.isfinite(summary.latency_ms_median) and summary.latency_ms_p90 >= summary.latency_ms_median
    assert summary.fps > 0


def test_failures_become_status_records():
    def flaky_inversion(gray):
        flaky_inversion.calls += 1
        if flaky_inversion.calls == 2:
            raise RuntimeError("solver diverged")
        if flaky_inversion.calls == 3:
            return np.zeros(5), None, "ok", ""
        return np.ones(6), None, "not_converged", "max steps"

    flaky_inversion.calls = 0

    def source_fn(i):
        if i == 2:
            raise OSError("sensor glitch")
        return None if i >= 6 else REST

    buffer = io.StringIO()
    summary = run_pipeline(CallableSource(source_fn), flaky_inversion, [StreamSink(buffer)], None)
    statuses = [(r["frame"], r["status"]) for r in records_of(buffer)]
    assert statuses == [
        (0, "not_converged"),
        (1, "process_error"),
        (2, "corrupt_frame"),
        (3, "bad_output"),
        (4, "not_converged"),
        (5, "not_converged"),
        (6, "end_of_stream"),
    ]
    messages = {r["status"]: r["message"] for r in records_of(buffer)}
    assert "solver diverged" in messages["process_error"] and "(6,)" in messages["bad_output"]
    assert "sensor glitch" in messages["corrupt_frame"]
    assert summary.frames == 5 and summary.status_counts["not_converged"] == 3


def test_corrupt_file_in_folder_yields_status_record(tmp_path):
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"{i:03d}.png"), (REST * 255).astype(np.uint8))
    (tmp_path / "001.png").write_bytes(b"garbage")
    path = tmp_path / "out.jsonl"
    with FileSink(path) as sink:
        summary = run_pipeline(FolderSource(tmp_path), stub_inversion, [sink], None)
    records = [json.loads(line) for line in path.read_text().splitlines()]
    assert [(r["frame"], r["status"]) for r in records] == [
        (0, "ok"),
        (1, "corrupt_frame"),
        (2, "ok"),
        (3, "ok"),
        (4, "end_of_stream"),
    ]
    assert "001.png" in records[1]["message"] and records[1]["force"] is None
    assert summary.frames == 3 and summary.stopped_by == "end_of_stream"


def test_max_frames_and_bad_sink():
    class Broken:
        def emit(self, record):
            raise OSError("disk full")

        def close(self):
            pass

    buffer = io.StringIO()
    summary = run_pipeline(
        CallableSource(lambda i: REST), stub_inversion, [Broken(), StreamSink(buffer)], None, max_frames=7
    )
    assert summary.frames == 7 and summary.stopped_by == "max_frames" and summary.output_errors == 7
    assert len(records_of(buffer)) == 7


def test_sigint_stops_cleanly():
    def interrupting(gray):
        interrupting.calls += 1
        if interrupting.calls == 5:
            os.kill(os.getpid(), signal.SIGINT)
        return np.zeros(6), None, "ok", ""

    interrupting.calls = 0
    previous = signal.getsignal(signal.SIGINT)
    buffer = io.StringIO()
    source = CallableSource(lambda i: REST, live=True)  # endless
    summary = run_pipeline(source, interrupting, [StreamSink(buffer)], None)
    assert summary.stopped_by == "interrupted" and summary.frames == 5
    assert records_of(buffer)[-1]["status"] == "interrupted"
    assert signal.getsignal(signal.SIGINT) is previous
    assert not source._thread.is_alive()


def test_stop_event_from_another_thread():
    stop = threading.Event()
    seen = threading.Event()

    def inversion(gray):
        seen.set()
        return np.zeros(6), None, "ok", ""

    threading.Thread(target=lambda: seen.wait(10) and stop.set(), daemon=True).start()
    summary = run_pipeline(CallableSource(lambda i: REST, live=True), inversion, [], None, stop=stop)
    assert summary.stopped_by == "interrupted" and summary.frames >= 1


def test_rectification_vision_hook_and_recording(tmp_path):
    # Identity-like rectification of the 96x96 frames to 64x64 at 1 px/mm around the centre.
    to_mm = np.array([[1.0, 0, -(W - 1) / 2], [0, -1.0, (H - 1) / 2], [0, 0, 1]])
    rect = Rectification(to_mm, (W, H), (64, 64), 1)
    shapes, hooks = [], []

    def inversion(gray):
        shapes.append(gray.shape)
        return np.zeros(6), None, "ok", ""

    def vision(frame):
        hooks.append(frame.index)
        return "scene ok"

    path = tmp_path / "run.mp4"
    buffer = io.StringIO()
    with VideoRecorder(path) as recorder:
        summary = run_pipeline(
            CallableSource(simulated(50)),
            inversion,
            [StreamSink(buffer)],
            GateER(),
            rectification=rect,
            vision=vision,
            record=recorder,
        )
    assert set(shapes) == {(64, 64)} and len(shapes) == 20
    assert hooks == list(range(20)) + list(range(40, 50))
    assert records_of(buffer)[0]["message"] == "scene ok"
    assert recorder.frames == 50 and summary.output_errors == 0
    # A rectification for another camera size: every frame is a status record, no crash.
    wrong = Rectification(to_mm, (W + 1, H), (64, 64), 1)
    summary = run_pipeline(CallableSource(simulated(5)), inversion, [], GateER(), rectification=wrong)
    assert summary.status_counts == {"rectify_error": 5, "end_of_stream": 1}
