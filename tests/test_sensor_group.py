"""Several sensors in one process: the grip wrench of a parallel gripper's two pads against
hand-computed statics and its covariance against finite differences; a group of two
simulated sensors whose merged stream holds every record of each exactly once; and the
`live --sensor` command with its errors."""

import json
import math

import numpy as np
import pytest

import moirejax as mj
from moirejax._fileio import validate_json
from moirejax.live import grip_wrench, make_record, Mount, open_sensors, SimulatedSensor


# Two sensors compiled once for the module, on one worker.
pytestmark = pytest.mark.xdist_group("sensor_group")

# A small field (16 mm at 8 px/mm) so that each sensor compiles in seconds.
DEVICE = mj.preset("mid", height=128, width=128, px_per_mm=8.0)
FRAMES = 12

# A parallel gripper: z_g the approach direction, the fingers closing along y_g, the left
# pad at y_g = +D facing -y_g, the right one at -D facing +y_g. "Into the pad" (the pad's
# +z, where a press points) is +y_g on the left and -y_g on the right; each pad's x is x_g.
D = 0.04
LEFT = Mount.from_rpy((0.0, D, 0.0), -math.pi / 2, 0.0, 0.0)
RIGHT = Mount.from_rpy((0.0, -D, 0.0), math.pi / 2, 0.0, 0.0)
MOUNTS = {"left": LEFT, "right": RIGHT}


def touched(sensor, wrench, covariance=None, stamp=100.0, status="converged"):
    return make_record(
        stamp=stamp,
        frame=0,
        mode="tactile",
        status=status,
        wrench=wrench,
        covariance=covariance,
        sensor_id=sensor,
        monotonic=stamp - 50.0,
        in_contact=True,
        latency_ms=5.0,
    )


def untouched(sensor, stamp=100.0):
    return make_record(
        stamp=stamp,
        frame=0,
        mode="vision",
        status="no_contact",
        wrench=np.zeros(6),
        sensor_id=sensor,
        monotonic=stamp - 50.0,
        latency_ms=5.0,
    )


def test_mounts_of_the_gripper_turn_the_pad_normals_to_face_each_other():
    assert np.allclose(LEFT.rotation @ [0, 0, 1], [0, 1, 0]) and np.allclose(RIGHT.rotation @ [0, 0, 1], [0, -1, 0])
    assert np.allclose(LEFT.rotation @ [1, 0, 0], [1, 0, 0]) and np.allclose(RIGHT.rotation @ [1, 0, 0], [1, 0, 0])


def test_an_off_centre_weight_held_by_two_pads():
    """Both pads squeeze with 5 N and carry half of a 2 N weight that hangs e = 1 cm off
    the gripper's axis along x_g: the squeeze cancels, the weight remains, and its moment
    about the gripper origin is e W about y_g (x_g cross -z_g = +y_g)."""
    squeeze, weight, e = 5.0, 2.0, 0.01
    # The object pushes each pad down (-z_g): the left pad's y is -z_g, the right's +z_g.
    f_left, f_right = np.array([0.0, weight / 2, squeeze]), np.array([0.0, -weight / 2, squeeze])
    # Both contacts at pad point (e, 0, 0): a pad's torque about its origin is c x f.
    c = np.array([e, 0.0, 0.0])
    records = {
        "left": touched("left", np.r_[f_left, np.cross(c, f_left)], stamp=100.0),
        "right": touched("right", np.r_[f_right, np.cross(c, f_right)], stamp=100.004),
    }
    grip = grip_wrench(records, MOUNTS, sensor_id="grip", frame_id="gripper_base")
    assert grip.status == "converged" and grip.in_contact and grip.sensor_id == "grip"
    assert grip.frame_id == "gripper_base"
    assert np.allclose(grip.force, [0.0, 0.0, -weight], atol=1e-12)
    assert np.allclose(grip.torque, [0.0, e * weight, 0.0], atol=1e-12)
    # The same torque as the sum of contact point x force in the gripper frame.
    points = [LEFT.rotation @ c + LEFT.translation, RIGHT.rotation @ c + RIGHT.translation]
    forces = [LEFT.rotation @ f_left, RIGHT.rotation @ f_right]
    assert np.allclose(grip.torque, sum(np.cross(p, f) for p, f in zip(points, forces)), atol=1e-12)
    # Stamped with the newer capture, the spread of the two carried along.
    assert grip.stamp == 100.004 and grip.skew_ms == pytest.approx(4.0)
    validate_json(grip.to_dict(), "live_record")


