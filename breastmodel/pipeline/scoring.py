"""Scores of a predicted position against its measurements: the skin surface distances (in
total and per skin region), the errors of the internal landmarks, carried from the
reference by the mesh, and the fit's signed skin residual."""

from __future__ import annotations

import weakref
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from breastmodel.pipeline.problem import Problem

__all__ = ["RIM_FADE_MM", "fit_residual", "landmark_barycentric", "predicted_landmarks",
           "score_position", "skin_node_regions", "skin_residual"]


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

    Returns the :func:`breastmodel.evaluation.surface_metrics` dict (its shared-skin figures
    only with ``details``); with ``details`` also
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
    out = surface_metrics(pv, pf, mv, mf, overlap=details)
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


#: {problem: {(nodes, landmark names): (tet, barycentric)}} of :func:`predicted_landmarks`
_PLACES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


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
    # the landmarks' place in the reference mesh is the same for every evaluation of a fit:
    # found once per problem and mesh (36 ms a position on a 45.6k-tet mesh)
    found = _PLACES.setdefault(problem, {})
    key = (len(x), tuple(common))
    if key not in found:
        found[key] = landmark_barycentric(mesh, np.array([lm_ref[k] for k in common]))
    tet, bary = found[key]
    pred = np.einsum("ki,kij->kj", bary, x[np.asarray(mesh.tets)[tet]])
    return common, pred, np.array([lm_pos[k] for k in common])


def record_landmarks(out: dict, problem: Problem, x: np.ndarray, position: str,
                     sees) -> tuple | None:
    """Put each landmark's error at ``position`` (x: (N, 3) deformed nodes) in
    ``out["landmark_errors_mm"]`` whether the objective sees the landmarks or not (the
    diagnosis' independent witness, :mod:`breastmodel.diagnosis.landmarks`), and their mean
    in ``out["landmarks_mm"]`` when ``sees`` does; returns :func:`predicted_landmarks`'
    triple for the fit's residual when seen, else None."""
    lm = predicted_landmarks(problem, x, position) if problem.landmarks else None
    if lm is None:
        return None
    err = np.linalg.norm(lm[1] - lm[2], axis=1)
    out["landmark_errors_mm"][position] = err.tolist()
    if "landmarks" not in sees:
        return None
    out["landmarks_mm"][position] = float(err.mean())
    return lm


#: A skin node whose closest point on the measured skin lies on its rim (the field-of-view
#: cut, the edge left where the skin meets the muscle) has no defined side: the sign of its
#: distance follows whichever rim triangle is nearest and flips with sub-millimetre motions.
#: On the suite's full-size subject full-000, 11 of 1313 prone nodes did so between the fit's
#: first two evaluations (1.0 and 1.051 kPa), each residual jumping by 3-18 mm while the
#: others changed by at most 1.3 mm; they made three quarters of the Jacobian's squared norm,
#: so the least squares stepped a third as far as it would without them (1.0 -> 1.127 kPa
#: against 1.476) and needed 17 evaluations. The fit's residual is therefore weighted by the
#: closest point's distance to the rim over this length (0 on the rim, 1 from it on):
#: continuous, and the rim's nodes, which the measurement does not place, count for nothing.
#: The reported MHD (unsigned) is unchanged.
RIM_FADE_MM = 5.0


def skin_residual(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, *,
                  with_fade: bool = False):
    """The fit's skin residual of each point (mm): its signed distance to the measured skin
    (``vertices``, ``triangles``) times its closest point's distance to the skin's rim over
    :data:`RIM_FADE_MM`, at most 1 (that factor too with ``with_fade``: the residual's
    change when the measured skin moves inward by 1 mm)."""
    from breastmodel.evaluation.distances import TriangleSurface, boundary_distance

    d, closest = TriangleSurface(vertices, triangles).distance(points, signed=True)
    fade = np.clip(boundary_distance(vertices, triangles, closest) / RIM_FADE_MM, 0.0, 1.0)
    return (d * fade, fade) if with_fade else d * fade


def fit_residual(skin_points: np.ndarray, measured: tuple, lm, sees) -> tuple[np.ndarray,
                                                                           np.ndarray]:
    """What the least-squares fit minimises at one position, and its change per mm the
    measured skin moves outward along its normal (a segmentation bias).

    The residual: the skin nodes' (``skin_points``) :func:`skin_residual` to the measured
    skin (``measured``: vertices, triangles) and/or the landmarks' error components (``lm``:
    names, predicted, measured; mm), as ``sees`` says. With both, each part is divided by
    the square root of its length, so that each weighs as its mean square. The offset moves
    each signed distance by -1 mm per mm (the fade too stays), the landmarks not at all.
    """
    parts, slopes = [], []
    if "skin" in sees:
        r, fade = skin_residual(skin_points, *measured, with_fade=True)
        parts.append(r)
        slopes.append(-fade)
    if lm is not None:
        parts.append((lm[1] - lm[2]).ravel())
        slopes.append(np.zeros(parts[-1].size))
    if not parts:
        return np.zeros(0), np.zeros(0)
    scale = [1.0 / np.sqrt(len(p)) if len(parts) > 1 else 1.0 for p in parts]
    return (np.concatenate([p * c for p, c in zip(parts, scale)]),
            np.concatenate([g * c for g, c in zip(slopes, scale)]))
