"""Atomic writes: whole-or-nothing, no temporaries left behind, ordinary file modes."""

import os
import stat

import numpy as np
import pytest

from moirejax import _fileio
from moirejax._fileio import atomic_write_bytes, atomic_write_text, fingerprint, open_parts


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_new_file_gets_the_umask_mode_and_existing_file_keeps_its_own(tmp_path):
    path = tmp_path / "a.json"
    atomic_write_text(path, "{}")
    assert path.read_text() == "{}" and _mode(path) == 0o666 & ~_fileio._UMASK
    os.chmod(path, 0o600)
    atomic_write_text(path, "[]")
    assert path.read_text() == "[]" and _mode(path) == 0o600


def test_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "fit.json"
    atomic_write_bytes(path, b"old")

    def fail(fd):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["fit.json"]


def test_parts_of_a_long_job_belong_to_its_plan(tmp_path):
    import json

    parts = tmp_path / "fit.json.parts"
    plan = {"data": "cal", "frames": fingerprint(np.arange(5))}
    assert not open_parts(parts, plan, argument="out")
    (parts / "solved-000000.npz").write_bytes(b"part")
    # The same plan finds its parts; the plan's file is what tells them apart.
    assert open_parts(parts, json.loads(json.dumps(plan)), argument="out")
    assert (parts / "solved-000000.npz").exists()
    other = {**plan, "frames": fingerprint(np.arange(6))}
    assert other["frames"] != plan["frames"] and fingerprint(np.arange(5)) == plan["frames"]
    with pytest.raises(_fileio.DataError, match="different run.*remove the folder"):
        open_parts(parts, other, argument="out")
    assert (parts / "solved-000000.npz").exists()
    with pytest.warns(_fileio.DataWarning, match="different run dropped"):
        assert not open_parts(parts, other, argument="out", restart_other=True)
    assert [p.name for p in parts.iterdir()] == [_fileio.PLAN_NAME]
    assert json.loads((parts / _fileio.PLAN_NAME).read_text()) == other
