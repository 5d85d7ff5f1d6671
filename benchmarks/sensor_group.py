"""Several simulated sensors in one process: `python benchmarks/sensor_group.py --json`.

Opens a [`SensorGroup`][moirejax.live.SensorGroup] of one and then of two simulated Mid
units ([`open_sensors`][moirejax.open_sensors]), each on its own `sequence` load script
(approach, press, twist, slide, release) with every frame in order, the two mounted as the
opposed pads of a parallel gripper so that the group also emits grip records. Prints, per
run: the time to open the group (building and compiling each sensor's inversion), sensor
records per second (all sensors together, and each), grip records per second, the latency
from each record's capture to its delivery to a group callback (median, p90, for sensor
and grip records), the grip records' skew between the two captures, and at the end the
peak memory and the JAX device.
"""

import argparse
import json
import math
import resource
import time

import numpy as np
from _device import device_summary

import moirejax as mj
from moirejax.live import Mount, SimulatedSensor


def _stats(values) -> dict | None:
    if not values:
        return None
    values = np.asarray(values, np.float64)
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90))}


def _run(device, names: list[str], frames: int) -> dict:
    mounts = {
        "left": Mount.from_rpy((0.0, 0.04, 0.0), -math.pi / 2, 0.0, 0.0),
        "right": Mount.from_rpy((0.0, -0.04, 0.0), math.pi / 2, 0.0, 0.0),
    }
    specs = {
        name: {"device": device, "source": "sim", "sensor": SimulatedSensor(device, n_frames=frames, seed=k + 1)}
        for k, name in enumerate(names)
    }
    delivered: list[tuple[str, float, float | None]] = []

    def on_record(record) -> None:
        # The capture's monotonic time to now: grab, inversion, the group's hand-over.
        delay = (time.monotonic() - record.monotonic) * 1e3 if record.monotonic is not None else math.nan
        delivered.append((record.sensor_id, delay, record.skew_ms))

    t = time.perf_counter()
    # Built one sensor after another, then started together: time to the first frame.
    group = mj.open_sensors(specs, {n: mounts[n] for n in names} if len(names) > 1 else None, start=False)
    opened = time.perf_counter() - t
    group.on_record(on_record)
    started = time.monotonic()
    group.start()
    group.join()
    elapsed = time.monotonic() - started
    group.close()
    sensor = [d for d in delivered if d[0] in names]
    grip = [d for d in delivered if d[0] == "grip"]
    return {
        "sensors": len(names),
        "open_s": opened,
        "elapsed_s": elapsed,
        "records_per_s": len(sensor) / elapsed,
        "records_per_s_each": {n: sum(d[0] == n for d in sensor) / elapsed for n in names},
        "grip_records_per_s": len(grip) / elapsed,
        "capture_to_delivery_ms": _stats([d[1] for d in sensor]),
        "grip_capture_to_delivery_ms": _stats([d[1] for d in grip]),
        "grip_skew_ms": _stats([d[2] for d in grip if d[2] is not None]),
        "status_counts": {n: h.summary.status_counts for n, h in group.handles.items() if h.summary is not None},
        "errors": {n: repr(e) for n, e in group.errors.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="frames of the load script per sensor")
    parser.add_argument("--size", type=int, default=256, help="frame side in pixels (the field stays 32 mm)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    device = mj.preset("mid", height=args.size, width=args.size, px_per_mm=args.size / 32.0)
    result: dict = {"frames": args.frames, "size": args.size}
    result["one_sensor"] = _run(device, ["left"], args.frames)
    result["two_sensors"] = _run(device, ["left", "right"], args.frames)
    result["peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    result.update(device_summary())
    print(json.dumps(result, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
