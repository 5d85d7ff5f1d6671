"""Calibrate, evaluate, transfer and import on small simulated datasets: outputs, files, failure paths."""

import csv
import importlib.resources
import json
import math
import os
import shutil
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import moirejax as mj
from moirejax._fileio import validate_json
from moirejax.calibration import _calibration
from moirejax.calibration._calibration import load_recipe, observe_frames, Recipe
from moirejax.calibration._workflows import calibrate, evaluate, transfer
from moirejax.cli._docs import cli_reference
from moirejax.cli._main import main
from moirejax.data._dataset import Dataset, export_recording
from moirejax.inverse import invert
from moirejax.simulate._simulate import simulate_dataset

from .helpers import tree_allclose


# Mid's 32 mm field on a 256 x 256 px camera: the workflows at a quarter of the pixels.
SMALL: dict = dict(height=256, width=256, px_per_mm=8.0)


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


@pytest.mark.usefixtures("float32", "moire_bands_only")
def test_calibrate_evaluate_transfer(datasets, monkeypatch):
    root = datasets
    workflows = mj.calibration._workflows
    recipe = load_recipe("unit").replace(rounds=1, parameter_frames=8, parameter_steps=4, latent_steps=8)

    def run():
        return calibrate(
            root / "mid.json", root / "cal", root / "fit.json", recipe=recipe, baseline_sizes=(10,), progress=False
        )

    # The work kept in fit.json.parts/ as it is done: copied here before the run clears it,
    # to resume from below.
    parts = root / "fit.json.parts"
    write_fit_set = workflows._write_fit_set

    def write_and_keep_parts(*args):
        write_fit_set(*args)
        shutil.copytree(parts, root / "kept.parts")

    # Every stage of the parameter fit runs one program; what a stage holds comes back as it went in.
    parameter_solve, stages = _calibration._parameter_solve, []

    def recorded(problem, theta, free, *args):
        out = parameter_solve(problem, theta, free, *args)
        stages.append((np.asarray(theta), np.asarray(free), np.asarray(out[0])))
        return out

    monkeypatch.setattr(workflows, "_SOLVED_PER_PART", 4)
    with monkeypatch.context() as m:
        m.setattr(workflows, "_write_fit_set", write_and_keep_parts)
        m.setattr(_calibration, "_parameter_solve", recorded)
        summary = run()
    assert not parts.exists()
    assert [free.tolist() for _, free, _ in stages] == [[True] + [False] * 5, [False] + [True] * 5]
    for before, free, after in stages:
        np.testing.assert_array_equal(after[~free], before[~free])
        assert np.all(after[free] != before[free])
    (root / "kept.parts").rename(parts)
    solved = sorted(p.name for p in parts.glob("solved-*.npz"))
    assert (parts / "physical.json").is_file() and solved[:2] == ["solved-000000.npz", "solved-000004.npz"]
    first = {name: json.loads((root / name).read_text()) for name in ("fit.json", "fit_report/metrics.json")}

    # Interrupted in the cold solves: two parts not yet written, one torn. The rerun does not
    # fit again, solves only those three parts, writes the same numbers, and clears the parts.
    for name in solved[2:]:
        (parts / name).unlink()
    (parts / solved[1]).write_bytes((parts / solved[1]).read_bytes()[:100])
    solves = []
    with monkeypatch.context() as m:
        m.setattr(workflows, "fit_physical_parameters", lambda *a, **k: pytest.fail("refitted"))
        m.setattr(
            workflows, "invert", lambda inverter, frames, **k: solves.append(len(frames)) or invert(inverter, frames)
        )
        run()
    assert len(solves) == len(solved) - 1 and not parts.exists()
    for name, obj in first.items():
        assert json.loads((root / name).read_text()) == obj, name
    fitted, head = workflows.load_calibrated(root / "fit.json")
    # Too few frames for a residual head: the calibration says so instead of overfitting.
    assert head is None and "skipped" in json.loads((root / "fit_report" / "metrics.json").read_text())["residual_head"]
    obj = json.loads((root / "fit.json").read_text())
    assert set(obj["calibration"]["uncertainty"]) == set(load_recipe("unit").free)
    report = root / "fit_report"
    for name in ("metrics.json", "parity.png", "residuals.png", "parameters.png"):
        assert (report / name).exists(), name
    assert summary["parameters"][0]["parameter"] == "elastomer.E" and "true" in summary["parameters"][0]
    written_verdict = json.loads((report / "metrics.json").read_text())["verdict"]
    assert written_verdict == json.loads(json.dumps(summary["verdict"])) and "inside_model" in written_verdict

    metrics = evaluate(root / "fit.json", root / "test", root / "eval", progress=False)
    written = json.loads((root / "eval" / "metrics.json").read_text())
    for key in ("r2", "mae", "rmse", "coverage95"):
        assert set(written[key]) == set(mj.WRENCH_AXES)
    # A calibrated unit on model-fidelity frames: the normal force is well determined
    # even from this tiny calibration.
    assert metrics["r2"]["fz"] > 0.8, metrics["r2"]

    # A transfer recipe from a file whose prior pins the stiffness to unit A's value.
    pinned = load_recipe("transfer").replace(name="pinned", prior_sd=(("elastomer.E", 1e-5),))
    (root / "pinned.json").write_text(json.dumps(pinned.to_json()))
    transfer(
        root / "fit.json", root / "test", root / "fit_b.json", max_frames=5, recipe=root / "pinned.json", progress=False
    )
    fitted_b, head_b = mj.calibration._workflows.load_calibrated(root / "fit_b.json")
    assert head_b is None and fitted_b.layout == fitted.layout
    assert json.loads((root / "fit_b.json").read_text())["calibration"]["recipe"] == "pinned"
    assert float(fitted_b.elastomer.E) == pytest.approx(float(fitted.elastomer.E), rel=1e-3)


