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

Significance. Every added parameter can only lower the squared residual, so each candidate is
charged for its k columns by the Bayesian information criterion
Delta BIC = n_eff ln(SS_c / SS_0) + k ln(n_eff), with n_eff the effective number of independent
residuals (neighbouring skin nodes carry nearly the same error; see
:func:`~breastmodel.diagnosis.residual.effective_n`). A candidate explains "more than the
noise" when Delta BIC < -6, it lowers the residual RMS by more than a quarter of the noise
floor (and 0.02 mm), removes at least 20 % of the baseline's squared residual and, where a
position is held out, improves it (below); significant candidates rank first, each group by
Delta BIC. A misregistration must also lower its position's RMS by more than the residual RMS
the model leaves in the other scored positions (its misfit where no registration is in
question; see :mod:`.scoring`). When none is significant,
"nothing explains more than the noise" is the verdict. Noise floor: with the full-field
inverse the reference position is reproduced by construction, so its residual is what
meshing and segmentation leave; otherwise the best-fitting position stands in for it.
Held-out check: a candidate that acts on the calibration positions of the run is also re-fitted
on those alone, and the RMS of the held-out positions is reported without and with it (a real
effect improves the position that was not fitted). The check decides only for candidates that
act on the held-out positions too (the misregistration of one calibration position predicts
nothing there) and move their prediction by at least ``HELD_OUT_MIN_CHANGE_MM`` (a position
tilted a few degrees from the reference, which the inverse reproduces whatever the model,
cannot test anything).

Budgets. The fitted model is evaluated first (and stored); every variant starts from its
solution and may spend a budget of forward solves and seconds (:mod:`.budget`); one that
spends it, or whose solve fails, is listed under ``failed`` with the reason.

Evaluations are points of a :func:`breastmodel.sweep.run_sweep` (stored atomically, resumed
after a kill, on a local or remote dask cluster).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from breastmodel.diagnosis.budget import default_budget
from breastmodel.diagnosis.candidates import Candidate, enumerate_candidates
from breastmodel.diagnosis.evaluations import (
    base_evaluation,
    evaluate_model,
    fit_bounds,
    log_step,
    model_hash,
    variant_point,
)
from breastmodel.diagnosis.measurement import measurement_candidates
from breastmodel.diagnosis.mesh_probe import add_mesh_candidate
from breastmodel.diagnosis.residual import (
    Baseline,
    Linearisation,
    away_from_rim,
    linearise,
    measured_geometry,
)
from breastmodel.diagnosis.scoring import (
    SIGNIFICANT_FLOOR_FRACTION,
    SIGNIFICANT_MIN_MM,
    answer,
    confounders,
    confounding_sentence,
    mesh_sentence,
    score_candidates,
    verdict_sentence,
)
from breastmodel.diagnosis.verify import verify_best

__all__ = ["evaluate_model", "rank_candidates", "SIGNIFICANT_FLOOR_FRACTION"]

#: How many of the best candidates get a map of their correction in the result.
MAPPED = 6
#: Default width of the skin rim left out of the residual, mm (about two 8 mm elements).
RIM_MM = 15.0


