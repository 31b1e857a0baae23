"""The prepared problem of a subject and the model computations on it.

A *problem folder* holds everything the mechanics and the scoring need, in the reference
frame: ``mesh.npz`` (built from the reference position's labels), ``gravity.json``
(position -> unit gravity vector), ``<position>_skin.npz`` (measured skin: ``vertices``
(n, 3) mm, ``triangles`` (m, 3)) and ``landmarks.json`` (position -> name -> (3,) mm).
Workers of a sweep read it from disk, so :func:`evaluate_params` is a picklable
module-level function of (parameters, folder, settings). The scores of a prediction
(:func:`score_position`, the landmarks) are in :mod:`breastmodel.pipeline.scoring` and
importable from here.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.pipeline.config import materials_by_code, set_params
from breastmodel.pipeline.scoring import (
    RIM_FADE_MM,
    fit_residual,
    landmark_barycentric,
    predicted_landmarks,
    record_landmarks,
    score_position,
    skin_node_regions,
    skin_residual,
)

log = logging.getLogger("breastmodel.pipeline")

__all__ = [
    "RIM_FADE_MM", "Problem", "evaluate_params", "forget_problem", "landmark_barycentric",
    "load_problem", "mesh_of", "model_mesh", "move_measured_skin", "on_mesh", "position_model",
    "skin_nodes", "predict_position", "predicted_landmarks", "score_position",
    "skin_node_regions", "skin_residual", "solver_options", "stress_free_geometry",
]


@dataclass(frozen=True, eq=False)
class Problem:
    """mesh : mechanics.mesh.Mesh (reference-position geometry, mm)
    gravity : position -> (3,) unit vector in the reference frame
    skins : position -> (vertices (n, 3) mm, triangles (m, 3)) measured skin
    landmarks : position -> {name: (3,) mm} in the reference frame (may be empty)
    reference : name of the reference position
    """

    mesh: Any
    gravity: Mapping[str, np.ndarray]
    skins: Mapping[str, tuple[np.ndarray, np.ndarray]]
    landmarks: Mapping[str, Mapping[str, np.ndarray]]
    reference: str
    _split: dict = field(default_factory=dict, repr=False)  # the split mesh, made once


def model_mesh(problem: Problem, model: Mapping[str, Any]):
    """The mesh a model runs on: the problem's conforming mesh, or (when an effect of the
    model declares ``split_interface``) the same mesh with the interface nodes duplicated,
    the breast copies appended after the original nodes at the same positions."""
    from mechanics.effects import needs_split_interface

    if not needs_split_interface(model["effects"]):
        return problem.mesh
    return _split_mesh(problem)


def _split_mesh(problem: Problem):
    """The problem's mesh with its interface split (made once per problem)."""
    if "interface_muscle" in problem.mesh.face_sets:
        return problem.mesh
    if "mesh" not in problem._split:
        from mechanics.effects._interface import split_interface

        problem._split["mesh"] = split_interface(problem.mesh)
    return problem._split["mesh"]


def skin_nodes(problem: Problem, n_nodes: int) -> np.ndarray:
    """Skin node indices in one canonical order (that of the conforming mesh), mapped into
    the mesh with ``n_nodes`` nodes: residuals of conforming and split models line up."""
    nodes = np.unique(np.asarray(problem.mesh.face_sets["skin"]))
    if n_nodes == problem.mesh.n_nodes:
        return nodes
    mesh_of(problem, n_nodes)  # checks the count
    shared = np.unique(np.asarray(problem.mesh.face_sets["interface"]))
    new_id = np.arange(problem.mesh.n_nodes)
    new_id[shared] = problem.mesh.n_nodes + np.arange(len(shared))
    return new_id[nodes]


def on_mesh(problem: Problem, a: np.ndarray, n_nodes: int) -> np.ndarray | None:
    """Per-node values ``a`` of the conforming or split mesh on the one with ``n_nodes``
    nodes (a breast copy takes its original's value, as where the sides were bonded), or
    None where ``a`` fits neither."""
    a = np.asarray(a)
    if len(a) == n_nodes:
        return a
    n_conf, n_split = problem.mesh.n_nodes, _split_mesh(problem).n_nodes
    if (len(a), n_nodes) == (n_conf, n_split):
        return np.concatenate([a, a[np.unique(np.asarray(problem.mesh.face_sets["interface"]))]])
    return a[:n_conf] if (len(a), n_nodes) == (n_split, n_conf) else None