@pytest.mark.usefixtures("float32", "moire_bands_only")
def test_the_stiffness_is_fitted_although_each_frames_contact_trades_with_it(datasets):
    # A stiffer layer under the same reading looks like a smaller patch. One round of a fit
    # started 30 % stiff lands within 2 % of the unit's stiffness only when the parameter
    # step takes that trade into account: with every frame's contact held where the
    # starting device put it, it lands 4.6 % off on these frames (and, on frames of a
    # high-fidelity unit, did not move at all).
    dataset = Dataset(datasets / "cal")
    truth = mj.physics.device_from_json(dataset.manifest["true_device"])
    true_E = float(truth.elastomer.E)
    start = mj.load_device(datasets / "mid.json")
    start = eqx.tree_at(lambda d: d.elastomer.E, start, jnp.asarray(1.3 * true_E, start.elastomer.E.dtype))
    loaded = np.flatnonzero(np.abs(dataset.wrenches).sum(axis=1) > 0)[:8]
    recipe = Recipe(
        name="stiffness", free=("elastomer.E",), log=("elastomer.E",), rounds=1, parameter_frames=8, latent_steps=8
    )
    result = mj.fit_physical_parameters(
        start, mj.dataset_reference(dataset), dataset.frames(loaded), dataset.wrenches[loaded], recipe, progress=False
    )
    fitted = float(result.device.elastomer.E)
    assert abs(fitted / true_E - 1) < 0.02, (fitted, true_E)
    assert 0 < result.uncertainty["elastomer.E"] < 0.1 * true_E


def test_a_calibration_keeps_the_fringe_fields_of_its_frames_read_a_chunk_at_a_time(datasets, monkeypatch, caplog):
    dataset = Dataset(datasets / "cal")
    inverter = mj.Inverter(mj.load_device(datasets / "mid.json"), reference=dataset.frame(0))
    frames = dataset.frames()
    monkeypatch.setattr(_calibration, "_OBSERVE_CHUNK", 5)
    with jax.log_compiles(), caplog.at_level("WARNING"):
        chunked = observe_frames(inverter, frames)
    # 16 frames, 5 at a time: one program for the three full chunks, one for the last frame.
    compiles = [r for r in caplog.records if r.getMessage().startswith("Compiling jit(_observe_chunk)")]
    assert len(compiles) == 2, [r.getMessage()[:80] for r in compiles]
    whole = jax.lax.map(inverter.observe, jnp.asarray(np.asarray(frames), inverter.device.p1.dtype))
    assert tree_allclose(chunked, whole)
    with pytest.raises(ValueError, match="no frames"):
        observe_frames(inverter, frames[:0])


