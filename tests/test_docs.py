"""The documentation site: complete, self-contained, and its example runs.

`mkdocs build --strict` (run by `.ci/run`) checks that every cross-reference resolves;
these tests check what a build cannot: that every public name has a place in the API
reference, that every JSON Schema has a table on the data-formats page, that nothing links
outside the repository, that the documentation, notebooks and benchmarks use only the
public names, that the README stays a short front door whose paths and commands exist, and
that the Python examples of the README and the getting-started page do what they say.
"""

import argparse
import importlib
import importlib.resources
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import moirejax as mj
import moirejax.live


ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
API = DOCS / "api"
README = ROOT / "README.md"

# Everything outside the package that users read or run: the README and changelog, the
# documentation site (pages and hooks), the notebooks (both halves of each jupytext pair),
# the README files beside them, the benchmarks, and examples when there are any.
_OUTSIDE_PATTERNS = (
    "*.md",
    "docs/**/*.md",
    "docs/**/*.py",
    "moirejax/fits/**/*.md",
    "notebooks/*.ipynb",
    "notebooks/*.py",
    "notebooks/*.md",
    "benchmarks/**/*.py",
    "examples/**/*.py",
    "examples/**/*.md",
    "examples/**/*.ipynb",
)
# A private module reached from outside: `moirejax._name`, `moirejax.live._name`, `mj._name`
# (imports, attributes, `::: ` lines of the API pages). Dunders such as `mj.__version__` are public.
_PRIVATE_MODULE = re.compile(r"\b(?:moirejax|mj)(?:\.[A-Za-z]\w*)*\._(?!_)\w*")

# `::: dotted.path` lines of the API reference pages.
_DIRECTIVE = re.compile(r"^::: ([\w.]+)$", re.MULTILINE)


def _public_names(module) -> set[str]:
    # Modules reached as attributes (`importlib`, the `live` subpackage) are not API entries.
    return {
        f"{module.__name__}.{name}"
        for name in dir(module)
        if not name.startswith("_") and not isinstance(getattr(module, name), type(sys))
    }


def _documented() -> list[str]:
    return [path for page in sorted(API.glob("*.md")) for path in _DIRECTIVE.findall(page.read_text())]


def _resolve(path: str):
    """The object a `::: path` line documents (a module, then attributes)."""
    parts = path.split(".")
    for split in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        for attribute in parts[split:]:
            obj = getattr(obj, attribute)
        return obj
    raise ImportError(path)


def test_api_reference_lists_every_public_name_once():
    documented = _documented()
    public = _public_names(mj) | _public_names(moirejax.live)
    # A name re-exported at the top level (`moirejax.open_sensor` for
    # `moirejax.live.open_sensor`) is documented once, under either path.
    entries = {(path.rsplit(".", 1)[-1], id(_resolve(path))) for path in documented}
    missing = sorted(path for path in public if (path.rsplit(".", 1)[-1], id(_resolve(path))) not in entries)
    assert not missing, f"public names missing from docs/api/*.md: {missing}"
    repeated = sorted({path for path in documented if documented.count(path) > 1})
    assert not repeated, f"documented twice: {repeated}"


def test_api_reference_names_only_things_that_exist():
    for path in _documented():
        try:
            _resolve(path)
        except (ImportError, AttributeError):
            pytest.fail(f"docs/api names {path}, which does not exist")


def test_every_schema_has_a_table_on_the_data_formats_page():
    page = (DOCS / "data-formats.md").read_text()
    schemas = importlib.resources.files("moirejax") / "data_schema"
    names = {p.name.removesuffix(".schema.json") for p in schemas.iterdir() if p.name.endswith(".schema.json")}
    tabled = set(re.findall(r"^<!-- schema: ([a-z_]+) -->$", page, re.MULTILINE))
    assert names == tabled


def _outside_the_package() -> list[Path]:
    return sorted({path for pattern in _OUTSIDE_PATTERNS for path in ROOT.glob(pattern)})


def test_outside_files_are_found():
    names = {path.relative_to(ROOT).as_posix() for path in _outside_the_package()}
    assert {"README.md", "docs/index.md", "notebooks/01_design_space.ipynb", "benchmarks/render.py"} <= names


def test_nothing_outside_the_package_uses_a_private_module():
    uses = [
        f"{path.relative_to(ROOT)}:{line}: {match.group(0)}"
        for path in _outside_the_package()
        for line, text in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1)
        for match in _PRIVATE_MODULE.finditer(text)
    ]
    assert not uses, "private modules used outside the package (export the name instead):\n" + "\n".join(uses)


