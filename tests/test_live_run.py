"""The live sensor end to end: simulated sensor, gate, inversion and sinks; the cap-removal cycle."""

import io
import json
import logging
import socket

import cv2
import jax
import numpy as np
import pytest

import moirejax as mj
from moirejax._fileio import validate_json
from moirejax.inverse._inversion import Inverter
from moirejax.live import (
    capture_reference,
    FileSink,
    FolderSource,
    format_summary,
    make_tactile_processor,
    parse_sink,
    plot_timeline,
    run_cap_removal,
    run_live,
    SimulatedSensor,
    StreamSink,
    UdpSink,
)
from moirejax.physics._contact import Contact
from moirejax.simulate._simulate import load_schedule


@pytest.fixture(scope="module")
def device():
    return mj.preset("mid")


@pytest.fixture(scope="module")
def reference(device):
    return SimulatedSensor(device).reference_frame()


@pytest.fixture(scope="module")
def inverter(device, reference):
    """One inverter for the module, compiled here once (tens of seconds on a 2-core CPU)."""
    inverter = Inverter(device, reference=reference)
    make_tactile_processor(inverter, reference)
    return inverter


def runs(values):
    """Consecutive duplicates collapsed: the sequence of modes or phases."""
    return [v for i, v in enumerate(values) if i == 0 or v != values[i - 1]]


def test_simulated_run_streams_gated_wrenches_close_to_the_truth(device, inverter, tmp_path, caplog):
    path = tmp_path / "wrench.jsonl"
    sink = FileSink(path)
    with jax.log_compiles(), caplog.at_level(logging.WARNING):
        summary = run_live(device, "sim", sinks=[sink], max_frames=32, inverter=inverter)
    sink.close()
    # The stream's step compiles once, when the processor warms up before the first frame,
    # and no frame compiles it again.
    compiles = [r for r in caplog.records if r.getMessage().startswith("Compiling jit(track_frame)")]
    assert len(compiles) == 1, [r.getMessage()[:80] for r in compiles]

    records = [json.loads(line) for line in path.read_text().splitlines()]
    for r in records:
        validate_json(r, "live_record")
    assert [r["frame"] for r in records] == list(range(32))
    assert runs([r["mode"] for r in records]) == ["vision", "tactile", "vision"]
    # The default script is the "sequence" protocol over the run's 32 frames: compare with
    # the schedule itself, not with anything the sensor reports.
    truth = load_schedule("sequence", 32, 0)
    tactile = [r for r in records if r["mode"] == "tactile"]
    assert all(truth.contact[r["frame"]] for r in tactile)
    assert len(tactile) >= 20  # the gate catches the press by about 0.3 N and lets go below it
    converged = [r for r in tactile if r["status"] == "converged"]
    assert len(converged) == len(tactile)
    for r in converged:
        true = truth.wrench[r["frame"]]
        assert abs(r["force"][2] - true[2]) < 0.1
        assert abs(r["force"][0] - true[0]) < 0.02 and abs(r["torque"][2] - true[5]) < 5e-4
        assert np.all(np.isfinite(r["covariance"])) and r["covariance"][2][2] > 0
    vision = [r for r in records if r["mode"] == "vision"]
    assert all(r["status"] == "no_contact" and r["force"] == [0.0, 0.0, 0.0] for r in vision)
    assert all(b["stamp"] >= a["stamp"] for a, b in zip(records, records[1:]))

    assert summary.frames == 32 and summary.dropped == 0 and summary.stopped_by == "max_frames"
    assert summary.mode_switches == 2 and summary.output_errors == 0
    assert summary.status_counts == {"no_contact": len(vision), "converged": len(converged)}
    assert summary.latency_ms_p90 >= summary.latency_ms_median > 0
    text = format_summary(summary)
    assert "frames 32 (dropped 0)" in text and f"converged {len(converged)}" in text and "p90" in text


def test_simulated_sensor_truth_and_end_of_script(device):
    rig_load = np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.002])
    sensor = SimulatedSensor(device, lambda i: (rig_load, Contact(0.0, 0.0, 4.0)) if i < 2 else None)
    items = list(sensor.source())
    assert [type(x).__name__ for x in items] == ["Frame", "Frame", "SourceEvent"]
    assert items[-1].status == "end_of_stream" and items[-1].final
    assert items[0].gray.shape == (device.height, device.width) and items[0].gray.dtype == np.float32
    np.testing.assert_array_equal(sensor.truth(1), rig_load)
    scheduled = SimulatedSensor(device, n_frames=10)
    assert len(scheduled) == 10
    np.testing.assert_array_equal(scheduled.truth(5), load_schedule("sequence", 10, 0).wrench[5])


