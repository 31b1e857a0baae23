"""The diagnosis' model evaluations: one model's residuals, the fitted model's stored
evaluation, the sweep point of a variant, and the small helpers that name and step them.

:func:`evaluate_model` solves the stress-free geometry and every position of one model
under a :class:`~breastmodel.diagnosis.budget.Budget`; :func:`variant_point` is the
:func:`breastmodel.sweep.run_sweep` function of the variants (each warm-started from the
fitted model's solution, which :func:`base_evaluation` stores in the work folder).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.config import write_atomic_with
from breastmodel.diagnosis.budget import Budget

__all__ = ["evaluate_model"]

#: Log step of the finite differences (about 22 %).
STEP = 0.2


def evaluate_model(model: Mapping[str, Any], problem_dir: str | Path,
                   settings: Mapping[str, Any], *, budget: Budget | None = None,
                   start: Mapping[str, Any] | None = None, keep_state: bool = False) -> dict:
    """Residuals of one model: stress-free geometry, then every position.

    Parameters
    ----------
    model : a resolved ``[model]`` table
    problem_dir : the run's problem folder
    settings : ``{"solver", "stress_free", "positions"}``
    budget : charged before every forward solve (default: unlimited)
    start : ``{"X": (N, 3), "u": {position: (N, 3)}}`` a nearby model's solution, mm: the
        stress-free inverse and every position start from it (on a split interface the breast
        copies of the interface nodes start where their originals are)
    keep_state : also return ``X`` and ``u`` per position (a later warm start)

    Returns
    -------
    dict
        ``residual`` {position: (n_skin,) signed error, mm, canonical skin-node order},
        ``mhd_mm`` {position: mm}, ``solves`` (forward solves), ``wall_s``; raises on a
        failed solve or a spent budget (the sweep records it).
    """
    import time

    from breastmodel.evaluation import point_to_surface
    from breastmodel.pipeline.problem import (
        load_problem,
        model_mesh,
        on_mesh,
        predict_position,
        score_position,
        skin_nodes,
        stress_free_geometry,
    )

    t0 = time.perf_counter()
    budget = budget or Budget(10**9, math.inf)
    problem = load_problem(problem_dir)
    start = start or {}
    if "X" in start:  # a split interface added or removed: the start moves with it
        n = model_mesh(problem, model).n_nodes
        moved = {"X": on_mesh(problem, start["X"], n),
                 "u": {k: on_mesh(problem, v, n) for k, v in start.get("u", {}).items()}}
        start = moved if moved["X"] is not None else {}
    u_start = start.get("u", {})
    sf_start = (np.asarray(start["X"]), u_start.get(problem.reference)) if "X" in start \
        else None
    solver = dict(settings["solver"])
    if math.isfinite(budget.max_seconds):  # a solve stops inside too, not only between solves
        solver["deadline"] = budget.deadline
    solved: dict = {}  # the reference position, solved by the inverse's last iteration
    with budget.solving("the stress-free inverse"):
        X, _ = stress_free_geometry(
            problem, model, settings["stress_free"], solver, start=sf_start, solved=solved,
            before_solve=lambda: budget.charge("a stress-free iteration"))
    out: dict[str, Any] = {"residual": {}, "mhd_mm": {}}
    us = {}
    for pos in settings["positions"]:
        if pos in solved:
            x = solved[pos].x
        else:
            budget.charge(f"position {pos}")
            u0 = u_start.get(pos)
            with budget.solving(f"position {pos}"):
                x = predict_position(problem, model, X, pos, solver,
                                     u0=None if u0 is None else np.asarray(u0)).x
        us[pos] = x - X
        d, _ = point_to_surface(x[skin_nodes(problem, len(x))], *problem.skins[pos],
                                signed=True)
        out["residual"][pos] = d
        out["mhd_mm"][pos] = score_position(problem, x, pos)["mhd_mm"]
    out["solves"] = budget.solves
    out["wall_s"] = time.perf_counter() - t0
    if keep_state:
        out["X"], out["u"] = X, us
    return out


def variant_point(point: Mapping[str, Any], *, variants: Mapping[str, dict],
                  problem_dir: str, settings: Mapping[str, Any],
                  limits: tuple[int, float] | None = None,
                  start: Mapping[str, Any] | None = None) -> dict:
    """Evaluate the variant named by ``point["variant"]`` within ``limits`` (forward solves,
    seconds), from ``start``; its record for the sweep (residuals as lists)."""
    budget = Budget(*limits) if limits else None
    res = evaluate_model(variants[point["variant"]], problem_dir, settings, budget=budget,
                         start=start)
    return {"residual": {p: np.asarray(v).tolist() for p, v in res["residual"].items()},
            "mhd_mm": res["mhd_mm"], "solves": res["solves"], "eval_s": res["wall_s"]}


def base_evaluation(model: Mapping[str, Any], problem_dir: str | Path,
                    settings: Mapping[str, Any], work_dir: Path) -> tuple[dict, dict]:
    """The fitted model's evaluation (stored in ``work_dir``, reused by a rerun): its record
    in the sweep's format and its solution (the variants' warm start)."""
    import json

    path = work_dir / f"base-{model_hash({'model': model, **settings})}.npz"
    if path.is_file():
        with np.load(path) as z:
            meta = json.loads(str(z["meta"]))
            state = {"X": z["X"], "u": {p: z[f"u_{p}"] for p in meta["positions"]}}
            meta["result"]["residual"] = {p: z[f"r_{p}"] for p in meta["positions"]}
        return meta, state
    try:
        res = evaluate_model(model, problem_dir, settings, keep_state=True)
    except Exception as exc:  # noqa: BLE001 - reported as the diagnosis' own error below
        return {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}, {}
    pos = list(res["residual"])
    rec = {"status": "ok", "error": None, "positions": pos,
           "result": {"mhd_mm": res["mhd_mm"], "solves": res["solves"],
                      "eval_s": res["wall_s"]}}
    work_dir.mkdir(parents=True, exist_ok=True)
    arrays = {"X": res["X"], **{f"u_{p}": res["u"][p] for p in pos},
              **{f"r_{p}": res["residual"][p] for p in pos}}
    write_atomic_with(path, lambda tmp: np.savez(tmp, meta=json.dumps(rec), **arrays),
                      suffix=".npz")
    rec["result"]["residual"] = res["residual"]
    return rec, {"X": res["X"], "u": res["u"]}


def log_step(value: float, lo: float, hi: float) -> float:
    """+STEP unless that leaves [lo, hi], then -STEP."""
    return STEP if value * math.exp(STEP) <= hi * (1 + 1e-12) else -STEP


def model_hash(model: Mapping[str, Any]) -> str:
    """12 hex digits naming ``model`` (hash of its canonical JSON)."""
    import hashlib

    from breastmodel.cache import canonical_json

    return hashlib.sha256(canonical_json(model).encode()).hexdigest()[:12]


def fit_bounds(cfg: Mapping[str, Any], path: str) -> tuple[float, float]:
    """(min, max) of the fitted parameter ``path`` in the run's ``[fit]`` table."""
    spec = cfg["fit"]["parameters"][path]
    vals = spec.get("values")
    return (float(min(vals)), float(max(vals))) if vals else (float(spec["min"]),
                                                             float(spec["max"]))
