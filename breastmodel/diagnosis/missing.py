"""Which physical effect is missing: score every candidate by how much of the residual it
explains.

The residual is the vector of signed node-to-surface errors of the predicted skin in every
scored position (mm). Around the fitted model, each candidate is linearised from a few full
model evaluations (stress-free geometry + every position, the run's own settings):

    r(dtheta, a, dp) ~ r0 + J_theta dtheta + a (r_c - r0) + J_c dp

with r0 the fitted model's residual, J_theta the derivatives with respect to the fitted
parameters (log scale, finite differences), r_c the residual with the candidate switched on
at its probe strength, a the amount of that switch-on (fixed at 1 for on/off changes), and
J_c the derivatives with respect to the candidate's own parameters at the probe. A bounded
linear least-squares solve gives the residual the model would have after adding the
candidate and re-fitting everything, so candidates are compared at their best, and never
credited for what re-fitting the existing parameters alone achieves (the baseline is the same
solve without the candidate). The best candidate is then checked by a real (nonlinear)
least-squares re-fit with it switched on, started from the linear estimate.

The rim of the skin (nodes within ``rim_mm`` of its open edge, where the mesh ends at the
field-of-view cut) is left out of the residual: there the model's truncation boundary
conditions differ from the body's, which no physical effect explains; the error maps still
show it.

Errors of the measurement are candidates beside the physics
(:mod:`breastmodel.diagnosis.measurement`): a rigid misregistration of each scored position
(six columns) and an offset of the measured skin along its normal (one column); their columns
are exact derivatives of the residual and cost no model evaluation.

Significance. Every added parameter can only lower the squared residual, so each candidate
is charged for its k columns by the Bayesian information criterion
Delta BIC = n_eff ln(SS_c / SS_0) + k ln(n_eff), with n_eff the effective number of
independent residuals (neighbouring skin nodes carry nearly the same error; see
:func:`_effective_n`). Candidates are ranked by Delta BIC. A candidate explains "more than
the noise" when Delta BIC < -6, it lowers the residual RMS by more than a quarter of the noise
floor (and 0.02 mm) and removes at least 20 % of the baseline's squared residual; when none
does, "nothing explains more than the noise" is the verdict. Noise floor: with the full-field
inverse the reference position is reproduced by construction, so its residual is what
meshing and segmentation leave; otherwise the best-fitting position stands in for it.
Held-out check: a candidate that acts on the calibration positions of the run is also re-fitted
on those alone, and the RMS of the held-out positions is reported without and with it (a real
effect improves the position that was not fitted).

Budgets. The fitted model is evaluated first (and stored); every variant starts from its
solution and may spend a budget of forward solves and seconds (:mod:`.budget`); one that
spends it, or whose solve fails, is listed under ``failed`` with the reason.

Evaluations are points of a :func:`breastmodel.sweep.run_sweep` (stored atomically, resumed
after a kill, on a local or remote dask cluster).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.diagnosis.budget import Budget, default_budget
from breastmodel.diagnosis.candidates import Candidate, enumerate_candidates
from breastmodel.diagnosis.measurement import (
    measurement_candidates,
    measurement_columns,
    rigid_transform,
)

log = logging.getLogger("breastmodel.diagnosis")

__all__ = ["evaluate_model", "rank_candidates", "SIGNIFICANT_FLOOR_FRACTION"]

#: How many of the best candidates get a map of their correction in the result.
MAPPED = 6
#: Log step of the finite differences (about 22 %).
STEP = 0.2
#: Default width of the skin rim left out of the residual, mm (about two 8 mm elements).
RIM_MM = 15.0
#: A candidate must lower the residual RMS by this fraction of the noise floor ...
SIGNIFICANT_FLOOR_FRACTION = 0.25
#: ... and by at least this much, mm ...
SIGNIFICANT_MIN_MM = 0.02
#: ... and remove at least this fraction of the baseline's squared residual ...
SIGNIFICANT_EXPLAINED = 0.2
#: ... and lower the Bayesian information criterion by more than this ("strong" evidence on
#: the scale of Kass & Raftery 1995).
SIGNIFICANT_BIC = 6.0


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
        stress-free inverse and every position start from it (ignored when the model's mesh
        has another node count, e.g. a split interface)
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
        predict_position,
        score_position,
        skin_nodes,
        stress_free_geometry,
    )

    t0 = time.perf_counter()
    budget = budget or Budget(10**9, math.inf)
    problem = load_problem(problem_dir)
    start = start or {}
    if "X" in start and len(start["X"]) != model_mesh(problem, model).n_nodes:
        start = {}  # another mesh (a split interface added or removed): no warm start
    u_start = start.get("u", {})
    sf_start = (np.asarray(start["X"]), u_start.get(problem.reference)) if "X" in start \
        else None
    X, _ = stress_free_geometry(problem, model, settings["stress_free"], settings["solver"],
                                before_solve=lambda: budget.charge("a stress-free iteration"),
                                start=sf_start)
    out: dict[str, Any] = {"residual": {}, "mhd_mm": {}}
    us = {}
    for pos in settings["positions"]:
        budget.charge(f"position {pos}")
        u0 = u_start.get(pos)
        x = predict_position(problem, model, X, pos, settings["solver"],
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


def _variant_point(point: Mapping[str, Any], *, variants: Mapping[str, dict],
                   problem_dir: str, settings: Mapping[str, Any],
                   limits: tuple[int, float] | None = None,
                   start: Mapping[str, Any] | None = None) -> dict:
    budget = Budget(*limits) if limits else None
    res = evaluate_model(variants[point["variant"]], problem_dir, settings, budget=budget,
                         start=start)
    return {"residual": {p: np.asarray(v).tolist() for p, v in res["residual"].items()},
            "mhd_mm": res["mhd_mm"], "solves": res["solves"], "eval_s": res["wall_s"]}


def _base_evaluation(model: Mapping[str, Any], problem_dir: str | Path,
                     settings: Mapping[str, Any], work_dir: Path) -> tuple[dict, dict]:
    """The fitted model's evaluation (stored in ``work_dir``, reused by a rerun): its record
    in the sweep's format and its solution (the variants' warm start)."""
    import json
    import os

    path = work_dir / f"base-{_model_hash({'model': model, **settings})}.npz"
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
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.npz")
    np.savez(tmp, meta=json.dumps(rec), X=res["X"],
             **{f"u_{p}": res["u"][p] for p in pos}, **{f"r_{p}": res["residual"][p]
                                                        for p in pos})
    os.replace(tmp, path)
    rec["result"]["residual"] = res["residual"]
    return rec, {"X": res["X"], "u": res["u"]}


def _log_step(value: float, lo: float, hi: float) -> float:
    """+STEP unless that leaves [lo, hi], then -STEP."""
    return STEP if value * math.exp(STEP) <= hi * (1 + 1e-12) else -STEP


def _model_hash(model: Mapping[str, Any]) -> str:
    import hashlib

    from breastmodel.cache import canonical_json

    return hashlib.sha256(canonical_json(model).encode()).hexdigest()[:12]


def _fit_bounds(cfg: Mapping[str, Any], path: str) -> tuple[float, float]:
    spec = cfg["fit"]["parameters"][path]
    vals = spec.get("values")
    return (float(min(vals)), float(max(vals))) if vals else (float(spec["min"]),
                                                             float(spec["max"]))


def rank_candidates(run, *, work_dir: str | Path | None = None, n_workers: int = 0,
                    scheduler: str | None = None, verify_top: int = 1,
                    candidates: Sequence[Candidate] | None = None,
                    rim_mm: float = RIM_MM, verify_budget: int = 12,
                    max_solves: int | None = None, max_seconds: float | None = None,
                    progress: bool = True) -> dict:
    """Score every candidate missing effect of a finished run.

    Parameters
    ----------
    run : :class:`breastmodel.diagnosis.RunData`
    work_dir : where evaluations are stored (default ``run.out / "diagnosis" / "evaluations"``);
        a rerun reuses them
    n_workers, scheduler : the dask cluster (see :func:`breastmodel.sweep.run_sweep`; the
        default 0 evaluates in this process)
    verify_top : how many of the best significant candidates get a nonlinear check: a
        least-squares re-fit with the candidate on (at most ``verify_budget`` evaluations)
    candidates : override the enumeration (tests, or a user's own list)
    rim_mm : skin nodes closer than this to the skin's open edge (the field-of-view cut) are
        left out of the residual, mm (0 keeps every node)
    max_solves, max_seconds : the budget of every variant's evaluation (forward solves,
        seconds); default from the fitted model's own evaluation (:func:`default_budget`).
        A variant that spends it fails with the reason, and the others still answer.

    Returns
    -------
    dict (JSON-ready)
        ``positions`` (scored), ``objective_positions``, ``noise_floor_mm``,
        ``baseline`` (per-position RMS now and after re-fitting alone), ``ranking`` (best
        first: name, kind, doc, explained fraction, predicted RMS and mean |e| per position,
        estimated parameters, significant, evidence per region, verified metrics),
        ``skipped`` (what is not scored and why), ``failed`` (candidates whose evaluation
        failed), ``verdict`` (one sentence).
    """
    from scipy.optimize import lsq_linear

    from breastmodel.pipeline.config import get_param, set_params
    from breastmodel.pipeline.problem import skin_node_regions, skin_nodes
    from breastmodel.sweep import run_sweep

    cfg, model, problem = run.config, run.model, run.problem
    positions = list(run.positions)
    inverse = cfg["stress_free"]["method"] == "inverse"
    obj_pos = [p for p in positions if not (inverse and p == problem.reference)] or positions
    settings = {"solver": cfg["solver"], "stress_free": cfg["stress_free"],
                "positions": positions}
    fitted = list(cfg["fit"]["parameters"]) if cfg["fit"]["enabled"] else []
    mesh = problem.mesh
    default_candidates = candidates is None
    if candidates is None:
        candidates, skipped = enumerate_candidates(
            model, set(fitted), regions={int(r) for r in np.unique(mesh.region)},
            node_pairs=set(mesh.node_pairs))
    else:
        skipped = []

    # ---- the model variants to evaluate
    variants: dict[str, dict] = {"base": model}
    steps: dict[str, float] = {}
    theta0 = {}
    for q in fitted:
        v = float(get_param(model, q))
        lo, hi = _fit_bounds(cfg, q)
        theta0[q] = v
        steps[f"theta|{q}"] = h = _log_step(v, lo, hi)
        variants[f"theta|{q}"] = set_params(model, {q: v * math.exp(h)})
    cand_models: dict[str, dict] = {}
    for c in candidates:
        cm = set_params(c.apply(model), c.start)
        cand_models[c.name] = cm
        if c.effects:
            variants[f"cand|{c.name}"] = cm
        for f, (lo, hi) in c.free.items():
            v = float(c.start.get(f, get_param(cm, f) or 1.0))
            steps[f"cand|{c.name}|{f}"] = h = _log_step(v, lo, hi)
            variants[f"cand|{c.name}|{f}"] = set_params(cm, {f: v * math.exp(h)})
    # the skin rim is checked before any model evaluation: a rim too wide stops at once
    nodes = skin_nodes(problem, mesh.n_nodes)
    keep = _away_from_rim(mesh, nodes, run.X[:mesh.n_nodes], rim_mm)
    work_dir = Path(work_dir) if work_dir else run.out / "diagnosis" / "evaluations"
    base_rec, base_state = _base_evaluation(model, run.problem_dir, settings, work_dir)
    if base_rec["status"] != "ok":
        raise RuntimeError(f"diagnose: the fitted model itself failed to solve: "
                           f"{base_rec['error']}")
    auto = default_budget(int(base_rec["result"]["solves"]), float(base_rec["result"]["eval_s"]))
    limits = (int(max_solves) if max_solves else auto[0],
              float(max_seconds) if max_seconds else auto[1])
    points = [{"variant": k, "model": _model_hash(m)} for k, m in variants.items()
              if k != "base"]
    if progress:
        print(f"diagnose: {len(candidates)} candidates, {len(points) + 1} model evaluations "
              f"(stored in {work_dir}; each within {limits[0]} forward solves and "
              f"{limits[1]:.0f} s)", flush=True)
    fn = functools.partial(_variant_point, variants=variants, problem_dir=str(run.problem_dir),
                           settings=settings, limits=limits, start=base_state)
    recs = run_sweep(fn, points, work_dir, scheduler=scheduler, n_workers=n_workers,
                     progress=progress, retry_failed=True)
    res = {p["variant"]: r for p, r in zip(points, recs)}
    res["base"] = base_rec
    evaluation_cost = {k: {"status": r["status"], "solves": (r["result"] or {}).get("solves"),
                           "seconds": (r["result"] or {}).get("eval_s", r.get("wall_s"))}
                       for k, r in res.items()}

    # ---- geometry of the residual vector: which entries are which position / region
    n_skin = int(keep.sum())
    region_masks = {k: m[keep] for k, m in _regions(problem, nodes, run.X[:mesh.n_nodes],
                                                     skin_node_regions(mesh)).items()}
    slices = {p: slice(i * n_skin, (i + 1) * n_skin) for i, p in enumerate(obj_pos)}

    def vec(name: str, which: Sequence[str] = obj_pos) -> np.ndarray | None:
        r = res[name]
        if r["status"] != "ok":
            return None
        return np.concatenate([np.asarray(r["result"]["residual"][p], float)[keep]
                               for p in which])

    def rms(v):
        return float(np.sqrt(np.mean(np.square(v)))) if len(v) else math.nan

    all_base = {p: np.asarray(res["base"]["result"]["residual"][p])[keep] for p in positions}
    if inverse and problem.reference in all_base:
        floor = rms(all_base[problem.reference])
        floor_from = f"reference position {problem.reference!r} (reproduced by construction)"
    else:
        floor = min(rms(v) for v in all_base.values())
        floor_from = "the best-fitting position (no position is reproduced by construction)"
    floor = max(floor, SIGNIFICANT_MIN_MM)

    r0 = vec("base")
    J_theta, th_lo, th_hi, th_names = [], [], [], []
    for q in fitted:
        rq = vec(f"theta|{q}")
        if rq is None:
            continue
        h = steps[f"theta|{q}"]
        J_theta.append((rq - r0) / h)
        lo, hi = _fit_bounds(cfg, q)
        th_lo.append(math.log(lo / theta0[q]))
        th_hi.append(math.log(hi / theta0[q]))
        th_names.append(q)

    # rows of the calibration positions (the run's fit) and of the held-out ones
    calibrate = [p for p in (cfg["fit"].get("calibrate") or []) if p in obj_pos]
    held_out = [p for p in obj_pos if p not in calibrate] if calibrate else []
    cal_rows = np.zeros(len(r0), bool)
    for p in calibrate:
        cal_rows[slices[p]] = True

    def solve(extra_cols, lo, hi, inert=(), rows=None):
        """Bounded linear re-fit (on ``rows`` of the residual, default all); fitted
        parameters in ``inert`` (made inert by the candidate, e.g. moduli that the regions
        effect overrides) are left out. Returns the whole predicted residual."""
        use = [i for i, q in enumerate(th_names) if not set(q.split("|")) & set(inert)]
        cols = [J_theta[i] for i in use] + list(extra_cols)
        if not cols:
            return r0.copy(), {}, np.zeros(0)
        A = np.column_stack(cols)
        lb = np.array([th_lo[i] for i in use] + list(lo), float)
        ub = np.array([th_hi[i] for i in use] + list(hi), float)
        ub = np.maximum(ub, lb + 1e-12)
        m = slice(None) if rows is None else rows
        sol = lsq_linear(A[m], -r0[m], bounds=(lb, ub), method="bvls")
        z_th = {th_names[i]: float(z) for i, z in zip(use, sol.x)}
        return r0 + A @ sol.x, z_th, sol.x[len(use):]

    r_base, z_base, _ = solve([], [], [])
    ss_base = float(r_base @ r_base)
    rms_now = rms(r0)
    rms_base = rms(r_base)
    n_eff = _effective_n(mesh, nodes, keep, r_base, slices)
    r_base_cal = solve([], [], [], rows=cal_rows)[0] if held_out else None

    # ---- the measured skin's geometry (non-physical candidates' columns)
    geometry = _measured_geometry(problem, base_state, nodes, keep, obj_pos)
    if default_candidates:
        candidates = list(candidates) + measurement_candidates(obj_pos)

    def per_position(r):
        return {p: {"rms_mm": rms(r[s]), "mean_abs_mm": float(np.mean(np.abs(r[s])))}
                for p, s in slices.items()}

    def per_region(r):
        out = {}
        for p, s in slices.items():
            for name, m in region_masks.items():
                if m.any():
                    out[f"{p}.{name}"] = rms(r[s][m])
        return out

    def _failure(c, variant):
        r = res[variant]
        return {"name": c.name, "kind": c.kind, "doc": c.doc, "evaluation": variant,
                "error": r["error"], "seconds": r.get("wall_s")}

    base_regions = per_region(r_base)
    ranking, failed = [], []
    corrections: dict[str, np.ndarray] = {}
    for c in candidates:
        cols, lo, hi, labels = [], [], [], []
        rc = r0
        if c.measurement:
            cols, lo, hi, labels = measurement_columns(c, geometry, obj_pos)
        if c.effects:
            rc = vec(f"cand|{c.name}")
            if rc is None:
                failed.append(_failure(c, f"cand|{c.name}"))
                continue
            shift = rc - r0
            cols.append(shift)
            lo.append(c.amplitude[0])
            hi.append(c.amplitude[1])
            labels.append("amplitude")
        ok = True
        for f, (flo, fhi) in c.free.items():
            rf = vec(f"cand|{c.name}|{f}")
            if rf is None:
                failed.append(_failure(c, f"cand|{c.name}|{f}"))
                ok = False
                break
            cols.append((rf - rc) / steps[f"cand|{c.name}|{f}"])
            v0 = float(c.start[f])
            lo.append(math.log(max(flo, 1e-3 * v0) / v0))
            hi.append(math.log(fhi / v0))
            labels.append(f)
        if not ok:
            continue
        r_c, z_theta, z = solve(cols, lo, hi, inert=c.replaces)
        ss = float(r_c @ r_c)
        z_c = dict(zip(labels, z))
        est = {q: theta0[q] * math.exp(zq) for q, zq in z_theta.items()}
        est.update({f: float(c.start[f]) * math.exp(z_c[f]) for f in c.free})
        if c.measurement:
            est.update({f"measured.{k}": float(v) for k, v in z_c.items()})
        explained = 1.0 - ss / ss_base if ss_base > 0 else 0.0
        drop = rms_base - rms(r_c)
        k_added = max(len(cols), 1)
        delta_bic = _delta_bic(ss, ss_base, n_eff, k_added)
        regions_after = per_region(r_c)
        gains = sorted(((base_regions[k] - regions_after[k], k) for k in base_regions),
                       reverse=True)
        corrections[c.name] = r_c - r_base
        entry = {
            **c.to_dict(),
            "explained": explained,
            "predicted_rms_mm": rms(r_c),
            "rms_drop_mm": drop,
            "predicted": per_position(r_c),
            "amount": float(z_c.get("amplitude", 1.0 if c.effects else 0.0)),
            "estimate": est,
            "n_parameters": k_added,
            "delta_bic": delta_bic,
            "evidence": [{"where": k, "rms_before_mm": base_regions[k],
                          "rms_after_mm": regions_after[k]} for g, k in gains[:4] if g > 0],
            "significant": bool(drop > max(SIGNIFICANT_FLOOR_FRACTION * floor,
                                           SIGNIFICANT_MIN_MM)
                                and explained >= SIGNIFICANT_EXPLAINED
                                and delta_bic < -SIGNIFICANT_BIC),
        }
        acts = set(c.acts_on) if c.measurement and c.acts_on else set(obj_pos)
        if held_out and acts & set(calibrate):
            r_h = solve(cols, lo, hi, inert=c.replaces, rows=cal_rows)[0]
            entry["held_out"] = {
                p: {"rms_before_mm": rms(r_base_cal[slices[p]]),
                    "rms_after_mm": rms(r_h[slices[p]])} for p in held_out}
            entry["held_out_improves"] = bool(all(
                v["rms_after_mm"] < v["rms_before_mm"] for v in entry["held_out"].values()))
        if c.measurement == "rigid":
            entry["transform"] = rigid_transform(z_c, geometry[c.acts_on[0]]["y"])
        ranking.append(entry)
    ranking.sort(key=lambda r: r["delta_bic"])

    # ---- nonlinear check of the best significant candidates: a short least-squares re-fit
    # (candidate on, its parameters and the fitted ones free) from the linear estimate
    by_name = {c.name: c for c in candidates}
    for r in [r for r in ranking if r["significant"]][:max(int(verify_top), 0)]:
        if r["measurement"]:
            r["verified"] = _verify_measurement(by_name[r["name"]], r, run, cfg, model, fitted,
                                                obj_pos, positions, work_dir, verify_budget,
                                                progress)
        else:
            r["verified"] = _verify(by_name[r["name"]], r["estimate"], run, cfg, model, fitted,
                                    obj_pos, positions, work_dir, verify_budget, progress)

    base_mhd = res["base"]["result"]["mhd_mm"]
    sig = [r for r in ranking if r["significant"]]
    if sig:
        verdict = _verdict(sig[0], rms_base)
    else:
        worst = sorted(base_regions.items(), key=lambda kv: -kv[1])[:3]
        carriers = ", ".join(f"{k} ({v:.2f} mm)" for k, v in worst)
        verdict = (f"no candidate explains more than the noise (floor {floor:.3f} mm, "
                   f"residual RMS {rms_base:.3f} mm): the residual is noise, or the missing "
                   f"effect is not in the library; the largest residuals are at {carriers}")
    # where each of the best candidates acts: its predicted change of the residual, beside
    # the residual it is to explain (over the scored nodes, in canonical skin-node order)
    shown = [r["name"] for r in ranking[:MAPPED]]
    maps = {"index": np.flatnonzero(keep).tolist(), "n_skin_nodes": int(len(keep)),
            "positions": list(obj_pos), "residual": r_base.tolist(),
            "corrections": {k: corrections[k].tolist() for k in shown}}
    return {
        "positions": positions, "objective_positions": obj_pos,
        "noise_floor_mm": floor, "noise_floor_from": floor_from,
        "baseline": {"rms_mm": rms_now, "rms_after_refit_mm": rms_base,
                     "per_position": per_position(r_base), "mhd_mm": base_mhd,
                     "refit_estimate": {q: theta0[q] * math.exp(zq)
                                        for q, zq in z_base.items()}},
        "fitted_parameters": fitted,
        "rim_mm": float(rim_mm), "n_skin_nodes": int(len(keep)), "n_scored_nodes": n_skin,
        "ranking": ranking, "skipped": skipped, "failed": failed,
        "budget": {"max_solves": limits[0], "max_seconds": limits[1],
                   "base_solves": base_rec["result"]["solves"],
                   "base_seconds": base_rec["result"]["eval_s"]},
        "evaluations": evaluation_cost,
        "n_effective": n_eff, "calibrate": calibrate, "held_out": held_out,
        "correction_maps": maps,
        "n_evaluations": len(points) + 1 + sum(r.get("verified", {}).get("evaluations", 0)
                                           for r in ranking), "verdict": verdict,
    }


def _verify(c: Candidate, estimate: Mapping[str, float], run, cfg, model, fitted, obj_pos,
            positions, work_dir: Path, budget: int, progress: bool) -> dict:
    """Switch ``c`` on and re-fit its parameters and the (not inert) fitted ones by least
    squares on the scored positions, from the linear estimate. Returns the best
    evaluation's MHD per position and parameters, or the error."""
    from breastmodel.pipeline.config import set_params
    from breastmodel.pipeline.fit import least_squares

    params = {q: dict(zip(("min", "max"), _fit_bounds(cfg, q))) for q in fitted
              if not set(q.split("|")) & set(c.replaces)}
    params.update({f: {"min": lo, "max": hi} for f, (lo, hi) in c.free.items()})
    start = {**c.start, **estimate}
    x0 = {p: min(max(float(start[p]), spec["min"]), spec["max"]) for p, spec in params.items()
          if p in start}
    settings = {"model": set_params(c.apply(model), start), "solver": cfg["solver"],
                "stress_free": cfg["stress_free"], "calibrate": list(obj_pos),
                "evaluate": [p for p in positions if p not in obj_pos]}
    folder = work_dir / f"verify-{c.name.replace(':', '_')}-{_model_hash(settings)}"
    try:
        if not params:  # nothing to re-fit: one evaluation
            from breastmodel.pipeline.problem import evaluate_params

            rec = evaluate_params({}, run.problem_dir, settings)
            if rec["error"]:
                return {"error": rec["error"]}
            return {"mhd_mm": rec["mhd_mm"], "objective_mm": rec["objective"],
                    "params": {}, "evaluations": 1}
        res = least_squares(run.problem_dir, settings, params, budget=budget,
                            work_dir=folder, progress=progress,
                            x0=x0 if len(x0) == len(params) else None)
    except RuntimeError as exc:  # every evaluation failed
        return {"error": str(exc)}
    best = res["best"]
    return {"mhd_mm": best["mhd_mm"], "objective_mm": best["objective"],
            "params": best["params"], "evaluations": res["n_simulations"]}


