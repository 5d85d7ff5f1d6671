"""The package as a user installs it: a wheel built from the checkout, installed into a fresh
virtual environment and run from a folder outside the checkout.

What this guards: every file the code loads at run time (the JSON Schemas, the named
calibration recipes) is inside the wheel and found through the installed package, not
through the checkout; the licence travels with it; `moirejax --version` answers.

The virtual environment sees the system's site-packages, so the dependencies (JAX and the
rest) need no download; `moirejax` itself comes from the wheel, which the test checks.
Building the wheel uses the environment's own setuptools (no build isolation, no network).
The whole file takes about 20 s.
"""

import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

import moirejax as mj
from moirejax.cli._main import main


ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "moirejax"

# What the code loads at run time, relative to the package.
RESOURCES = ["data_schema/*.schema.json", "fits/recipes/*.json", "fits/examples/*.json", "fits/examples/*.eqx"]


def _run(argv: list[str], cwd: Path) -> str:
    """Run a command of the virtual environment with nothing of the checkout on its path."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env["PYTHONNOUSERSITE"] = "1"
    done = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{argv} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built from a copy of the checkout so the build leaves nothing in it."""
    source = tmp_path_factory.mktemp("source") / "moirejax"
    ignore = shutil.ignore_patterns(".git", "build", "dist", "site", "*.egg-info", "__pycache__", ".*_cache", ".venv")
    shutil.copytree(ROOT, source, ignore=ignore)
    out = tmp_path_factory.mktemp("wheel")
    pip_wheel = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(out), "."]
    _run(pip_wheel, cwd=source)
    (built,) = out.glob("moirejax-*.whl")
    return built


@pytest.fixture(scope="module")
def environment(wheel, tmp_path_factory) -> Path:
    """A fresh virtual environment with the wheel installed; returns its bin folder."""
    env_dir = tmp_path_factory.mktemp("venv")
    venv.create(env_dir, system_site_packages=True, with_pip=False, symlinks=True)
    bin_dir = env_dir / "bin"
    # The environment's pip is the system's (visible through the system site-packages);
    # --force-reinstall puts the wheel into the environment even where the system already
    # has moirejax (an editable install of the checkout, as in development).
    install = [str(bin_dir / "python"), "-m", "pip", "install", "-q", "--no-deps", "--force-reinstall", str(wheel)]
    _run(install, cwd=env_dir)
    return bin_dir


def test_wheel_holds_every_resource_and_the_licence(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    expected = {f"moirejax/{p.relative_to(PACKAGE).as_posix()}" for pattern in RESOURCES for p in PACKAGE.glob(pattern)}
    assert len(expected) >= 12, expected  # seven schemas, two recipes and the example unit's three files
    assert expected <= names, f"missing from the wheel: {sorted(expected - names)}"
    dist_info = f"moirejax-{importlib.metadata.version('moirejax')}.dist-info"
    assert f"{dist_info}/licenses/LICENSE" in names
    metadata = zipfile.ZipFile(wheel).read(f"{dist_info}/METADATA").decode()
    assert "License-Expression: Apache-2.0" in metadata
    # Nothing outside the package (the checkout's fits/, tests/, docs/) rides along.
    assert {name.split("/")[0] for name in names} == {"moirejax", dist_info}


def test_version_flag(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"moirejax {importlib.metadata.version('moirejax')}"


def test_installed_wheel_runs_outside_the_checkout(environment, tmp_path):
    version = _run([str(environment / "moirejax"), "--version"], cwd=tmp_path)
    assert version.strip() == f"moirejax {importlib.metadata.version('moirejax')}"

    # Loads every schema, both named recipes and the example unit with its residual head
    # through the installed package, and writes and reads back a device file (validated
    # against its schema on the way in and out).
    script = """
import importlib.resources, json, sys
import jsonschema
import moirejax as mj

schemas = importlib.resources.files("moirejax") / "data_schema"
names = sorted(p.name for p in schemas.iterdir() if p.name.endswith(".schema.json"))
for name in names:
    jsonschema.Draft202012Validator.check_schema(json.loads((schemas / name).read_text()))
recipes = {name: mj.load_recipe(name).free for name in ("unit", "transfer")}
mj.save_device("device.json", mj.preset("mid"))
device = mj.load_device("device.json")
example = importlib.resources.files("moirejax").joinpath("fits", "examples", "mid-sim-unit3.json")
unit, head = mj.load_calibrated(str(example))
report = {"file": mj.__file__, "schemas": names, "recipes": recipes, "p1": float(device.p1)}
print(json.dumps(report | {"example_E": float(unit.elastomer.E), "example_head": head is not None}))
"""
    report = json.loads(_run([str(environment / "python"), "-c", script], cwd=tmp_path))
    installed = Path(report["file"]).resolve()
    assert environment.parent.resolve() in installed.parents, f"imported {installed}, not the wheel's copy"
    assert ROOT not in installed.parents
    assert report["schemas"] == sorted(p.name for p in (PACKAGE / "data_schema").glob("*.schema.json"))
    assert "elastomer.E" in report["recipes"]["unit"] and "elastomer.E" in report["recipes"]["transfer"]
    assert report["p1"] == pytest.approx(float(mj.preset("mid").p1))
    # The example unit is softer than its design (E 0.830 MPa); its fit says so, within a tenth.
    assert abs(report["example_E"] / 0.830 - 1) < 0.1 and report["example_head"]
