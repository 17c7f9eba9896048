"""notebooks/fit_real_jwst.ipynb fits the real JWST cutout top to bottom (skipped without the data).

Slow: three compiles of the three-band model (host, joint, Fisher); see the notebook's own timing.
"""

import json
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "fit_real_jwst.ipynb"
DATA = ROOT.parent / "shared" / "data" / "real"


def test_notebook_outputs_are_stripped():
    nb = json.loads(NOTEBOOK.read_text(encoding="utf-8"))
    assert all(not c.get("outputs") and not c.get("execution_count")
               for c in nb["cells"] if c["cell_type"] == "code")


@pytest.mark.slow
@pytest.mark.skipif(not (DATA / "abell_s1063_sys4_im1").is_dir(), reason="real data absent")
def test_fit_real_jwst_notebook_runs(monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setenv("CLUMPYLEN_REAL_DATA", str(DATA))
    try:
        import nbclient
        import nbformat
    except ImportError:
        nbclient = None
    if nbclient is not None:
        nb = nbformat.read(NOTEBOOK, as_version=4)
        nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                resources={"metadata": {"path": str(NOTEBOOK.parent)}}).execute()
        return
    import matplotlib
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    ns = {"__name__": "__fit_real_jwst__"}
    cells = [("".join(c["source"])) for c in json.loads(NOTEBOOK.read_text())["cells"]
             if c["cell_type"] == "code"]
    cwd = os.getcwd()
    try:
        os.chdir(NOTEBOOK.parent)
        for i, src in enumerate(cells):
            try:
                exec(compile(src, f"{NOTEBOOK.name}[cell {i}]", "exec"), ns)
            except Exception as exc:
                pytest.fail(f"cell {i} failed: {exc!r}")
    finally:
        os.chdir(cwd)
        plt.close("all")
    assert ns["fit"].n_clumps >= 3