def test_spanning_frames_load_every_axis():
    # An isolated-axis session, as the paper's: mostly normal presses, a few shear and twist.
    rng = np.random.default_rng(0)
    wrenches = np.zeros((60, 6))
    wrenches[:, 2] = rng.uniform(0.3, 1.2, 60)
    for row, axis, value in ((7, 0, 0.15), (19, 1, -0.18), (33, 5, 0.006), (41, 3, 0.01), (52, 0, -0.12)):
        wrenches[row, axis] = value
    chosen = mj.calibration._workflows.spanning_frames(wrenches, 8)
    assert len(set(chosen.tolist())) == 8 and {7, 19, 33, 41, 52} <= set(chosen.tolist())
    assert int(np.argmax(wrenches[:, 2])) in chosen
    assert len(mj.calibration._workflows.spanning_frames(wrenches[:3], 8)) == 3


def test_named_recipes_round_trip_and_bad_recipes_are_refused(tmp_path):
    for name in ("unit", "transfer"):
        recipe = load_recipe(name)
        assert recipe.name == name and Recipe.from_json(recipe.to_json()) == recipe
        assert set(dict(recipe.prior_sd)) <= set(recipe.free)
    with pytest.raises(ValueError, match="not a Device parameter"):
        Recipe(name="bad", free=("elastomer.stiffness",))
    with pytest.raises(ValueError, match="not among its free"):
        Recipe(name="bad", free=("elastomer.E",), log=("optics.gain",))
    bad = load_recipe("unit").to_json() | {"rounds": 0}
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(mj.DataError, match="rounds"):
        load_recipe(tmp_path / "bad.json")
    (tmp_path / "typo.json").write_text(json.dumps(load_recipe("unit").to_json() | {"free": ["optics.gian"]}))
    with pytest.raises(mj.DataError, match="optics.gian"):
        load_recipe(tmp_path / "typo.json")
    with pytest.raises(mj.DataError, match="named: transfer, unit"):
        load_recipe("nonesuch")


def test_interrupted_calibration_leaves_no_device_file(datasets, monkeypatch):
    root = datasets

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mj.calibration._workflows, "fit_physical_parameters", interrupt)
    with pytest.raises(KeyboardInterrupt):
        calibrate(root / "mid.json", root / "cal", root / "never.json", progress=False)
    assert not (root / "never.json").exists()
    assert not any(p.name.startswith(".never.json") for p in root.iterdir())