def rank_candidates(run, *, work_dir: str | Path | None = None, n_workers: int = 0,
                    scheduler: str | None = None, verify_top: int = 1,
                    candidates: Sequence[Candidate] | None = None,
                    rim_mm: float = RIM_MM, verify_budget: int = 12,
                    max_solves: int | None = None, max_seconds: float | None = None,
                    refine: bool = True, progress: bool = True) -> dict:
    """Score every candidate missing effect of a finished run.

    Parameters
    ----------
    run : :class:`breastmodel.diagnosis.RunData`
    work_dir : where evaluations are stored (default ``run.out / "diagnosis" / "evaluations"``);
        a rerun reuses them
    n_workers, scheduler : the dask cluster (see :func:`breastmodel.sweep.run_sweep`; the
        default 0 evaluates in this process)
    verify_top : how many of the best significant candidates get a least-squares re-fit
        with it on (at most ``verify_budget`` evaluations); 0 skips the landmark check too
    candidates : override the enumeration (tests, or a user's own list)
    rim_mm : skin nodes closer than this to the skin's open edge (the field-of-view cut) are
        left out of the residual, mm (0 keeps every node)
    max_solves, max_seconds : the budget of every variant's evaluation (forward solves,
        seconds); default from the fitted model's own evaluation (:func:`default_budget`).
        A variant that spends it fails with the reason, and the others still answer.
    refine : probe the mesh (``mesh_refinement``: the fitted model on a mesh of half the edge
        length, :mod:`.mesh_probe`; not within the budget above)

    Returns
    -------
    dict (JSON-ready)
        ``positions`` (scored), ``objective_positions``, ``noise_floor_mm``,
        ``baseline`` (per-position RMS now and after re-fitting alone), ``ranking`` (best
        first: name, kind, doc, explained fraction, predicted RMS and mean |e| per position,
        estimated parameters, significant, evidence per region, verified metrics),
        ``skipped`` (what is not scored and why), ``failed`` (candidates whose evaluation
        failed), ``confounders`` (candidates not significant whose re-fit moves a fitted
        parameter by :data:`~breastmodel.diagnosis.scoring.CONFOUNDING_CHANGE` or more,
        named in the verdict too), ``verdict`` (one sentence).
    """
    from breastmodel.pipeline.problem import skin_nodes

    cfg, model, problem = run.config, run.model, run.problem
    positions = list(run.positions)
    inverse = cfg["stress_free"]["method"] == "inverse"
    obj_pos = [p for p in positions if not (inverse and p == problem.reference)] or positions
    fitted = list(cfg["fit"]["parameters"]) if cfg["fit"]["enabled"] else []
    default_candidates = candidates is None
    if candidates is None:
        candidates, skipped = enumerate_candidates(
            model, set(fitted), regions={int(r) for r in np.unique(problem.mesh.region)},
            node_pairs=set(problem.mesh.node_pairs),
            node_sets={k for k, v in problem.mesh.node_sets.items() if len(v)})
    else:
        skipped = []
    plan = _plan_variants(cfg, model, fitted, candidates)
    # the skin rim is checked before any model evaluation: a rim too wide stops at once
    nodes = skin_nodes(problem, problem.mesh.n_nodes)
    keep = away_from_rim(problem.mesh, nodes, run.X[:problem.mesh.n_nodes], rim_mm)
    work_dir = Path(work_dir) if work_dir else run.out / "diagnosis" / "evaluations"
    ev = _evaluate_variants(run, plan, positions, work_dir, n_candidates=len(candidates),
                            limits=(max_solves, max_seconds), scheduler=scheduler,
                            n_workers=n_workers, progress=progress)
    lin, base = linearise(run, ev.records, keep=keep, nodes=nodes, obj_pos=obj_pos,
                          fitted=fitted, steps=plan.steps, theta0=plan.theta0,
                          floor_min_mm=SIGNIFICANT_MIN_MM)
    # the measured skin's geometry (non-physical candidates' columns)
    geometry = measured_geometry(problem, ev.base_state, nodes, keep, obj_pos)
    probe = None
    if default_candidates:
        extra, probe = _non_physical(run, ev.base_state, nodes, keep, obj_pos, geometry,
                                     skipped, refine=refine, progress=progress)
        candidates = list(candidates) + extra
    ranking, failed, corrections = score_candidates(candidates, lin, base, plan, geometry)
    for r in ranking:
        r.update({"probe": probe} if r["measurement"] == "refinement" else {})
    lm = verify_best(ranking, candidates, run, fitted, obj_pos, positions, work_dir,
                     state=ev.base_state, base_mhd=ev.records["base"]["result"]["mhd_mm"],
                     verify_top=verify_top, verify_budget=verify_budget, progress=progress)
    return _result(run, ev, lin, base, plan, ranking, corrections, skipped=skipped,
                   failed=failed, fitted=fitted, obj_pos=obj_pos, rim_mm=rim_mm,
                   landmark_check=lm)