def _away_from_rim(mesh, nodes: np.ndarray, X: np.ndarray, rim_mm: float) -> np.ndarray:
    """(n_skin,) bool: skin nodes farther than ``rim_mm`` from the skin's open edge (edges
    of one skin triangle only). All True when the skin is closed or ``rim_mm`` <= 0."""
    from scipy.spatial import cKDTree

    faces = np.asarray(mesh.face_sets["skin"])
    e = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    edge_nodes = np.unique(uniq[count == 1])
    if rim_mm <= 0 or not len(edge_nodes):
        return np.ones(len(nodes), bool)
    d, _ = cKDTree(X[edge_nodes]).query(X[nodes])
    keep = d > rim_mm
    if keep.sum() < 0.2 * len(nodes):
        raise ValueError(f"diagnose: a {rim_mm} mm rim leaves {int(keep.sum())} of "
                         f"{len(nodes)} skin nodes; use a smaller rim_mm")
    return keep


def _regions(problem, nodes: np.ndarray, X: np.ndarray, node_region: np.ndarray,
             ) -> dict[str, np.ndarray]:
    """Boolean masks over the canonical skin nodes: the skin regions of the maps module
    where it is available, else left / right breast."""
    try:
        from breastmodel.diagnosis.maps import skin_regions
    except ImportError:
        skin_regions = None
    if skin_regions is not None:
        try:
            return {k: np.asarray(v, bool) for k, v in skin_regions(problem.mesh, X).items()}
        except Exception as exc:  # noqa: BLE001 - regions are evidence, not the ranking
            log.warning("diagnose: skin regions unavailable (%s); using left/right", exc)
    from mechanics.mesh import REGIONS

    reg = node_region[nodes]
    return {"left": np.isin(reg, (REGIONS["breast_left"], REGIONS["gland_left"])),
            "right": np.isin(reg, (REGIONS["breast_right"], REGIONS["gland_right"]))}