def mesh_of(problem: Problem, n_nodes: int):
    """The problem mesh (conforming or split) that has ``n_nodes`` nodes."""
    if n_nodes == problem.mesh.n_nodes:
        return problem.mesh
    split = _split_mesh(problem)
    if n_nodes != split.n_nodes:
        raise ValueError(f"pipeline: {n_nodes} node positions fit neither the problem mesh "
                         f"({problem.mesh.n_nodes} nodes) nor its split ({split.n_nodes})")
    return split


_PROBLEMS: dict[str, Problem] = {}  # per process: workers evaluate many points on one problem


def load_problem(folder: str | Path) -> Problem:
    """Read a problem folder (memoised per process by its absolute path)."""
    from mechanics.mesh import Mesh

    key = str(Path(folder).resolve())
    if key not in _PROBLEMS:
        folder = Path(folder)
        meta = json.loads((folder / "problem.json").read_text())
        gravity = {k: np.asarray(v, float) for k, v in meta["gravity"].items()}
        skins = {}
        for pos in gravity:
            with np.load(folder / f"{pos}_skin.npz") as z:
                skins[pos] = (z["vertices"].copy(), z["triangles"].copy())
        landmarks = {p: {n: np.asarray(v, float) for n, v in d.items()}
                     for p, d in meta.get("landmarks", {}).items()}
        _PROBLEMS[key] = Problem(Mesh.load_npz(folder / "mesh.npz"), gravity, skins, landmarks,
                                 meta["reference"])
    return _PROBLEMS[key]


def forget_problem(folder: str | Path) -> None:
    """Drop a problem folder from this process's memo (after its files were rewritten)."""
    _PROBLEMS.pop(str(Path(folder).resolve()), None)


def move_measured_skin(folder: str | Path, position: str, move) -> np.ndarray:
    """Rewrite a problem folder's measured skin of ``position`` as ``move(vertices,
    triangles)`` (a known error put into the data: a misregistration, a segmentation offset)
    and drop the folder from the memo. Returns the vertices before the move."""
    path = Path(folder) / f"{position}_skin.npz"
    with np.load(path) as z:
        v, t = z["vertices"].copy(), z["triangles"].copy()
    np.savez(path, vertices=move(v, t), triangles=t)
    forget_problem(folder)
    return v


def solver_options(solver: Mapping[str, Any]):
    """``SolverOptions`` from the ``[solver]`` table."""
    from mechanics.solver import SolverOptions

    return SolverOptions(**dict(solver))


def position_model(problem: Problem, model: Mapping[str, Any], position: str):
    """The loaded model of one position: materials, effects and that position's gravity.

    Parameters
    ----------
    problem : Problem
    model : the resolved ``[model]`` table (materials by region name, effects, density kg/m^3,
        g m/s^2, formulation)
    position : position name (its gravity comes from the problem)
    """
    from mechanics.effects.gravity import Gravity
    from mechanics.model import build_model

    mesh = model_mesh(problem, model)
    effects = {k: v for k, v in model["effects"].items()}
    effects[Gravity.name] = {"direction": tuple(float(v) for v in problem.gravity[position]),
                          "density": float(model["density"]), "g": float(model["g"])}
    mats = materials_by_code(model, np.unique(mesh.region))
    return build_model(mesh, mats, effects, formulation=model["formulation"])


def _paper_position(problem: Problem, sf: Mapping[str, Any]) -> str:
    pos = sf.get("position")
    if pos is None:
        others = [p for p in problem.gravity if p != problem.reference]
        pos = "prone" if "prone" in others else others[0]
    if pos not in problem.gravity:
        raise ValueError(f"stress-free: position {pos!r} is not among {sorted(problem.gravity)}")
    return pos


