"""The notebooks run: each paired `notebooks/*.py` is executed in a fresh kernel in smoke mode.

The jupytext percent-format `.py` file is the reviewed source; the paired `.ipynb` is committed
without outputs. Notebooks added later are picked up by the glob.
"""

import re
from pathlib import Path

import pytest


jupytext = pytest.importorskip("jupytext")
nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
PAIRED = sorted(path for path in NOTEBOOKS.glob("*.py") if path.with_suffix(".ipynb").exists())
ANSI_COLOUR = re.compile(r"\x1b\[[0-9;]*m")


def _cells(notebook) -> list[tuple[str, str]]:
    return [(cell.cell_type, cell.source) for cell in notebook.cells]


def test_notebooks_found():
    assert PAIRED, f"no paired notebooks (*.py with a .ipynb beside it) in {NOTEBOOKS}"


@pytest.mark.parametrize("source", PAIRED, ids=lambda path: path.stem)
def test_notebook_pair_in_sync_and_without_outputs(source):
    paired = nbformat.read(source.with_suffix(".ipynb"), as_version=4)
    assert _cells(paired) == _cells(jupytext.read(source)), (
        f"{source.with_suffix('.ipynb').name} differs from {source.name}: run `jupytext --sync {source}`"
    )
    executed = [i for i, cell in enumerate(paired.cells) if cell.get("outputs") or cell.get("execution_count")]
    assert not executed, f"{source.with_suffix('.ipynb').name} has outputs in cells {executed}: clear them"


@pytest.mark.parametrize("source", PAIRED, ids=lambda path: path.stem)
@pytest.mark.usefixtures("moire_bands_only")
def test_notebook_runs_in_smoke_mode(source, tmp_path, monkeypatch):
    # The kernel inherits this environment; the notebooks shrink themselves under MOIREJAX_SMOKE.
    monkeypatch.setenv("MOIREJAX_SMOKE", "1")
    notebook = jupytext.read(source)
    client = nbclient.NotebookClient(
        notebook, kernel_name="python3", timeout=600, resources={"metadata": {"path": str(tmp_path)}}
    )
    try:
        client.execute()
    except nbclient.exceptions.CellExecutionError as error:
        pytest.fail(f"{source.name} failed in smoke mode:\n{ANSI_COLOUR.sub('', str(error))}", pytrace=False)
