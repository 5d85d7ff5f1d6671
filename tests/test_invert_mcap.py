"""ROS 2 messages without ROS: `moirejax invert --mcap` (every inverted frame, read back with
the `mcap_ros2` decoder and checked against the CSV `invert` writes; statuses, stamps, no half
file after an interruption) and the `examples/ros2_node.py` node's message of a record."""

import csv
import dataclasses
import functools
import importlib.util
import json
import math
import sys
from pathlib import Path

import cv2
import equinox as eqx
import jax
import numpy as np
import pytest

import moirejax as mj
import moirejax.calibration
import moirejax.inverse
import moirejax.live
from moirejax._fileio import validate_json
from moirejax.cli._main import main
from moirejax.live import McapSink, record_inversion, RecordStream

from .test_live_mcap import read


# The invert run is built once, on one worker.
pytestmark = pytest.mark.xdist_group("invert_mcap")

CORRUPT = 3  # the frame of the recording whose file is not an image
# The camera of the other `invert` tests (tests/test_workflows.py): 256 x 256 px at 8 px/mm.
SMALL = dict(height=256, width=256, px_per_mm=8.0)

SCHEMAS = {
    "/moirejax/record": "std_msgs/msg/String",
    "/moirejax/wrench": "geometry_msgs/msg/WrenchStamped",
    "/moirejax/image": "sensor_msgs/msg/CompressedImage",
    "/moirejax/pressure": "sensor_msgs/msg/Image",
}


def stamp_ns(message):
    return message.ros_msg.header.stamp.sec * 10**9 + message.ros_msg.header.stamp.nanosec