def test_parse_sink(tmp_path):
    assert isinstance(parse_sink("-"), StreamSink) and isinstance(parse_sink("stdout"), StreamSink)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver:
        receiver.bind(("127.0.0.1", 0))
        port = receiver.getsockname()[1]
        udp = parse_sink(f"udp://127.0.0.1:{port}")
        assert isinstance(udp, UdpSink) and udp.address == ("127.0.0.1", port)
        udp.close()
    file = parse_sink(str(tmp_path / "out.jsonl"))
    assert isinstance(file, FileSink) and file.path == str(tmp_path / "out.jsonl")
    file.close()
    for bad in ("udp://127.0.0.1", "udp://:9000", "udp://host:notaport"):
        with pytest.raises(ValueError, match="udp://host:port"):
            parse_sink(bad)


def test_one_cap_removal_cycle_reaches_the_target_and_plots(device, inverter, tmp_path):
    timeline = run_cap_removal(device, cycles=1, inverter=inverter)
    assert timeline.cycles == 1
    assert runs(list(timeline.phase)) == ["approach", "press", "twist", "release", "return"]
    assert timeline.mode[0] == "vision" and timeline.mode[-1] == "vision"
    twist = timeline.phase == "twist"
    estimated, true = timeline.wrench_estimated, timeline.wrench_true
    # The press loop closes on the estimate; the true force must follow it.
    assert np.all(np.abs(estimated[twist, 2] - 1.0) < 0.06)
    assert np.all(np.abs(true[twist, 2] - 1.0) < 0.1)
    # Twisting winds the grip up to the cap's breakaway torque; the cap then turns.
    assert true[:, 5].max() == pytest.approx(0.006, abs=1e-6)
    assert estimated[:, 5].max() == pytest.approx(0.006, abs=5e-4)
    assert timeline.cap_angle[-1] > 0.0
    # Nothing presses or twists once the gate is back in vision mode.
    vision = timeline.mode == "vision"
    assert np.all(estimated[vision] == 0.0) and np.all(true[vision & (timeline.phase == "return")] == 0.0)

    png = tmp_path / "timeline.png"
    plot_timeline(png, timeline)
    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 600


def test_cap_removal_refuses_targets_outside_the_calibrated_range(device):
    from moirejax.live import CapController

    with pytest.raises(ValueError, match="calibrated"):
        run_cap_removal(device, cycles=1, controller=CapController(target_fz=6.0))


def test_folder_with_a_corrupt_image_gives_a_status_record(device, inverter, reference, tmp_path):
    sensor = SimulatedSensor(device)
    rest = reference
    pressed = sensor.render(np.array([0.0, 0.0, 0.8, 0.0, 0.0, 0.0]), Contact(0.0, 0.0, 4.0))
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, frame in enumerate([rest, rest, rest, None, pressed, rest]):
        path = folder / f"frame{i}.png"
        if frame is None:
            path.write_bytes(b"\x89PNG this is not an image")
        else:
            cv2.imwrite(str(path), (frame * 255 + 0.5).astype(np.uint8))
    buffer = io.StringIO()
    summary = run_live(device, str(folder), sinks=[StreamSink(buffer)], inverter=inverter)
    records = [json.loads(line) for line in buffer.getvalue().splitlines()]
    for r in records:
        validate_json(r, "live_record")
    assert [r["frame"] for r in records] == list(range(7))
    assert [r["status"] for r in records[:4]] == ["no_contact"] * 3 + ["corrupt_frame"]
    assert "frame3.png" in records[3]["message"] and records[3]["force"] is None
    assert records[4]["mode"] == "tactile" and records[4]["status"] == "converged"
    assert records[4]["force"][2] == pytest.approx(0.8, abs=0.1)  # through 8-bit quantisation
    assert records[5]["mode"] == "vision" and records[6]["status"] == "end_of_stream"
    assert summary.frames == 5 and summary.stopped_by == "end_of_stream"

    # Without a given reference, run_live averages the first frames of the source.
    reference = capture_reference(FolderSource(folder), frames=3)
    expected = np.round(rest * 255) / 255
    np.testing.assert_allclose(reference, expected, atol=1e-6)