def _effective_n(mesh, nodes: np.ndarray, keep: np.ndarray, r: np.ndarray,
                 slices: Mapping[str, slice]) -> float:
    """Effective number of independent entries of the residual ``r``.

    Neighbouring skin nodes carry nearly the same error wherever the residual is a smooth
    field, so the node count overstates the evidence. With rho the correlation of the
    residual across skin edges (pooled over positions), n_eff = n (1 - rho) / (1 + rho), the
    count of an AR(1) sequence of the same lag-one correlation; white noise keeps n.
    """
    idx = np.full(mesh.n_nodes, -1, np.int64)
    idx[nodes[keep]] = np.arange(int(keep.sum()))
    faces = np.asarray(mesh.face_sets["skin"])
    e = np.unique(np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1), axis=0)
    e = idx[e]
    e = e[(e >= 0).all(axis=1)]
    num = den = 0.0
    for s in slices.values():
        v = r[s] - r[s].mean()
        num += float(np.sum(v[e[:, 0]] * v[e[:, 1]])) / max(len(e), 1)
        den += float(np.mean(v * v))
    rho = min(max(num / den, 0.0), 0.999) if den > 0 else 0.0
    return float(max(len(r) * (1 - rho) / (1 + rho), 2.0))


def _delta_bic(ss: float, ss_base: float, n_eff: float, k: int) -> float:
    """BIC of the re-fit with the candidate minus that of the re-fit without it (Gaussian
    residual of unknown variance): n_eff ln(ss / ss_base) + k ln(n_eff); negative favours
    the candidate, and every added parameter costs ln(n_eff)."""
    tiny = 1e-30
    return float(n_eff * math.log(max(ss, tiny) / max(ss_base, tiny)) + k * math.log(n_eff))


