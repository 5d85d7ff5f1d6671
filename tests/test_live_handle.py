"""The in-process sensor handle on a simulated unit: records while the caller's loop runs,
a tare that removes a drift of the gratings, a camera that disappears and comes back, MCAP
output; and the record stream's filter and centre of pressure against their definitions."""

import json
import socket
import threading
import time

import cv2
import equinox as eqx
import jax.random as jr
import numpy as np
import pytest

import moirejax as mj
from moirejax._conventions import WRENCH_SCALE
from moirejax._fileio import validate_json
from moirejax.live import (
    CallableSource,
    make_record,
    McapSink,
    Reconnect,
    RecordStream,
    WrenchFilter,
)
from moirejax.physics import Contact
from moirejax.simulate import Simulator

from .helpers import wait_until
from .test_live_mcap import read


# The session fixture is built once, on one worker.
pytestmark = pytest.mark.xdist_group("live_handle")


# A small field (32 mm at 8 px/mm) so that the handle compiles in seconds.
DEVICE = mj.preset("mid", height=256, width=256, px_per_mm=8.0)
# A press centred at (1, -2) mm: its moments about the origin are Tx = y Fz, Ty = -x Fz.
CONTACT = Contact(x0=1.0, y0=-2.0, radius=3.0)
PRESS = np.array([0.05, -0.03, 0.6, -2e-3 * 0.6, -1e-3 * 0.6, 0.0])
# Frame indices of the session: gate warm-up, a press on the unit as it was when its
# reference was taken (from FIRST), the drift of the upper grating (from DRIFT), a press on
# the drifted unit (PRESSED to RELEASED), the camera unplugged (at UNPLUG, for a few grabs).
FIRST, DRIFT, PRESSED, RELEASED, UNPLUG = 20, 60, 160, 180, 220
PRESS_FRAMES = 20
# The upper grating slides by 0.3 rad of its phase (a few micrometres, as a holder's
# thermal expansion does) over 100 frames, five times the gate's baseline memory: drift.
DRIFT_PHASE = 0.3


class Rig:
    """Frames of a simulated unit by index (see the constants); after the test sets
    `tared`, a second press of `PRESS_FRAMES` frames."""

    def __init__(self, device):
        self.device = device
        self.unplugged_grabs = 0
        self.tared = threading.Event()
        self.second_press: int | None = None

    def __call__(self, index):
        if index == UNPLUG and self.unplugged_grabs < 3:
            self.unplugged_grabs += 1
            return None
        drift = DRIFT_PHASE * float(np.clip((index - DRIFT) / (PRESSED - DRIFT), 0.0, 1.0))
        pressed = FIRST <= index < FIRST + PRESS_FRAMES or PRESSED <= index < RELEASED
        if index >= UNPLUG and self.tared.is_set():
            self.second_press = index if self.second_press is None else self.second_press
            pressed = index < self.second_press + PRESS_FRAMES
        elif index >= UNPLUG + 40 and not self.tared.is_set():
            time.sleep(0.05)  # hold the camera back until the tare is done
        wrench, contact = (PRESS, CONTACT) if pressed else (np.zeros(6), Contact())
        return self.render(index, wrench, contact, drift)

    def render(self, index, wrench, contact, drift=0.0):
        """A frame with the renderer's camera effects the inversion does not model: the
        unit's grating fabrication errors, vignetting, PSF, shot and read noise, 8 bits."""
        unit = eqx.tree_at(lambda d: d.optics.phase2, self.device, self.device.optics.phase2 + drift)
        return np.asarray(Simulator(unit, fidelity="high").frame(jr.PRNGKey(index), wrench, contact), np.float32)

    def reference(self):
        """The unit's no-contact reference before the drift: the mean of eight untouched frames."""
        return np.mean([self.render(-1 - i, np.zeros(6), Contact()) for i in range(8)], axis=0)


