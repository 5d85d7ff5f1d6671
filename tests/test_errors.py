"""Fault injection: every failure path of the error policy (docs/errors.md), each one cheap.

No test here compiles the inverter: where a command would, the inverter is replaced, and a
test that must fail before the compile replaces it with one that fails the test.
"""

import errno
import json
import os
import re
import signal
import tempfile
import warnings
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, HealthCheck, settings, strategies as st

import moirejax as mj
import moirejax.calibration._workflows as workflows
import moirejax.inverse
import moirejax.inverse._invert as invert_module
from moirejax import _fileio
from moirejax.calibration._residual_head import N_BASIS, ResidualHead
from moirejax.cli import _errors, _main
from moirejax.cli._main import main
from moirejax.data._dataset import DatasetWriter
from moirejax.inverse._invert_io import _failed_row, CSV_HEADER, find_reference, invert_recording, iter_source_frames


ROOT = Path(__file__).resolve().parents[1]
SHAPE = (16, 16)


def _one_error_line(err: str) -> str:
    """The one error line of a failed command; no traceback."""
    assert "Traceback" not in err, err
    errors = [line for line in err.strip().splitlines() if re.match(r"moirejax [\w-]+: (internal )?error: ", line)]
    assert len(errors) == 1, err
    return errors[0]


@pytest.fixture
def device_file(tmp_path):
    path = tmp_path / "mid.json"
    mj.save_device(path, mj.preset("mid"))
    return path


@pytest.fixture
def no_compile(monkeypatch):
    """Any attempt to build an inverter fails the test: the error had to come first."""

    def fail(*args, **kwargs):
        raise AssertionError("the inverter was built before the input was checked")

    monkeypatch.setattr(moirejax.inverse, "Inverter", fail)
    monkeypatch.setattr(workflows, "fit_physical_parameters", fail)


def _unbuilt_inverter() -> mj.Inverter:
    """An Inverter that holds only its device: nothing is compiled."""
    inverter = object.__new__(mj.Inverter)
    object.__setattr__(inverter, "device", mj.preset("mid"))
    return inverter


def _images(folder: Path, n: int = 3) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i:03d}.png"), rng.integers(0, 256, SHAPE, dtype=np.uint8))
    return folder


def _dataset(path: Path, frames, wrenches, contact) -> Path:
    with DatasetWriter(path, device=mj.device_to_json(mj.preset("mid"))) as writer:
        for frame, wrench, c in zip(frames, wrenches, contact):
            writer.add(frame, wrench, contact=c)
    return path


# --------------------------------------------------------------------------- the policy


def test_every_exit_code_is_documented():
    page = (ROOT / "docs" / "errors.md").read_text()
    documented = {int(code) for code in re.findall(r"^\|\s*(\d+)\s*\|", page, flags=re.M)}
    assert documented == set(_errors.EXIT_CODES)
    assert (_errors.EXIT_USAGE, _errors.EXIT_DATA, _errors.EXIT_OUTPUT) == (2, 3, 4)


def test_internal_error_is_one_line_and_debug_shows_the_traceback(monkeypatch, capsys):
    def broken(args):
        raise TypeError("boom")

    monkeypatch.setattr(_main, "_cmd_design", broken)
    assert main(["design"]) == 1
    line = _one_error_line(capsys.readouterr().err)
    assert "TypeError: boom" in line and "--debug" in line
    for argv in (["--debug", "design"], ["design", "--debug"]):
        assert main(argv) == 1
        assert "Traceback" in capsys.readouterr().err


def test_ctrl_c_and_sigterm_exit_130_and_restore_the_handler(monkeypatch, capsys):
    def interrupted(args):
        raise KeyboardInterrupt

    def terminated(args):
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM did not stop the command")

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(_main, "_cmd_design", interrupted)
    assert main(["design"]) == 130
    assert "interrupted" in capsys.readouterr().err
    monkeypatch.setattr(_main, "_cmd_design", terminated)
    assert main(["design"]) == 130
    assert "terminated (SIGTERM)" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) == before