def _non_physical(run, state, nodes, keep, obj_pos, geometry, skipped: list, *, refine: bool,
                  progress: bool) -> tuple[list[Candidate], dict | None]:
    """The candidates that are no physics: errors of the measured skin, and the mesh probe
    (with the probe's sizes and folder; where there is none, ``skipped`` says why)."""
    mesh, probe = add_mesh_candidate(run, state, nodes, keep, obj_pos, geometry,
                                     refine=refine, progress=progress)
    if mesh is None:
        skipped.append(probe)
        return measurement_candidates(obj_pos), None
    return measurement_candidates(obj_pos) + [mesh], probe


@dataclass
class Plan:
    """The model variants to evaluate: ``variants`` {name: model} (``base``, a log step of
    each fitted parameter ``theta|q``, each candidate switched on ``cand|name`` and a log step
    of each of its parameters ``cand|name|f``), the log ``steps`` and the fitted values
    ``theta0``."""

    variants: dict[str, dict]
    steps: dict[str, float]
    theta0: dict[str, float]


def _plan_variants(cfg, model, fitted: Sequence[str],
                   candidates: Sequence[Candidate]) -> Plan:
    """The variants whose residuals linearise the fitted model and every candidate."""
    from breastmodel.pipeline.config import get_param, set_params

    variants: dict[str, dict] = {"base": model}
    steps: dict[str, float] = {}
    theta0 = {}
    for q in fitted:
        v = float(get_param(model, q))
        lo, hi = fit_bounds(cfg, q)
        theta0[q] = v
        steps[f"theta|{q}"] = h = log_step(v, lo, hi)
        variants[f"theta|{q}"] = set_params(model, {q: v * math.exp(h)})
    for c in candidates:
        cm = set_params(c.apply(model), c.start)
        if c.effects:
            variants[f"cand|{c.name}"] = cm
        for f, (lo, hi) in c.free.items():
            v = float(c.start.get(f, get_param(cm, f) or 1.0))
            steps[f"cand|{c.name}|{f}"] = h = log_step(v, lo, hi)
            variants[f"cand|{c.name}|{f}"] = set_params(cm, {f: v * math.exp(h)})
    return Plan(variants, steps, theta0)


@dataclass
class _Evaluations:
    """The evaluated variants: ``records`` {variant: sweep record}, the fitted model's
    ``base_record`` and solution ``base_state``, the sweep's ``points``, the budget ``limits``
    (forward solves, seconds) and the ``cost`` of every evaluation."""

    records: dict[str, dict]
    base_record: dict
    base_state: dict
    points: list[dict]
    limits: tuple[int, float]
    cost: dict[str, dict]


def _evaluate_variants(run, plan: Plan, positions: Sequence[str], work_dir: Path, *,
                       n_candidates: int, limits: tuple[int | None, float | None],
                       scheduler: str | None, n_workers: int, progress: bool) -> _Evaluations:
    """Evaluate the fitted model (stored, its solution the others' warm start), then every
    variant as a point of a sweep within the budget ``limits`` (default from the fitted
    model's own evaluation)."""
    from breastmodel.sweep import run_sweep

    cfg, model = run.config, run.model
    settings = {"solver": cfg["solver"], "stress_free": cfg["stress_free"],
                "positions": positions}
    base_rec, base_state = base_evaluation(model, run.problem_dir, settings, work_dir)
    if base_rec["status"] != "ok":
        raise RuntimeError(f"diagnose: the fitted model itself failed to solve: "
                           f"{base_rec['error']}")
    auto = default_budget(int(base_rec["result"]["solves"]), float(base_rec["result"]["eval_s"]))
    max_solves, max_seconds = limits
    limits = (int(max_solves) if max_solves else auto[0],
              float(max_seconds) if max_seconds else auto[1])
    points = [{"variant": k, "model": model_hash(m)} for k, m in plan.variants.items()
              if k != "base"]
    if progress:
        print(f"diagnose: {n_candidates} candidates, {len(points) + 1} model evaluations "
              f"(stored in {work_dir}; each within {limits[0]} forward solves and "
              f"{limits[1]:.0f} s)", flush=True)
    fn = functools.partial(variant_point, variants=plan.variants,
                           problem_dir=str(run.problem_dir), settings=settings, limits=limits,
                           start=base_state)
    recs = run_sweep(fn, points, work_dir, scheduler=scheduler, n_workers=n_workers,
                     progress=progress, retry_failed=True)
    res = {p["variant"]: r for p, r in zip(points, recs)}
    res["base"] = base_rec
    cost = {k: {"status": r["status"], "solves": (r["result"] or {}).get("solves"),
                "seconds": (r["result"] or {}).get("eval_s", r.get("wall_s"))}
            for k, r in res.items()}
    return _Evaluations(res, base_rec, base_state, points, limits, cost)