# Generous: the handle compiles its inversion before the first record, and a loaded
# machine may take minutes; a passing run waits only as long as the handle needs.
COMPILE_TIMEOUT = 900.0


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """One handle through a whole session (see `Rig`): its records, MCAP file and counters."""
    folder = tmp_path_factory.mktemp("handle")
    rig = Rig(DEVICE)
    reconnect = Reconnect(max_attempts=8, initial_delay_s=0.05, max_delay_s=0.2)
    source = CallableSource(rig, live=True, latest=False, reconnect=reconnect)
    mcap = McapSink(folder / "session.mcap")
    seen: list = []
    handle = mj.open_sensor(
        DEVICE, source, reference=rig.reference(), sinks=[mcap], sensor_id="left", frame_id="left_pad"
    )
    handle.on_record(seen.append)
    handle.on_record(lambda record: 1 / 0)  # a broken callback must not stop the stream
    out: dict = {"handle": handle, "seen": seen, "mcap": folder / "session.mcap"}
    records: list = []
    reader = threading.Thread(target=lambda: records.extend(handle), daemon=True)
    reader.start()
    try:
        assert wait_until(lambda: handle.mode == "tactile" and handle.latest().frame >= PRESSED, COMPILE_TIMEOUT)
        out["refused"] = pytest.raises(RuntimeError, handle.tare)
        assert wait_until(lambda: handle.latest().frame >= UNPLUG + 10 and handle.mode == "vision", COMPILE_TIMEOUT)
        compiled = handle._processor.step._compiled
        out["programs_before"] = compiled._cache_size()
        handle.tare()
        rig.tared.set()
        assert wait_until(
            lambda: rig.second_press is not None and handle.latest().frame > rig.second_press + 30, COMPILE_TIMEOUT
        )
        out["programs_after"] = handle._processor.step._compiled._cache_size()
        out["same_program"] = handle._processor.step._compiled is compiled
        out["second_press"] = rig.second_press
    finally:
        handle.close()
        mcap.close()
        reader.join(10)
    out["records"] = records
    return out


def test_a_tare_removes_a_drift_of_the_gratings(session):
    records, second = session["records"], session["second_press"]
    first = [r for r in records if FIRST + 5 <= r.frame < FIRST + PRESS_FRAMES and r.status == "converged"]
    before = [r for r in records if PRESSED <= r.frame < RELEASED and r.mode == "tactile"]
    after = [r for r in records if second + 5 <= r.frame < second + PRESS_FRAMES and r.in_contact]
    assert len(first) > 5 and len(before) > 5 and len(after) > 5
    # What the unit read before it drifted: the model's own error on this load, on every axis.
    undrifted = np.mean([r.wrench for r in first], axis=0)

    def as_before_the_drift(r):
        return r.status == "converged" and np.all(np.abs(r.wrench - undrifted) < 0.1 * WRENCH_SCALE)

    # Against the old reference the drift ruins every reading (a wrong load or a fit the
    # model cannot explain). After the tare every frame converges (but at most one that
    # stops at the solver's step limit, and says so: with the contact's flatness among the
    # unknowns one frame of this press does) and, averaged over the press, the unit reads
    # what it read before the drift to 5% of each range (a frame's own noise is up to a
    # tenth of the shear range on this small, noisy camera).
    assert not any(as_before_the_drift(r) for r in before), [(r.status, r.wrench) for r in before]
    converged = [r for r in after if r.status == "converged"]
    assert len(after) - len(converged) <= 1, [(r.frame, r.status) for r in after if r.status != "converged"]
    assert all(r.status in ("converged", "max_steps") for r in after), [r.status for r in after]
    shift = np.mean([r.wrench for r in converged], axis=0) - undrifted
    assert np.all(np.abs(shift) < 0.05 * WRENCH_SCALE), shift / WRENCH_SCALE
    assert np.all(np.abs(undrifted - PRESS) < 0.25 * WRENCH_SCALE), undrifted


def test_a_tare_is_refused_in_contact_and_reuses_the_compiled_inversion(session):
    assert "in contact" in str(session["refused"].value)
    assert session["handle"].bias.tolist() == [0.0] * 6
    # The new reference went into the same compiled step: one program before and after.
    assert session["same_program"] and session["programs_before"] == session["programs_after"] == 1


def test_records_carry_what_a_driver_record_carries(session):
    records = session["records"]
    seqs = [r.seq for r in records]
    assert seqs == list(range(len(records)))  # the iterator missed none, in order
    assert session["seen"] == records  # and callbacks saw the same, despite a failing one
    assert session["handle"].callback_errors == len(records)
    for r in records:
        assert (r.sensor_id, r.frame_id) == ("left", "left_pad")
        validate_json(r.to_dict(), "live_record")
    second = session["second_press"]
    pressed = [r for r in records if second <= r.frame < second + PRESS_FRAMES and r.status == "converged"]
    assert pressed
    for r in pressed:
        assert r.in_contact and r.out_of_range == (False,) * 6
        # A centred-on-the-patch normal load: the centre of pressure is the patch's centre.
        x, y = r.centre_of_pressure_mm
        assert abs(x - float(CONTACT.x0)) < 0.5 and abs(y - float(CONTACT.y0)) < 0.5
        assert r.contact_area_mm2 == pytest.approx(np.pi * float(CONTACT.radius) ** 2, rel=0.3)
        assert r.pressure is not None and r.pressure.shape == (64, 64)
        assert r.monotonic is not None and r.stamp - r.monotonic > 1e6
    statuses = {r.status for r in records}
    assert {"reconnecting", "reconnected"} <= statuses, statuses