def test_bad_input_names_the_file_and_its_flag(device_file, tmp_path, capsys):
    assert main(["invert", "--device", str(tmp_path / "nope.json"), "--data", "x", "--out", "y.csv"]) == 3
    line = _one_error_line(capsys.readouterr().err)
    assert "nope.json: no such file" in line and line.endswith("(given by --device)")


@pytest.mark.parametrize(
    "argv", [["invert", "--batch", "0"], ["simulate", "--n", "-1"], ["calibrate", "--rounds", "0"]]
)
def test_nonsense_numbers_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main([*argv, "--device", "d.json", "--data", "x", "--out", "y"])
    assert info.value.code == 2
    assert "must be at least 1" in capsys.readouterr().err


def test_invert_recording_rejects_batch_zero():
    with pytest.raises(ValueError, match="batch must be a whole number >= 1"):
        invert_recording(_unbuilt_inverter(), "x", "y.csv", batch=0)


# --------------------------------------------------------------------------- outputs


def test_invert_out_that_is_a_folder_fails_before_the_compile(device_file, tmp_path, capsys, no_compile):
    frames = _images(tmp_path / "frames")
    (tmp_path / "out").mkdir()
    argv = ["invert", "--device", str(device_file), "--data", str(frames), "--out", str(tmp_path / "out")]
    assert main(argv) == 4
    line = _one_error_line(capsys.readouterr().err)
    assert "is a folder" in line and "--out needs a file name" in line


def test_calibrate_unwritable_outputs_fail_before_the_fit(tmp_path, capsys, monkeypatch, no_compile):
    (tmp_path / "a_file").write_text("")
    argv = ["calibrate", "--data", str(tmp_path / "whatever"), "--quiet", "--out"]
    assert main([*argv, str(tmp_path / "a_file" / "fit.json")]) == 4
    line = _one_error_line(capsys.readouterr().err)
    assert "is a file, not a folder" in line and "change --out" in line

    # A read-only folder (root ignores permission bits, so the probe is refused instead).
    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    assert main([*argv, str(tmp_path / "ro" / "fit.json")]) == 4
    line = _one_error_line(capsys.readouterr().err)
    assert "Permission denied" in line and "change --out" in line


def test_full_disk_is_an_output_error_and_keeps_the_old_file(tmp_path, capsys, monkeypatch):
    out = tmp_path / "d.json"
    out.write_text("old")

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    assert main(["design", "--preset", "mid", "--write", str(out)]) == 4
    line = _one_error_line(capsys.readouterr().err)
    assert "No space left on device" in line
    assert out.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["d.json"]


def test_non_empty_dataset_folder_needs_the_overwrite_flag(tmp_path, capsys):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "keep.txt").write_text("x")
    assert main(["simulate", "--out", str(tmp_path / "ds"), "--n", "2"]) == 4
    line = _one_error_line(capsys.readouterr().err)
    assert "pass --overwrite" in line and "overwrite=True" not in line


# --------------------------------------------------------------------------- inputs


def test_missing_manifest_is_reported_before_the_compile(device_file, tmp_path, capsys, no_compile):
    _images(tmp_path / "rec" / "frames")
    (tmp_path / "rec" / "wrench.csv").write_text("frame,fx,fy,fz,tx,ty,tz\n")
    argv = ["invert", "--device", str(device_file), "--data", str(tmp_path / "rec"), "--out", str(tmp_path / "w.csv")]
    assert main(argv) == 3
    line = _one_error_line(capsys.readouterr().err)
    assert "manifest.json: no such file" in line and "incomplete" in line and "--data" in line


def test_reference_of_the_wrong_size_names_the_flag(device_file, tmp_path, capsys, no_compile):
    frames = _images(tmp_path / "frames")
    argv = ["invert", "--device", str(device_file), "--data", str(frames), "--out", str(tmp_path / "w.csv")]
    assert main([*argv, "--reference", str(frames / "000.png")]) == 3
    line = _one_error_line(capsys.readouterr().err)
    assert "the device expects" in line and "--reference" in line


