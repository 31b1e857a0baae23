"""Every evaluation of the diagnosis has a budget: an ill-posed candidate fails fast, with its
reason, and the others still answer."""

from __future__ import annotations

import copy
import time

import numpy as np
import pytest

from breastmodel.diagnosis import load_run, rank_candidates
from breastmodel.diagnosis.budget import Budget, BudgetExceeded, default_budget
from breastmodel.diagnosis.candidates import Candidate, candidate_by_name
from breastmodel.phantom.mounds import mound_problem
from breastmodel.pipeline.config import resolve_config
from breastmodel.pipeline.run import run_problem

NH = {"name": "neo_hookean", "nu": 0.49}
BASE = {"materials": {"breast_left": {**NH, "E": 1.0}, "breast_right": {**NH, "E": 1.0},
                      "muscle": {**NH, "E": 10.0}},
        "effects": {"fixed": {"node_set": "fixed"}}}
TIED_E = "materials.breast_left.E|materials.breast_right.E"
#: Seconds one evaluation may spend: several times what a model of the test's size takes on
#: a loaded machine, so that only the stand-in below spends it.
LIMIT_S = 10.0
#: Seconds the stand-in sleeps per residual evaluation: more than the limit, so that the
#: prone solve's first evaluation spends it. (At 2 s, six evaluations of a few Newton
#: iterations spent it, until a solve from a guess took the whole load from it: the stand-in
#: adds no force, so the fitted model's solution, its warm start, solves it at once.)
SLEEP_S = 11.0


def test_budget_counts_solves_and_seconds():
    b = Budget(2, 60.0)
    b.charge()
    b.charge()
    with pytest.raises(BudgetExceeded, match="2 forward solves spent.*before position x"):
        b.charge("position x")
    b = Budget(100, 0.05)
    b.charge()
    time.sleep(0.06)
    with pytest.raises(BudgetExceeded, match="s spent .limit 0.1 s"):
        b.charge()
    assert default_budget(5, 2.0) == (15, 20.0)
    assert default_budget(1, 30.0) == (5, 90.0)


def test_the_inverse_damping_loop_is_bounded(monkeypatch, tmp_path):
    """A model whose forward solves fail every other time (fail, damp, recover, fail...)
    gives up after ``max_total_failures`` failures, not after ``max_iter`` solves."""
    import mechanics.stress_free as sf
    from mechanics.solver import SolverError

    calls = []

    def flaky(model, X, u, options):
        calls.append(1)
        if len(calls) % 2 == 0:
            raise SolverError("mechanics: diverged (test)")
        return real(model, X, u, options)

    real = sf._forward
    monkeypatch.setattr(sf, "_forward", flaky)
    from breastmodel.pipeline.problem import load_problem, position_model

    prob = load_problem(mound_problem(tmp_path / "p", BASE, cells=(4, 3, 2, 1)))
    m = position_model(prob, resolve_config({"model": BASE})["model"], "supine")
    with pytest.raises(SolverError):
        sf.inverse_fixed_point(m, m.mesh.nodes, tol=1e-12, max_iter=50, max_total_failures=3)
    assert len(calls) == 8  # 4 good, 4 failed: the 4th failure is one too many
    # a caller's budget stops it before the solve it cannot afford
    calls.clear()
    budget = Budget(5, 60.0)
    with pytest.raises(BudgetExceeded, match="5 forward solves spent"):
        sf.inverse_fixed_point(m, m.mesh.nodes, tol=1e-12, max_iter=50,
                               before_solve=budget.charge)
    assert len(calls) == 5


@pytest.fixture()
def slow_effect():
    """A stand-in for an ill-posed candidate: an effect that adds no force but makes every
    residual evaluation slow (a solve that cuts back over and over costs the same way)."""
    from mechanics.effects import EFFECTS, Contribution, Effect, register_effect

    @register_effect
    class Slow(Effect):
        name = "test_slow"
        doc = "a deliberately slow stand-in"
        params = ()

        def contribute(self, X, x, load):
            time.sleep(SLEEP_S)
            return Contribution.zero(len(X))

    yield "test_slow"
    del EFFECTS["test_slow"]


def test_an_ill_posed_candidate_fails_fast_and_the_others_still_answer(tmp_path, slow_effect):
    prob = mound_problem(tmp_path / "problem", {**BASE, "effects": {**BASE["effects"],
                                                                    "skin": {"E": 4.0}}})
    cfg = resolve_config({
        "model": copy.deepcopy(BASE), "stress_free": {"method": "none"},
        "fit": {"enabled": True, "budget": 20, "sensitivity": False, "method": "least_squares",
                "calibrate": ["prone", "supine"],
                "parameters": {TIED_E: {"min": 0.2, "max": 5.0}}}})
    run_problem(prob, cfg, tmp_path / "run", progress=False)
    run = load_run(tmp_path / "run")
    slow = Candidate(slow_effect, "effect", "slow", {slow_effect: {}})
    t0 = time.perf_counter()
    d = rank_candidates(run, candidates=[slow, candidate_by_name(run.model, "skin")],
                        progress=False, verify_top=0, max_seconds=LIMIT_S,
                        work_dir=tmp_path / "ev")
    wall = time.perf_counter() - t0
    failed = {f["name"]: f for f in d["failed"]}
    assert set(failed) == {slow_effect}
    assert "BudgetExceeded" in failed[slow_effect]["error"]
    assert "s spent (limit 10.0 s)" in failed[slow_effect]["error"]
    # the solver got the deadline: it stopped inside the prone solve, within one Newton
    # iteration (one or two evaluations) of it
    assert "in position prone" in failed[slow_effect]["error"]
    assert failed[slow_effect]["seconds"] < LIMIT_S + 2 * SLEEP_S
    assert [r["name"] for r in d["ranking"]] == ["skin"] and d["ranking"][0]["significant"]
    assert d["budget"]["max_seconds"] == LIMIT_S
    assert d["evaluations"][f"cand|{slow_effect}"]["status"] == "failed"
    # the whole diagnosis is bounded by the budgets, not by the slow candidate's own pace
    assert wall < 120.0
    assert np.isfinite(d["ranking"][0]["predicted_rms_mm"])
    # a rerun reuses the stored evaluations (the fitted model's solution included) and
    # retries only the failed one, which fails again within its budget
    again = rank_candidates(run, candidates=[slow, candidate_by_name(run.model, "skin")],
                            progress=False, verify_top=0, max_seconds=LIMIT_S,
                            work_dir=tmp_path / "ev")
    assert again["ranking"][0]["predicted_rms_mm"] == d["ranking"][0]["predicted_rms_mm"]
    assert again["budget"] == d["budget"]
    assert [f["name"] for f in again["failed"]] == [slow_effect]
