"""Inverting a recording on a local Dask cluster of two worker processes: the same file as the
single-process run with the same segments, a rerun that keeps the segments a previous run
finished, and the refusals (parts of another run, a video, flags of the other engine)."""

import json
import os

import pytest

import moirejax as mj
from moirejax._fileio import fingerprint, PLAN_NAME
from moirejax.cli import main
from moirejax.inverse import find_reference


pytest.importorskip("distributed")

# The dask engine's cluster and compiles are made once, on one worker of the test run.
pytestmark = pytest.mark.xdist_group("distributed")

# Mid's fringes on a 16 mm field (128 x 128 px at 8 px/mm): the machinery, quickly.
SMALL = dict(height=128, width=128, px_per_mm=8.0)
SEGMENT = 3


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    root = tmp_path_factory.mktemp("distributed")
    with pytest.MonkeyPatch.context() as patch, __import__("jax").enable_x64(False):
        patch.setenv("MOIREJAX_CARRIERS", "0")
        device = mj.preset("mid", **SMALL)
        mj.simulate_dataset(root / "seq", device, "sequence", 7, seed=3, fidelity="model", progress=False)
        reference, _ = find_reference(root / "seq", (device.height, device.width))
        inverter = mj.Inverter(device, reference=reference)
        local = root / "local.csv"
        mj.invert_recording(inverter, root / "seq", local, restart_every=SEGMENT, progress=False)
        remote = root / "dask.csv"
        counts = mj.invert_distributed(inverter, root / "seq", remote, segment=SEGMENT, workers=2, progress=False)
    return {"root": root, "inverter": inverter, "local": local, "dask": remote, "counts": counts}


def test_the_cluster_writes_the_single_process_runs_numbers(recording):
    local, remote = recording["local"].read_text(), recording["dask"].read_text()
    assert remote == local  # to the last digit, row for row, in the frames' order
    rows = local.splitlines()
    assert len(rows) == 8 and rows[0].startswith("frame,fx,fy,fz")
    assert sum(recording["counts"].values()) == 7 and "converged" in recording["counts"]
    assert not (recording["root"] / "dask.csv.parts").exists()  # kept only until the output is written


def test_a_rerun_keeps_the_segments_a_previous_run_finished(recording):
    root, inverter = recording["root"], recording["inverter"]
    rows = recording["local"].read_text().splitlines()[1:]
    out = root / "resumed.csv"
    parts = root / "resumed.csv.parts"
    parts.mkdir()
    plan = {
        "source": os.path.abspath(root / "seq"),
        "frames": 7,
        "segment": SEGMENT,
        "batch": 1,
        "inverter": fingerprint(inverter, None),
    }
    (parts / PLAN_NAME).write_text(json.dumps(plan))
    # Segment 3..5 finished before the run was interrupted; marked, to see that it is not redone.
    marked = [row.replace("converged", "converged_earlier") for row in rows[3:6]]
    finished = {"csv": "".join(r + "\n" for r in marked), "counts": {"converged_earlier": 3}, "frames": 3}
    (parts / "segment-000000003.json").write_text(json.dumps(finished))
    (parts / "segment-000000006.json").write_text("{not json")  # a torn part is redone
    with __import__("jax").enable_x64(False):
        counts = mj.invert_distributed(inverter, root / "seq", out, segment=SEGMENT, workers=2, progress=False)
    assert out.read_text().splitlines()[1:] == rows[:3] + marked + rows[6:]
    assert counts["converged_earlier"] == 3 and sum(counts.values()) == 7
    assert not parts.exists()

    # Parts of another run (another segment length) are refused, not mixed in.
    parts.mkdir()
    (parts / PLAN_NAME).write_text(json.dumps({**plan, "segment": 2}))
    out.unlink()
    with pytest.raises(mj.DataError, match="different run.*remove the folder"):
        mj.invert_distributed(inverter, root / "seq", out, segment=SEGMENT, progress=False)
    with pytest.raises(ValueError, match="segment must be"):
        mj.invert_distributed(inverter, root / "seq", root / "w.csv", segment=0)


def test_the_engines_flags_are_checked_before_anything_is_compiled(tmp_path, capsys):
    mj.save_device(tmp_path / "mid.json", mj.preset("mid", **SMALL))
    video = tmp_path / "clip.avi"
    import cv2
    import numpy as np

    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (128, 128), isColor=False)
    for _ in range(3):
        writer.write(np.zeros((128, 128), np.uint8))
    writer.release()
    base = ["invert", "--device", str(tmp_path / "mid.json"), "--out", str(tmp_path / "w.csv"), "--quiet"]
    for extra, expected in (
        (["--data", str(video), "--engine", "dask"], "import it into a dataset first"),
        (["--data", str(video), "--workers", "4"], "--workers and --scheduler apply to --engine dask"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            raise SystemExit(main(base + extra))
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and expected in err[0], err