def test_inverting_without_a_reference_warns_loudly(device_file, tmp_path, capsys, monkeypatch):
    frames = _images(tmp_path / "frames")
    built = []
    monkeypatch.setattr(moirejax.inverse, "Inverter", lambda device, reference: built.append(reference))
    monkeypatch.setattr(moirejax.inverse, "invert_recording", lambda *a, **k: {"converged": 3})
    argv = ["invert", "--device", str(device_file), "--data", str(frames), "--out", str(tmp_path / "w.csv")]
    assert main(argv) == 0
    err = capsys.readouterr().err
    warning = next(line for line in err.splitlines() if ": warning: " in line)
    assert "another unit" in warning and "--reference" in warning and built == [None]


def test_an_unreadable_frames_row_has_every_column_of_the_header():
    row = dict(zip(CSV_HEADER, _failed_row("f.png", mj.Status.UNREADABLE, "f.png: not a readable image")))
    assert len(row) == len(CSV_HEADER) == len(_failed_row("f.png", mj.Status.UNREADABLE, ""))
    assert row["frame"] == "f.png" and row["status"] == "unreadable" and row["message"].startswith("f.png")
    assert row["contacts"] == 0 and all(
        np.isnan(v) for k, v in row.items() if k not in ("frame", "contacts", "status", "message")
    )


def test_truncated_reference_frame_is_skipped_not_fatal(tmp_path):
    rng = np.random.default_rng(1)
    frames = rng.uniform(0.2, 0.8, (5, *SHAPE))
    path = _dataset(tmp_path / "ds", frames, np.zeros((5, 6)), [0, 0, 0, 1, 1])
    first = path / "frames" / "000000.png"
    first.write_bytes(first.read_bytes()[:40])
    with pytest.warns(mj.DataWarning, match="reference frame skipped: .*000000.png"):
        reference, note = find_reference(path, SHAPE)
    expected = np.mean([np.round(f * 255) / 255 for f in frames[1:3]], axis=0)
    np.testing.assert_allclose(reference, expected, atol=1e-6)
    assert "mean of 2" in note
    with pytest.warns(mj.DataWarning):
        np.testing.assert_allclose(mj.dataset_reference(mj.open_dataset(path)), expected, atol=1e-6)
    # The frame still gets its own status row when the recording is inverted.
    rows = list(iter_source_frames(path, SHAPE))
    assert rows[0][1] is None and "not a readable image" in rows[0][2] and len(rows) == 5


