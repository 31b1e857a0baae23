"""The run's outputs: metrics.json, predicted surfaces (PLY), params.json and report.html."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_outputs"]

_SUMMARY_KEYS = ("mhd_mm", "hausdorff_mm", "rmse_mm", "p95_mm", "median_mm",
                 "mean_pred_to_meas_mm", "mean_meas_to_pred_mm", "n_pred", "n_meas",
                 "converged", "load_reached", "max_displacement_mm", "error")


def write_outputs(out: Path, problem_dir: Path, sf_dir: Path, pred_dirs: Mapping[str, Path],
                  params: Mapping[str, Any], fit_info: Mapping[str, Any] | None, *,
                  subject_id: str) -> dict:
    """Assemble the run's outputs from finished stages (cheap; redone on every run).

    Writes ``out/metrics.json`` ({"positions": {position: {mhd_mm, hausdorff_mm, rmse_mm,
    p95_mm, ..., "regions": {...}, "landmarks": {...}}}, "stress_free": {...}}),
    ``out/<position>_predicted.ply`` (reference frame, mm), ``out/params.json`` and
    ``out/report.html``. Returns the metrics dict.
    """
    from breastmodel.config import write_json
    from breastmodel.pipeline.problem import load_problem, mesh_of
    from breastmodel.pipeline.report import write_report
    from meshing.export import write_ply

    problem = load_problem(problem_dir)
    sf = json.loads((sf_dir / "stress_free.json").read_text())
    metrics: dict[str, Any] = {"subject": subject_id, "reference": problem.reference,
                               "units": "mm", "positions": {},
                               "stress_free": {k: v for k, v in sf.items() if k != "history"}}
    pictures = {}
    for pos, d in pred_dirs.items():
        m = json.loads((d / "metrics.json").read_text())
        metrics["positions"][pos] = {**{k: m[k] for k in _SUMMARY_KEYS if k in m},
                                     "regions": m.get("regions", {}),
                                     **({"landmarks": m["landmarks"]} if "landmarks" in m
                                        else {})}
        with np.load(d / "predicted.npz") as z:
            x, err, nodes = z["x"], z["signed_error"], z["skin_nodes"]
        faces = np.asarray(mesh_of(problem, len(x)).face_sets["skin"])
        remap = np.full(len(x), -1, np.int64)
        remap[nodes] = np.arange(len(nodes))
        write_ply(x[nodes], remap[faces], out / f"{pos}_predicted.ply")
        pictures[pos] = (x[nodes], remap[faces], err, problem.skins[pos])
    write_json(out / "metrics.json", metrics)
    write_json(out / "params.json", params)
    write_report(out / "report.html", metrics, params, pictures, fit_info, sf,
                 subject_id=subject_id)
    return metrics
