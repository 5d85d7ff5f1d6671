"""The Rerun sink (optional `viewer` extra): what it logs, read back from the file it saves.
Skipped where rerun-sdk is not installed."""

import numpy as np
import pytest

from moirejax.live import make_record, RerunSink


rerun = pytest.importorskip("rerun")


def _entities(path):
    from rerun.chunk import RrdReader

    summary = str(RrdReader(path).stream().collect().summary())
    rows = {}
    for line in summary.splitlines():
        entity, _, rest = line.partition(" rows=")
        if rest:
            rows[entity] = int(rest.split()[0])
    return rows


def test_records_frames_and_pressure_maps_land_on_their_timelines(tmp_path):
    sink = RerunSink(save=tmp_path / "run.rrd", prefix="left")
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
    assert sink.stats == {"sent": 5, "errors": 0}
    rows = _entities(tmp_path / "run.rrd")
    # Every record has its mode, status and frame; only the touched ones a wrench and a map.
    assert rows["/left/mode"] == rows["/left/status"] == rows["/left/frame"] == 5
    assert all(rows[f"/left/wrench/{axis}"] == 3 for axis in ("fx", "fy", "fz", "tx", "ty", "tz"))
    assert rows["/left/pressure"] == 3
    sink.emit(make_record(stamp=0.0, frame=9, mode="vision", status="no_contact"))
    assert sink.stats["errors"] == 1  # closed: counted, not raised
    with pytest.raises(ValueError, match="exactly one"):
        RerunSink(save=tmp_path / "a.rrd", spawn=True)
