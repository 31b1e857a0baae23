"""The missing-effect notebook runs the whole loop headless: fit, diagnose, add, compare."""

import json

from nbrun import assert_stripped, execute

NOTEBOOK = "notebooks/missing_effect.ipynb"


def test_committed_notebook_has_no_outputs():
    assert_stripped(NOTEBOOK)


def test_notebook_finds_the_hidden_effect_and_the_error_falls(tmp_path, monkeypatch):
    text, n_images = execute(NOTEBOOK, tmp_path, monkeypatch)
    assert "missing effect: skin" in text
    assert n_images >= 2
    cmp = json.loads((tmp_path / "compare" / "compare.json").read_text())
    worst = [max(t["mhd_mm"]["values"][i] for t in cmp["positions"].values()) for i in (0, 1)]
    assert worst[1] <= 0.5 * worst[0]
