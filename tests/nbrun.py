"""Run a project notebook headless, as its users would, and read back what it printed."""

from __future__ import annotations

import nbformat
from nbclient import NotebookClient


def assert_stripped(path: str) -> None:
    """The committed notebook carries no outputs or execution counts."""
    for cell in nbformat.read(path, as_version=4).cells:
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None


def execute(path: str, out_dir, monkeypatch, *, timeout: int = 600):
    """Execute the notebook with its outputs going to ``out_dir`` (``BREASTMODEL_NB_OUT``).

    Returns
    -------
    text : str, everything the code cells printed
    n_images : int, PNG outputs shown
    """
    monkeypatch.setenv("BREASTMODEL_NB_OUT", str(out_dir))
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=timeout, kernel_name="python3",
                   resources={"metadata": {"path": "."}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    text = "\n".join(o.get("text", "") for o in outputs)
    return text, sum("image/png" in o.get("data", {}) for o in outputs)