def stress_free_geometry(problem: Problem, model: Mapping[str, Any], sf: Mapping[str, Any],
                         solver: Mapping[str, Any], *,
                         callback: Callable[[dict], None] | None = None,
                         before_solve: Callable[[], None] | None = None,
                         start: tuple[np.ndarray, np.ndarray | None] | None = None,
                         solved: dict | None = None):
    """Stress-free node positions by the method of the ``[stress_free]`` table.

    ``"inverse"``: full-field inverse of the reference position (its mesh nodes are measured
    loaded positions), Anderson-accelerated. ``"paper"``: the paper's fixed point on the
    measured skin of ``sf["position"]`` (default prone). ``"none"``: the reference geometry.
    ``before_solve`` is called before every forward solve (it may raise: a caller's budget);
    ``start`` = (X0, u0) warm-starts the inverse from a nearby model's solution (mm).
    ``solved``: filled with {position: State} for the positions already solved from the
    returned X (a converged inverse ends with the reference position's forward solve from
    it: a caller that predicts that position need not solve it again).

    Returns
    -------
    X : (N, 3) mm
    info : dict (method, converged, history rows, forward solves)

    Raises
    ------
    mechanics.solver.SolverError
        When the very first forward solve fails.
    """
    from breastmodel.evaluation import TriangleSurface
    from mechanics.stress_free import inverse_fixed_point, paper_fixed_point

    mesh = model_mesh(problem, model)
    opts = solver_options(solver)
    method = sf["method"]
    if method == "none":
        return np.array(mesh.nodes, float), {"method": "none", "converged": True, "history": []}
    if method == "inverse":
        m = position_model(problem, model, problem.reference)
        X0, u0 = start if start is not None else (None, None)
        res = inverse_fixed_point(m, mesh.nodes, tol=float(sf["tol_mm"]),
                                  max_iter=int(sf["max_iter"]), anderson=int(sf["anderson"]),
                                  X0=X0, u0=u0, options=opts, callback=callback,
                                  before_solve=before_solve)
        pos = problem.reference
        if solved is not None and res.converged:
            solved[pos] = res.state
    else:
        pos = _paper_position(problem, sf)
        m = position_model(problem, model, pos)
        surf = TriangleSurface(*problem.skins[pos])
        active = np.unique(mesh.face_sets["skin"])
        res = paper_fixed_point(m, lambda y: surf.closest(y)[0], active,
                                mesh.node_sets["fixed"], lam=float(sf["lam"]),
                                min_improvement=float(sf["min_improvement_mm"]),
                                max_iter=int(sf["max_iter"]), options=opts, callback=callback,
                                before_solve=before_solve)
    info = {"method": res.method, "position": pos, "converged": bool(res.converged),
            "forward_solves": len(res.history), "history": [dict(r) for r in res.history]}
    return np.asarray(res.X, float), info


def predict_position(problem: Problem, model: Mapping[str, Any], X: np.ndarray, position: str,
                     solver: Mapping[str, Any], *, u0: np.ndarray | None = None):
    """Forward solve of one position from the stress-free geometry X; returns the State.

    Raises
    ------
    mechanics.solver.SolverError
        Divergence (``.state`` holds the last converged state).
    """
    from mechanics.solver import solve

    m = position_model(problem, model, position)
    return solve(m, X=X, u0=u0, options=solver_options(solver))


def evaluate_params(params: Mapping[str, float], problem_dir: str | Path,
                    settings: Mapping[str, Any], *, residuals: bool = False,
                    start: np.ndarray | None = None, keep_X: bool = False,
                    u_start: Mapping[str, np.ndarray] | None = None) -> dict:
    """The fitting objective: stress-free estimate -> forward solve of every calibration
    position -> MHD on the skin and/or mean landmark error (``settings["sees"]``). Never
    raises for a failed solve (NaN instead).

    Parameters
    ----------
    params : parameter path -> value (e.g. ``{"materials.breast_left.E": 0.8}``, kPa)
    problem_dir : problem folder (see the module notes)
    settings : ``{"model", "solver", "stress_free"}`` tables of the resolved config and
        ``"calibrate"`` (position names), optionally ``"evaluate"`` (also scored, not in
        the objective) and ``"sees"`` (``pipeline.config.FIT_SEES``; default ``["skin"]``)
    residuals : also return ``residual`` and ``residual_offset`` {calibration position: the
        fit's vector, and its change per mm the measured skin moves outward}
    start : (N, 3) stress-free geometry of a nearby parameter vector, mm: the stress-free
        inverse starts from it (a fit's warm start; None: from the reference geometry)
    keep_X : also return ``X``, the stress-free geometry (once it is found), and ``u``
        {position: displacement from X, mm} of every position solved
    u_start : {position: displacement, mm} of a nearby parameter vector (the ``u`` it
        returned): each forward solve of that position starts its Newton iterations from it
        at full load instead of ramping the load (measured on the suite's full-000, 46k
        tets: prone 15 -> 7 Newton iterations, 2.2 -> 1.2 s)

    Returns
    -------
    dict
        ``objective`` (mean over the calibration positions and the seen measurements of the
        skin MHD and the mean landmark error, mm; NaN on failure), ``mhd_mm`` {position:
        mm}, ``landmarks_mm`` {position: mean landmark error, mm; when seen},
        ``landmark_errors_mm`` {position: each landmark's error, mm; seen or not},
        ``forward_solves``, ``wall_s``, ``error`` (str or None).
    """
    t0 = time.perf_counter()
    problem = load_problem(problem_dir)
    model = set_params(settings["model"], params)
    calibrate = list(settings["calibrate"])
    positions = calibrate + [p for p in settings.get("evaluate") or () if p not in calibrate]
    sees = list(settings.get("sees") or ["skin"])
    out: dict[str, Any] = {"objective": math.nan, "mhd_mm": {}, "landmarks_mm": {},
                           "landmark_errors_mm": {}, "forward_solves": 0, "error": None,
                           **({"residual": {}, "residual_offset": {}} if residuals else {})}
    if start is not None and len(start) != model_mesh(problem, model).n_nodes:
        start = None  # another mesh (an effect that splits the interface): no warm start
    u_start = dict(u_start or {}) if start is not None else {}
    try:
        solved: dict = {}
        X, info = stress_free_geometry(
            problem, model, settings["stress_free"], settings["solver"], solved=solved,
            start=None if start is None else (start, u_start.get(problem.reference)))
        out["forward_solves"] += len(info["history"])
        if keep_X:
            out["X"], out["u"] = X, {p: st.u for p, st in solved.items()}
        for pos in positions:
            try:
                state = solved[pos] if pos in solved else _predict_counted(
                    problem, model, X, pos, settings["solver"], out, u_start.get(pos))
                if keep_X:
                    out["u"][pos] = state.u
            except Exception:
                if pos in calibrate:
                    raise
                out["mhd_mm"][pos] = math.nan  # a held-out failure does not void the point
                continue
            out["mhd_mm"][pos] = score_position(problem, state.x, pos)["mhd_mm"]
            lm = record_landmarks(out, problem, state.x, pos, sees)
            if residuals and pos in calibrate:
                _store_residual(out, problem, state.x, pos, sees, lm)
        out["objective"] = float(np.mean(
            [out["mhd_mm"][p] for p in calibrate if "skin" in sees]
            + [out["landmarks_mm"][p] for p in calibrate if p in out["landmarks_mm"]]))
    except Exception as exc:  # noqa: BLE001 - one failed point must not end a fit or sweep
        # (SolverError, inverted elements, and any failure inside the stress-free iteration
        # are recorded with their type; a fit where every point fails reports the first)
        out["error"] = f"{type(exc).__name__}: {exc}"
    out["wall_s"] = time.perf_counter() - t0
    return out


