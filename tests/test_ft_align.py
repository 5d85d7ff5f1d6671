"""Aligning a force/torque log to the frames of a recording: `align_ft`, `read_ft_log` and
`moirejax import --ft --align`, on simulated sessions whose clock offset is known."""

import json

import numpy as np
import pytest

import moirejax as mj
from moirejax.cli._main import main
from moirejax.simulate._simulate import simulate_dataset


FPS = 60.0
FT_RATE = 1000.0


def _load(t: np.ndarray, seed: int) -> np.ndarray:
    """Presses (some twisting, some shearing) on the frames' clock: a (len(t), 6) wrench."""
    rng = np.random.default_rng(seed)
    wrench = np.zeros((len(t), 6))
    for centre in np.arange(1.5, 19.0, 1.6) + rng.uniform(-0.3, 0.3, 11):
        width = rng.uniform(0.25, 0.6)
        bump = np.clip(1 - np.abs(t - centre) / width, 0, None) ** 1.5
        wrench += bump[:, None] * np.array(
            [
                rng.uniform(-0.2, 0.2),
                rng.uniform(-0.2, 0.2),
                rng.uniform(0.3, 1.2),
                0.0,
                0.0,
                rng.uniform(-0.006, 0.006),
            ]
        )
    return wrench


def _session(seed: int, offset: float, ft_span: tuple[float, float] = (1.005, 17.995)):
    """Frames at 60 fps over 20 s with a fringe-change activity that saturates and is noisy,
    and a 1 kHz log from `ft_span` (frame clock) on a clock `offset` ahead, with noise."""
    rng = np.random.default_rng(seed + 100)
    frame_times = np.arange(0.0, 20.0, 1 / FPS)
    truth = _load(frame_times, seed)
    # The fringe-change energy is a quadratic form in the wrench for small loads (twist
    # weighted strongly, as on the sensor); the activity saturates at hard presses.
    scale = np.array([0.2, 0.2, 1.0, 1.0, 1.0, 0.006])
    mixing = rng.normal(size=(6, 6)) * 0.3 + np.diag([1.0, 1.0, 1.0, 0.0, 0.0, 2.0])
    energy = np.sum(((truth / scale) @ mixing.T) ** 2, axis=1)
    activity = np.tanh(0.5 * np.sqrt(energy)) + rng.normal(0, 0.01, len(frame_times))
    ft_times = offset + np.arange(ft_span[0], ft_span[1], 1 / FT_RATE)
    ft_wrench = _load(ft_times - offset, seed) + rng.normal(0, 1, (len(ft_times), 6)) * np.array(
        [0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4]
    )
    return frame_times, activity, ft_times, ft_wrench, truth


@pytest.mark.parametrize(("seed", "offset"), [(0, 0.137), (1, -2.5), (2, 1000.137)])
def test_align_ft_recovers_a_known_offset_to_a_fraction_of_a_frame(seed, offset):
    frame_times, activity, ft_times, ft_wrench, truth = _session(seed, offset)
    alignment = mj.align_ft(frame_times, activity, ft_times, ft_wrench)
    # Within 2 ms of the truth: an eighth of the 16.7 ms frame period.
    assert abs(alignment.offset_s - offset) < 2e-3, alignment.offset_s - offset
    assert alignment.peak > 0.95
    # Frames outside the log's span (1.005 to 17.995 s on the frames' clock) are dropped.
    at = frame_times + offset
    expected = (at >= ft_times[0]) & (at <= ft_times[-1])
    np.testing.assert_array_equal(alignment.kept, expected)
    assert (~alignment.kept).sum() == np.sum(frame_times < 1.005) + np.sum(frame_times > 17.995) == 181
    assert np.all(np.isnan(alignment.wrench[~alignment.kept]))
    # The interpolated wrench is the true one to within the log's noise.
    error = np.abs(alignment.wrench[alignment.kept] - truth[alignment.kept]).max(axis=0)
    assert np.all(error < [0.05, 0.05, 0.05, 5e-4, 5e-4, 5e-4]), error


