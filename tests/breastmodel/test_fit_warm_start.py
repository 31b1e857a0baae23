"""The fit's warm starts and held-out positions (breastmodel.pipeline.fit_evaluations).

The FE objective is replaced by an analytic one that also returns a "stress-free geometry"
(an array made from the parameters) and records the start each evaluation was given, so the
tests check which earlier evaluation each one starts from, that a resumed fit gives every
evaluation the start the uninterrupted fit gave it, that a failed warm start is retried from
the reference geometry, and that the held-out positions are solved once, at the optimum.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from breastmodel.pipeline import fit as fitmod
from breastmodel.pipeline import problem as problem_mod
from breastmodel.sweep import point_key

E_OPT = 0.93
NAME = "materials.breast_left.E"
PARAMS = {NAME: {"min": 0.1, "max": 4.0}}


def _geometry(e: float) -> np.ndarray:
    return np.full((4, 3), e)


def _objective(calls, fail_warm_below=None):
    def evaluate(params, problem_dir, settings, residuals=False, start=None, keep_X=False):
        e = params[NAME]
        calls.append({"e": e, "start": None if start is None else float(start[0, 0]),
                      "positions": list(settings["calibrate"]) + list(settings.get("evaluate")
                                                                      or [])})
        if fail_warm_below is not None and start is not None and e < fail_warm_below:
            return {"objective": math.nan, "mhd_mm": {}, "forward_solves": 1,
                    "error": "SolverError: diverged from the warm start"}
        r = np.array([math.log(e / E_OPT), 0.5 * math.log(e / E_OPT)])
        mhd = {p: float(np.abs(r).mean()) + 0.1 * k
               for k, p in enumerate(calls[-1]["positions"])}
        out = {"objective": float(np.mean([mhd[p] for p in settings["calibrate"]])),
               "mhd_mm": mhd, "forward_solves": 3, "error": None}
        if residuals:
            out["residual"] = {p: r.tolist() for p in settings["calibrate"]}
        if keep_X:
            out["X"] = _geometry(e)
        return out
    return evaluate


def test_each_evaluation_starts_from_the_nearest_earlier_one_and_resumes_alike(
        monkeypatch, tmp_path):
    calls: list = []
    monkeypatch.setattr(problem_mod, "evaluate_params", _objective(calls))
    settings = {"calibrate": ["prone", "supine"]}
    res = fitmod.least_squares(tmp_path, settings, PARAMS, budget=30, work_dir=tmp_path / "w",
                               x0={NAME: 2.5})
    assert res["best"]["params"][NAME] == pytest.approx(E_OPT, rel=2e-3)
    assert calls[0]["start"] is None  # the first one from the reference geometry
    for k, c in enumerate(calls[1:], 1):  # later ones from the nearest earlier one (log p)
        nearest = min((d["e"] for d in calls[:k]), key=lambda e: abs(math.log(c["e"] / e)))
        assert c["start"] == pytest.approx(nearest)
    assert any(c["start"] != calls[0]["e"] for c in calls[2:])  # not always the first one

    # killed after 4 evaluations, then resumed: the same starts as without the interruption
    folder = tmp_path / "w" / "least_squares"
    for c in calls[4:]:
        key = point_key({NAME: float(f"{c['e']:.6g}")})
        (folder / f"{key}.json").unlink()
        (folder / f"{key}.X.npy").unlink()
    again: list = []
    monkeypatch.setattr(problem_mod, "evaluate_params", _objective(again))
    res2 = fitmod.least_squares(tmp_path, settings, PARAMS, budget=30,
                                work_dir=tmp_path / "w", x0={NAME: 2.5})
    first = {c["e"]: c["start"] for c in calls}
    assert 0 < len(again) < len(calls)
    assert all(first[c["e"]] == c["start"] for c in again)
    assert res2["best"] == res["best"]


def test_a_failed_warm_start_is_retried_from_the_reference_geometry(monkeypatch, tmp_path):
    calls: list = []
    monkeypatch.setattr(problem_mod, "evaluate_params", _objective(calls, fail_warm_below=1.5))
    res = fitmod.least_squares(tmp_path, {"calibrate": ["prone"]}, PARAMS, budget=30,
                               work_dir=tmp_path / "w", x0={NAME: 2.5})
    assert res["n_failed"] == 0  # every failed warm start succeeded from the reference
    retried = [c for c in calls if c["start"] is None and c["e"] < 1.5]
    assert retried and all(any(d["e"] == c["e"] and d["start"] is not None for d in calls)
                           for c in retried)
    assert res["best"]["params"][NAME] == pytest.approx(E_OPT, rel=2e-3)


def test_held_out_positions_are_solved_once_at_the_optimum(monkeypatch, tmp_path):
    calls: list = []
    monkeypatch.setattr(problem_mod, "evaluate_params", _objective(calls))
    settings = {"calibrate": ["prone", "supine"], "evaluate": ["supine_tilted"]}
    res = fitmod.optimise(tmp_path, settings, PARAMS, budget=40, work_dir=tmp_path / "w",
                          x0={NAME: 2.5})
    with_held = [c for c in calls if "supine_tilted" in c["positions"]]
    assert len(with_held) == 1 and with_held[0] is calls[-1]
    best = res["best"]["params"][NAME]
    assert with_held[0]["e"] == best and with_held[0]["start"] == best  # its own geometry
    assert with_held[0]["positions"] == ["supine_tilted"]
    assert set(res["best"]["mhd_mm"]) == {"prone", "supine", "supine_tilted"}
    assert res["n_simulations"] == len(calls)


def test_sensitivity_at_a_bound_reuses_the_optimum(monkeypatch, tmp_path):
    calls: list = []
    monkeypatch.setattr(problem_mod, "evaluate_params", _objective(calls))
    sens = fitmod.sensitivity(tmp_path, {"calibrate": ["prone"]}, {NAME: 4.0}, PARAMS,
                              work_dir=tmp_path / "w", objective=1.5)
    assert [c["e"] for c in calls] == [pytest.approx(3.6)]  # the low side only
    s = sens[NAME]
    assert s["objective"] == s["objective_high"] == 1.5 and s["high"] == 4.0


def test_each_forward_solve_starts_from_the_nearest_evaluations_displacement(
        monkeypatch, tmp_path):
    """An evaluation that returns its displacements (``u``) gives them to the next one that
    starts from it, position by position, and a resumed fit reads them back from disk."""
    calls: list = []
    plain = _objective(calls)

    def evaluate(params, problem_dir, settings, residuals=False, start=None, keep_X=False,
                 u_start=None):
        out = plain(params, problem_dir, settings, residuals=residuals, start=start,
                    keep_X=keep_X)
        calls[-1]["u_start"] = None if u_start is None else {
            p: float(v[0, 0]) for p, v in u_start.items()}
        if keep_X:
            out["u"] = {p: np.full((4, 3), 10 * params[NAME] + k)
                        for k, p in enumerate(calls[-1]["positions"])}
        return out

    monkeypatch.setattr(problem_mod, "evaluate_params", evaluate)
    settings = {"calibrate": ["prone", "supine"]}
    fitmod.least_squares(tmp_path, settings, PARAMS, budget=30, work_dir=tmp_path / "w",
                         x0={NAME: 2.5})
    assert calls[0]["u_start"] is None
    for c in calls[1:]:
        assert c["u_start"] == pytest.approx({"prone": 10 * c["start"],
                                              "supine": 10 * c["start"] + 1})
    folder = tmp_path / "w" / "least_squares"
    for c in calls[3:]:
        key = point_key({NAME: float(f"{c['e']:.6g}")})
        for suffix in (".json", ".X.npy", ".u.npz"):
            (folder / f"{key}{suffix}").unlink()
    first = {c["e"]: c["u_start"] for c in calls}
    calls.clear()
    fitmod.least_squares(tmp_path, settings, PARAMS, budget=30, work_dir=tmp_path / "w",
                         x0={NAME: 2.5})
    assert calls and all(first[c["e"]] == c["u_start"] for c in calls)