def test_the_mcap_file_holds_every_record_and_wrench(session):
    records = session["records"]
    wrenches = read(session["mcap"], "/moirejax/wrench")
    strings = read(session["mcap"], "/moirejax/record")
    pressure = read(session["mcap"], "/moirejax/pressure")
    assert len(strings) == len(records)
    with_wrench = [r for r in records if r.force is not None]
    assert len(wrenches) == len(with_wrench)
    last = wrenches[-1].ros_msg
    assert last.header.frame_id == "left_pad"
    assert [last.wrench.force.x, last.wrench.force.y, last.wrench.force.z] == list(with_wrench[-1].force)
    assert len(pressure) == sum(r.pressure is not None for r in records) > 0


# ----------------------------------------------------------------------------------------
# The record stream and the filter, against their definitions.


def test_centre_of_pressure_of_a_point_load():
    stream = RecordStream()
    x, y, fz = 2.5e-3, -1.5e-3, 0.8  # m, m, N
    wrench = np.array([0.0, 0.0, fz, y * fz, -x * fz, 0.0])  # Tx = y Fz, Ty = -x Fz
    record = stream.finish(make_record(stamp=0.0, frame=0, mode="tactile", status="converged", wrench=wrench))
    assert record.centre_of_pressure_mm == pytest.approx((2.5, -1.5))
    assert record.out_of_range == (False,) * 6
    loud = stream.finish(make_record(stamp=0.0, frame=1, mode="tactile", status="converged", wrench=wrench * 2))
    assert loud.out_of_range == (False, False, True, False, False, False)
    assert loud.seq == 1
    # No resolved normal force, no centre of pressure; no wrench, no contact.
    light = stream.finish(make_record(stamp=0.0, frame=2, mode="tactile", status="converged", wrench=wrench * 1e-3))
    assert light.centre_of_pressure_mm is None
    idle = stream.finish(make_record(stamp=0.0, frame=3, mode="vision", status="no_contact", wrench=np.zeros(6)))
    assert not idle.in_contact and idle.out_of_range is None
    # Touched, but a fit the model cannot explain: in contact, its wrench passed on untouched.
    odd = stream.finish(make_record(stamp=0.0, frame=4, mode="tactile", status="unexplained", wrench=wrench * 30))
    assert odd.in_contact and odd.out_of_range is None and odd.centre_of_pressure_mm is None
    lost = stream.finish(make_record(stamp=0.0, frame=5, mode="tactile", status="source_lost"))
    assert not lost.in_contact


