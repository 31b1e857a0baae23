"""Slow checks of fitting and sweeps with the finite-element objective (run with -m slow).

The measurements are synthetic (:mod:`breastmodel.pipeline.synthetic`): a truth model's
predicted skins on a small phantom's prepared problem, so the truth modulus is known.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from breastmodel.pipeline import fit as fitmod
from breastmodel.pipeline import prepare_subject, resolve_config, run_subject
from breastmodel.pipeline.config import set_params
from breastmodel.pipeline.synthetic import synthetic_problem

pytestmark = pytest.mark.slow

TIED = "materials.breast_left.E|materials.breast_right.E"
E_TRUE = 0.6  # kPa


def _raw(truth: Path) -> dict:
    return {
        "segment": {"labels": str(truth)},
        "register": {"shrink": [2, 1], "smooth_mm": [2.0, 0.0], "iterations": 30},
        "mesh": {"size_mm": 12.0},
        "surface": {"edge_mm": 4.0},
        "stress_free": {"tol_mm": 0.1, "max_iter": 15},
    }


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    from breastmodel.phantom import make_phantom

    root = tmp_path_factory.mktemp("slow")
    subj = make_phantom(root / "subject", seed=5, small=True, voxel_size=2.0, progress=False)
    cfg = resolve_config(_raw(Path(str(subj) + "_truth")))
    prep = prepare_subject(subj, cfg, root / "run", progress=False)
    synth = synthetic_problem(prep.problem_dir, root / "synthetic",
                              set_params(cfg["model"], {TIED: E_TRUE}), cfg["stress_free"],
                              cfg["solver"])
    settings = {"model": cfg["model"], "solver": cfg["solver"],
                "stress_free": cfg["stress_free"], "calibrate": ["prone", "supine"],
                "evaluate": ["supine_tilted"]}
    return subj, cfg, synth, settings, root


def test_optimizer_recovers_the_breast_modulus(prepared):
    _, _, synth, settings, root = prepared
    res = fitmod.optimise(synth, settings, {TIED: {"min": 0.1, "max": 4.0}}, budget=40,
                          work_dir=root / "opt")
    best = res["best"]
    # acceptance targets of the issue: modulus within 10 %, MHD <= 1.0 mm on the calibration
    # positions and <= 1.5 mm on the held-out one
    assert abs(best["params"][TIED] / E_TRUE - 1) < 0.10
    assert best["mhd_mm"]["prone"] <= 1.0 and best["mhd_mm"]["supine"] <= 1.0
    assert best["mhd_mm"]["supine_tilted"] <= 1.5
    assert res["n_simulations"] <= 40


def test_grid_on_two_dask_workers_stores_and_resumes(prepared):
    _, _, synth, settings, root = prepared
    params = {TIED: {"values": [0.1, 0.6, 1.2]}}
    first = fitmod.grid_search(synth, settings, params, work_dir=root / "grid", n_workers=2,
                               progress=False)
    assert first["n_simulations"] == 3
    by_e = {h["params"][TIED]: h["objective"] for h in first["history"]}
    assert by_e[0.6] is not None and all(v is None or v >= by_e[0.6] for v in by_e.values())
    again = fitmod.grid_search(synth, settings, params, work_dir=root / "grid", n_workers=2,
                               progress=False)
    assert json.loads((root / "grid" / "grid" / "sweep.json").read_text())[
        "n_computed_now"] == 0
    assert again["best"] == first["best"]


def test_run_with_fit_writes_fitted_params_and_history(prepared):
    subj, _, _, _, root = prepared
    raw = _raw(Path(str(subj) + "_truth"))
    raw["fit"] = {"enabled": True, "budget": 6, "sensitivity": False,
                  "parameters": {TIED: {"min": 0.3, "max": 3.0}}}
    res = run_subject(subj, resolve_config(raw), root / "run", progress=False)
    params = json.loads((root / "run" / "params.json").read_text())
    assert params["fitted"] and params["fit"]["n_simulations"] <= 6
    assert 0.3 <= params["parameters"][TIED] <= 3.0
    assert math.isfinite(res["metrics"]["positions"]["prone"]["mhd_mm"])
    html = (root / "run" / "report.html").read_text()
    assert "Fit (optimizer)" in html and "simulations" in html


def test_paper_stress_free_method_runs_end_to_end(prepared):
    subj, _, _, _, root = prepared
    raw = _raw(Path(str(subj) + "_truth"))
    raw["stress_free"] = {"method": "paper", "position": "prone", "max_iter": 6}
    res = run_subject(subj, resolve_config(raw), root / "run", progress=False)
    sf = json.loads((root / "run" / "metrics.json").read_text())["stress_free"]
    assert sf["method"] == "paper_fixed_point" and sf["position"] == "prone"
    assert 1 <= sf["forward_solves"] <= 6
    for m in res["metrics"]["positions"].values():
        assert math.isfinite(m["mhd_mm"])