def test_calibrate_refuses_dataset_without_reference(tmp_path, datasets):
    nominal = mj.preset("mid", **SMALL)
    simulate_dataset(tmp_path / "nocontactfree", nominal, "mixed", 6, seed=1, fidelity="model", progress=False)
    assert (
        main(["calibrate", "--data", str(tmp_path / "nocontactfree"), "--out", str(tmp_path / "x.json"), "--quiet"])
        == 3
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
    assert main(argv) == 3
    err = capsys.readouterr().err
    assert "tz" in err and "(given by --wrench)" in err
    assert not (tmp_path / "imported2").exists()


@pytest.mark.usefixtures("float32", "moire_bands_only")
def test_invert_cli_writes_status_rows(tmp_path, datasets):
    frames = tmp_path / "frames"
    export_recording(Dataset(datasets / "test"), frames, tmp_path / "ft.csv")
    (frames / "zz_corrupt.png").write_bytes(b"not a png")
    out = tmp_path / "w.csv"
    # The unit's own no-contact frame as the reference, as a user records one.
    truth = Dataset(datasets / "test")
    rest = next(name for name, touching in zip(truth.frame_names, truth.contact) if not touching)
    command = ["invert", "--device", str(datasets / "mid.json"), "--data", str(frames), "--out", str(out)]
    assert main([*command, "--reference", str(frames / rest), "--quiet"]) == 0
    rows = out.read_text().splitlines()
    assert rows[0].startswith("frame,fx,fy,fz,tx,ty,tz,sigma_fx")
    assert rows[-1].startswith("zz_corrupt.png") and "unreadable" in rows[-1]
    # The nominal design read on a unit that deviates from it: every press is seen, and
    # its normal force read to within a fifth of a newton.
    read = {row["frame"]: row for row in csv.DictReader(rows)}
    for name, touching, wrench in zip(truth.frame_names, truth.contact, truth.wrenches):
        assert (read[name]["status"] == "no_contact") != bool(touching), (name, read[name]["status"])
        assert abs(float(read[name]["fz"]) - float(wrench[2])) < 0.2, (name, read[name]["fz"], wrench[2])
    # Every row, parsed, is what data_schema/wrench_csv.schema.json describes.
    for row in read.values():
        parsed = {k: v if k in ("frame", "status", "message") else _number(v) for k, v in row.items()}
        validate_json(parsed, "wrench_csv", source=str(out))


def _number(text: str) -> float | None:
    value = float(text)
    return value if math.isfinite(value) else None


@pytest.mark.parametrize("setting", ["default", "own", "off"])
def test_commands_keep_compiled_programs_in_a_cache_folder(tmp_path, setting):
    # A fresh process: the choice must be made before JAX compiles anything.
    cache_settings = (
        "JAX_COMPILATION_CACHE_DIR",
        "MOIREJAX_COMPILATION_CACHE",
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
    )
    env = {k: v for k, v in os.environ.items() if k not in cache_settings}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    if setting == "own":
        env["JAX_COMPILATION_CACHE_DIR"] = str(tmp_path / "own")
    if setting == "off":
        env["MOIREJAX_COMPILATION_CACHE"] = "0"
    code = (
        "import jax; from moirejax.cli._main import use_compilation_cache as u; "
        "print(u(), jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs)"
    )
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    expected = {"default": str(tmp_path / "xdg" / "moirejax" / "jax"), "own": str(tmp_path / "own"), "off": "None"}
    # The small programs a command compiles are kept too, unless the cache is off.
    threshold = "1.0" if setting == "off" else "0.0"
    assert result.stdout.split() == [expected[setting]] * 2 + [threshold]


def test_readme_cli_reference_is_current():
    # The reference lives on the documentation site (docs/cli.md), generated from the parser.
    from pathlib import Path

    page = (Path(__file__).resolve().parent.parent / "docs" / "cli.md").read_text()
    assert cli_reference() in page, "run `python -m moirejax.cli._docs` to regenerate the CLI reference in docs/cli.md"


def test_example_unit_in_the_package_loads_with_its_head():
    example = importlib.resources.files("moirejax").joinpath("fits", "examples", "mid-sim-unit3.json")
    device, head = mj.load_calibrated(str(example))
    assert head is not None and device.layout == mj.preset("mid").layout
    calibration = json.loads(example.read_text())["calibration"]
    assert calibration["recipe"] == "unit" and set(calibration["uncertainty"]) == set(load_recipe("unit").free)
    # The simulated unit is softer than its design (E 0.830 MPa against 1.0); the fit says
    # so, to within a tenth of the unit's own stiffness.
    assert abs(float(device.elastomer.E) / 0.830 - 1) < 0.1
    # The float32 head corrects float64 estimates (this suite runs with x64 enabled).
    corrected = head.correct(np.array([[0.0, 0.0, 0.6, 0.0, 0.0, 0.0]]), np.zeros(1), np.zeros(1), np.full(1, 3.5))
    assert corrected.shape == (1, 6) and np.all(np.isfinite(corrected))
    assert abs(corrected[0, 2] - 0.6) < 0.1


@pytest.mark.usefixtures("float32", "moire_bands_only")
@pytest.mark.usefixtures("float32", "moire_bands_only")
def test_demo_runs_end_to_end_in_smoke_mode(tmp_path, capsys):
    from moirejax.cli._demo import run_demo

    assert run_demo(str(tmp_path / "demo"), smoke=True) == 0
    out = capsys.readouterr().out
    assert "before calibration" in out and "ridge R2" in out and "ms per independent frame" in out
    for name in ("design_maps.png", "fit.json", "after/parity.png", "after/metrics.json", "fit_report/parameters.png"):
        assert (tmp_path / "demo" / name).exists(), name
    # Each axis row: before and after R2 and MAE, two ridge R2 values, the paper's R2.
    rows = [line for line in out.splitlines() if line[:2] in mj.WRENCH_AXES]
    assert len(rows) == 6 and all(len(row.split()) >= 11 for row in rows)


def test_calibration_verdict_names_the_axes_a_pixel_regression_reads_better():
    recipe = Recipe(name="t", free=("p1", "elastomer.E"), log=("elastomer.E",), prior_sd=(("p1", 0.001),))
    r2 = dict.fromkeys(mj.WRENCH_AXES, 0.99)
    baselines = {"20": dict.fromkeys(mj.WRENCH_AXES, 0.999), "400": {**dict.fromkeys(mj.WRENCH_AXES, 0.5), "fz": 0.995}}
    parameters = [
        {"parameter": "p1", "nominal": 0.35, "fitted": 0.3515, "sd": 1e-4},
        {"parameter": "elastomer.E", "nominal": 1.0, "fitted": 1.1, "sd": 0.01},
    ]
    # The baseline trained on the most frames is the one compared with; a NaN R² (an axis the
    # calibration never read) counts as behind.
    verdict = mj.calibration_verdict({"r2": {**r2, "tz": math.nan}}, baselines, parameters, recipe)
    assert not verdict["inside_model"]
    assert set(verdict["axes_behind_baseline"]) == {"fz", "tz"}
    assert verdict["axes_behind_baseline"]["fz"] == {"calibrated": 0.99, "ridge_baseline": 0.995}
    # p1 moved 1.5 prior widths: not strained; the free modulus moved 10%: not strained.
    assert verdict["strained_parameters"] == []
    moved = [{**parameters[0], "fitted": 0.354}, {**parameters[1], "fitted": 1.5}]
    strained = mj.calibration_verdict({"r2": r2}, baselines, moved, recipe)["strained_parameters"]
    assert [p["parameter"] for p in strained] == ["p1", "elastomer.E"]
    assert strained[0]["prior_widths"] == pytest.approx(4.0)
    assert mj.calibration_verdict({"r2": r2}, {"400": dict.fromkeys(mj.WRENCH_AXES, 0.9)}, parameters, recipe)[
        "inside_model"
    ]


_CONTACT_PER_FRAME = """
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import moirejax as mj
from moirejax.calibration._calibration import _latent_solve, _Problem, latents_from_wrench, load_recipe, parameter_vector
from moirejax.physics._contact import Contact
from moirejax.physics._render import render_frame

mid = mj.preset("mid")
contacts = [(2.0, -1.5, 3.0, 0.9), (-3.0, 2.0, 4.0, 0.6), (0.5, 0.5, 2.5, 1.1)]
wrenches = np.array([[0.05, -0.03, fz, y0 * fz * 1e-3, -x0 * fz * 1e-3, 0.002] for x0, y0, _, fz in contacts])
frames = jnp.stack(
    [render_frame(mid, jnp.asarray(w), Contact(x0, y0, r)) for w, (x0, y0, r, _) in zip(wrenches, contacts)]
)
inverter = mj.Inverter(mid, reference=render_frame(mid, jnp.zeros(6), Contact()))
observed = jax.lax.map(inverter.observe, frames)
start = latents_from_wrench(wrenches, jnp.float32)
start = eqx.tree_at(
    lambda s: (s.x0, s.y0, s.log_radius), start, (start.x0 + 0.8, start.y0 - 0.8, jnp.log(jnp.asarray([2.2, 3.2, 3.2])))
)
recipe = load_recipe("unit")
problem = _Problem(inverter.phase_only(), recipe.free, recipe.log)
fitted = _latent_solve(problem, parameter_vector(inverter.device, recipe), start, observed, 20)
truth = np.array(contacts)[:, :3]
np.testing.assert_allclose(np.asarray(fitted.x0), truth[:, 0], atol=0.05)
np.testing.assert_allclose(np.asarray(fitted.y0), truth[:, 1], atol=0.05)
np.testing.assert_allclose(np.exp(np.asarray(fitted.log_radius)), truth[:, 2], rtol=0.05)
"""


def test_each_frames_contact_is_fitted_to_its_own_fringe_phase():
    # Noise-free frames of three presses, each solved for its contact from a start 0.8 mm and
    # a quarter of the radius away: every frame finds its own, whatever the others do. In a
    # process of its own, in JAX's default single precision: compiling this program inside a
    # long-lived test worker crashed XLA (a segmentation fault, three full runs in a row),
    # while it compiles and passes in a fresh process.
    done = subprocess.run([sys.executable, "-c", _CONTACT_PER_FRAME], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout + done.stderr