def _measured_geometry(problem, state: Mapping[str, Any], nodes: np.ndarray, keep: np.ndarray,
                       positions: Sequence[str]) -> dict:
    """Per position, the closest points ``y`` on the measured skin of the fitted model's
    scored skin nodes and the outward directions ``g`` (the non-physical candidates'
    columns)."""
    from breastmodel.diagnosis.measurement import _directions
    from breastmodel.evaluation import point_to_surface

    out = {}
    X = np.asarray(state["X"])
    for p in positions:
        x = (X + np.asarray(state["u"][p]))[nodes[keep]]
        v, t = problem.skins[p]
        d, y = point_to_surface(x, v, t, signed=True)
        out[p] = {"y": np.asarray(y), "g": _directions(x, np.asarray(d), np.asarray(y), v, t)}
    return out


def _verdict(best: Mapping[str, Any], rms_base: float) -> str:
    """One sentence about the best significant candidate."""
    gain = (f"adding it is predicted to lower the residual RMS from {rms_base:.3f} to "
            f"{best['predicted_rms_mm']:.3f} mm ({100 * best['explained']:.0f} % of the squared "
            "residual explained)")
    if best["measurement"] == "rigid":
        pos, tr = best["acts_on"][0], best["transform"]
        return (f"{pos} looks misregistered by about {tr['max_displacement_mm']:.1f} mm "
                f"(translation {tr['translation_mm']:.1f} mm, rotation {tr['angle_deg']:.1f} "
                f"deg; correcting it lowers the residual RMS from {rms_base:.3f} to "
                f"{best['predicted_rms_mm']:.3f} mm): rerun `breastmodel register` for {pos} "
                "(check its fiducials and the chest-wall correlation), then the run")
    if best["measurement"] == "offset":
        s = best["estimate"]["measured.offset_mm"]
        return (f"the measured skin looks offset by {abs(s):.2f} mm "
                f"{'inwards' if s > 0 else 'outwards'} in every position (segmentation bias: "
                f"correcting it lowers the residual RMS from {rms_base:.3f} to "
                f"{best['predicted_rms_mm']:.3f} mm): check the skin threshold of `segment`")
    held = "".join(
        f"; fitted on the calibration positions alone it changes the held-out {p} RMS from "
        f"{v['rms_before_mm']:.3f} to {v['rms_after_mm']:.3f} mm"
        for p, v in (best.get("held_out") or {}).items())
    return f"missing effect: {best['name']} ({best['doc']}); {gain}{held}"


