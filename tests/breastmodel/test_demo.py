"""``breastmodel demo``: the shipped phantom and the story (fit, diagnose, refit, compare)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from breastmodel.phantom.demo_data import DEMO_DATA, HIDDEN_EFFECT, demo_spec


def test_demo_data_is_shipped_small_and_matches_its_recipe():
    files = [p for p in DEMO_DATA.rglob("*") if p.is_file()]
    total = sum(p.stat().st_size for p in files)
    assert total <= 5 * 2**20, f"demo data is {total / 2**20:.1f} MB"
    meta = json.loads((DEMO_DATA / "demo.json").read_text())
    assert meta["hidden_effect"] == HIDDEN_EFFECT
    assert meta["truth_solver"] == "febio"
    # the shipped subject is the one `breastmodel demo --regenerate-data` makes
    shipped = json.loads((DEMO_DATA / "subject_truth" / "spec.json").read_text())
    assert shipped == demo_spec().to_dict() == meta["spec"]
    truth = json.loads((DEMO_DATA / "subject_truth" / "truth_model.json").read_text())
    assert all(s["solver"] == "febio" and s["converged"] for s in truth["solves"].values())
    E = {k: m["E"] for k, m in truth["materials"].items()}
    assert E["1"] != pytest.approx(E["3"], rel=0.1)  # the hidden effect: left != right
    for pos in meta["spec"]["positions"]:
        assert (DEMO_DATA / "subject" / f"{pos}.nii.gz").is_file()
        assert (DEMO_DATA / "subject_truth" / f"{pos}_labels.nii.gz").is_file()
        u = np.load(DEMO_DATA / "subject_truth" / f"{pos}_displacement.npy")
        assert np.linalg.norm(u, axis=1).max() > 3.0  # gravity moves the skin by mm


@pytest.mark.slow  # the whole story: two fits, the diagnosis' ~20 model evaluations (minutes)
def test_demo_story_names_the_hidden_effect_and_the_error_falls(tmp_path):
    from breastmodel.commands.demo import run_story
    from breastmodel.diagnosis import load_run

    res = run_story(DEMO_DATA, tmp_path, mesh_size_mm=10.0, progress=False)
    assert res["named"] == HIDDEN_EFFECT, res["verdict"]
    assert res["rank"] == 1
    before = np.array([b for b, _ in res["mhd_mm"].values()])
    after = np.array([a for _, a in res["mhd_mm"].values()])
    assert after.mean() < 0.8 * before.mean(), res["mhd_mm"]
    assert after.max() < before.max(), res["mhd_mm"]
    # no inverse crime: the fitted mesh is not the truth's
    truth = np.load(DEMO_DATA / "subject_truth" / "stress_free_mesh.npz")
    fitted = load_run(tmp_path / "run0").problem.mesh
    assert fitted.n_nodes != len(truth["nodes"])
    page = (tmp_path / "index.html").read_text()
    for link in ("run0/report.html", "run0/diagnosis.html", "compare/compare.html",
                 "run1/report.html"):
        assert link in page and (tmp_path / link).is_file()
