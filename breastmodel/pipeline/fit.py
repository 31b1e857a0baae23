"""Fitting material parameters: the paper's grid (a dask sweep), a bounded optimiser of the
MHD, or bounded least squares on the skin residual.

The objective of a parameter vector is :func:`breastmodel.pipeline.problem.evaluate_params`
(mean MHD over the calibration positions, mm). Failed solves give NaN: the grid records them
as NaN points (the paper lost many at low moduli), the optimiser sees them as a penalty.

The optimiser is Nelder-Mead in the unit cube of log-parameters (bounds by clipping), started
from the geometric centre of the bounds with a simplex spanning a quarter of each range. Every
evaluation is stored atomically in ``work_dir/optimizer/<point key>.json``; the search is
deterministic, so a killed fit replays its stored evaluations and resumes where it stopped.

The searches (optimiser, least squares, sensitivity) evaluate the calibration positions only,
each evaluation's stress-free inverse warm-started from the nearest earlier evaluation
(:class:`~breastmodel.pipeline.fit_evaluations.Evaluator`) and converged to ``[fit]
stress_free_tol_mm`` (0.005 mm; the run's own ``[stress_free] tol_mm`` is 0.05), then the
held-out positions once at the optimum. Measured (2026-11-26, ``bench/run_time.py``'s adult
phantom, 25.6k tets, and the demo's bulk fit): the inverse's tolerance biases the fitted
modulus (demo: 0.284 kPa at 0.05 mm from cold starts; 0.273 / 0.2725 kPa at 0.005 mm cold /
warm), and the warm starts pay for the tighter tolerance (adult, the search alone: 109 -> 91
forward solves, about 144 -> 108 s; demo 52 -> 48 solves). The grid's points stay
independent and cold.
"""

from __future__ import annotations

import functools
import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.pipeline.fit_evaluations import Evaluator as _Evaluator
from breastmodel.pipeline.fit_jacobian import PENALTY_MM, Jacobian, line_start
from breastmodel.pipeline.fit_statistics import (
    identifiability,
    lsq_uncertainty,
    offset_sensitivity,
)

log = logging.getLogger("breastmodel.pipeline")

__all__ = ["fit_parameters", "fit_work_dir", "grid_points", "least_squares",
           "lsq_uncertainty", "identifiability", "optimise", "sensitivity"]

def fit_work_dir(root: str | Path, problem_dir: str | Path,
                 settings: Mapping[str, Any]) -> Path:
    """``root/<hash>``: the folder of stored evaluations for one (problem, settings) pair.

    Stored evaluations are keyed by their parameter values only, so evaluations made with
    another model, solver or problem must live elsewhere.
    """
    import hashlib

    from breastmodel.cache import canonical_json

    h = hashlib.sha256((Path(problem_dir).resolve().name + "\0"
                        + canonical_json(dict(settings))).encode()).hexdigest()
    return Path(root) / h[:16]


def _bounds(spec: Mapping[str, Any]) -> tuple[float, float]:
    if "values" in spec:
        v = [float(x) for x in spec["values"]]
        return min(v), max(v)
    return float(spec["min"]), float(spec["max"])


def grid_points(parameters: Mapping[str, Mapping[str, Any]]) -> list[dict[str, float]]:
    """Cartesian grid of ``[fit.parameters]`` (``{min, max, step}`` or ``{values}`` each).

    A parameter without ``step`` or ``values`` takes 5 log-spaced values between its bounds.
    """
    from breastmodel.sweep import axis, grid

    axes = {}
    for path, spec in parameters.items():
        if "values" in spec:
            axes[path] = [float(v) for v in spec["values"]]
        elif "step" in spec:
            axes[path] = axis(float(spec["min"]), float(spec["max"]), float(spec["step"]))
        else:
            lo, hi = _bounds(spec)
            axes[path] = [float(f"{v:.6g}") for v in np.geomspace(lo, hi, 5)]
    return grid(**axes)


