"""Scores of a predicted position against its measurements: the skin surface distances (in
total and per skin region) and the errors of the internal landmarks, carried from the
reference by the mesh."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from breastmodel.pipeline.problem import Problem

__all__ = ["landmark_barycentric", "predicted_landmarks", "score_position",
           "skin_node_regions"]


def skin_node_regions(mesh) -> np.ndarray:
    """(N,) region code of every node: the breast region of a tet it belongs to (else the
    region of any tet), so skin nodes split into left and right breast."""
    from mechanics.mesh import BREAST_REGIONS

    reg = np.zeros(mesh.n_nodes, np.int64)
    order = np.argsort(np.isin(mesh.region, BREAST_REGIONS))  # breast tets written last win
    reg[mesh.tets[order].ravel()] = np.repeat(mesh.region[order], 4)
    return reg


def landmark_barycentric(mesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tet and barycentric coordinates of points in the mesh's reference geometry.

    Points outside the mesh use the nearest tet (by centroid) with clamped coordinates.

    Returns
    -------
    tet : (k,) int, bary : (k, 4) float
    """
    nodes, tets = np.asarray(mesh.nodes), np.asarray(mesh.tets)
    a = nodes[tets[:, 0]]
    T = np.stack([nodes[tets[:, i]] - a for i in (1, 2, 3)], axis=2)  # (M, 3, 3)
    Tinv = np.linalg.inv(T)
    cent = nodes[tets].mean(1)
    out_t, out_b = [], []
    for p in np.atleast_2d(points):
        lam = np.einsum("mij,mj->mi", Tinv, p - a)
        bary = np.column_stack([1 - lam.sum(1), lam])
        inside = np.flatnonzero(bary.min(1) >= -1e-9)
        if len(inside):
            t = int(inside[0])
            b = bary[t]
        else:
            t = int(np.argmin(np.linalg.norm(cent - p, axis=1)))
            b = np.clip(bary[t], 0, None)
            b = b / b.sum()
        out_t.append(t)
        out_b.append(b)
    return np.asarray(out_t, np.int64), np.asarray(out_b)


def score_position(problem: Problem, x: np.ndarray, position: str, *,
                   details: bool = False) -> dict:
    """Metrics of the predicted node positions x (N, 3) mm against a position's measured skin.

    Returns the :func:`breastmodel.evaluation.surface_metrics` dict; with ``details`` also
    ``regions`` (per skin region), ``landmarks`` (when known) and ``signed_error`` ((n_skin,)
    mm, predicted skin nodes to the measured surface, positive outside) with ``skin_nodes``.
    """
    from breastmodel.evaluation import (
        landmark_errors,
        per_region_metrics,
        point_to_surface,
        surface_metrics,
    )
    from breastmodel.pipeline.problem import mesh_of
    from mechanics.mesh import REGIONS

    mesh = mesh_of(problem, len(x))
    faces = np.asarray(mesh.face_sets["skin"])
    nodes = np.unique(faces)
    remap = np.full(mesh.n_nodes, -1, np.int64)
    remap[nodes] = np.arange(len(nodes))
    pv, pf = x[nodes], remap[faces]
    mv, mf = problem.skins[position]
    out = surface_metrics(pv, pf, mv, mf)
    if not details:
        return out
    d, _ = point_to_surface(pv, mv, mf, signed=True)
    names = {c: n for n, c in REGIONS.items()}
    out["regions"] = per_region_metrics(d, skin_node_regions(mesh)[nodes], names)
    out["signed_error"] = d
    out["skin_nodes"] = nodes
    lm = predicted_landmarks(problem, x, position)
    if lm is not None:
        out["landmarks"] = landmark_errors(lm[1], lm[2], lm[0])
    return out


def predicted_landmarks(problem: Problem, x: np.ndarray, position: str):
    """The landmarks known in the reference and in ``position``, carried by the mesh from
    the reference to x (N, 3): (names, predicted (k, 3) mm, measured (k, 3) mm), or None
    when the two positions share no landmark."""
    lm_ref = problem.landmarks.get(problem.reference, {})
    lm_pos = problem.landmarks.get(position, {})
    common = [k for k in lm_ref if k in lm_pos]
    if not common:
        return None
    from breastmodel.pipeline.problem import mesh_of

    mesh = mesh_of(problem, len(x))
    tet, bary = landmark_barycentric(mesh, np.array([lm_ref[k] for k in common]))
    pred = np.einsum("ki,kij->kj", bary, x[np.asarray(mesh.tets)[tet]])
    return common, pred, np.array([lm_pos[k] for k in common])