@pytest.fixture(scope="module")
def single_precision():
    """JAX's default float32 in every thread while this module runs: the precision the
    command runs in, which the sensor handle's own thread must share to reuse its programs."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", False)
    yield
    jax.config.update("jax_enable_x64", previous)


@pytest.fixture(scope="module")
def inverted(tmp_path_factory, single_precision):
    """`invert --mcap` on a press-twist-slide-release recording of 8 frames (60 fps, with
    capture times), at the size, precision and bands of the other `invert` tests (the moiré
    bands alone: this checks the files, not the accuracy)."""
    root = tmp_path_factory.mktemp("invert_mcap")
    device = mj.preset("mid", **SMALL)
    mj.save_device(root / "mid.json", device)
    mj.simulate_dataset(root / "seq", device, "sequence", 8, seed=3, fidelity="model", progress=False)
    (root / "seq" / "frames" / f"{CORRUPT:06d}.png").write_bytes(b"not a png")
    argv = ["invert", "--device", str(root / "mid.json"), "--data", str(root / "seq"), "--out"]
    argv += [str(root / "w.csv"), "--mcap", str(root / "bags" / "run.mcap"), "--frame-id", "left_pad", "--quiet"]
    argv += ["--maps", str(root / "maps.h5"), "--plot", str(root / "plots"), "--plot-frames", "3"]
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MOIREJAX_CARRIERS", "0")
        code = main(argv)
    with open(root / "w.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return {"code": code, "root": root, "rows": rows, "mcap": root / "bags" / "run.mcap"}


def test_every_frame_is_a_record_with_its_status_and_the_csv_wrench(inverted):
    assert inverted["code"] == 0
    path, rows = inverted["mcap"], inverted["rows"]
    assert path.exists() and not path.with_name("run.mcap.part").exists()
    messages = read(path)
    assert {m.channel.topic: m.schema.name for m in messages} == SCHEMAS

    statuses = [row["status"] for row in rows]
    assert statuses[CORRUPT] == "unreadable" and "converged" in statuses and "no_contact" in statuses
    records = [json.loads(m.ros_msg.data) for m in read(path, "/moirejax/record")]
    assert [r["status"] for r in records] == statuses
    assert [r["frame"] for r in records] == list(range(len(rows))) and [r["seq"] for r in records] == list(range(8))
    for record in records:
        validate_json(record, "live_record")
        assert record["frame_id"] == "left_pad" and record["mode"] == "tactile"
    # A frame without a wrench says so: no wrench at all, never a zero one.
    assert records[CORRUPT]["force"] is None and records[CORRUPT]["torque"] is None
    assert records[CORRUPT]["message"] == rows[CORRUPT]["message"] and not records[CORRUPT]["in_contact"]

    # A WrenchStamped for each frame whose wrench is a reading, equal to the CSV's to the bit.
    with_wrench = [row for row in rows if row["status"] in ("converged", "max_steps", "no_contact")]
    wrenches = read(path, "/moirejax/wrench")
    assert len(wrenches) == len(with_wrench) == len(rows) - 1
    for message, row in zip(wrenches, with_wrench):
        w = message.ros_msg.wrench
        got = (w.force.x, w.force.y, w.force.z, w.torque.x, w.torque.y, w.torque.z)
        assert got == tuple(float(row[axis]) for axis in mj.WRENCH_AXES)
        assert message.ros_msg.header.frame_id == "left_pad"
    in_contact = [r for r in records if r["status"] == "converged"]
    assert all(r["in_contact"] and r["contact_area_mm2"] > 0 for r in in_contact)


def test_frames_and_pressure_maps_of_the_recording(inverted):
    path, rows, root = inverted["mcap"], inverted["rows"], inverted["root"]
    images = read(path, "/moirejax/image")
    assert len(images) == len(rows) - 1  # all but the file that is not an image
    first = cv2.imdecode(np.frombuffer(images[0].ros_msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
    stored = cv2.imread(str(root / "seq" / "frames" / rows[0]["frame"]), cv2.IMREAD_UNCHANGED)
    scale = 257.0 if stored.dtype == np.uint16 else 1.0  # 16-bit frames are sent as 8-bit
    assert first.shape == stored.shape and np.abs(first - stored / scale).mean() < 4.0  # JPEG of fine fringes
    pressure = read(path, "/moirejax/pressure")
    loaded = [i for i, row in enumerate(rows) if row["status"] in ("converged", "max_steps")]
    assert len(pressure) == len(loaded) > 0
    # The map's resultant is the frame's normal force (Pa over the cells' area, in N).
    msg = pressure[0].ros_msg
    device = mj.preset("mid", **SMALL)
    cell_mm = device.width / msg.width / float(device.px_per_mm) * float((device.Z + device.a) / device.Z)
    p = np.frombuffer(msg.data, "<f4").reshape(msg.height, msg.width)
    assert p.sum() * (cell_mm * 1e-3) ** 2 == pytest.approx(float(rows[loaded[0]]["fz"]), rel=0.02)


def test_traction_maps_of_the_recording_carry_its_wrenches(inverted):
    rows, root = inverted["rows"], inverted["root"]
    maps = mj.read_traction_maps(root / "maps.h5")
    assert maps.frame == [row["frame"] for row in rows] and maps.status == [row["status"] for row in rows]
    assert maps.traction.shape == (len(rows), 3, *mj.TRACTION_MAP_SHAPE) and maps.traction.dtype == np.float32
    X, Y = np.meshgrid(maps.x_mm, maps.y_mm)
    cell_m2 = ((maps.x_mm[1] - maps.x_mm[0]) * 1e-3) ** 2
    loaded = [i for i, row in enumerate(rows) if row["status"] in ("converged", "max_steps")]
    assert loaded
    for i in loaded:
        tx, ty, p = maps.traction[i].astype(np.float64) * cell_m2
        # The map's resultant and moments about the origin on the surface are the CSV's wrench.
        moments = [tx.sum(), ty.sum(), p.sum(), (Y * p).sum() * 1e-3, -(X * p).sum() * 1e-3]
        moments.append((X * ty - Y * tx).sum() * 1e-3)
        wrench = [float(rows[i][axis]) for axis in mj.WRENCH_AXES]
        ranges = np.array([mj.PAPER_RANGES[a] for a in mj.WRENCH_AXES])
        assert np.all(np.abs(np.subtract(moments, wrench)) <= 1e-4 * np.abs(wrench) + 1e-5 * ranges), (moments, wrench)
        assert p.min() >= 0
        # The centre of pressure is the pressure's centroid.
        centroid = [(X * p).sum() / p.sum(), (Y * p).sum() / p.sum()]
        np.testing.assert_allclose(maps.centre_of_pressure_mm[i], centroid, atol=1e-3)
        assert maps.contact_area_mm2[i] == pytest.approx(math.pi * float(rows[i]["radius"]) ** 2)
    quiet = [i for i, row in enumerate(rows) if row["status"] == "no_contact"]
    assert quiet and all(np.all(maps.traction[i] == 0) for i in quiet)
    assert np.all(np.isnan(maps.traction[CORRUPT])) and maps.contacts[CORRUPT] == 0
    # One frame read alone, from its own chunk.
    one = mj.read_traction_maps(root / "maps.h5", frames=slice(loaded[0], loaded[0] + 1))
    np.testing.assert_array_equal(one.traction[0], maps.traction[loaded[0]])

    chosen = mj.inverse.frames_worth_a_look(rows, 3)
    assert len(chosen) == 3
    drawn = sorted(p.name for p in (root / "plots").iterdir())
    assert drawn == sorted(["timeline.png", *(f"frame-{Path(rows[i]['frame']).stem}.png" for i in chosen)])
    assert all(cv2.imread(str(root / "plots" / name)) is not None for name in drawn)


def test_the_misfit_map_shows_what_a_reading_leaves_of_the_fringes(inverted):
    rows, root = inverted["rows"], inverted["root"]
    dataset = mj.open_dataset(root / "seq")
    device = mj.preset("mid", **SMALL)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MOIREJAX_CARRIERS", "0")
        inverter = mj.Inverter(device, reference=moirejax.calibration.dataset_reference(dataset))
    i = max((k for k, row in enumerate(rows) if row["status"] == "converged"), key=lambda k: float(rows[k]["fz"]))
    frame = dataset.frames([i])[0]
    wrenches, contacts = moirejax.inverse.stack_patches(moirejax.inverse.row_patches(rows[i], "w.csv", i + 2), "f4")
    misfit = functools.partial(eqx.filter_jit(mj.Inverter.misfit_map), inverter)
    change, left = np.asarray(misfit(frame, wrenches, contacts))
    inner = np.asarray(inverter._quiet_mask())
    # The fringes moved far beyond their noise, and the reading explains almost all of it.
    assert change[inner].mean() > 100 and left[inner].sum() < 0.01 * change[inner].sum()
    # Without a load nothing is explained; with half the normal force much is left.
    change0, left0 = np.asarray(misfit(frame, np.zeros_like(wrenches), contacts))
    np.testing.assert_allclose(left0, change0, rtol=1e-3)
    np.testing.assert_array_equal(change0, change)
    half = wrenches.copy()
    half[:, 2] *= 0.5
    _, left_half = np.asarray(misfit(frame, half, contacts))
    assert left_half[inner].sum() > 20 * left[inner].sum()


def test_stamps_are_the_datasets_capture_times(inverted, capsys):
    path = inverted["mcap"]
    dataset = mj.open_dataset(inverted["root"] / "seq")
    assert dataset.fps == 60.0 and dataset.t is not None
    expected = [round(t * 1e9) for t in dataset.t]
    assert [m.log_time_ns for m in read(path, "/moirejax/record")] == expected
    wrench_times = [stamp_ns(m) for m in read(path, "/moirejax/wrench")]
    assert wrench_times == [t for i, t in enumerate(expected) if i != CORRUPT]
    with open(path, "rb") as f:
        from mcap.reader import make_reader

        (meta,) = [m for m in make_reader(f).iter_metadata() if m.name == "moirejax_inversion"]
    assert meta.metadata["stamps"] == "the dataset's t column (s)"


def frames_folder(tmp_path, n):
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(n):
        cv2.imwrite(str(folder / f"f{i}.png"), np.full((16, 16), 40 * i, np.uint8))
    return folder


CSV_HEADER = "frame,fx,fy,fz,tx,ty,tz,sigma_fx,sigma_fy,sigma_fz,sigma_tx,sigma_ty,sigma_tz,x0,y0,radius,status,message"


def test_unbelieved_and_failed_frames_are_records_only(tmp_path):
    folder = frames_folder(tmp_path, 4)
    rows = [
        "f0.png,0.01,0,0.5,0.001,-0.0005,0,0.001,0.001,0.01,1e-5,1e-5,1e-6,0.5,-1,3,converged,converged",
        "f1.png,0.3,-0.2,2.5,0.01,0.02,0.001,0.1,0.1,0.5,1e-3,1e-3,1e-4,0,0,3,unexplained,the model explains less",
        "f2.png,nan,nan,nan,nan,nan,nan,nan,nan,nan,nan,nan,nan,nan,nan,nan,bad_frame,frame is black",
        "f3.png,0,0,0,0,0,0,1e-7,1e-7,1e-7,1e-9,1e-9,1e-9,0,0,3.5,no_contact,no contact detected",
    ]
    (tmp_path / "w.csv").write_text(CSV_HEADER + "\n" + "\n".join(rows) + "\n")
    device = mj.preset("mid", height=64, width=64)
    with McapSink(tmp_path / "run.mcap", wrench_statuses=("converged", "max_steps", "no_contact")) as sink:
        stamps = record_inversion(sink, folder, tmp_path / "w.csv", device, records=RecordStream(sensor_id="s"))
    assert stamps == "the frame index as seconds: the recording gives no frame rate"
    records = [json.loads(m.ros_msg.data) for m in read(tmp_path / "run.mcap", "/moirejax/record")]
    assert [r["status"] for r in records] == ["converged", "unexplained", "bad_frame", "no_contact"]
    # The unexplained frame keeps its best fit in its record, flagged touched but not believed.
    assert records[1]["force"] == [0.3, -0.2, 2.5] and records[1]["in_contact"]
    assert records[2]["force"] is None and records[2]["message"] == "frame is black"
    wrenches = read(tmp_path / "run.mcap", "/moirejax/wrench")
    assert [stamp_ns(m) for m in wrenches] == [0, 3 * 10**9]
    assert wrenches[0].ros_msg.wrench.force.z == 0.5 and wrenches[1].ros_msg.wrench.force.z == 0.0
    assert len(read(tmp_path / "run.mcap", "/moirejax/pressure")) == 1
    assert len(read(tmp_path / "run.mcap", "/moirejax/image")) == 4

    with McapSink(tmp_path / "fps.mcap") as sink:
        assert record_inversion(sink, folder, tmp_path / "w.csv", device, fps=50) == "frame index / 50 fps (given)"
    assert [m.log_time_ns for m in read(tmp_path / "fps.mcap", "/moirejax/record")] == [
        0,
        20_000_000,
        40_000_000,
        60_000_000,
    ]
    # Without wrench_statuses, every finite wrench is written, as the live sink does.
    assert len(read(tmp_path / "fps.mcap", "/moirejax/wrench")) == 3

    (tmp_path / "bad.csv").write_text("frame,fx\nf0.png,1\n")
    with McapSink(tmp_path / "bad.mcap") as sink, pytest.raises(mj.DataError, match="bad.csv: no column"):
        record_inversion(sink, folder, tmp_path / "bad.csv", device)


@pytest.fixture
def no_inversion(monkeypatch, tmp_path):
    """`invert` with the inversion replaced by a CSV of two frames written at once."""
    folder = frames_folder(tmp_path, 2)
    mj.save_device(tmp_path / "mid.json", mj.preset("mid", height=64, width=64))
    rows = "f0.png" + ",0" * 15 + ",no_contact,none\nf1.png" + ",0" * 15 + ",no_contact,none\n"

    def invert_recording(inverter, source, out_csv, **kwargs):
        Path(out_csv).write_text(CSV_HEADER + "\n" + rows)
        return {"no_contact": 2}

    monkeypatch.setattr(moirejax.inverse, "Inverter", lambda device, reference=None: None)
    monkeypatch.setattr(moirejax.inverse, "invert_recording", invert_recording)
    return ["invert", "--device", str(tmp_path / "mid.json"), "--data", str(folder), "--out", str(tmp_path / "w.csv")]


def test_an_interrupted_run_leaves_no_mcap_file(no_inversion, tmp_path, monkeypatch, capsys):
    def interrupted(sink, *args, **kwargs):
        sink.emit(moirejax.live.make_record(stamp=0.0, frame=0, mode="tactile", status="no_contact"))
        raise KeyboardInterrupt

    monkeypatch.setattr(moirejax.live, "record_inversion", interrupted)
    assert main([*no_inversion, "--mcap", str(tmp_path / "run.mcap")]) == 130
    assert not (tmp_path / "run.mcap").exists() and not (tmp_path / "run.mcap.part").exists()


def test_the_mcap_path_is_checked_before_the_inversion(no_inversion, tmp_path, capsys):
    (tmp_path / "run.mcap.part").write_bytes(b"an interrupted run")
    assert main([*no_inversion, "--mcap", str(tmp_path / "run.mcap")]) == 4
    (line,) = capsys.readouterr().err.splitlines()
    assert "run.mcap.part: the unfinished file of an interrupted run" in line and line.endswith("change --mcap")
    assert (tmp_path / "run.mcap.part").read_bytes() == b"an interrupted run" and not (tmp_path / "w.csv").exists()
    (tmp_path / "adir.mcap").mkdir()
    assert main([*no_inversion, "--mcap", str(tmp_path / "adir.mcap")]) == 4
    assert "--mcap" in capsys.readouterr().err
    assert main([*no_inversion, "--fps", "30"]) == 2
    assert "--fps sets the stamps of --mcap" in capsys.readouterr().err
    # The fake inversion's two untouched frames, at the given rate.
    assert main([*no_inversion, "--mcap", str(tmp_path / "ok.mcap"), "--fps", "30"]) == 0
    assert "wrote " + str(tmp_path / "ok.mcap") + ": 2 records, 2 frames, 0 pressure maps" in capsys.readouterr().out
    assert [m.log_time_ns for m in read(tmp_path / "ok.mcap", "/moirejax/wrench")] == [0, round(1e9 / 30)]
    assert math.isclose(read(tmp_path / "ok.mcap", "/moirejax/wrench")[1].ros_msg.wrench.force.z, 0.0)


ROOT = Path(__file__).resolve().parents[1]


def test_ros2_example_imports_without_ros_and_turns_records_into_wrench_stamped(inverted, monkeypatch):
    spec = importlib.util.spec_from_file_location("ros2_node", ROOT / "examples" / "ros2_node.py")
    assert spec is not None and spec.loader is not None
    node = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(node)  # ROS is imported in main() only
    assert "rclpy" not in sys.modules or importlib.util.find_spec("rclpy") is not None

    # The device, precision and bands of the invert run above: its inversion is compiled already.
    device = mj.preset("mid", **SMALL)
    monkeypatch.setenv("MOIREJAX_CARRIERS", "0")
    with mj.open_sensor(device, "sim", max_frames=8, vision=False, sensor_id="left", frame_id="left_pad") as sensor:
        records = list(sensor)
    pressed = next(r for r in records if r.status == "converged" and r.in_contact)
    message = node.wrench_message(pressed)
    assert message["header"]["frame_id"] == "left_pad"
    stamp = message["header"]["stamp"]
    assert 0 <= stamp["nanosec"] < 10**9 and stamp["sec"] == math.floor(pressed.stamp)
    assert stamp["sec"] + stamp["nanosec"] * 1e-9 == pytest.approx(pressed.stamp, abs=1e-6)
    force, torque = message["wrench"]["force"], message["wrench"]["torque"]
    assert (force["x"], force["y"], force["z"]) == pressed.force and force["z"] > 0.1  # pressing is +Fz
    assert (torque["x"], torque["y"], torque["z"]) == pressed.torque
    untouched = next(r for r in records if r.status == "no_contact")
    assert node.wrench_message(untouched)["wrench"]["force"] == {"x": 0.0, "y": 0.0, "z": 0.0}
    # No reading, no wrench: the node publishes the record's status only.
    for status in ("unexplained", "bad_frame", "source_lost"):
        assert node.wrench_message(dataclasses.replace(pressed, status=status)) is None


def test_a_frame_read_with_two_contacts_has_a_pressure_map_of_two_patches(tmp_path):
    folder = frames_folder(tmp_path, 2)
    shares = ",".join(f"second_{axis}" for axis in mj.WRENCH_AXES)
    header = CSV_HEADER.replace("radius,status", f"radius,contacts,second_x0,second_y0,second_radius,{shares},status")
    # 0.6 N at (-4, 0) mm and 0.4 N at (4, 0) mm: moments about the origin Ty = -x Fz.
    second = [0.0, 0.0, 0.4, 0.0, -4e-3 * 0.4, 0.0]
    total = [0.0, 0.0, 1.0, 0.0, 4e-3 * 0.6 - 4e-3 * 0.4, 0.0]
    sigma = ",".join(["1e-3"] * 6)

    def row(name, with_share):
        share = ",".join(map(str, second)) if with_share else ",".join(["nan"] * 6)
        return f"{name},{','.join(map(str, total))},{sigma},-4,0,2.5,2,4,0,2.5,{share},converged,two contacts"

    (tmp_path / "w.csv").write_text(header + "\n" + row("f0.png", True) + "\n" + row("f1.png", False) + "\n")
    device = mj.preset("mid", height=256, width=256, px_per_mm=8.0)
    with McapSink(tmp_path / "run.mcap") as sink:
        record_inversion(sink, folder, tmp_path / "w.csv", device)
    maps = [
        np.frombuffer(m.ros_msg.data, "<f4").reshape(m.ros_msg.height, m.ros_msg.width)
        for m in read(tmp_path / "run.mcap", "/moirejax/pressure")
    ]
    records = [json.loads(m.ros_msg.data) for m in read(tmp_path / "run.mcap", "/moirejax/record")]
    two, old = maps
    w = two.shape[1]
    left, right = two[:, : w // 2].sum(), two[:, w // 2 :].sum()
    # Each patch carries its own share of the normal force, in its own half of the image.
    assert right / (left + right) == pytest.approx(0.4, abs=0.02)
    assert two.min() >= 0 and two[:, : w // 2].max() > 1.2 * two[:, w // 2 :].max() > 0
    assert records[0]["contact_area_mm2"] == pytest.approx(2 * math.pi * 2.5**2)
    # A file written before the second patch's share was a column draws the whole load on one patch.
    assert old[:, w // 2 :].sum() < 1e-3 * old.sum()
    assert records[1]["contact_area_mm2"] == pytest.approx(math.pi * 2.5**2)


def test_an_elongated_patch_has_an_elongated_pressure_map(tmp_path):
    folder = frames_folder(tmp_path, 1)
    header = CSV_HEADER.replace("radius,status", "radius,flatness,aspect_ratio,long_axis_angle,status")
    sigma = ",".join(["1e-3"] * 6)
    # An edge along y (90 degrees), four times as long as wide, at the centre.
    angle = math.pi / 2
    row = f"f0.png,0,0,1.0,0,0,0,{sigma},0,0,2.5,0,4,{angle},converged,edge"
    (tmp_path / "w.csv").write_text(header + "\n" + row + "\n")
    device = mj.preset("mid", height=256, width=256, px_per_mm=8.0)
    with McapSink(tmp_path / "run.mcap") as sink:
        record_inversion(sink, folder, tmp_path / "w.csv", device)
    (m,) = list(read(tmp_path / "run.mcap", "/moirejax/pressure"))
    pressure = np.frombuffer(m.ros_msg.data, "<f4").reshape(m.ros_msg.height, m.ros_msg.width).astype(float)
    rows, cols = np.indices(pressure.shape)
    centre_r, centre_c = (np.asarray(pressure.shape) - 1) / 2
    spread_rows = np.sum(pressure * (rows - centre_r) ** 2) / pressure.sum()
    spread_cols = np.sum(pressure * (cols - centre_c) ** 2) / pressure.sum()
    # Semi-axes 2 r along y and r / 2 across: second moments sixteen times apart.
    assert spread_rows / spread_cols == pytest.approx(16.0, rel=0.1)
    (record,) = [json.loads(m.ros_msg.data) for m in read(tmp_path / "run.mcap", "/moirejax/record")]
    assert record["contact_area_mm2"] == pytest.approx(math.pi * 2.5**2)
