"""The Rerun sink (optional `viewer` extra): what it logs, read back from the file it saves.
Skipped where rerun-sdk is not installed. The sink runs in a process of its own: rerun-sdk
loads pyarrow, whose native libraries should not share a test worker with JAX's compiler."""

import json
import subprocess
import sys

import pytest


pytest.importorskip("rerun")

SESSION = r"""
import json, sys
import numpy as np
from rerun.chunk import RrdReader
from moirejax.live import make_record, RerunSink

path = sys.argv[1]
sink = RerunSink(save=path, prefix="left")
for i in range(5):
    touched = i >= 2
    record = make_record(
        stamp=100.0 + i / 60,
        frame=i,
        mode="tactile" if touched else "vision",
        status="converged" if touched else "no_contact",
        wrench=0.1 * i * np.arange(6) if touched else None,
    )
    sink.emit(record)
    sink.emit_image(np.full((16, 20, 3), 128, np.uint8), record)
    if touched:
        sink.emit_pressure(np.full((8, 8), 1e3 * i), record)
sink.close()
stats = dict(sink.stats)
sink.emit(make_record(stamp=0.0, frame=9, mode="vision", status="no_contact"))
try:
    RerunSink(save=path + ".other", spawn=True)
    refused = False
except ValueError:
    refused = True
rows = {}
for line in str(RrdReader(path).stream().collect().summary()).splitlines():
    entity, _, rest = line.partition(" rows=")
    if rest:
        rows[entity] = int(rest.split()[0])
print(json.dumps({"stats": stats, "after_close": sink.stats["errors"], "refused": refused, "rows": rows}))
"""


def test_records_frames_and_pressure_maps_land_on_their_timelines(tmp_path):
    done = subprocess.run(
        [sys.executable, "-c", SESSION, str(tmp_path / "run.rrd")], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["stats"] == {"sent": 5, "errors": 0}
    rows = result["rows"]
    # Every record has its mode, status and frame; only the touched ones a wrench and a map.
    assert rows["/left/mode"] == rows["/left/status"] == rows["/left/frame"] == 5
    assert all(rows[f"/left/wrench/{axis}"] == 3 for axis in ("fx", "fy", "fz", "tx", "ty", "tz"))
    assert rows["/left/pressure"] == 3
    assert result["after_close"] == 1  # a record after close is counted, not raised
    assert result["refused"]  # exactly one of save, connect and spawn
