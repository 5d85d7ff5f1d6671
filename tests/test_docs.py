"""The documentation site: complete, self-contained, and its example runs.

`mkdocs build --strict` (run by `.ci/run`) checks that every cross-reference resolves;
these tests check what a build cannot: that every public name has a place in the API
reference, that every JSON Schema has a table on the data-formats page, that nothing links
outside the repository, and that the Python example of the getting-started page does what
the page says.
"""

import importlib
import importlib.resources
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
    missing = sorted(public - set(documented))
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


def test_nothing_links_outside_the_repository():
    sources = [ROOT / "mkdocs.yml", *DOCS.rglob("*.md")]
    for source in sources:
        text = source.read_text()
        # (udp://host:port sink specs are fine: they are examples, not links.)
        external = re.search(r"(https?|ftp)://|\]\(//|www\.", text)
        assert external is None, f"{source.relative_to(ROOT)} links outside the repository: {external}"
        assert "../shared" not in text and "shared/reference" not in text, f"{source.relative_to(ROOT)}"


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
