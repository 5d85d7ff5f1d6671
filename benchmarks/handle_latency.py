"""The in-process sensor handle on the simulated sensor: `python benchmarks/handle_latency.py --json`.

Opens one and then two [`open_sensor`][moirejax.open_sensor] handles on the `sequence`
load script (approach, press, twist, slide, release) of a Mid unit, every frame in order,
and reads them as a control loop would. Prints, per run: capture-to-`latest()` latency
(median, p90: the record's grab-to-emit latency plus the time until the caller's next
`latest()` sees it), records per second for each sensor and in total, the time `tare()`
takes, compile time and peak memory; the floor beside them is the bare streaming
inversion (`frame_tracker`) on the same frames, measured in the same run. Also the MCAP
sink's cost per record (wrench, record, frame and pressure map) against the JSON-lines
file sink's, and the recording sink's (`live --record-frames`) per raw frame, with the
frame rate it sustains.
"""

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

import moirejax as mj
from moirejax.live import FileSink, make_record, McapSink, RecordingSink, SimulatedSensor


def _stats(values) -> dict:
    values = np.asarray(values, np.float64)
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90))}


def _read_like_a_controller(handles, period_s: float) -> dict:
    """Poll `latest()` every `period_s` until every handle has ended; the delay from each
    record's capture to the first poll that sees it (ms)."""
    seen: list[set] = [set() for _ in handles]
    delays: list[float] = []
    started = time.monotonic()
    while any(h.running for h in handles):
        for h, got in zip(handles, seen):
            record = h.latest()
            if record is not None and record.seq not in got and record.monotonic is not None:
                got.add(record.seq)
                delays.append((time.monotonic() - record.monotonic) * 1e3)
        time.sleep(period_s)
    elapsed = time.monotonic() - started
    summaries = [h.summary for h in handles]
    return {
        "capture_to_latest_ms": _stats(delays),
        "records_per_s_each": [s.records / s.elapsed_s for s in summaries if s is not None],
        "records_per_s_total": sum(s.records for s in summaries if s is not None) / elapsed,
        "status_counts": [s.status_counts for s in summaries if s is not None],
    }


def _floor(device, sensor, n: int) -> dict:
    """The streaming inversion alone on the script's frames (ms per frame)."""
    inverter = mj.Inverter(device, reference=sensor.reference_frame())
    step = mj.frame_tracker(inverter)
    track = inverter.cold_track()
    frames = [sensor.frame(i) for i in range(n)]
    estimate, _ = step(frames[0], track)
    times = []
    for frame in frames:
        t = time.perf_counter()
        estimate, track = step(frame, track)
        estimate.wrench.block_until_ready()
        times.append((time.perf_counter() - t) * 1e3)
    return {"frame_tracker_ms": _stats(times), "frame_tracker_fps": 1e3 / float(np.mean(times))}


def _sink_cost(folder: Path, shape, n: int = 300) -> dict:
    rng = np.random.default_rng(0)
    image = rng.random(shape, dtype=np.float32)
    pressure = rng.random((64, 64), dtype=np.float32) * 1e4
    records = [
        make_record(stamp=time.time(), frame=i, mode="tactile", status="converged", wrench=rng.normal(size=6) * 0.1)
        for i in range(n)
    ]
    costs = {}
    for name, sink in (("file", FileSink(folder / "r.jsonl")), ("mcap", McapSink(folder / "r.mcap"))):
        t = time.perf_counter()
        for record in records:
            sink.emit(record)
            if name == "mcap":
                sink.emit_image(image, record)
                sink.emit_pressure(pressure, record)
        sink.close()
        costs[f"{name}_ms_per_record"] = (time.perf_counter() - t) * 1e3 / n
    # The raw frames of a calibration session (live --record-frames): each frame's write,
    # against the 16.7 ms a 60 fps camera allows; 8-bit noise is the hardest case for PNG.
    camera = (image * 255).astype(np.uint8)
    recording = RecordingSink(folder / "session")
    times = []
    for record in records:
        t = time.perf_counter()
        recording.emit_image(camera, record)
        times.append((time.perf_counter() - t) * 1e3)
    recording.close()
    costs["recording_ms_per_frame"] = _stats(times)
    costs["recording_sustained_fps"] = 1e3 / float(np.mean(times))
    costs["recording_errors"] = recording.stats["errors"]
    return costs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120, help="frames of the load script per sensor")
    parser.add_argument("--size", type=int, default=512, help="frame side in pixels (the field stays 32 mm)")
    parser.add_argument("--poll-hz", type=float, default=500.0, help="the control loop's polling rate")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    device = mj.preset("mid", height=args.size, width=args.size, px_per_mm=args.size / 32.0)
    result: dict = {"frames": args.frames, "size": args.size, "poll_hz": args.poll_hz}

    t = time.perf_counter()
    handle = mj.open_sensor(device, "sim", sensor=SimulatedSensor(device, n_frames=args.frames))
    result["compile_s"] = time.perf_counter() - t
    result["one_sensor"] = _read_like_a_controller([handle], 1.0 / args.poll_hz)
    handle.close()

    sensors = [SimulatedSensor(device, n_frames=args.frames, seed=s) for s in (1, 2)]
    handles = [mj.open_sensor(device, "sim", sensor=s, sensor_id=f"finger{i}") for i, s in enumerate(sensors)]
    result["two_sensors"] = _read_like_a_controller(handles, 1.0 / args.poll_hz)
    for h in handles:
        h.close()

    # A tare on an idle stream: long enough to take its frames and build the new reference.
    idle = mj.open_sensor(device, "sim", sensor=SimulatedSensor(device, script=lambda i: (np.zeros(6), mj.Contact())))
    time.sleep(1.0)
    t = time.perf_counter()
    idle.tare(frames=5)
    result["tare_s"] = time.perf_counter() - t
    idle.close()

    result["floor"] = _floor(device, SimulatedSensor(device, n_frames=args.frames), args.frames)
    with tempfile.TemporaryDirectory() as folder:
        result["sinks"] = _sink_cost(Path(folder), (args.size, args.size))
    result["peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(result, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