def optimise(problem_dir: Path, settings: Mapping[str, Any],
             parameters: Mapping[str, Mapping[str, Any]], *, budget: int = 100,
             work_dir: Path, progress: bool = False, x0: Mapping[str, float] | None = None,
             warm: list | bool = True) -> dict:
    """Bounded Nelder-Mead in log-parameter space; at most ``budget`` objective evaluations.
    ``warm``: warm-start each evaluation from the nearest earlier one (see ``_Evaluator``;
    a list shares the earlier evaluations with another search of the same fit).

    Returns
    -------
    dict
        ``best`` {params, objective, mhd_mm}, ``history`` (every evaluation in order),
        ``n_simulations`` (objective evaluations), ``forward_solves``.
    """
    from scipy.optimize import minimize

    names = list(parameters)
    lo = np.log([_bounds(parameters[n])[0] for n in names])
    hi = np.log([_bounds(parameters[n])[1] for n in names])
    warm = _starts(warm)
    ev = _Evaluator(Path(problem_dir), _search(settings), Path(work_dir) / "optimizer",
                    progress, warm=warm)

    def params_of(z):
        z = np.clip(z, 0.0, 1.0)
        return dict(zip(names, np.exp(lo + z * (hi - lo)).tolist()))

    def f(z):
        if len(ev.history) >= budget:
            raise _BudgetSpent
        obj = ev(params_of(z))["objective"]
        return obj if obj is not None and math.isfinite(obj) else PENALTY_MM

    if x0:
        z0 = np.clip((np.log([x0[n] for n in names]) - lo) / np.maximum(hi - lo, 1e-300), 0, 1)
    else:
        z0 = np.full(len(names), 0.5)
    d = len(names)
    simplex = np.vstack([z0] + [z0 + 0.25 * np.eye(d)[i] * (1 if z0[i] <= 0.75 else -1)
                                for i in range(d)])
    try:
        minimize(f, z0, method="Nelder-Mead",
                 options={"initial_simplex": simplex, "xatol": 2e-3, "fatol": 1e-3,
                          "maxfev": budget, "adaptive": d > 2})
    except _BudgetSpent:
        pass
    return _held_out(_summary(ev.history, "optimizer"), problem_dir, settings, work_dir, warm)


class _StartFailed(Exception):
    """The least squares' first evaluation failed (its residual's length is unknown)."""


class _BudgetSpent(Exception):
    pass


def _starts(warm: list | bool) -> list | None:
    """The warm-start list of an evaluator: shared (a list), new (True) or none (False)."""
    return warm if isinstance(warm, list) else ([] if warm else None)


def _search(settings: Mapping[str, Any]) -> dict:
    """The settings a search evaluates: the calibration positions only (the held-out ones
    are solved once, at the optimum: :func:`_held_out`), and the stress-free inverse to
    ``settings["search_tol_mm"]`` where that is tighter than its own tolerance."""
    out = {**settings, "evaluate": []}
    tol = settings.get("search_tol_mm")
    if tol is not None and "stress_free" in settings:
        sf = settings["stress_free"]
        out["stress_free"] = {**sf, "tol_mm": min(float(sf["tol_mm"]), float(tol))}
    return out


def _held_out(res: dict, problem_dir, settings: Mapping[str, Any], work_dir,
              warm: list | None) -> dict:
    """Add the held-out positions' MHD at the optimum to ``res["best"]["mhd_mm"]``: one more
    evaluation (stored in ``work_dir/held_out``) of those positions, its stress-free inverse
    warm-started from the optimum's own."""
    held = [p for p in settings.get("evaluate") or () if p not in settings["calibrate"]]
    if not held:
        return res
    ev = _Evaluator(Path(problem_dir), {**_search(settings), "calibrate": held},
                    Path(work_dir) / "held_out", False, warm=warm)
    rec = ev(res["best"]["params"])
    res["best"]["mhd_mm"] = {**res["best"]["mhd_mm"],
                             **{p: rec["mhd_mm"].get(p, math.nan) for p in held}}
    res["n_simulations"] += 1
    res["forward_solves"] += int(rec.get("forward_solves", 0))
    return res


