"""A reference force/torque sensor logged beside the camera: text readings over UDP, an ATI
Net F/T box over its raw data transfer protocol (against a fake box on this host), the log
`import --ft` reads, and the failure paths (malformed datagrams, faulted samples, a clock
stepping back, bad specs)."""

import json
import socket
import struct
import threading
import time

import numpy as np
import pytest

from moirejax.data import read_ft_log
from moirejax.live import (
    ForceTorqueLog,
    make_record,
    NetFTSource,
    open_ft_source,
    RecordingSink,
    UdpForceTorqueSource,
)

from .helpers import wait_until


def send(address, *payloads):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for payload in payloads:
            s.sendto(payload.encode() if isinstance(payload, str) else payload, address)


def test_udp_readings_in_every_accepted_form_and_malformed_ones_counted():
    source = UdpForceTorqueSource("127.0.0.1", 0, clock=lambda: 1000.0)
    got: list = []
    source.start(lambda t, w: got.append((t, w)))
    try:
        send(
            source.address,
            "1.5,0.1,0.2,0.3,0.004,0.005,0.006\n2.5 0.1 0.2 0.3 0.004 0.005 0.006",  # two lines, own clock
            "0.1,0.2,0.3,0.004,0.005,0.006",  # no time: stamped on arrival
            json.dumps({"t": 3.5, "force": [1, 2, 3], "torque": [0.01, 0.02, 0.03]}),
            json.dumps({"wrench": [1, 2, 3, 0.01, 0.02, 0.03]}),
            "t,fx,fy,fz,tx,ty,tz",  # a header: not a reading
            "1,2,3",  # too few numbers
            "4.5,nan,0,0,0,0,0",  # not finite
            b"\xff\xfe",  # not text
        )
        assert wait_until(lambda: source.stats["malformed"] >= 4 and len(got) >= 5, 10.0)
    finally:
        source.close()
    times = [t for t, _ in got]
    assert times == [1.5, 2.5, 1000.0, 3.5, 1000.0]
    np.testing.assert_allclose(got[0][1], [0.1, 0.2, 0.3, 0.004, 0.005, 0.006])
    np.testing.assert_allclose(got[3][1], [1, 2, 3, 0.01, 0.02, 0.03])
    assert source.stats["readings"] == 5 and source.stats["malformed"] == 4


def test_a_mounting_map_turns_readings_into_the_sensors_convention():
    # An F/T sensor mounted upside down about x: y and z flip, for forces and torques alike.
    flip = np.diag([1.0, -1.0, -1.0, 1.0, -1.0, -1.0])
    source = UdpForceTorqueSource("127.0.0.1", 0, to_sensor=flip)
    got: list = []
    source.start(lambda t, w: got.append(w))
    try:
        send(source.address, "0,0.1,0.2,0.3,0.004,0.005,0.006")
        assert wait_until(lambda: got, 10.0)
    finally:
        source.close()
    np.testing.assert_allclose(got[0], [0.1, -0.2, -0.3, 0.004, -0.005, -0.006])
    with pytest.raises(ValueError, match="6 x 6"):
        UdpForceTorqueSource("127.0.0.1", 0, to_sensor=np.eye(3))


class FakeNetFT:
    """An ATI Net F/T box on this host: answers the streaming request with `samples`, each
    `(status, counts)`, and records the commands it was sent."""

    def __init__(self, samples):
        self.samples = samples
        self.commands: list[tuple[int, int, int]] = []
        self.socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.socket.bind(("127.0.0.1", 0))
        self.socket.settimeout(0.1)
        self.port = self.socket.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.serve, daemon=True)
        self.thread.start()

    def serve(self):
        while not self.stop.is_set():
            try:
                data, peer = self.socket.recvfrom(64)
            except TimeoutError:
                continue
            header, command, count = struct.unpack(">HHI", data)
            self.commands.append((header, command, count))
            if command == 2:
                for seq, (status, counts) in enumerate(self.samples):
                    self.socket.sendto(struct.pack(">III6i", seq, seq, status, *counts), peer)
                self.socket.sendto(b"short", peer)  # not a sample

    def close(self):
        self.stop.set()
        self.thread.join(2)
        self.socket.close()