def test_a_pure_translation_adds_t_cross_f():
    t = np.array([0.01, -0.02, 0.15])
    wrench = np.array([0.3, -0.2, 1.1, 2e-3, -1e-3, 5e-4])
    grip = grip_wrench({"a": touched("a", wrench)}, {"a": Mount(np.eye(3), t)})
    assert np.allclose(grip.force, wrench[:3]) and np.allclose(grip.torque, wrench[3:] + np.cross(t, wrench[:3]))


def test_covariance_goes_through_the_adjoint_of_each_pad():
    """The grip covariance is J_s Sigma_s J_s^T summed over the independent pads, J_s the
    Jacobian of the grip wrench in pad s's wrench, here by central differences."""
    rng = np.random.default_rng(3)
    mounts = {"left": LEFT, "right": Mount.from_rpy((0.01, -D, 0.02), 1.2, -0.3, 0.7)}
    wrenches = {name: rng.normal(size=6) * [0.1, 0.1, 1.0, 1e-3, 1e-3, 1e-3] for name in mounts}
    covariances = {}
    for name in mounts:
        a = rng.normal(size=(6, 6)) * [0.01, 0.01, 0.05, 1e-4, 1e-4, 1e-4]
        covariances[name] = a @ a.T
    records = {name: touched(name, wrenches[name], covariances[name]) for name in mounts}
    grip = grip_wrench(records, mounts)
    expected = np.zeros((6, 6))
    for name in mounts:
        jacobian = np.zeros((6, 6))
        for k in range(6):
            step = np.zeros(6)
            step[k] = 1e-3
            moved = [{**records, name: touched(name, wrenches[name] + s * step)} for s in (1, -1)]
            ends = [grip_wrench(m, mounts).wrench for m in moved]
            jacobian[:, k] = (ends[0] - ends[1]) / 2e-3
        expected += jacobian @ covariances[name] @ jacobian.T
    assert np.allclose(np.asarray(grip.covariance), expected, rtol=1e-8, atol=1e-14)


def test_an_untouched_pad_adds_nothing_and_a_bad_one_makes_the_grip_unavailable():
    wrench = np.array([0.0, 0.1, 1.0, 0.0, 0.0, 0.0])
    cov = np.diag([1e-4, 1e-4, 1e-3, 1e-8, 1e-8, 1e-8])
    one = grip_wrench({"left": touched("left", wrench, cov), "right": untouched("right")}, MOUNTS)
    assert one.status == "converged" and np.allclose(one.wrench, LEFT.adjoint @ wrench)
    assert np.allclose(np.asarray(one.covariance), LEFT.adjoint @ cov @ LEFT.adjoint.T)
    none = grip_wrench({"left": untouched("left"), "right": untouched("right")}, MOUNTS)
    assert none.status == "no_contact" and not none.in_contact and np.all(none.wrench == 0)
    slow = grip_wrench({"left": touched("left", wrench, status="max_steps"), "right": untouched("right")}, MOUNTS)
    assert slow.status == "max_steps" and slow.covariance is None
    for bad in ("unexplained", "bad_frame", "source_lost"):
        record = touched("right", wrench, status=bad)
        grip = grip_wrench({"left": touched("left", wrench), "right": record}, MOUNTS)
        assert grip.status == "unavailable" and grip.wrench is None and "right: " + bad in grip.message
        validate_json(grip.to_dict(), "live_record")
    early = grip_wrench({"left": touched("left", wrench)}, MOUNTS)
    assert early.status == "unavailable" and "right: no record yet" in early.message


