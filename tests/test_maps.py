"""Traction maps of inverted frames (`moirejax.write_traction_maps`, `invert --maps`): their
moments are the CSV's wrench, two patches carry their own shares, frames are read alone from
the file, and a bad CSV or an unwritable path loses nothing."""

import math

import numpy as np
import pytest

import moirejax as mj
from moirejax.inverse._invert_io import CSV_HEADER


DEVICE = mj.preset("mid", height=256, width=256, px_per_mm=8.0)


def _row(name, wrench, patch, *, status="converged", contacts=1, shape=(0.0, 1.0, 0.0), second=None, share=None):
    values = dict.fromkeys(CSV_HEADER, "nan")
    values.update(frame=name, status=status, message=status, contacts=str(contacts))
    values.update({axis: repr(float(v)) for axis, v in zip(mj.WRENCH_AXES, wrench)})
    values.update({f"sigma_{axis}": "0.001" for axis in mj.WRENCH_AXES})
    values.update(zip(("x0", "y0", "radius"), map(repr, patch)))
    values.update(zip(("flatness", "aspect_ratio", "long_axis_angle"), map(repr, shape)))
    if second is not None:
        values.update(zip(("second_x0", "second_y0", "second_radius"), map(repr, second)))
        values.update({f"second_{axis}": repr(float(v)) for axis, v in zip(mj.WRENCH_AXES, share)})
    return ",".join(values[column] for column in CSV_HEADER)


def _write_csv(path, rows):
    path.write_text(",".join(CSV_HEADER) + "\n" + "\n".join(rows) + "\n")
    return path


def _moments(traction, maps):
    X, Y = np.meshgrid(maps.x_mm, maps.y_mm)
    tx, ty, p = traction.astype(np.float64) * ((maps.x_mm[1] - maps.x_mm[0]) * 1e-3) ** 2
    return np.array(
        [tx.sum(), ty.sum(), p.sum(), (Y * p).sum() * 1e-3, -(X * p).sum() * 1e-3, (X * ty - Y * tx).sum() * 1e-3]
    )


def test_each_map_is_the_wrench_it_was_drawn_from(tmp_path):
    # A sheared, tilted, twisted press on an elongated, partly flat patch off centre.
    sheared = [0.1, -0.05, 0.8, 0.8 * 2e-3 + 1e-4, 0.8 * 3e-3, 0.004]
    # 0.6 N at (-4, 0) mm and 0.4 N at (4, 0) mm: the moments about the origin are Ty = -x Fz.
    share = [0.02, 0.0, 0.4, 0.0, -4e-3 * 0.4, 0.0]
    total = [0.05, 0.0, 1.0, 0.0, 4e-3 * 0.6 - 4e-3 * 0.4, 0.0]
    rows = [
        _row("press.png", sheared, (-3.0, 2.0, 2.5), shape=(0.4, 1.5, 0.3)),
        _row("quiet.png", [0] * 6, (0.0, 0.0, 3.0), status="no_contact"),
        _row("lost.png", [math.nan] * 6, (math.nan,) * 3, status="unreadable", contacts=0),
        _row("two.png", total, (-4.0, 0.0, 2.5), contacts=2, second=(4.0, 0.0, 2.0), share=share),
    ]
    csv_path = _write_csv(tmp_path / "w.csv", rows)
    assert mj.write_traction_maps(tmp_path / "out" / "maps.h5", DEVICE, csv_path) == 4
    maps = mj.read_traction_maps(tmp_path / "out" / "maps.h5")
    assert maps.frame == ["press.png", "quiet.png", "lost.png", "two.png"]
    assert maps.status == ["converged", "no_contact", "unreadable", "converged"]
    ranges = np.array([mj.PAPER_RANGES[a] for a in mj.WRENCH_AXES])
    for k, wrench in ((0, sheared), (3, total)):
        assert np.all(np.abs(_moments(maps.traction[k], maps) - wrench) < 1e-5 * ranges)
    np.testing.assert_allclose(maps.wrench[0], sheared)
    # The sheared press's centre of pressure: x = -Ty / Fz, y = Tx / Fz.
    np.testing.assert_allclose(maps.centre_of_pressure_mm[0], [-3.0, 2.0 + 0.125], atol=1e-9)
    assert np.all(maps.traction[1] == 0) and np.all(np.isnan(maps.traction[2]))
    assert np.all(np.isnan(maps.centre_of_pressure_mm[1:3]))
    # Each patch of the two carries its own share, in its own half of the pad.
    p = maps.traction[3, 2].astype(np.float64)
    half = p.shape[1] // 2
    assert p[:, half:].sum() / p.sum() == pytest.approx(0.4, abs=0.01)
    assert list(maps.contacts) == [1, 0, 0, 2]
    np.testing.assert_allclose(maps.contact_area_mm2[[0, 3]], [math.pi * 2.5**2, math.pi * (2.5**2 + 2.0**2)])
    # Frames read alone come from their own chunks, unchanged.
    alone = mj.read_traction_maps(tmp_path / "out" / "maps.h5", frames=np.array([3]))
    np.testing.assert_array_equal(alone.traction[0], maps.traction[3])
    assert alone.frame == ["two.png"]


