"""Stage bodies of the model half of the pipeline: fit, stress-free geometry, predict and
score one position; each returns the function that fills its stage folder."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.errors import StageError

log = logging.getLogger("breastmodel.pipeline")


def fit_stage(problem_dir: Path, cfg: Mapping[str, Any], settings: Mapping[str, Any],
              out: Path, progress: bool):
    """The fit (``fit.json``); its evaluations are kept under ``out/fit``. Where the search
    stored its best evaluation's solution, ``start.npz`` holds it (``X`` and ``u_<position>``
    of every position solved): the stress-free and predict stages start from it."""

    def fn(d: Path) -> None:
        from breastmodel.config import write_json
        from breastmodel.pipeline.fit import fit_parameters, fit_work_dir
        from breastmodel.pipeline.fit_evaluations import stored_solution
        from breastmodel.sweep import point_key

        work = fit_work_dir(out / "fit", problem_dir, settings)
        res = fit_parameters(problem_dir, settings, cfg["fit"], work_dir=work,
                             progress=progress)
        key = point_key(res["best"]["params"])
        X, u = None, {}
        for search in ("least_squares", "optimizer", "held_out"):  # the held-out positions' u
            stored = stored_solution(work / search, key)
            if stored is not None:
                X = stored[0] if X is None else X
                u.update(stored[1])
        if X is not None:
            np.savez(d / "start.npz", X=X, **{f"u_{p}": v for p, v in u.items()})
        write_json(d / "fit.json", res)
    return fn


def fit_start(fit_dir: Path | None) -> dict | None:
    """The fit's best solution (``{"X", "u": {position: displacement}}``, mm) from its stage
    folder, or None (no fit, or a search that keeps no solutions: the grid)."""
    if fit_dir is None or not (fit_dir / "start.npz").is_file():
        return None
    with np.load(fit_dir / "start.npz") as z:
        return {"X": z["X"], "u": {k[2:]: z[k] for k in z.files if k.startswith("u_")}}


def stress_free_stage(problem_dir: Path, cfg: Mapping[str, Any], model: Mapping[str, Any],
                      progress: bool, start: dict | None = None):
    """The stress-free geometry of ``model`` (``X.npy``, ``stress_free.json``); ``start``
    (:func:`fit_start`): the inverse starts from the fit's solution of this model."""

    def show(row: dict) -> None:
        print(f"     iteration {row['iteration']:2d}: node mismatch mean "
              f"{row['mean_error']:.4f} mm, max {row['max_error']:.4f} mm", flush=True)

    def fn(d: Path) -> None:
        from breastmodel.config import write_json
        from breastmodel.pipeline.problem import load_problem, stress_free_geometry
        from mechanics.solver import SolverError

        problem = load_problem(problem_dir)
        try:
            X, info = stress_free_geometry(
                problem, model, cfg["stress_free"], cfg["solver"],
                callback=show if progress else None,
                start=None if start is None else (start["X"],
                                                  start["u"].get(problem.reference)))
        except SolverError as exc:
            raise StageError("stress-free", f"forward solve failed: {exc}") from None
        np.save(d / "X.npy", X)
        write_json(d / "stress_free.json", info)
    return fn


def predict_stage(problem_dir: Path, sf_dir: Path, position: str, cfg: Mapping[str, Any],
                  model: Mapping[str, Any], start: dict | None = None):
    """Predict ``position`` from the stress-free geometry in ``sf_dir`` and score it
    (``predicted.npz``, ``metrics.json``); a solve that stops short is scored at its last
    converged state. ``start`` (:func:`fit_start`): Newton starts from the fit's
    displacement of this position where it has one."""

    def fn(d: Path) -> None:
        from breastmodel.config import write_json
        from breastmodel.pipeline.problem import load_problem, predict_position, score_position
        from mechanics.solver import SolverError

        problem = load_problem(problem_dir)
        X = np.load(sf_dir / "X.npy")
        error = verdict = None
        try:
            u0 = None if start is None else start["u"].get(position)
            state = predict_position(problem, model, X, position, cfg["solver"], u0=u0)
        except SolverError as exc:
            if exc.state is None:
                raise StageError("predict", f"position {position!r}: {exc}") from None
            state, error, verdict = exc.state, str(exc), exc.verdict
            log.warning("predict: %s %s (%s); scoring the last converged state", position,
                        "has no equilibrium" if verdict else "did not converge", exc)
        x = state.x
        m = score_position(problem, x, position, details=True)
        fields = {"X": state.X, "stress": np.asarray(state.stress).reshape(-1, 9),
                  "J": state.J}
        if state.pressure is not None:
            fields["pressure"] = state.pressure
        np.savez(d / "predicted.npz", x=x, signed_error=m.pop("signed_error"),
                 skin_nodes=m.pop("skin_nodes"), **fields)
        m.update(converged=bool(state.converged), load_reached=float(state.load),
                 newton_iterations=state.newton_iterations, error=error, verdict=verdict,
                 max_displacement_mm=float(state.max_displacement()))
        write_json(d / "metrics.json", m)
    return fn


def check_landmarks(problem_dir: Path, settings: Mapping[str, Any]) -> None:
    """A fit that sees the landmarks needs some in the reference and in every calibration
    position: fail before the first solve otherwise."""
    if "landmarks" not in settings["sees"]:
        return
    meta = json.loads((problem_dir / "problem.json").read_text())
    lm = meta.get("landmarks", {})
    ref = set(lm.get(meta["reference"], {}))
    missing = [p for p in settings["calibrate"] if not ref & set(lm.get(p, {}))]
    if missing:
        raise StageError("fit", f"[fit] sees = {settings['sees']} needs landmarks known in "
                         f"the reference ({meta['reference']}) and in {missing} "
                         "(landmarks.csv in the subject folder)", problem_dir / "problem.json")


def n_tets(problem_dir: Path) -> int:
    """The number of tetrahedra of a problem folder's mesh."""
    with np.load(problem_dir / "mesh.npz") as z:
        return int(len(z["tets"]))