def test_align_ft_max_offset_bounds_the_search():
    frame_times, activity, ft_times, ft_wrench, _ = _session(0, 0.137)
    bounded = mj.align_ft(frame_times, activity, ft_times, ft_wrench, max_offset=0.2)
    assert abs(bounded.offset_s - 0.137) < 2e-3 and abs(bounded.offset_s) <= 0.2
    with pytest.raises(ValueError, match="overlap at no clock offset within ±1 s"):
        mj.align_ft(frame_times, activity, ft_times + 100.0, ft_wrench, max_offset=1.0)


def test_align_ft_refuses_bad_input():
    frame_times, activity, ft_times, ft_wrench, _ = _session(0, 0.137)
    with pytest.raises(ValueError, match="cannot align"):
        mj.align_ft(frame_times, np.zeros_like(activity), ft_times, ft_wrench)
    backwards = ft_times.copy()
    backwards[5] = backwards[3]
    with pytest.raises(ValueError, match="ft_times must increase"):
        mj.align_ft(frame_times, activity, backwards, ft_wrench)
    ft_wrench[10, 2] = np.nan
    with pytest.raises(ValueError, match="ft_wrench must be a finite"):
        mj.align_ft(frame_times, activity, ft_times, ft_wrench)


def test_fringe_change_ignores_brightness_and_measures_fringes():
    rng = np.random.default_rng(0)
    reference = rng.uniform(0.2, 0.8, (64, 64))
    assert mj.fringe_change(reference + 0.1, reference) == pytest.approx(0.0, abs=1e-12)
    # A fringe of amplitude a over whole periods has an RMS of a / sqrt(2).
    fringe = 0.05 * np.cos(2 * np.pi * np.arange(64) / 16)[None, :] * np.ones((64, 1))
    assert mj.fringe_change(reference + fringe, reference) == pytest.approx(0.05 / np.sqrt(2), rel=1e-9)


def _write_log(path, times, wrench, header="time,Fx,Fy,Fz,Tx,Ty,Tz"):
    rows = [header] + [",".join(f"{v:.6f}" for v in (t, *w)) for t, w in zip(times, wrench)]
    path.write_text("\n".join(rows) + "\n")


def test_read_ft_log_accepts_names_in_any_case_and_refuses_bad_logs(tmp_path):
    times, wrench = np.array([0.0, 0.001, 0.002]), np.arange(18.0).reshape(3, 6)
    _write_log(tmp_path / "ft.csv", times, wrench, header="Timestamp,FX,Fy,fz,tx,ty,tz")
    read_times, read_wrench = mj.read_ft_log(tmp_path / "ft.csv")
    np.testing.assert_allclose(read_times, times)
    np.testing.assert_allclose(read_wrench, wrench)
    _write_log(tmp_path / "bad.csv", times, wrench[:, :5], header="t,fx,fy,fz,tx,ty")
    with pytest.raises(mj.DataError, match="missing column.*'tz'"):
        mj.read_ft_log(tmp_path / "bad.csv")
    _write_log(tmp_path / "bad.csv", times, wrench[:, :5], header="fx,fy,fz,tx,ty,tz")
    with pytest.raises(mj.DataError, match="exactly one time column"):
        mj.read_ft_log(tmp_path / "bad.csv")
    _write_log(tmp_path / "bad.csv", times[[0, 2, 1]], wrench)
    with pytest.raises(mj.DataError, match="row 4: field 'time'.*times must increase"):
        mj.read_ft_log(tmp_path / "bad.csv")


# --------------------------------------------------------------------------- command line


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A small simulated press-twist-slide-release recording at 60 fps, exported as image
    files and a frame CSV with capture times, with the device file."""
    root = tmp_path_factory.mktemp("ft")
    device = mj.preset("mid", height=128, width=128, px_per_mm=4.0)
    dataset = mj.open_dataset(
        simulate_dataset(root / "sim", device, "sequence", 90, seed=3, fidelity="model", progress=False)
    )
    mj.export_recording(dataset, root / "frames", root / "frames.csv")
    (root / "device.json").write_text(json.dumps(dataset.device))
    return root, dataset


OFFSET = 500.137  # the log's clock: seconds since its driver started


def _shifted_log(root, dataset, start=-0.5, stop=1.44):
    """A 1 kHz log of the recording's true wrench on a clock OFFSET ahead, from `start` to
    `stop` on the frames' clock, with noise."""
    rng = np.random.default_rng(1)
    times = OFFSET + np.arange(start, stop, 1 / FT_RATE)
    wrench = np.stack([np.interp(times - OFFSET, dataset.t, dataset.wrenches[:, k]) for k in range(6)], axis=1)
    wrench += rng.normal(0, 1, wrench.shape) * np.array([0.003, 0.003, 0.003, 3e-6, 3e-6, 3e-6])
    _write_log(root / "ft.csv", times, wrench)
    return times


