"""Element quality of a tet mesh with the ANSYS definitions the paper quotes.

- Skewness (equilateral-volume): ``1 - V / V_eq`` with ``V_eq`` the volume of the regular
  tet of the same circumradius; 0 for a regular tet, 1 for a flat one.
- Aspect ratio (ANSYS Mechanical APDL): for each triangular face, two rectangles are built
  on the median from a vertex and the mid-line joining the other two edge midpoints; the
  face ratio is the largest rectangle side ratio divided by sqrt(3) (1 for an equilateral
  triangle), repeated for the three vertices; a tet takes its worst face.
- Minimum dihedral angle (degrees), radius ratio ``R / (3 r)`` (1 for a regular tet).
"""

from __future__ import annotations

import numpy as np

from mechanics.mesh import REGIONS, Mesh
from meshing.sets import OUTWARD_FACES

#: A tet is counted as a sliver below this minimum dihedral angle (degrees).
SLIVER_DIHEDRAL_DEG = 5.0


def _triangle_aspect(p: np.ndarray) -> np.ndarray:
    """(..., 3, 3) triangle vertices -> (...) ANSYS aspect ratio."""
    worst = np.zeros(p.shape[:-2])
    for i in range(3):
        a, b, c = p[..., i, :], p[..., (i + 1) % 3, :], p[..., (i + 2) % 3, :]
        l1 = 0.5 * (b + c) - a  # median
        l2 = 0.5 * (c - b)  # joins the midpoints of the two edges at a
        n1 = np.linalg.norm(l1, axis=-1)
        n2 = np.linalg.norm(l2, axis=-1)
        cross = np.linalg.norm(np.cross(l1, l2), axis=-1)
        w1 = cross / np.maximum(n1, 1e-300)  # extent of l2 across l1
        w2 = cross / np.maximum(n2, 1e-300)  # extent of l1 across l2
        for s, t in ((n1, w1), (n2, w2)):
            r = np.maximum(s, t) / np.maximum(np.minimum(s, t), 1e-300)
            worst = np.maximum(worst, r)
    return worst / np.sqrt(3.0)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``np.cross`` of (M, 3) arrays, the same products and differences (so the same bits)
    without its axis handling, which costs more than the arithmetic on the few tets of a
    local move."""
    out = np.empty_like(u)
    out[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    out[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    out[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    return out


def _volume_skewness(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, 4, 3) tet vertices -> signed volume, skewness and circumradius, each (M,)."""
    a, b, c = (x[:, k] - x[:, 0] for k in (1, 2, 3))
    bc = _cross(b, c)
    det = np.einsum("ij,ij->i", a, bc)
    vol = det / 6.0
    num = (
        np.einsum("ij,ij->i", a, a)[:, None] * bc
        + np.einsum("ij,ij->i", b, b)[:, None] * _cross(c, a)
        + np.einsum("ij,ij->i", c, c)[:, None] * _cross(a, b)
    )
    circ_r = np.linalg.norm(num, axis=1) / np.maximum(np.abs(2.0 * det), 1e-300)
    edge_eq = 4.0 * circ_r / np.sqrt(6.0)
    vol_eq = edge_eq**3 / (6.0 * np.sqrt(2.0))
    skew = np.clip(1.0 - np.abs(vol) / np.maximum(vol_eq, 1e-300), 0.0, 1.0)
    # two coincident nodes leave no circumsphere (0 / 0 above, skewness 0): such a tet is as
    # flat as a tet gets (a fine mesh of 2026-12-07 kept two of them, zero volume, unseen)
    skew = np.where(vol_eq > 0.0, skew, 1.0)
    return vol, skew, circ_r