def test_the_centre_of_pressure_follows_the_convention():
    # A press at (x, y) = (2, -1) mm: Tx = y Fz, Ty = -x Fz.
    fz = 0.5
    wrench = np.array([[0, 0, fz, -1e-3 * fz, -2e-3 * fz, 0], [0, 0, 0, 0, 0, 0], [0, 0, -0.1, 0, 0, 0]])
    cop = mj.centre_of_pressure_mm(wrench)
    np.testing.assert_allclose(cop[0], [2.0, -1.0])
    assert np.all(np.isnan(cop[1:]))


def test_a_bad_csv_or_an_unwritable_path_loses_nothing(tmp_path):
    good = _write_csv(tmp_path / "good.csv", [_row("f.png", [0, 0, 0.5, 0, 0, 0], (0.0, 0.0, 3.0))])
    out = tmp_path / "maps.h5"
    mj.write_traction_maps(out, DEVICE, good)
    before = out.read_bytes()
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    with pytest.raises(mj.DataError, match=r"other\.csv: no column frame.*not a wrench CSV"):
        mj.write_traction_maps(out, DEVICE, tmp_path / "other.csv")
    broken = tmp_path / "broken.csv"
    broken.write_text(good.read_text().replace("0.5", "lots"))
    with pytest.raises(mj.DataError, match=r"broken\.csv row 2: field 'fz': 'lots' is not a number"):
        mj.write_traction_maps(out, DEVICE, broken)
    with pytest.raises(mj.DataError, match="missing.csv"):
        mj.write_traction_maps(out, DEVICE, tmp_path / "missing.csv")
    # The old file is whole, and nothing is left beside it.
    assert out.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["good.csv", "maps.h5", "other.csv", "broken.csv"]
    )
    (tmp_path / "a_folder.h5").mkdir()
    with pytest.raises(mj.OutputError, match="a_folder.h5"):
        mj.write_traction_maps(tmp_path / "a_folder.h5", DEVICE, good)
    (tmp_path / "not_maps.h5").write_bytes(b"not hdf5")
    with pytest.raises(mj.DataError, match=r"not_maps\.h5: not a traction-map file"):
        mj.read_traction_maps(tmp_path / "not_maps.h5")


def test_the_cli_checks_its_outputs_before_inverting(tmp_path, capsys):
    from moirejax.cli._main import main

    mj.save_device(tmp_path / "mid.json", DEVICE)
    data = tmp_path / "frames"
    data.mkdir()
    import cv2

    cv2.imwrite(str(data / "f0.png"), np.zeros((256, 256), np.uint8))
    base = ["invert", "--device", str(tmp_path / "mid.json"), "--data", str(data), "--out", str(tmp_path / "w.csv")]
    assert main([*base, "--plot-frames", "3"]) == 2
    assert "--plot-frames sets how many frames --plot draws" in capsys.readouterr().err
    assert main([*base, "--maps", str(tmp_path / "w.csv")]) == 2
    assert "--out and --maps name the same path" in capsys.readouterr().err
    (tmp_path / "taken").write_text("a file")
    assert main([*base, "--plot", str(tmp_path / "taken")]) == 4
    assert "taken: is a file; --plot needs a folder" in capsys.readouterr().err
    assert not (tmp_path / "w.csv").exists()
