"""Synthetic measurements on a prepared problem: a known model's predictions as the data.

Checks the fitting end to end without imaging noise: the measured skin of every position
except the reference is replaced by the skin that a truth model predicts from its own
stress-free geometry, so the truth parameters reach (near) zero MHD.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.pipeline.problem import (
    load_problem,
    mesh_of,
    predict_position,
    stress_free_geometry,
)

__all__ = ["synthetic_problem"]


def synthetic_problem(problem_dir: str | Path, out: str | Path, model: Mapping[str, Any],
                      stress_free: Mapping[str, Any], solver: Mapping[str, Any]) -> Path:
    """Copy ``problem_dir`` to ``out`` with simulated skins.

    Parameters
    ----------
    problem_dir : a problem folder (see :mod:`breastmodel.pipeline.problem`)
    out : new folder (replaced if it exists)
    model : the truth ``[model]`` table
    stress_free, solver : ``[stress_free]`` and ``[solver]`` tables for the truth geometry

    Returns
    -------
    Path
        ``out``; the reference keeps its mesh skin, every other position gets the truth
        model's predicted skin (vertices mm, the mesh's skin triangles).
    """
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(problem_dir, out)
    prob = load_problem(problem_dir)
    X, _ = stress_free_geometry(prob, model, stress_free, solver)
    for pos in prob.gravity:
        x = prob.mesh.nodes if pos == prob.reference else predict_position(
            prob, model, X, pos, solver).x
        faces = np.asarray(mesh_of(prob, len(x)).face_sets["skin"])
        nodes = np.unique(faces)
        remap = np.full(len(x), -1, np.int64)
        remap[nodes] = np.arange(len(nodes))
        np.savez(out / f"{pos}_skin.npz", vertices=np.asarray(x)[nodes], triangles=remap[faces])
    return out