def volume_skewness(nodes: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed volume (mm^3) and skewness of each tet, as :func:`element_quality` gives
    them, without the other measures: the mesh improvement's local moves ask for these
    alone, tens of thousands of times."""
    vol, skew, _ = _volume_skewness(np.asarray(nodes, float)[np.asarray(tets)])
    return vol, skew


def element_quality(nodes: np.ndarray, tets: np.ndarray) -> dict[str, np.ndarray]:
    """Per-element quality measures.

    Parameters
    ----------
    nodes : (N, 3) float, mm
    tets : (M, 4) int

    Returns
    -------
    dict of (M,) arrays: ``volume`` (mm^3, signed), ``skewness``, ``aspect_ratio``,
    ``radius_ratio``, ``min_dihedral_deg``, ``min_edge``, ``max_edge`` (mm)
    """
    x = np.asarray(nodes, float)[np.asarray(tets)]
    vol, skew, circ_r = _volume_skewness(x)
    faces = x[:, OUTWARD_FACES]  # (M, 4, 3, 3)
    fn = np.cross(faces[:, :, 1] - faces[:, :, 0], faces[:, :, 2] - faces[:, :, 0])
    area = 0.5 * np.linalg.norm(fn, axis=2)
    unit = fn / np.maximum(2.0 * area[..., None], 1e-300)
    in_r = 3.0 * np.abs(vol) / np.maximum(area.sum(1), 1e-300)
    dihedral = []
    for i in range(4):
        for j in range(i + 1, 4):
            cosang = -np.einsum("ij,ij->i", unit[:, i], unit[:, j])
            dihedral.append(np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0))))
    edges = np.stack([x[:, j] - x[:, i] for i in range(4) for j in range(i + 1, 4)], axis=1)
    elen = np.linalg.norm(edges, axis=2)
    return {
        "volume": vol,
        "skewness": skew,
        "aspect_ratio": _triangle_aspect(faces).max(axis=1),
        "radius_ratio": circ_r / np.maximum(3.0 * in_r, 1e-300),
        "min_dihedral_deg": np.min(dihedral, axis=0),
        "min_edge": elen.min(1),
        "max_edge": elen.max(1),
    }


def _stats(v: np.ndarray) -> dict[str, float]:
    if len(v) == 0:
        return {}
    p = np.percentile(v, [1, 50, 99])
    return {"min": float(v.min()), "p01": float(p[0]), "median": float(p[1]),
            "p99": float(p[2]), "max": float(v.max()), "mean": float(v.mean())}


def report(mesh: Mesh) -> dict:
    """Quality summary of a mesh (JSON-ready).

    Returns
    -------
    dict
        Counts (nodes, tets, per region), volume per region (mm^3), statistics of
        skewness, aspect ratio, radius ratio, minimum dihedral angle (deg) and edge length
        (mm), number of inverted (volume <= 0) and sliver (minimum dihedral below
        ``SLIVER_DIHEDRAL_DEG``) tets, and the size of every named set.
    """
    q = element_quality(mesh.nodes, mesh.tets)
    names = {v: k for k, v in REGIONS.items()}
    regions = {}
    for code in np.unique(mesh.region):
        sel = mesh.region == code
        regions[names.get(int(code), str(int(code)))] = {
            "tets": int(sel.sum()),
            "volume_mm3": float(q["volume"][sel].sum()),
        }
    return {
        "n_nodes": int(mesh.n_nodes),
        "n_tets": int(mesh.n_tets),
        "regions": regions,
        "volume_mm3": float(q["volume"].sum()),
        "skewness": _stats(q["skewness"]),
        "aspect_ratio": _stats(q["aspect_ratio"]),
        "radius_ratio": _stats(q["radius_ratio"]),
        "min_dihedral_deg": _stats(q["min_dihedral_deg"]),
        "edge_mm": {"min": float(q["min_edge"].min()) if mesh.n_tets else 0.0,
                    "median": float(np.median(np.r_[q["min_edge"], q["max_edge"]]))
                    if mesh.n_tets else 0.0,
                    "max": float(q["max_edge"].max()) if mesh.n_tets else 0.0},
        "n_inverted": int((q["volume"] <= 0).sum()),
        "n_slivers": int((q["min_dihedral_deg"] < SLIVER_DIHEDRAL_DEG).sum()),
        "sliver_dihedral_deg": SLIVER_DIHEDRAL_DEG,
        "node_sets": {k: int(len(v)) for k, v in mesh.node_sets.items()},
        "face_sets": {k: int(len(v)) for k, v in mesh.face_sets.items()},
        "node_pairs": {k: int(len(v)) for k, v in mesh.node_pairs.items()},
        "paper_reference": {"tets": 18453, "element_size_mm": [7, 10],
                            "skewness": [0.005, 0.9], "aspect_ratio": [1.18, 11.53]},
    }