@pytest.mark.parametrize(
    "rotation, match",
    [
        (2 * np.eye(3), "orthonormal"),
        (np.diag([1.0, 1.0, -1.0]), "reflection"),
        ([[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "orthonormal"),
        (np.full((3, 3), np.nan), "finite"),
        (np.eye(2), "3x3"),
    ],
)
def test_a_mount_refuses_what_is_not_a_rotation(rotation, match):
    with pytest.raises(ValueError, match=match):
        Mount(rotation, (0.0, 0.0, 0.0))


def test_roll_pitch_yaw_compose_about_the_fixed_axes():
    """R = Rz(yaw) Ry(pitch) Rx(roll): a quarter yaw after a quarter roll takes the pad's y
    axis (rolled onto z) to z, and its x axis (yawed onto y) to y."""
    mount = Mount.from_rpy((0.0, 0.0, 0.0), math.pi / 2, 0.0, math.pi / 2)
    assert np.allclose(mount.rotation @ [0, 1, 0], [0, 0, 1]) and np.allclose(mount.rotation @ [1, 0, 0], [0, 1, 0])


# ---------------------------------------------------------------------------------------
# Two simulated sensors in one process.


@pytest.fixture(scope="module")
def group_run():
    """A group of two simulated sensors on different load scripts, mounted as the gripper's
    pads: what an iterator, a callback and `latest()` saw."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MOIREJAX_CARRIERS", "0")
        specs = {
            name: {"device": DEVICE, "source": "sim", "sensor": SimulatedSensor(DEVICE, n_frames=FRAMES, seed=seed)}
            for name, seed in (("left", 1), ("right", 2))
        }
        seen: list = []
        group = open_sensors(specs, MOUNTS, grip_frame="gripper_base", max_frames=FRAMES, start=False)
        group.on_record(seen.append)
        records = iter(group)  # every record from here on, and none has come yet
        group.start()
        iterated = list(records)
        finished = group.join(60.0)
        latest = group.latest()
        group.close()
    return {"group": group, "seen": seen, "iterated": iterated, "finished": finished, "latest": latest}


def test_the_merged_stream_holds_every_record_of_each_sensor_once(group_run):
    assert group_run["finished"] and not group_run["group"].errors
    records = group_run["iterated"]
    for name in ("left", "right"):
        mine = [r for r in records if r.sensor_id == name]
        summary = group_run["group"].handles[name].summary
        assert [r.seq for r in mine] == list(range(summary.records)) and len(mine) == FRAMES
        assert {r.frame_id for r in mine} == {f"{name}_sensor"}
    # The callback saw the same records, in the same (arrival) order, as the iterator.
    assert [(r.sensor_id, r.seq) for r in group_run["seen"]] == [(r.sensor_id, r.seq) for r in records]
    newest = {r.sensor_id: r for r in records}
    assert {k: r.seq for k, r in group_run["latest"].items()} == {k: r.seq for k, r in newest.items()}
    for record in records:
        validate_json(json.loads(record.to_json()), "live_record")


def test_each_sensor_record_after_both_have_one_is_followed_by_the_grip(group_run):
    records = group_run["iterated"]
    first_both = max(next(i for i, r in enumerate(records) if r.sensor_id == name) for name in MOUNTS)
    grips = [r for r in records if r.sensor_id == "grip"]
    assert [r.seq for r in grips] == list(range(len(grips)))
    assert len(grips) == sum(r.sensor_id in MOUNTS for r in records[first_both:])
    newest: dict = {}
    for record, after in zip(records, records[1:] + [None]):
        if record.sensor_id == "grip":
            continue
        newest[record.sensor_id] = record
        if len(newest) == 2:
            assert after is not None and after.sensor_id == "grip" and after.frame_id == "gripper_base"
            expected = grip_wrench(newest, MOUNTS)
            assert after.status == expected.status and after.stamp == max(r.stamp for r in newest.values())
            if expected.wrench is not None:
                assert np.allclose(after.wrench, expected.wrench)
            assert after.skew_ms == pytest.approx(expected.skew_ms) and after.latency_ms >= 0


def test_a_group_refuses_what_cannot_be_a_group():
    with pytest.raises(ValueError, match="at least one"):
        mj.live.SensorGroup({})
    with pytest.raises(ValueError, match="no device"):
        open_sensors({"left": {"source": "sim"}})
    with pytest.raises(ValueError, match="by its key"):
        open_sensors({"left": (DEVICE, "sim")}, sensor_id="x")


# ---------------------------------------------------------------------------------------
# The command line.


@pytest.fixture
def unit_file(tmp_path):
    from moirejax.physics._device import device_to_json

    mj.write_json(tmp_path / "unit.json", device_to_json(DEVICE))
    return str(tmp_path / "unit.json")


def test_live_command_streams_two_sensors_and_the_grip_to_one_sink(tmp_path, unit_file, monkeypatch):
    from moirejax.cli import main

    monkeypatch.setenv("MOIREJAX_CARRIERS", "0")
    out = tmp_path / "records.jsonl"
    args = ["live", "--sensor", f"left={unit_file}@sim", "--sensor", f"right={unit_file}@sim"]
    args += ["--mount", f"left=0,{D},0,-90,0,0", "--mount", f"right=0,{-D},0,90,0,0", "--grip-frame", "hand"]
    args += ["--max-frames", str(FRAMES), "--sink", str(out)]
    assert main(args) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    for record in records:
        validate_json(record, "live_record")
    for name in ("left", "right"):
        assert [r["seq"] for r in records if r["sensor_id"] == name] == list(range(FRAMES))
    grips = [r for r in records if r["sensor_id"] == "grip"]
    assert grips and {r["frame_id"] for r in grips} == {"hand"} and all("skew_ms" in r for r in grips)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--sensor", "left"], "--sensor: 'left' is not NAME=DEVICE.json@SOURCE"),
        (["--sensor", "left=unit.json"], "--sensor: 'left=unit.json' is not NAME=DEVICE.json@SOURCE"),
        (["--sensor", "a=UNIT@sim", "--sensor", "a=UNIT@sim"], "--sensor: the name 'a' is given twice"),
        (["--sensor", "a=UNIT@sim", "--mount", "b=0,0,0,0,0,0"], "--mount: 'b' is not a sensor"),
        (["--sensor", "a=UNIT@sim", "--mount", "a=0,0,0"], "--mount: 'a=0,0,0' is not NAME=x,y,z,roll,pitch,yaw"),
        (["--sensor", "a=UNIT@sim", "--device", "UNIT"], "--sensor and --device"),
        (["--sensor", "a=UNIT@sim", "--source", "0"], "--sensor and --source"),
        (["--sensor", "a=UNIT@sim", "--grip-frame", "hand"], "--grip-frame needs --mount"),
        (["--sensor", "grip=UNIT@sim", "--mount", "grip=0,0,0,0,0,0"], "--sensor: the name 'grip'"),
        (["--device", "UNIT", "--mount", "a=0,0,0,0,0,0"], "--mount needs --sensor"),
        ([], "needs --device FIT.json (one sensor) or --sensor"),
    ],
)
def test_live_command_names_the_flag_of_a_bad_sensor_spec(extra, message, unit_file, capsys):
    from moirejax.cli import main

    code = main(["live", *(a.replace("UNIT", unit_file) for a in extra)])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_live_command_names_the_sensor_of_a_missing_unit_file(tmp_path, capsys):
    from moirejax.cli import main

    code = main(["live", "--sensor", f"left={tmp_path / 'nowhere.json'}@sim"])
    err = capsys.readouterr().err
    assert code == 3 and "nowhere.json" in err and "(given by --sensor left)" in err
