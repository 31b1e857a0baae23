"""The missing-effect notebook runs the whole loop headless: fit, diagnose, add, compare."""

import json

import nbformat
from nbclient import NotebookClient

NOTEBOOK = "notebooks/missing_effect.ipynb"


def test_committed_notebook_has_no_outputs():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None


def test_notebook_finds_the_hidden_effect_and_the_error_falls(tmp_path, monkeypatch):
    monkeypatch.setenv("BREASTMODEL_NB_OUT", str(tmp_path))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3",
                   resources={"metadata": {"path": "."}}).execute()
    text = "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                     for o in c.outputs)
    assert "missing effect: skin" in text
    assert sum(1 for c in nb.cells if c.cell_type == "code" for o in c.outputs
               if "image/png" in o.get("data", {})) >= 2
    cmp = json.loads((tmp_path / "compare" / "compare.json").read_text())
    worst = [max(t["mhd_mm"]["values"][i] for t in cmp["positions"].values()) for i in (0, 1)]
    assert worst[1] <= 0.5 * worst[0]
