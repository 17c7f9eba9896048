"""Every notebook in notebooks/ runs top to bottom, on its small settings, with its outputs stripped.

Each notebook is executed by nbclient (the `test` extra) in the notebooks/ folder. A notebook whose
first tagged cell is `parameters` (as in papermill) gets one cell after it that sets `SMALL = True`:
its small scene or short run. Every notebook runs in the default suite (`make test`); one whose
metadata names shared data ({"clumpylen": {"needs_data": "real/..."}}) is skipped, with the reason,
where ../shared/data lacks it. See notebooks/README.md for how to add one.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
ALL = sorted(NOTEBOOKS.glob("*.ipynb"))
SMALL_CELL = "SMALL = True  # injected by tests/test_notebook.py: the notebook's small settings"


SHARED_DATA = Path(os.environ.get("CLUMPYLEN_SHARED_DATA")
                   or Path(__file__).resolve().parents[2] / "shared" / "data")


def _meta(path) -> dict:
    """Notebook metadata "clumpylen": {"needs_data": "real/..."} (a folder of ../shared/data;
    skipped without it)."""
    return json.loads(path.read_text(encoding="utf-8")).get("metadata", {}).get("clumpylen", {})


def _marks(path) -> list:
    need = _meta(path).get("needs_data")
    if need and not (SHARED_DATA / need).is_dir():
        return [pytest.mark.skip(reason=f"shared data not found at {SHARED_DATA / need}")]
    return []


RUNS = [pytest.param(p, id=p.stem, marks=_marks(p)) for p in ALL]


def test_there_are_notebooks():
    assert {"quickstart.ipynb", "simulate-and-look.ipynb", "fit-mock-arc.ipynb", "accuracy-vs-time.ipynb",
            "fit-real-jwst.ipynb", "fit-without-truth.ipynb", "study-completeness.ipynb"} <= {p.name for p in ALL}


@pytest.mark.parametrize("path", ALL, ids=[p.stem for p in ALL])
def test_small_settings_and_no_slow_flag(path):
    """Every notebook runs in the default suite: none is flagged slow (the flag is gone), and each
    has a `parameters` cell defining SMALL, after which the test turns its small settings on."""
    nb = json.loads(path.read_text(encoding="utf-8"))
    assert "slow" not in _meta(path), f"{path.name}: give it SMALL settings instead of a slow flag"
    tagged = [c for c in nb["cells"] if "parameters" in c.get("metadata", {}).get("tags", [])]
    assert tagged and "SMALL" in "".join(tagged[0]["source"]), f"{path.name}: no parameters cell with SMALL"


@pytest.mark.parametrize("path", ALL, ids=[p.stem for p in ALL])
def test_outputs_are_stripped(path):
    nb = json.loads(path.read_text(encoding="utf-8"))
    assert nb["nbformat"] == 4
    dirty = [i for i, c in enumerate(nb["cells"]) if c["cell_type"] == "code"
             and (c.get("outputs") or c.get("execution_count") is not None)]
    assert not dirty, f"{path.name}: cells {dirty} keep outputs; strip them (see notebooks/README.md)"


@pytest.mark.parametrize("path", ALL, ids=[p.stem for p in ALL])
def test_code_cells_compile(path):
    """Every notebook, slow or not, is at least valid Python in every code cell (no kernel needed)."""
    nb = json.loads(path.read_text(encoding="utf-8"))
    for i, c in enumerate(nb["cells"]):
        if c["cell_type"] == "code":
            src = "".join(c["source"])
            lines = [ln for ln in src.splitlines() if not ln.lstrip().startswith(("%", "!"))]  # IPython magics
            compile("\n".join(lines), f"{path.name}[cell {i}]", "exec")


@pytest.mark.parametrize("path", RUNS)
def test_notebook_runs(path, monkeypatch):
    nbclient = pytest.importorskip("nbclient", reason="nbclient is in the `test` extra: pip install -e .[test]")
    import nbformat

    monkeypatch.setenv("MPLBACKEND", "Agg")  # no display on the test machine
    monkeypatch.setenv("CLUMPYLEN_REAL_DATA", str(SHARED_DATA / "real"))
    nb = nbformat.read(path, as_version=4)
    tagged = [i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", [])]
    if tagged:
        nb.cells.insert(tagged[0] + 1, nbformat.v4.new_code_cell(SMALL_CELL))
    before = set(NOTEBOOKS.iterdir())
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()  # raises CellExecutionError naming the cell and its traceback
    assert all(c.get("execution_count") for c in nb.cells if c.cell_type == "code")
    assert set(NOTEBOOKS.iterdir()) == before, "a notebook wrote into notebooks/; write into a temporary folder"