def least_squares(problem_dir: Path, settings: Mapping[str, Any],
                  parameters: Mapping[str, Mapping[str, Any]], *, budget: int = 100,
                  work_dir: Path, progress: bool = False,
                  x0: Mapping[str, float] | None = None, warm: list | bool = True) -> dict:
    """Bounded trust-region least squares (scipy ``least_squares``, "trf") on the signed
    node-to-surface errors of the calibration positions (faded to 0 at the measured skin's
    rim: :func:`breastmodel.pipeline.scoring.skin_residual`), in log-parameter space.

    Uses the residual vector rather than its MHD summary, so each iteration gains from every
    skin node: a few parameters converge in a few tens of evaluations (forward-difference
    Jacobian with 5 % log steps, counted in ``budget``). The best evaluation by the objective
    (mean MHD) is returned, as for :func:`optimise` (often a Jacobian probe beside the
    least-squares optimum, ``optimum``, where the uncertainty and the sensitivity to a skin
    offset are computed: on the suite's small-000 1.054 against 1.003 kPa, truth 0.94), with
    scipy's ``termination`` message or the
    stopping rule that ended it (:class:`~breastmodel.pipeline.fit_jacobian.Jacobian`: a
    step below the parameters' uncertainty, or below 1 %); evaluations are stored in
    ``work_dir/least_squares`` and replayed on resume; ``warm`` as for :func:`optimise`.
    """
    names = list(parameters)
    lo = np.log([_bounds(parameters[n])[0] for n in names])
    hi = np.log([_bounds(parameters[n])[1] for n in names])
    warm = _starts(warm)
    ev = _Evaluator(Path(problem_dir), _search(settings), Path(work_dir) / "least_squares",
                    progress, residuals=True, warm=warm)
    calibrate = list(settings["calibrate"])
    size: list[int] = []
    # The solver works on w = ln p - ln p_min + 1 >= 1: trf's first trust radius is |w0| and
    # its step tests are relative to |w|, both useless near w = 0 (a parameter of 1 in log).
    shift = lo - 1.0

    def fun(w):
        if len(ev.history) >= budget:
            raise _BudgetSpent
        z = np.clip(np.asarray(w, float) + shift, lo, hi)
        rec = ev(dict(zip(names, np.exp(z).tolist())))
        res = rec.get("residual") or {}
        if rec.get("error") or not all(p in res for p in calibrate):
            if not size:  # the start failed: no residual's length to penalise with
                raise _StartFailed(rec.get("error") or "no residual at a calibrated position")
            # a failed solve: a large residual pushes the trust region back
            return np.full(size[0], PENALTY_MM)
        r = np.concatenate([np.asarray(res[p], float) for p in calibrate])
        if not size:
            size.append(len(r))
        return r

    z0 = (np.log([x0[n] for n in names]) if x0 else 0.5 * (lo + hi)).astype(float)
    w0 = np.clip(z0, lo + 1e-9, hi - 1e-9) - shift
    jac = Jacobian(fun, shift, lo, hi, w0)
    stop, uncertainty, offset, optimum = "budget spent", {}, {}, None
    try:
        w, J, r, stop = _solve(fun, jac, w0, lo - shift, hi - shift, budget)
        p_opt = np.exp(w + shift)
        optimum = dict(zip(names, p_opt.tolist()))
        uncertainty = lsq_uncertainty(J, r, p_opt, names)
        ident = identifiability(J, names)
        offset = _offset_sensitivity(ev, J, p_opt, names, calibrate)
    except _BudgetSpent:
        ident = None
    except _StartFailed as exc:  # _summary below names the error (every evaluation failed)
        stop, ident = f"the starting point failed: {exc}", None
    res = _held_out(_summary(ev.history, "least_squares"), problem_dir, settings, work_dir,
                    warm)
    return {**res, "termination": stop, "uncertainty": uncertainty, "identifiability": ident,
            "optimum": optimum, "skin_offset_sensitivity": offset}