def test_truncated_video_warns_with_both_counts(tmp_path):
    writer = cv2.VideoWriter(str(tmp_path / "v.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, SHAPE[::-1], False)
    rng = np.random.default_rng(2)
    for _ in range(30):
        writer.write(rng.integers(0, 256, SHAPE, dtype=np.uint8))
    writer.release()
    data = (tmp_path / "v.avi").read_bytes()
    (tmp_path / "t.avi").write_bytes(data[: len(data) // 2])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(iter_source_frames(tmp_path / "v.avi", SHAPE))) == 30
    with pytest.warns(mj.DataWarning, match=r"t\.avi: read (\d+) of the 30 frames"):
        n = len(list(iter_source_frames(tmp_path / "t.avi", SHAPE)))
    assert 0 < n < 30


def test_uint_frames_are_scaled_not_bad(monkeypatch):
    frame8 = np.full(SHAPE, 255, np.uint8)
    assert mj.unit_frame(frame8).dtype == np.float32 and mj.unit_frame(frame8).max() == 1.0
    assert mj.unit_frame(np.full(SHAPE, 65535, np.uint16)).max() == 1.0
    with pytest.raises(ValueError, match="2-D"):
        mj.unit_frame(np.zeros(3))
    seen = []

    class Seen(Exception):
        pass

    def solve(inverter, frame, init):
        seen.append(float(frame.max()))
        raise Seen

    monkeypatch.setattr(invert_module, "_solve", solve)
    with pytest.raises(Seen):
        mj.invert(_unbuilt_inverter(), [np.full(SHAPE, 128, np.uint8)])
    assert seen == [pytest.approx(128 / 255)]


# --------------------------------------------------------------------------- import


def _recording(root: Path, n: int = 4, bad: int | None = None) -> list[str]:
    _images(root / "images", n)
    names = sorted(p.name for p in (root / "images").iterdir())
    if bad is not None:
        (root / "images" / names[bad]).write_bytes(b"corrupt")
    lines = ["frame,fx,fy,fz,tx,ty,tz"] + [f"{name},0,0,{i},0,0,0" for i, name in enumerate(names)]
    (root / "ft.csv").write_text("\n".join(lines) + "\n")
    return names


def test_failed_import_names_the_flag_and_leaves_nothing(device_file, tmp_path, capsys):
    _recording(tmp_path / "rec", bad=2)
    out = tmp_path / "new" / "ds"
    argv = ["import", "--frames", str(tmp_path / "rec" / "images"), "--wrench", str(tmp_path / "rec" / "ft.csv")]
    argv += ["--device", str(device_file), "--out", str(out)]
    assert main(argv) == 3
    err = capsys.readouterr().err
    assert "(pass --skip-bad to skip them)" in err and "skip_bad=True" not in err and "Traceback" not in err
    assert not (tmp_path / "new").exists()
    assert main([*argv, "--skip-bad"]) == 0
    assert len(mj.open_dataset(out)) == 3


def test_interrupted_overwrite_keeps_the_old_dataset(device_file, tmp_path, monkeypatch):
    _recording(tmp_path / "rec", n=4)
    args = (tmp_path / "rec" / "images", tmp_path / "rec" / "ft.csv", str(device_file), tmp_path / "ds")
    mj.import_recording(*args, progress=False)
    before = {p.relative_to(tmp_path): p.read_bytes() for p in (tmp_path / "ds").rglob("*") if p.is_file()}
    calls = []
    real_add = DatasetWriter.add

    def add(self, *a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real_add(self, *a, **k)

    def reimport():
        return mj.import_recording(
            tmp_path / "rec2" / "images",
            tmp_path / "rec2" / "ft.csv",
            str(device_file),
            args[3],
            progress=False,
            overwrite=True,
        )

    monkeypatch.setattr(DatasetWriter, "add", add)
    _recording(tmp_path / "rec2", n=5)
    with pytest.raises(KeyboardInterrupt):
        reimport()
    after = {p.relative_to(tmp_path): p.read_bytes() for p in (tmp_path / "ds").rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "mid.json", "rec", "rec2"]
    monkeypatch.setattr(DatasetWriter, "add", real_add)
    reimport()
    assert len(mj.open_dataset(tmp_path / "ds")) == 5


# --------------------------------------------------------------------------- calibration


def test_identical_frames_are_refused_before_the_fit(tmp_path, capsys, no_compile):
    rng = np.random.default_rng(3)
    reference = rng.uniform(0.2, 0.8, SHAPE)
    pressed = np.clip(reference + 0.1, 0, 1)
    n = 14
    wrenches = np.zeros((n, 6))
    wrenches[2:, 2] = np.linspace(0.1, 1.0, n - 2)
    frames = [reference, reference] + [pressed] * (n - 2)
    data = _dataset(tmp_path / "same", frames, wrenches, [0, 0] + [1] * (n - 2))
    problems = mj.identification_problems(np.stack(frames[2:]), wrenches[2:], reference)
    assert "only 1 distinct images among 12" in problems["refuse"][0]
    assert problems["axes_not_excited"] == ["fx", "fy", "tx", "ty", "tz"]
    assert main(["calibrate", "--data", str(data), "--out", str(tmp_path / "fit.json"), "--quiet"]) == 3
    line = _one_error_line(capsys.readouterr().err)
    assert "cannot identify a calibration" in line and "pass --force" in line
    assert not (tmp_path / "fit.json").exists() and not (tmp_path / "fit_report").exists()
    # Varied frames pass; an unloaded axis is reported, not refused.
    varied = rng.uniform(0.2, 0.8, (12, *SHAPE))
    assert mj.identification_problems(varied, wrenches[2:], reference)["refuse"] == []


def _set(out: Path, value: float, head: bool = True):
    """Write a calibration set whose device, head and report all carry `value`."""
    device = mj.preset("mid")
    zeros = jnp.zeros(6, jnp.float32)
    residual = ResidualHead(jnp.full((6, N_BASIS), value, jnp.float32), zeros, zeros) if head else None

    def report(folder: Path):
        folder.mkdir()
        (folder / "metrics.json").write_text(json.dumps({"value": value}))

    workflows._write_fit_set(
        out, device, {"dataset": str(value), "recipe": "unit", "uncertainty": {}}, residual, report
    )


def _read_set(out: Path):
    device, head = mj.load_calibrated(out)
    value = json.loads(out.read_text())["calibration"]["dataset"]
    report = json.loads((out.parent / "fit_report" / "metrics.json").read_text())["value"]
    return float(value), report, head


def test_calibration_set_lands_whole_whenever_it_is_interrupted(tmp_path, monkeypatch):
    out = tmp_path / "fit.json"
    _set(out, 1.0)
    old = out.read_bytes()
    # A failure while staging (most of the time) leaves the old set byte for byte.

    def stop(folder):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        workflows._write_fit_set(out, mj.preset("mid"), {}, None, stop)
    assert out.read_bytes() == old and _read_set(out)[:2] == (1.0, 1.0)
    # Interrupted at every rename, staging and commit alike: the old set or the new one,
    # each whole (device, head and report agree), and no staging folder left behind.
    real_replace = os.replace
    outcomes = []
    for k in range(1, 10):
        _set(out, 1.0)
        calls = []

        def replace(src, dst, k=k, calls=calls):
            calls.append(dst)
            if len(calls) == k:
                raise KeyboardInterrupt
            real_replace(src, dst)

        monkeypatch.setattr(_fileio.os, "replace", replace)
        try:
            _set(out, 2.0)
        except KeyboardInterrupt:
            pass
        monkeypatch.setattr(_fileio.os, "replace", real_replace)
        assert not [p for p in tmp_path.iterdir() if ".staging-" in p.name]
        value, report, head = _read_set(out)
        assert value == report and head is not None
        outcomes.append(value)
    assert outcomes == [1.0] * 8 + [2.0]
    calibration = json.loads(out.read_text())["calibration"]
    assert set(calibration["files"]) == {"fit.head.eqx", "fit.head.eqx.json", "fit_report/metrics.json"}


def test_a_head_out_of_step_with_its_device_is_refused(tmp_path):
    _set(tmp_path / "a" / "fit.json", 1.0)
    _set(tmp_path / "b" / "fit.json", 2.0)
    # What a kill that cannot be caught, between two renames, would leave: a new head
    # beside the old device file.
    (tmp_path / "a" / "fit.head.eqx").write_bytes((tmp_path / "b" / "fit.head.eqx").read_bytes())
    with pytest.raises(mj.DataError, match=r"fit\.head\.eqx: is not the file .*fit\.json was written with"):
        mj.load_calibrated(tmp_path / "a" / "fit.json")
    (tmp_path / "a" / "fit.head.eqx").unlink()
    with pytest.raises(mj.DataError, match="no such file"):
        mj.load_calibrated(tmp_path / "a" / "fit.json")


# --------------------------------------------------------------------------- fuzzing


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=200))
def test_any_bytes_as_a_json_file_are_a_data_error(tmp_path, data):
    path = tmp_path / "device.json"
    path.write_bytes(data)
    try:
        mj.load_calibrated(path)  # what invert, evaluate, transfer and live read a device with
    except mj.DataError as e:
        assert str(e).startswith(str(path))
    except ValueError as e:  # valid JSON, not a valid device: the message names the file
        assert str(e).startswith(str(path))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.integers(0, 400), flip=st.integers(0, 400), value=st.integers(0, 255))
def test_a_corrupted_frame_fails_the_import_cleanly_or_imports(tmp_path_factory, cut, flip, value):
    root = tmp_path_factory.mktemp("fuzz")
    names = _recording(root, n=3)
    target = root / "images" / names[1]
    data = bytearray(target.read_bytes())
    if flip < len(data):
        data[flip] = value
    target.write_bytes(bytes(data[: max(cut, 1)] if cut < len(data) else data))
    out = root / "ds"
    try:
        report = mj.import_recording(
            root / "images", root / "ft.csv", mj.device_to_json(mj.preset("mid")), out, progress=False
        )
    except mj.DataError as e:
        assert "could not be imported" in str(e)
        assert not out.exists() and sorted(p.name for p in root.iterdir()) == ["ft.csv", "images"]
    else:
        assert report.n_frames == 3 and len(mj.open_dataset(out)) == 3
