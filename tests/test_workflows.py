"""Calibrate, evaluate, transfer and import on small simulated datasets: outputs, files, failure paths."""

import json

import numpy as np
import pytest

import moirejax as mj
from moirejax._calibration import Recipe
from moirejax._cli import main
from moirejax._dataset import Dataset, export_recording
from moirejax._docs import cli_reference
from moirejax._simulate import simulate_dataset
from moirejax._workflows import calibrate, evaluate, transfer

from .helpers import tree_allclose


SMALL: dict = {}


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    root = tmp_path_factory.mktemp("workflows")
    nominal = mj.preset("mid", **SMALL)
    mj.save_device(root / "mid.json", nominal)
    # Model fidelity keeps this fast; the unit still deviates from its design.
    unit = mj.perturb_device(__import__("jax").random.PRNGKey(5), nominal)
    simulate_dataset(root / "cal", nominal, "paper", 16, seed=5, fidelity="model", unit=unit, progress=False)
    simulate_dataset(root / "test", nominal, "mixed", 8, seed=6, fidelity="model", unit=unit, progress=False)
    return root


def test_calibrate_evaluate_transfer(datasets):
    root = datasets
    summary = calibrate(
        root / "mid.json",
        root / "cal",
        root / "fit.json",
        recipe=Recipe(rounds=1, parameter_frames=8, parameter_steps=4, latent_steps=8),
        baseline_sizes=(10,),
        progress=False,
    )
    fitted, head = mj._workflows.load_calibrated(root / "fit.json")
    # Too few frames for a residual head: the calibration says so instead of overfitting.
    assert head is None and "skipped" in json.loads((root / "fit_report" / "metrics.json").read_text())["residual_head"]
    obj = json.loads((root / "fit.json").read_text())
    assert set(obj["calibration"]["uncertainty"]) == set(Recipe().free)
    report = root / "fit_report"
    for name in ("metrics.json", "parity.png", "residuals.png", "parameters.png"):
        assert (report / name).exists(), name
    assert summary["parameters"][0]["parameter"] == "elastomer.E" and "true" in summary["parameters"][0]

    metrics = evaluate(root / "fit.json", root / "test", root / "eval", progress=False)
    written = json.loads((root / "eval" / "metrics.json").read_text())
    for key in ("r2", "mae", "rmse", "coverage95"):
        assert set(written[key]) == {"fx", "fy", "fz", "tx", "ty", "tz"}
    # A calibrated unit on model-fidelity frames: the normal force is well determined
    # even from this tiny calibration.
    assert metrics["r2"]["fz"] > 0.8, metrics["r2"]

    transfer(root / "fit.json", root / "test", root / "fit_b.json", max_frames=5, progress=False)
    fitted_b, head_b = mj._workflows.load_calibrated(root / "fit_b.json")
    assert head_b is None and fitted_b.layout == fitted.layout


def test_interrupted_calibration_leaves_no_device_file(datasets, monkeypatch):
    root = datasets

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mj._workflows, "fit_physical_parameters", interrupt)
    with pytest.raises(KeyboardInterrupt):
        calibrate(root / "mid.json", root / "cal", root / "never.json", progress=False)
    assert not (root / "never.json").exists()
    assert not any(p.name.startswith(".never.json") for p in root.iterdir())


def test_calibrate_refuses_dataset_without_reference(tmp_path, datasets):
    nominal = mj.preset("mid", **SMALL)
    simulate_dataset(tmp_path / "nocontactfree", nominal, "mixed", 6, seed=1, fidelity="model", progress=False)
    assert (
        main(["calibrate", "--data", str(tmp_path / "nocontactfree"), "--out", str(tmp_path / "x.json"), "--quiet"])
        == 2
    )


def test_import_cli_round_trip(tmp_path, datasets, capsys):
    source = Dataset(datasets / "test")
    export_recording(source, tmp_path / "frames", tmp_path / "ft.csv")
    argv = ["import", "--frames", str(tmp_path / "frames"), "--wrench", str(tmp_path / "ft.csv")]
    argv += ["--device", str(datasets / "mid.json"), "--out", str(tmp_path / "imported")]
    assert main(argv) == 0
    imported = Dataset(tmp_path / "imported")
    np.testing.assert_array_equal(imported.wrenches, source.wrenches)
    np.testing.assert_array_equal(imported.frame(3), source.frame(3))
    assert tree_allclose(mj.device_from_json(imported.device), mj.device_from_json(source.device))
    # A CSV without a column is refused, naming the column.
    (tmp_path / "bad.csv").write_text("frame,fx,fy,fz,tx,ty\n000000.png,0,0,0,0,0\n")
    argv[4] = str(tmp_path / "bad.csv")
    argv[-1] = str(tmp_path / "imported2")
    assert main(argv) == 2
    assert "tz" in capsys.readouterr().err


def test_invert_cli_writes_status_rows(tmp_path, datasets):
    frames = tmp_path / "frames"
    export_recording(Dataset(datasets / "test"), frames, tmp_path / "ft.csv")
    (frames / "zz_corrupt.png").write_bytes(b"not a png")
    out = tmp_path / "w.csv"
    assert (
        main(["invert", "--device", str(datasets / "mid.json"), "--data", str(frames), "--out", str(out), "--quiet"])
        == 0
    )
    rows = out.read_text().splitlines()
    assert rows[0].startswith("frame,fx,fy,fz,tx,ty,tz,sigma_fx")
    assert rows[-1].startswith("zz_corrupt.png") and "unreadable" in rows[-1]


def test_readme_cli_reference_is_current():
    from pathlib import Path

    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    assert cli_reference() in readme, "run `python -m moirejax._docs` to regenerate the README's CLI reference"