def test_nothing_links_outside_the_repository():
    # The documents, not the benchmarks: `benchmarks/peer_frames.py --render` runs a renderer
    # that sits beside the checkout when there is one.
    documents = [path for path in _outside_the_package() if path.parts[len(ROOT.parts)] != "benchmarks"]
    sources = [ROOT / "mkdocs.yml", *documents]
    for source in sources:
        text = source.read_text()
        # (udp://host:port sink specs are fine: they are examples, not links.)
        external = re.search(r"(https?|ftp)://|\]\(//|www\.", text)
        assert external is None, f"{source.relative_to(ROOT)} links outside the repository: {external}"
        assert "../shared" not in text and "shared/reference" not in text, f"{source.relative_to(ROOT)}"


def test_readme_is_a_short_front_door():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines; move long content into docs/"
    # The two commands for a fresh machine come first (.ci/run runs the second verbatim).
    assert lines[:4] == [
        "```bash",
        "python3 -m pip install -e . && moirejax demo",
        'python3 -m pip install -e ".[test]" && python3 -m pytest',
        "```",
    ]


def test_readme_links_only_to_pages_that_exist():
    links = re.findall(r"\]\(([^)\s]+)\)", README.read_text(encoding="utf-8"))
    assert any(link.startswith("docs/") and link.endswith(".md") for link in links), links
    missing = sorted({link for link in links if not (ROOT / link.split("#")[0]).is_file()})
    assert not missing, f"README.md links to files that do not exist: {missing}"


def test_every_path_the_readme_names_exists():
    text = README.read_text(encoding="utf-8")
    # Code spans that are a single path, and link targets, rooted in a folder of the repository
    # (command lines such as `--out fits/unit.json` name files they would write, not files that exist).
    spans = re.findall(r"`([^`\s]+)`", text) + re.findall(r"\]\(([^)\s]+)\)", text)
    paths = [span for span in spans if re.match(r"(docs|moirejax|tests|benchmarks|notebooks|fits)/", span)]
    paths += re.findall(r"python3? (benchmarks/\S+\.py)", text)
    assert len(paths) > 10, paths
    missing = sorted({path for path in paths if not (ROOT / path).exists()})
    assert not missing, f"README.md names paths that do not exist: {missing}"


def test_readme_command_table_has_every_cli_command_once():
    from moirejax.cli._main import build_parser

    (subparsers,) = [action for action in build_parser()._actions if isinstance(action, argparse._SubParsersAction)]
    text = README.read_text(encoding="utf-8")
    section = text.split("\n## Command line\n", 1)[1].split("\n## ", 1)[0]
    rows = [line.split("|") for line in section.splitlines() if line.startswith("| `moirejax ")]
    listed = [re.fullmatch(r" `moirejax (\S+)` ", row[1]).group(1) for row in rows]
    assert sorted(listed) == sorted(subparsers.choices), listed
    assert all(row[2].strip() for row in rows), "every command says what it does"


@pytest.mark.usefixtures("moire_bands_only")
def test_readme_example_calibrates_and_inverts(tmp_path):
    (example,) = re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), re.DOTALL)
    assert "moirejax._" not in example and "import moirejax as mj" in example
    # The example says it inverts a new frame of the calibrated unit: check it is read well.
    check = """
assert mj.Status(int(estimate.status)) == mj.Status.CONVERGED, estimate.status
assert abs(float(estimate.wrench[2]) - test.wrenches[0][2]) < 0.1, (estimate.wrench, test.wrenches[0])
"""
    # The checkout, importable without an install; the tests' model grid (tests/conftest.py) keeps it quick.
    env = os.environ | {"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run(
        [sys.executable, "-c", example + check], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "wrench" in done.stdout and "sigma" in done.stdout
    assert (tmp_path / "fit.json").is_file()


def test_getting_started_example_runs_and_recovers_the_wrench(tmp_path):
    page = (DOCS / "getting-started.md").read_text()
    (example,) = [block for block in re.findall(r"```python\n(.*?)```", page, re.DOTALL) if "render_frame" in block]
    # The page promises the rendered wrench back, converged, to a few thousandths of a newton.
    check = """
assert mj.Status(int(estimate.status)) == mj.Status.CONVERGED, estimate.status
error = abs(estimate.wrench - wrench)
assert float(error[:3].max()) < 0.01 and float(error[3:].max()) < 1e-4, error
"""
    done = subprocess.run([sys.executable, "-c", example + check], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "amplification 14.0" in done.stdout