def test_bias_is_subtracted_from_in_contact_wrenches_only():
    stream = RecordStream()
    stream.set_bias(np.array([0.01, 0.0, 0.1, 0.0, 0.0, 0.0]))
    touched = stream.finish(make_record(stamp=0, frame=0, mode="tactile", status="converged", wrench=np.full(6, 0.5)))
    assert touched.force == pytest.approx((0.49, 0.5, 0.4))
    idle = stream.finish(make_record(stamp=0, frame=1, mode="vision", status="no_contact", wrench=np.zeros(6)))
    assert idle.force == (0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        stream.set_bias(np.full(6, np.nan))


def test_filter_of_a_still_load_is_the_precision_weighted_mean():
    """With no load change allowed, the Kalman filter is the information-weighted mean of the frames."""
    rng = np.random.default_rng(0)
    f = WrenchFilter(process_noise=1e-9)
    truth = np.array([0.05, -0.02, 0.7, 0.001, -0.002, 0.0005])
    information, weighted = np.zeros((6, 6)), np.zeros(6)
    for _ in range(30):
        a = rng.normal(size=(6, 6)) * 0.01
        cov = a @ a.T + np.diag(rng.uniform(1e-5, 1e-3, 6))
        z = rng.multivariate_normal(truth, cov)
        mean, covariance = f.update(z, cov)
        information += np.linalg.inv(cov)
        weighted += np.linalg.solve(cov, z)
    np.testing.assert_allclose(mean, np.linalg.solve(information, weighted), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(covariance, np.linalg.inv(information), rtol=1e-5, atol=1e-12)


def test_filter_follows_a_step_in_a_few_frames_and_restarts_on_release():
    stream = RecordStream(filter=WrenchFilter(process_noise=0.05))
    cov = np.diag((0.02 * WRENCH_SCALE) ** 2)

    def frame(i, wrench, mode="tactile", status="converged"):
        return stream.finish(make_record(stamp=i, frame=i, mode=mode, status=status, wrench=wrench, covariance=cov))

    low, high = np.array([0, 0, 0.2, 0, 0, 0.0]), np.array([0, 0, 1.0, 0, 0, 0.0])
    for i in range(10):
        record = frame(i, low)
    assert record.filtered and record.force[2] == pytest.approx(0.2)
    settled = [frame(10 + i, high).force[2] for i in range(6)]
    assert 0.2 < settled[0] < 1.0 and settled[-1] == pytest.approx(1.0, abs=0.02)
    frame(20, np.zeros(6), mode="vision", status="no_contact")
    assert frame(21, low).force[2] == pytest.approx(0.2)  # a new contact starts afresh


def test_filter_refuses_a_non_positive_process_noise():
    with pytest.raises(ValueError, match="process_noise"):
        WrenchFilter(process_noise=0.0)


def test_version_one_records_still_validate():
    old = {
        "stamp": 1.0,
        "frame": 0,
        "mode": "tactile",
        "status": "converged",
        "force": [0.0, 0.0, 0.5],
        "torque": [0.0, 0.0, 0.0],
        "covariance": None,
        "latency_ms": 3.0,
        "message": "",
    }
    validate_json(old, "live_record")


def test_a_source_object_needs_a_reference():
    with pytest.raises(ValueError, match="reference="):
        mj.live.SensorHandle(DEVICE, CallableSource(lambda i: None))


def test_live_command_writes_filtered_named_records_and_mcap(tmp_path):
    from moirejax.cli import main
    from moirejax.physics._device import device_to_json

    mj.write_json(tmp_path / "unit.json", device_to_json(DEVICE))
    out, mcap = tmp_path / "records.jsonl", tmp_path / "run.mcap"
    args = ["live", "--device", str(tmp_path / "unit.json"), "--max-frames", "40", "--sink", str(out)]
    args += ["--mcap", str(mcap), "--filter", "kalman", "--sensor-id", "right", "--frame-id", "right_pad"]
    # A reference force/torque sensor streaming text readings over UDP while the camera runs.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    args += ["--record-frames", str(tmp_path / "session"), "--ft", f"udp://127.0.0.1:{port}"]
    streaming = threading.Event()
    streaming.set()

    def ft_sensor():
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            while streaming.is_set():
                s.sendto(b"0.01,0.02,0.5,0.001,0.002,0.0003", ("127.0.0.1", port))
                time.sleep(0.005)

    sender = threading.Thread(target=ft_sensor, daemon=True)
    sender.start()
    try:
        assert main(args) == 0
    finally:
        streaming.clear()
        sender.join(5)
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 40 and {r["sensor_id"] for r in records} == {"right"}
    touched = [r for r in records if r["in_contact"] and r["status"] in ("converged", "max_steps")]
    assert touched and all(r["filtered"] for r in touched)
    assert len(read(mcap, "/moirejax/record")) == 40
    assert {m.ros_msg.header.frame_id for m in read(mcap, "/moirejax/wrench")} == {"right_pad"}
    assert len(read(mcap, "/moirejax/pressure")) == len(touched)
    assert not (tmp_path / "run.mcap.part").exists()

    # The recorded frames, with their capture times, are a recording `import` reads: here
    # with a force/torque log sampled at those times (the records' own wrench), which the
    # dataset takes frame by frame.
    index = (tmp_path / "session" / "frames.csv").read_text().splitlines()
    assert index[0] == "frame,t,contact" and len(index) == 41
    rows = [line.split(",") for line in index[1:]]
    assert [float(r[1]) for r in rows] == [r["stamp"] for r in records]
    assert [int(r[2]) for r in rows] == [int(r["mode"] == "tactile") for r in records]
    # The F/T log beside the frames: readings stamped on arrival, on the frames' clock, over the session.
    logged_t, logged = mj.read_ft_log(tmp_path / "session" / "ft.csv")
    assert len(logged_t) > 10 and np.allclose(logged, [0.01, 0.02, 0.5, 0.001, 0.002, 0.0003])
    assert logged_t[0] < records[-1]["stamp"] and logged_t[-1] > records[0]["stamp"]
    first = cv2.imread(str(tmp_path / "session" / "frames" / rows[0][0]), cv2.IMREAD_UNCHANGED)
    assert first.shape == (DEVICE.height, DEVICE.width) and first.dtype == np.uint8
    wrenches = np.array([(r["force"] or [0.0] * 3) + (r["torque"] or [0.0] * 3) for r in records])
    ft = "t,fx,fy,fz,tx,ty,tz\n" + "".join(
        f"{r['stamp']!r}," + ",".join(repr(float(v)) for v in w) + "\n" for r, w in zip(records, wrenches)
    )
    (tmp_path / "ft.csv").write_text(ft)
    mj.import_recording(
        tmp_path / "session" / "frames",
        tmp_path / "session" / "frames.csv",
        tmp_path / "unit.json",
        tmp_path / "dataset",
        ft_csv=tmp_path / "ft.csv",
        progress=False,
    )
    dataset = mj.Dataset(tmp_path / "dataset")
    assert len(dataset) == 40 and np.allclose(dataset.wrenches, wrenches, atol=1e-9)