def test_wrong_sized_frames_and_missing_sources_are_reported(device, inverter, reference, tmp_path):
    processor = make_tactile_processor(inverter, reference)
    wrench, covariance, status, message, extras = processor(np.zeros((100, 120), np.float32))
    assert status == "wrong_size" and np.all(np.isnan(wrench)) and covariance is None and "(100, 120)" in message
    assert extras == {}
    with pytest.raises(FileNotFoundError, match="no_such_video"):
        run_live(device, str(tmp_path / "no_such_video.mp4"), sinks=[], inverter=inverter)
    # A source that fails before its first frame is reported before an inverter is built.
    with pytest.raises(ValueError, match="open_failed"):
        capture_reference(FolderSource(tmp_path / "gone"))


def test_the_approach_aligns_on_the_cap_it_sees(device, inverter):
    from moirejax.live import CapRig

    # The green cap 3.6 mm off the sensor's axis, 0.5 mm below the pad: the robot moves
    # sideways onto what it locates through the sensor, then descends; the first frames in
    # contact are read against the approach's last frames, which show the cap.
    rig = CapRig(cap_x=3.0, cap_y=-2.0, cap_rgb=(0.1, 0.7, 0.2))
    timeline = run_cap_removal(device, cycles=1, inverter=inverter, rig=rig, max_frames=11)
    vision = timeline.mode == "vision"
    seen = np.isfinite(timeline.cap_seen[:, 0])
    assert seen[0] and np.all(np.hypot(*(timeline.cap_seen - timeline.cap_offset)[seen].T) < 0.1)
    touching = np.flatnonzero(~vision)
    assert touching.size >= 2 and np.all(vision[: touching[0]])
    # Aligned before it touched, and it did not move while touching.
    assert np.hypot(*timeline.cap_offset[touching[0]]) < 0.3
    assert np.all(timeline.cap_offset[touching] == timeline.cap_offset[touching[0]])
    assert np.all(timeline.status[touching] == "converged")
    assert np.all(np.abs(timeline.wrench_estimated[touching, 2] - timeline.wrench_true[touching, 2]) < 0.03)


def test_a_calibrations_head_corrects_each_live_wrench_and_widens_its_covariance(device, inverter, reference):
    # The head's correction and residual, applied per frame, are the ones `invert` applies to
    # a recording: the same wrench and, on the covariance's diagonal, the same sigma.
    sensor = SimulatedSensor(device)
    frame = sensor.render(np.array([0.1, -0.05, 0.8, 0.001, -0.002, 0.002]), Contact(1.0, -2.0, 3.0))
    rng = np.random.default_rng(0)
    head = mj.ResidualHead(
        jax.numpy.asarray(rng.normal(0.0, 0.05, (6, 12)), jax.numpy.float32),
        jax.numpy.asarray(rng.normal(0.0, 0.05, 6), jax.numpy.float32),
        jax.numpy.asarray([0.01, 0.02, 0.03, 0.01, 0.02, 0.005], jax.numpy.float32),
    )
    plain = make_tactile_processor(inverter, reference, pressure_shape=(16, 16))
    corrected = make_tactile_processor(inverter, reference, pressure_shape=(16, 16), head=head)
    wrench, covariance, status, _, extras = plain(frame)
    fixed, fixed_covariance, fixed_status, _, fixed_extras = corrected(frame)
    assert status == fixed_status == "converged"
    contact = plain.step(np.asarray(frame, plain.dtype), plain.cold_track)[0].contact
    position = [np.asarray(v, np.float64).reshape(1) for v in (contact.x0, contact.y0, contact.radius)]
    np.testing.assert_allclose(fixed, head.correct(wrench[None], *position)[0], rtol=1e-6, atol=1e-9)
    scale = np.array([mj.PAPER_RANGES[axis] for axis in mj.WRENCH_AXES])
    assert np.max(np.abs(fixed - wrench) / scale) > 1e-3
    np.testing.assert_allclose(
        np.sqrt(np.diag(fixed_covariance)), head.corrected_sigma(np.sqrt(np.diag(covariance))[None])[0], rtol=1e-9
    )
    np.testing.assert_allclose(
        fixed_covariance - np.diag(np.diag(fixed_covariance)), covariance - np.diag(np.diag(covariance))
    )
    # The pressure map is drawn from the corrected wrench, not the physical one.
    assert not np.allclose(fixed_extras["pressure"], extras["pressure"])