def _predict_counted(problem: Problem, model: Mapping[str, Any], X: np.ndarray, pos: str,
                     solver: Mapping[str, Any], out: dict, u0: np.ndarray | None):
    """:func:`predict_position`, counted in ``out["forward_solves"]`` (failed or not)."""
    try:
        return predict_position(problem, model, X, pos, solver, u0=u0)
    finally:
        out["forward_solves"] += 1


def sweep_point(point: Mapping[str, float], *, problem_dir: str,
                settings: Mapping[str, Any]) -> dict:
    """:func:`evaluate_params` in the form ``run_sweep`` calls (use functools.partial)."""
    return evaluate_params(point, problem_dir, settings)


def _store_residual(out: dict, problem: Problem, x: np.ndarray, position: str,
                    sees: Sequence[str], lm) -> None:
    """Put the least squares' residual of one position and its change per mm the measured
    skin moves outward (:func:`~breastmodel.pipeline.scoring.fit_residual` of the skin
    nodes) in ``out["residual"]`` and ``out["residual_offset"]``."""
    r, g = fit_residual(x[skin_nodes(problem, len(x))], problem.skins[position], lm, sees)
    out["residual"][position], out["residual_offset"][position] = r.tolist(), g.tolist()


def fit_settings(cfg: Mapping[str, Any], positions: Sequence[str], reference: str) -> dict:
    """Settings of :func:`evaluate_params` from a resolved run config.

    Calibration positions default to prone and the reference (the paper's calibration),
    evaluation positions to the rest. ``search_tol_mm``: the stress-free tolerance of a
    search's evaluations (``[fit] stress_free_tol_mm``, see :func:`breastmodel.pipeline.fit
    .least_squares`).
    """
    fit = cfg["fit"]
    cal = fit["calibrate"] or [p for p in ("prone", reference) if p in positions]
    cal = list(dict.fromkeys(cal))
    ev = fit["evaluate"] if fit["evaluate"] is not None else [p for p in positions
                                                            if p not in cal]
    for p in [*cal, *ev]:
        if p not in positions:
            raise ValueError(f"fit: position {p!r} is not among the subject's {sorted(positions)}")
    return {"model": cfg["model"], "solver": cfg["solver"], "stress_free": cfg["stress_free"],
            "calibrate": cal, "evaluate": list(ev), "sees": list(fit["sees"]),
            "search_tol_mm": float(fit["stress_free_tol_mm"])}
