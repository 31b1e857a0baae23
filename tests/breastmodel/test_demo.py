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


@pytest.mark.slow  # the story: two fits, the diagnosis' ~20 evaluations, its mesh probe (minutes)
def test_demo_story_names_the_hidden_effect_and_the_error_falls(tmp_path):
    from breastmodel.demo import run_story
    from breastmodel.diagnosis import load_run

    res = run_story(DEMO_DATA, tmp_path, mesh_size_mm=8.0, progress=False)
    assert res["named"] == HIDDEN_EFFECT, res["verdict"]
    assert res["rank"] == 1
    # 8 mm is twice this subject's "auto" edge: the mesh probe (4 mm) moves the fitted modulus
    # by +43 %, and the verdict says so beside the answer (at 10 mm, +65 %, the mesh came
    # first: Delta BIC -12.1 against the asymmetry's -11.3)
    assert "the mesh looks too coarse: on a mesh of 4 mm edges" in res["verdict"]
    # the MHD falls on every position the effect acts on; the reference position is
    # reproduced by the stress-free inverse in both runs (at the voxels' noise floor)
    reference = json.loads((tmp_path / "run0" / "metrics.json").read_text())["reference"]
    moved = {p: ba for p, ba in res["mhd_mm"].items() if p != reference}
    assert len(moved) == 2
    for p, (before, after) in moved.items():
        assert after < before, (p, res["mhd_mm"])
    before, after = np.array(list(res["mhd_mm"].values())).T
    assert after.mean() < before.mean()
    # no inverse crime: the fitted mesh is not the truth's
    truth = np.load(DEMO_DATA / "subject_truth" / "stress_free_mesh.npz")
    fitted = load_run(tmp_path / "run0").problem.mesh
    assert fitted.n_nodes != len(truth["nodes"])
    page = (tmp_path / "index.html").read_text()
    for link in ("run0/report.html", "run0/diagnosis.html", "compare/compare.html",
                 "run1/report.html"):
        assert link in page and (tmp_path / link).is_file()


def test_regenerate_data_replaces_the_subject_and_writes_the_recipe(tmp_path, monkeypatch):
    """The plumbing of ``breastmodel demo --regenerate-data`` (FEBio itself takes minutes:
    the subject writer is replaced by one that records its arguments)."""
    import breastmodel.phantom.family as family
    from breastmodel.phantom.demo_data import make_demo_data

    calls = []

    def fake_make_subject(spec, out, **kw):
        calls.append((spec, kw))
        for d in (out, out.with_name(out.name + "_truth")):
            d.mkdir(parents=True)
            (d / "new.txt").write_text("new")
        (out.with_name(out.name + "_truth") / "timings.json").write_text("{}")
        return out

    monkeypatch.setattr(family, "make_subject", fake_make_subject)
    (tmp_path / "subject").mkdir()
    (tmp_path / "subject" / "old.txt").write_text("old")
    make_demo_data(tmp_path, febio="/x/febio4", progress=False)
    (spec, kw), = calls
    assert spec == demo_spec() and kw["truth_solver"] == "febio" and kw["febio"] == "/x/febio4"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo.json", "subject",
                                                          "subject_truth"]
    assert [p.name for p in (tmp_path / "subject").iterdir()] == ["new.txt"]
    assert [p.name for p in (tmp_path / "subject_truth").iterdir()] == ["new.txt"]
    meta = json.loads((tmp_path / "demo.json").read_text())
    assert meta["hidden_effect"] == HIDDEN_EFFECT and meta["spec"] == demo_spec().to_dict()