def _solve(fun, jac: Jacobian, w0: np.ndarray, lo: np.ndarray, hi: np.ndarray, budget: int):
    """(w, J, r, termination) of the least squares in w (bounds ``lo``, ``hi``): the search
    along the first Gauss-Newton direction (:func:`~breastmodel.pipeline.fit_jacobian
    .line_start`), which is the whole fit for one parameter, then scipy's trust region."""
    from scipy.optimize import least_squares as scipy_lsq

    w0, steps = line_start(fun, jac, w0, lo, hi)
    jac.x = w0
    if steps and len(w0) == 1:  # the line search minimised along the only direction
        return w0, jac(w0), fun(w0), (f"the line search {steps:.3g} times the first "
                                      "Gauss-Newton step away found the least squares' "
                                      "minimum (one parameter)")
    if steps:
        log.info("fit: the least squares start %.3g times their first Gauss-Newton step "
                 "away, where the sum of squares stopped falling", steps)
    sol = scipy_lsq(fun, w0, jac=jac, bounds=(lo, hi), method="trf", x_scale=1.0, xtol=1e-4,
                    ftol=1e-4, max_nfev=budget, callback=jac.settled)
    return sol.x, sol.jac, sol.fun, jac.stop or str(sol.message)


def _offset_sensitivity(ev, J, p_opt, names, calibrate) -> dict:
    """:func:`offset_sensitivity` at the least squares' optimum ``p_opt`` (Jacobian ``J``),
    from the residuals' offset derivative its evaluation stored (empty for a record stored
    before it was)."""
    slopes = (ev.stored(dict(zip(names, p_opt.tolist()))) or {}).get("residual_offset") or {}
    if not all(p in slopes for p in calibrate):
        return {}
    g = np.concatenate([np.asarray(slopes[p], float) for p in calibrate])
    return offset_sensitivity(J, g, p_opt, names)


def _summary(history: list[dict], method: str) -> dict:
    ok = [h for h in history if h.get("objective") is not None
          and math.isfinite(h["objective"])]
    if not ok:
        raise RuntimeError(f"fit ({method}): every one of {len(history)} evaluations failed; "
                           f"first error: {history[0].get('error') if history else None}")
    best = min(ok, key=lambda h: h["objective"])
    return {"method": method,
            "best": {"params": best["params"], "objective": best["objective"],
                     "mhd_mm": best["mhd_mm"],
                     # None: a record stored before landmark errors were reported
                     "landmark_errors_mm": best.get("landmark_errors_mm")},
            "n_simulations": len(history),
            "n_failed": len(history) - len(ok),
            "forward_solves": int(sum(h.get("forward_solves", 0) for h in history)),
            "history": [{"params": h["params"], "objective": h["objective"]
                         if h["objective"] is not None and math.isfinite(h["objective"])
                         else None, "mhd_mm": h.get("mhd_mm"), "error": h.get("error")}
                        for h in history]}


def grid_search(problem_dir: Path, settings: Mapping[str, Any],
                parameters: Mapping[str, Mapping[str, Any]], *, work_dir: Path,
                scheduler: str | None = None, n_workers: int = 2,
                progress: bool = True) -> dict:
    """Every grid point on a dask cluster (:func:`breastmodel.sweep.run_sweep`), stored point
    by point in ``work_dir/grid``; failed points are NaN. Returns like :func:`optimise`."""
    from breastmodel.pipeline.problem import sweep_point
    from breastmodel.sweep import run_sweep

    fn = functools.partial(sweep_point, problem_dir=str(Path(problem_dir).resolve()),
                           settings=json.loads(json.dumps(settings)))
    recs = run_sweep(fn, grid_points(parameters), Path(work_dir) / "grid", scheduler=scheduler,
                     n_workers=n_workers, progress=progress)
    history = []
    for r in recs:
        res = r.get("result") or {}
        obj = res.get("objective")
        history.append({"params": r["point"], "objective": obj, "mhd_mm": res.get("mhd_mm"),
                        "forward_solves": res.get("forward_solves", 0),
                        "error": res.get("error") or r.get("error")})
    return _summary(history, "grid")


