"""The mesh-refinement probe: a finished run's fitted model again on a finer mesh.

The measured skins and the fitted parameters stay; the reference's label map is meshed at a
smaller edge length, and the stress-free geometry and every position's prediction are made on
that mesh (cached stages labelled ``refinement: ...``). ``[evaluate] refinement = true``
reports the change of each position's MHD (:func:`refinement_check`); the diagnosis scores
the change of the predicted skin as its ``mesh_refinement`` candidate (:func:`refine_run`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from breastmodel.errors import StageError
from breastmodel.pipeline.model_stages import n_tets, predict_stage, stress_free_stage
from breastmodel.pipeline.runner import Prepared
from breastmodel.pipeline.subject_stages import (
    mesh_key,
    mesh_options,
    mesh_stage,
    problem_stage,
    reference_labels,
)

__all__ = ["refine_run", "refinement_check", "refinement_stages"]


def refinement_stages(prep: Prepared, cfg: Mapping[str, Any], model: Mapping[str, Any],
                      positions, size_mm: float) -> dict:
    """The model (at its fitted parameters) again on a mesh of edge ``size_mm``: its mesh,
    problem, stress-free geometry and each position's prediction, cached stages labelled
    ``refinement: ...``. The measured skins are the run's (they do not depend on the mesh).

    Returns
    -------
    dict: ``problem_dir``, ``stress_free_dir`` and ``predict_dirs`` {position: folder}
    """
    R, ref = prep.runner, prep.subject.reference
    fine = {**cfg, "mesh": {**cfg["mesh"], "size_mm": size_mm}}
    mesh_dir, m_key = R.stage("mesh", mesh_key(fine["mesh"]), [prep.segment_keys[ref]],
                              mesh_stage(reference_labels(prep.segment_dirs, ref),
                                         mesh_options(fine)),
                              label=f"refinement: mesh {size_mm:g} mm")
    prob_dir, prob_key = R.stage("problem", {}, [m_key, *prep.problem_inputs],
                                 problem_stage(prep.subject, prep.register_dir, mesh_dir,
                                               prep.problem_dir),
                                 label=f"refinement: problem {size_mm:g} mm")
    sf_dir, sf_key = R.stage("stress_free", {"model": model, "stress_free": cfg["stress_free"],
                                             "solver": cfg["solver"]}, [prob_key],
                             stress_free_stage(prob_dir, cfg, model, R.progress),
                             label="refinement: stress-free")
    pred = {}
    for pos in positions:
        pred[pos], _ = R.stage("predict", {"position": pos, "model": model,
                                           "solver": cfg["solver"]}, [prob_key, sf_key],
                               predict_stage(prob_dir, sf_dir, pos, cfg, model),
                               label=f"refinement: predict {pos}")
    return {"problem_dir": prob_dir, "stress_free_dir": sf_dir, "predict_dirs": pred}


def refinement_check(prep: Prepared, cfg: Mapping[str, Any], model: Mapping[str, Any],
                     pred_dirs: Mapping[str, Path]) -> dict:
    """The prediction at the model's (fitted) parameters again on a mesh of half the edge
    length: the change of each position's MHD bounds what the mesh size costs.

    Returns
    -------
    dict
        ``size_mm``, ``fine_size_mm``, ``n_tets``, ``fine_n_tets`` and per position
        ``mhd_mm``, ``fine_mhd_mm``, ``change_mm`` (fine minus default); or ``skipped`` with
        the reason (a given problem folder has no label map to remesh).
    """
    if prep.register_dir is None:
        return {"skipped": "a given problem folder has no label map to remesh"}
    h = _mesh_size(prep, cfg)
    fine = refinement_stages(prep, cfg, model, list(pred_dirs), h / 2)
    out = {"size_mm": h, "fine_size_mm": h / 2, "positions": {},
           "n_tets": n_tets(prep.problem_dir), "fine_n_tets": n_tets(fine["problem_dir"])}
    for pos, d in pred_dirs.items():
        a = json.loads((d / "metrics.json").read_text())["mhd_mm"]
        b = json.loads((fine["predict_dirs"][pos] / "metrics.json").read_text())["mhd_mm"]
        out["positions"][pos] = {"mhd_mm": a, "fine_mhd_mm": b, "change_mm": b - a}
    return out


def refine_run(run_dir: str | Path, *, factor: float = 0.5, progress: bool = True) -> dict:
    """The mesh-refinement probe of a finished subject run: its fitted model on a mesh of
    ``factor`` times its edge length, the stages cached in the run's own cache (a run made
    with ``[evaluate] refinement = true`` has them already); the probe's config and
    provenance go to ``run_dir/refinement``.

    Returns
    -------
    dict: ``size_mm``, ``fine_size_mm``, ``n_tets``, ``fine_n_tets`` and the folders of
    :func:`refinement_stages`

    Raises
    ------
    StageError
        The run was made from a given problem folder (no label map to remesh), or a stage
        meets bad input (its subject folder gone, say).
    """
    import tomllib

    from breastmodel.pipeline.config import load_run_config
    from breastmodel.pipeline.run import cache_of, prepare_subject

    run_dir = Path(run_dir)
    raw = tomllib.loads((run_dir / "config.toml").read_text())
    stages = json.loads((run_dir / "stages.json").read_text())["stages"]
    if not any(s["name"] == "register" for s in stages):
        raise StageError("refinement", "the run was made from a given problem folder: no "
                         "label map to remesh", run_dir / "stages.json")
    cfg = load_run_config(run_dir / "config.toml", drop=("subject",))
    model = json.loads((run_dir / "params.json").read_text())["model"]
    positions = json.loads((run_dir / "metrics.json").read_text())["positions"]
    prep = prepare_subject(raw["subject"], cfg, run_dir / "refinement", progress=progress,
                           cache=cache_of(run_dir), command="refinement")
    h = _mesh_size(prep, cfg)
    fine_h = round(factor * h, 2)
    fine = refinement_stages(prep, cfg, model, list(positions), fine_h)
    return {"size_mm": h, "fine_size_mm": fine_h, "n_tets": n_tets(prep.problem_dir),
            "fine_n_tets": n_tets(fine["problem_dir"]), **fine}


def _mesh_size(prep: Prepared, cfg: Mapping[str, Any]) -> float:
    """The element edge the run's mesh was made with, mm ("auto" resolved)."""
    meta = json.loads((prep.problem_dir / "problem.json").read_text())
    return float(meta.get("mesh_size_mm", cfg["mesh"]["size_mm"]))