def _corrected_problem(problem_dir: Path, out: Path, moves: Mapping[str, Any]) -> Path:
    """A copy of the problem folder whose measured skins are moved by ``moves`` (position ->
    callable (vertices, triangles) -> vertices)."""
    import shutil

    from breastmodel.pipeline.problem import forget_problem

    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(problem_dir, out)
    for p, move in moves.items():
        with np.load(out / f"{p}_skin.npz") as z:
            v, t = z["vertices"].copy(), z["triangles"].copy()
        np.savez(out / f"{p}_skin.npz", vertices=move(v, t), triangles=t)
    forget_problem(out)
    return out


def _verify_measurement(c: Candidate, entry: Mapping[str, Any], run, cfg, model, fitted,
                        obj_pos, positions, work_dir: Path, budget: int,
                        progress: bool) -> dict:
    """Correct the measured skin as estimated (rigid motion exact, offset along the vertex
    normals) in a copy of the problem, and re-fit the fitted parameters there by least
    squares (at most ``budget`` evaluations)."""
    from breastmodel.diagnosis.measurement import _vertex_normals
    from breastmodel.pipeline.fit import least_squares
    from breastmodel.pipeline.problem import evaluate_params

    if c.measurement == "rigid":
        tr = entry["transform"]
        R, t, ctr = (np.asarray(tr[k]) for k in ("rotation", "translation", "centre"))
        moves = {c.acts_on[0]: lambda v, tri: ctr + (v - ctr) @ R.T + t}
    else:
        s = float(entry["estimate"]["measured.offset_mm"])
        moves = {p: (lambda v, tri: v + s * _vertex_normals(v, tri)) for p in c.acts_on}
    folder = work_dir / f"verify-{c.name.replace(':', '_')}-{_model_hash(dict(entry['estimate']))}"
    prob = _corrected_problem(Path(run.problem_dir), folder / "problem", moves)
    settings = {"model": model, "solver": cfg["solver"], "stress_free": cfg["stress_free"],
                "calibrate": list(obj_pos), "evaluate": [p for p in positions
                                                          if p not in obj_pos]}
    params = {q: dict(zip(("min", "max"), _fit_bounds(cfg, q))) for q in fitted}
    try:
        if not params:
            rec = evaluate_params({}, prob, settings)
            if rec["error"]:
                return {"error": rec["error"]}
            return {"mhd_mm": rec["mhd_mm"], "objective_mm": rec["objective"], "params": {},
                    "evaluations": 1}
        from breastmodel.pipeline.config import get_param

        x0 = {q: min(max(float(get_param(model, q)), p["min"]), p["max"])
              for q, p in params.items()}
        res = least_squares(prob, settings, params, budget=budget, work_dir=folder / "fit",
                            progress=progress, x0=x0)
    except RuntimeError as exc:
        return {"error": str(exc)}
    best = res["best"]
    return {"mhd_mm": best["mhd_mm"], "objective_mm": best["objective"],
            "params": best["params"], "evaluations": res["n_simulations"]}