def _import(root, out, *extra):
    argv = ["import", "--frames", str(root / "frames"), "--ft", str(root / "ft.csv"), *extra]
    return main([*argv, "--device", str(root / "device.json"), "--out", str(root / out)])


def test_import_aligns_a_log_on_its_own_clock(recording, capsys):
    root, dataset = recording
    times = _shifted_log(root, dataset)
    dropped = int(np.sum(dataset.t + OFFSET > times[-1]))
    assert dropped > 0
    # The frames and their capture times from the frame CSV; its wrench columns are ignored.
    assert _import(root, "from_csv", "--wrench", str(root / "frames.csv"), "--align") == 0
    out = capsys.readouterr().out
    assert f"{dropped} frames outside its span dropped" in out and "ignored columns: fx" in out
    imported = mj.open_dataset(root / "from_csv")
    record = imported.manifest["ft_alignment"]
    assert abs(record["offset_s"] - OFFSET) < 2e-3, record["offset_s"] - OFFSET
    assert record["estimated"] and record["peak"] > 0.9 and record["frames_outside"] == dropped
    assert len(imported) == len(dataset) - dropped
    np.testing.assert_allclose(imported.t, dataset.t[: len(imported)])
    np.testing.assert_allclose(imported.wrenches, dataset.wrenches[: len(imported)], atol=0.02)
    # The images alone, timed by --fps: the same result.
    assert _import(root, "from_fps", "--fps", "60", "--align") == 0
    by_fps = mj.open_dataset(root / "from_fps")
    assert by_fps.fps == 60.0 and by_fps.frame_names == imported.frame_names
    assert by_fps.manifest["ft_alignment"]["offset_s"] == pytest.approx(record["offset_s"], abs=1e-9)


def _one_line_error(capsys) -> str:
    """The error line of the command (the progress bars go to stderr too)."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("moirejax import:")]
    assert len(lines) == 1 and "Traceback" not in err
    return lines[0]


def test_import_refuses_bad_logs_in_one_line(recording, tmp_path, capsys):
    root, dataset = recording
    times = _shifted_log(root, dataset)
    # A log on another clock, not aligned: no frame inside its span.
    assert _import(root, tmp_path / "a", "--fps", "60") == 3
    assert "no frame lies inside the log's span" in _one_line_error(capsys)
    # Aligned, but the offset lies beyond --max-offset.
    assert _import(root, tmp_path / "b", "--fps", "60", "--align", "--max-offset", "1") == 3
    assert "overlap at no clock offset" in _one_line_error(capsys)
    # No frame times.
    assert _import(root, tmp_path / "c", "--align") == 3
    err = _one_line_error(capsys)
    assert "no capture times" in err and "--fps" in err
    # A missing column and time that goes backwards name the file and the flag.
    wrench = np.zeros((len(times), 6))
    _write_log(root / "ft.csv", times, wrench[:, :5], header="t,fx,fy,fz,tx,ty")
    assert _import(root, tmp_path / "d", "--fps", "60", "--align") == 3
    err = _one_line_error(capsys)
    assert "'tz'" in err and "(given by --ft)" in err
    _write_log(root / "ft.csv", times[::-1], wrench)
    assert _import(root, tmp_path / "e", "--fps", "60", "--align") == 3
    err = _one_line_error(capsys)
    assert "times must increase" in err and "(given by --ft)" in err
    # --align without a log is a usage error.
    argv = ["import", "--frames", str(root / "frames"), "--wrench", str(root / "frames.csv"), "--align"]
    assert main([*argv, "--device", str(root / "device.json"), "--out", str(tmp_path / "f")]) == 2
    assert not any((tmp_path / name).exists() for name in "abcdef")
