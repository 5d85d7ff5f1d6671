"""Live pipeline latency and rate from a 512x512 MP4, as a camera would deliver it:
`python benchmarks/live_latency.py --json`.

Simulates a `sequence` recording (approach, press, twist, slide, release; `high`
fidelity: fabrication deviations, noise, 8-bit) of a Mid unit, writes it as an MP4, and
runs `run_live` on it twice: replayed at the camera rate (`--fps`, latest-frame delivery,
so latency is decode-to-emit with nothing queued) and as fast as it decodes (in order,
every frame: the sustainable rate). Prints median and p90 latency, frames/s, mode
switches and their lag in frames behind the recording's contact onset and release (from
the in-order run), statuses, whether the frames came out in order, compile time and peak memory.
"""

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

import moirejax as mj
from moirejax import Dataset, Inverter, simulate_dataset
from moirejax.live import capture_reference, FileSink, make_tactile_processor, open_source, run_live


def _switch_lags(records, contact) -> dict:
    """Frames from each recorded contact onset/release to the gate's switch (+ = late)."""
    mode = {r["frame"]: r["mode"] == "tactile" for r in records if r["status"] != "end_of_stream"}
    frames = sorted(mode)
    gate = [f for a, f in zip(frames, frames[1:]) if mode[a] != mode[f]]
    truth = [int(i) + 1 for i in np.flatnonzero(np.diff(contact.astype(int)))]
    return {
        "contact_changes": truth,
        "gate_switches": gate,
        "lags_frames": [min((g - t for g in gate), key=abs) if gate else None for t in truth],
    }


def _run(device, video, inverter, replay_fps, out, contact):
    sink = FileSink(out)
    try:
        summary = run_live(device, str(video), sinks=[sink], inverter=inverter, replay_fps=replay_fps, vision=False)
    finally:
        sink.close()
    records = [json.loads(line) for line in Path(out).read_text().splitlines()]
    frames = [r["frame"] for r in records if r.get("frame") is not None]
    return {
        "latency_ms_median": summary.latency_ms_median,
        "latency_ms_p90": summary.latency_ms_p90,
        "fps": summary.fps,
        "frames": summary.frames,
        "dropped": summary.dropped,
        "mode_switches": summary.mode_switches,
        "status_counts": summary.status_counts,
        "in_order": frames == sorted(frames),
        "mode_switch_lag": _switch_lags(records, contact),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--fps", type=float, default=60.0)
    args = parser.parse_args(argv)

    device = mj.preset("mid")
    with tempfile.TemporaryDirectory() as tmp:
        data = simulate_dataset(Path(tmp) / "sequence", device, "sequence", args.frames, seed=5, progress=False)
        contact = Dataset(data).contact
        video = data.with_suffix(".mp4")
        reference = capture_reference(open_source(str(video)), frames=5)
        start = time.perf_counter()
        inverter = Inverter(device, reference=reference)
        make_tactile_processor(inverter, reference)
        compile_s = time.perf_counter() - start
        camera = _run(device, video, inverter, args.fps, Path(tmp) / "camera.jsonl", contact)
        flat_out = _run(device, video, inverter, None, Path(tmp) / "flat_out.jsonl", contact)
    result = {
        "frame_shape": [device.height, device.width],
        "camera_fps": args.fps,
        "at_camera_rate": camera,
        "as_fast_as_decoded": flat_out,
        "median_ms": camera["latency_ms_median"],
        "p90_ms": camera["latency_ms_p90"],
        "sustained_fps": flat_out["fps"],
        "mode_switch_lag_frames": flat_out["mode_switch_lag"]["lags_frames"],
        "compile_s": compile_s,
        "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k:22s} {v}")


if __name__ == "__main__":
    main()