def test_netft_samples_are_scaled_by_the_boxs_counts_and_faults_dropped():
    counts = [100_000, -200_000, 1_200_000, 4_000, -5_000, 6_000]
    box = FakeNetFT([(0, counts), (0x80000000, counts), (0, [0] * 6)])
    source = NetFTSource("127.0.0.1", box.port, counts_per_force=1e6, counts_per_torque=1e6, bias=True)
    got: list = []
    source.start(lambda t, w: got.append(w))
    try:
        assert wait_until(lambda: len(got) == 2 and source.stats["malformed"] == 1, 10.0)
    finally:
        source.close()
        time.sleep(0.2)
        box.close()
    np.testing.assert_allclose(got[0], [0.1, -0.2, 1.2, 0.004, -0.005, 0.006])
    np.testing.assert_allclose(got[1], np.zeros(6))
    assert source.stats["faults"] == 1  # the sample with a status bit set
    # Bias, then stream without end, then stop: each a request with the RDT header.
    assert box.commands == [(0x1234, 0x42, 0), (0x1234, 2, 0), (0x1234, 0, 0)]


def test_the_log_is_what_import_reads_and_a_clock_stepping_back_is_left_out(tmp_path):
    source = UdpForceTorqueSource("127.0.0.1", 0)
    log = ForceTorqueLog(tmp_path / "ft.csv", source, flush_every=0.0)
    send(source.address, *[f"{0.001 * i!r},{i},0,{2 * i},0,0,0" for i in range(50)], "0.0005,9,9,9,9,9,9")
    assert wait_until(lambda: log.stats["written"] + log.stats["out_of_order"] == 51, 10.0)
    # Flushed as it goes: readable before the log is closed.
    times, wrenches = read_ft_log(tmp_path / "ft.csv")
    assert len(times) == 50
    log.close()
    times, wrenches = read_ft_log(tmp_path / "ft.csv")
    np.testing.assert_allclose(times, 0.001 * np.arange(50))
    np.testing.assert_allclose(wrenches[:, 2], 2 * np.arange(50))
    assert log.stats["out_of_order"] == 1
    with pytest.raises(OSError, match="ft.csv"):  # an existing log is never overwritten
        ForceTorqueLog(tmp_path / "ft.csv", UdpForceTorqueSource("127.0.0.1", 0))


def test_a_recording_with_a_force_torque_source_writes_both_logs(tmp_path):
    source = UdpForceTorqueSource("127.0.0.1", 0)
    sink = RecordingSink(tmp_path / "session", ft=source)
    frame = np.full((8, 8), 0.5, np.float32)
    for i in range(3):
        sink.emit_image(frame, make_record(stamp=100.0 + i, frame=i, mode="tactile", status="converged"))
        send(source.address, f"{100.0 + i + 0.5},0,0,{i},0,0,0")
    assert wait_until(lambda: source.stats["readings"] == 3, 10.0)
    sink.close()
    assert len((tmp_path / "session" / "frames.csv").read_text().splitlines()) == 4
    times, wrenches = read_ft_log(tmp_path / "session" / "ft.csv")
    np.testing.assert_allclose(times, [100.5, 101.5, 102.5])
    np.testing.assert_allclose(wrenches[:, 2], [0, 1, 2])


def test_source_specs():
    udp = open_ft_source("udp://127.0.0.1:0")
    assert isinstance(udp, UdpForceTorqueSource)
    udp.close()
    netft = open_ft_source("netft://127.0.0.1:49999?cpf=1000000&cpt=1000")
    assert isinstance(netft, NetFTSource) and netft.port == 49999
    for bad in ("tcp://host:1", "udp://host", "netft://", "netft://h?cpf=1"):
        with pytest.raises(ValueError, match="force/torque source"):
            open_ft_source(bad)
    with pytest.raises(ValueError, match="both"):
        NetFTSource("127.0.0.1", counts_per_force=1e6)


def test_live_refuses_a_force_torque_source_without_a_recording(tmp_path, capsys):
    from moirejax.cli import main

    with pytest.raises(SystemExit) as exit_info:
        raise SystemExit(main(["live", "--device", "unit.json", "--ft", "udp://127.0.0.1:0"]))
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--record-frames" in err[0]