def _result(run, ev: _Evaluations, lin: Linearisation, base: Baseline, plan: Plan,
            ranking: list, corrections: dict, *, skipped, failed, fitted, obj_pos,
            rim_mm: float, landmark_check: dict | None) -> dict:
    """The diagnosis' JSON-ready result (see :func:`rank_candidates`)."""
    base_mhd = ev.records["base"]["result"]["mhd_mm"]
    best = answer(ranking)
    if best is not None:
        verdict = verdict_sentence(best, base.rms_base)
    else:
        worst = sorted(base.regions.items(), key=lambda kv: -kv[1])[:3]
        carriers = ", ".join(f"{k} ({v:.2f} mm)" for k, v in worst)
        verdict = (f"no candidate explains more than the noise (floor {base.floor:.3f} mm, "
                   f"residual RMS {base.rms_base:.3f} mm): the residual is noise, or the "
                   f"missing effect is not in the library; the largest residuals are at "
                   f"{carriers}")
    for r in ranking:
        if r.get("unconfirmed"):
            u = r["unconfirmed"]
            verdict = (f"{verdict}; {r['name']} looked significant by its linear estimate, "
                       f"but its re-fit left the worst MHD at {u['worst_mhd_after_mm']:.2f} mm "
                       f"({u['worst_mhd_before_mm']:.2f} mm before): not confirmed")
    mesh = next((r for r in ranking if r["measurement"] == "refinement"), None)
    if best is not None and mesh is not None and mesh["significant"] and mesh is not best:
        verdict = f"{verdict}; {mesh_sentence(mesh)}"
    refit = {q: plan.theta0[q] * math.exp(zq) for q, zq in base.z_base.items()}
    confounding = confounders(ranking, refit)
    if confounding:
        verdict = f"{verdict}; {confounding_sentence(confounding)}"
    # where each of the best candidates acts: its predicted change of the residual, beside
    # the residual it is to explain (over the scored nodes, in canonical skin-node order)
    keep = lin.keep
    shown = [r["name"] for r in ranking[:MAPPED]]
    maps = {"index": np.flatnonzero(keep).tolist(), "n_skin_nodes": int(len(keep)),
            "positions": list(obj_pos), "residual": base.r_base.tolist(),
            "corrections": {k: corrections[k].tolist() for k in shown}}
    return {
        "positions": list(run.positions), "objective_positions": obj_pos,
        "noise_floor_mm": base.floor, "noise_floor_from": base.floor_from,
        "baseline": {"rms_mm": base.rms_now, "rms_after_refit_mm": base.rms_base,
                     "per_position": lin.per_position(base.r_base), "mhd_mm": base_mhd,
                     "refit_estimate": refit},
        "fitted_parameters": fitted, "confounders": confounding,
        "rim_mm": float(rim_mm), "n_skin_nodes": int(len(keep)),
        "n_scored_nodes": int(keep.sum()),
        "ranking": ranking, "skipped": skipped, "failed": failed,
        "budget": {"max_solves": ev.limits[0], "max_seconds": ev.limits[1],
                   "base_solves": ev.base_record["result"]["solves"],
                   "base_seconds": ev.base_record["result"]["eval_s"]},
        "evaluations": ev.cost,
        "n_effective": base.n_eff, "calibrate": base.calibrate, "held_out": base.held_out,
        "correction_maps": maps,
        "landmark_check": landmark_check,
        "n_evaluations": len(ev.points) + 1 + sum(
            r.get(k, {}).get("evaluations", 0) for r in ranking
            for k in ("verified", "landmark_refit")), "verdict": verdict,
    }