def sensitivity(problem_dir: Path, settings: Mapping[str, Any], best: Mapping[str, float],
                parameters: Mapping[str, Mapping[str, Any]], *, work_dir: Path,
                rel: float = 0.1, progress: bool = False, objective: float | None = None,
                warm: list | bool = True) -> dict:
    """One-at-a-time sensitivity at ``best``: objective at p(1 -+ rel) (clipped to bounds)
    and the log-log slope d ln MHD / d ln p (2 evaluations per parameter). ``objective``:
    the objective at ``best`` when the fit has it (else evaluated); ``warm`` as for
    :func:`optimise`."""
    ev = _Evaluator(Path(problem_dir), _search(settings), Path(work_dir) / "optimizer",
                    progress, warm=_starts(warm))
    f0 = ev(best)["objective"] if objective is None else float(objective)
    out = {}
    for name, spec in parameters.items():
        lo, hi = _bounds(spec)
        p = float(best[name])
        pl, ph = max(lo, p * (1 - rel)), min(hi, p * (1 + rel))
        # at a bound one side is the optimum itself, whose objective is known
        fl = f0 if pl == p else ev({**best, name: pl})["objective"]
        fh = f0 if ph == p else ev({**best, name: ph})["objective"]
        slope = None
        if (f0 and fl is not None and fh is not None and ph > pl
                and all(math.isfinite(v) for v in (f0, fl, fh))):
            slope = (fh - fl) / (math.log(ph) - math.log(pl)) / f0
        out[name] = {"value": p, "low": pl, "high": ph, "objective_low": fl,
                     "objective_high": fh, "objective": f0, "elasticity": slope}
    return out


def fit_parameters(problem_dir: Path, settings: Mapping[str, Any], fit: Mapping[str, Any], *,
                   work_dir: Path, progress: bool = True) -> dict:
    """Fit ``fit["parameters"]`` by ``fit["method"]`` ("grid" or "optimizer"), then (if
    ``fit["sensitivity"]``) the sensitivity at the optimum. Returns the fit record (see
    :func:`optimise`) plus ``calibrate``, ``evaluate`` and ``sensitivity``."""
    from breastmodel.pipeline.config import get_param

    params = fit["parameters"]
    starts: list = []  # the searches' stress-free geometries, shared with the sensitivity
    if fit["method"] == "grid":
        res = grid_search(problem_dir, settings, params, work_dir=work_dir,
                          scheduler=fit.get("scheduler"), n_workers=int(fit.get("n_workers", 2)),
                          progress=progress)
    elif fit["method"] == "least_squares":
        x0 = {n: float(get_param(settings["model"], n)) for n in params
              if get_param(settings["model"], n) is not None}
        res = least_squares(problem_dir, settings, params, budget=int(fit["budget"]),
                            work_dir=work_dir, progress=progress,
                            x0=x0 if len(x0) == len(params) else None, warm=starts)
    else:
        x0 = {}
        for n, spec in params.items():
            v = get_param(settings["model"], n)
            lo, hi = _bounds(spec)
            if v is not None and lo <= float(v) <= hi:
                x0[n] = float(v)
        res = optimise(problem_dir, settings, params, budget=int(fit["budget"]),
                       work_dir=work_dir, progress=progress,
                       x0=x0 if len(x0) == len(params) else None, warm=starts)
    res["calibrate"] = list(settings["calibrate"])
    res["evaluate"] = list(settings.get("evaluate") or [])
    res["sees"] = list(settings.get("sees") or ["skin"])
    if fit.get("sensitivity", True):
        res["sensitivity"] = sensitivity(problem_dir, settings, res["best"]["params"], params,
                                         work_dir=work_dir, progress=progress, warm=starts,
                                         objective=res["best"]["objective"])
    return res
