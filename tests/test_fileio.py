"""Atomic writes: whole-or-nothing, no temporaries left behind, ordinary file modes."""

import os
import stat

import pytest

from moirejax import _fileio
from moirejax._fileio import atomic_write_bytes, atomic_write_text


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
