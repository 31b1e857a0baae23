"""Candidates that are not physics: errors of the measured skin itself.

A residual the model cannot explain may come from the data: one position registered with a
small rigid error, or a segmentation that puts the skin systematically inside or outside the
body. Both act on the residual (the signed distance d = g . (x - y) of a predicted skin node
x to its closest point y on the measured skin, g the unit outward direction) linearly, with
no model evaluation: moving the measured skin by a small displacement delta(y) changes d by
-g . delta(y).

- ``misregistration:<position>``: a rigid motion of that position's measured skin, six
  parameters (translation t, mm, and rotation theta about the scored skin's centroid c,
  expressed as the displacement it causes at the skin's RMS radius L, mm):
  delta(y) = t + (theta / L) x (y - c).
- ``skin_offset``: the measured skin of every scored position offset along its normal by s,
  mm (segmentation bias, one parameter): delta(y) = s g.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from breastmodel.diagnosis.candidates import Candidate

__all__ = ["MAX_OFFSET_MM", "MAX_RIGID_MM", "measurement_candidates", "measurement_columns",
           "rigid_transform"]

#: Bounds of the rigid motion's parameters, mm (translation, and rotation as displacement at
#: the skin's RMS radius).
MAX_RIGID_MM = 20.0
#: Bound of the skin offset, mm.
MAX_OFFSET_MM = 5.0
_RIGID = ("tx", "ty", "tz", "rx", "ry", "rz")


def measurement_candidates(positions: Sequence[str]) -> list[Candidate]:
    """The non-physical candidates of a diagnosis whose scored positions are ``positions``.

    Returns
    -------
    list of Candidate (kind ``"registration"`` or ``"segmentation"``; ``measurement`` says
    which columns they take, ``acts_on`` the positions they change)
    """
    out = [Candidate(f"misregistration:{p}", "registration",
                     f"a rigid misregistration of the {p} measured skin (6 parameters)",
                     amplitude=(0.0, 0.0), measurement="rigid", acts_on=(p,))
           for p in positions]
    out.append(Candidate("skin_offset", "segmentation",
                         "the measured skin offset along its normal in every position "
                         "(segmentation bias, 1 parameter)", amplitude=(0.0, 0.0),
                         measurement="offset", acts_on=tuple(positions)))
    return out


def _vertex_normals(v: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(n, 3) unit area-weighted vertex normals (right-hand rule: the signed distance's
    outward side)."""
    v = np.asarray(v, float)
    tri = np.asarray(tri)
    fn = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, tri[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def _directions(x: np.ndarray, d: np.ndarray, y: np.ndarray, vertices: np.ndarray,
                triangles: np.ndarray) -> np.ndarray:
    """(n, 3) unit outward directions g = dd/dx: (x - y) / d away from the surface, the
    measured skin's vertex normal at the nearest vertex where the point lies on it."""
    from scipy.spatial import cKDTree

    v = np.asarray(vertices, float)
    g = _vertex_normals(v, triangles)[cKDTree(v).query(y)[1]]
    away = np.abs(d) > 1e-6
    g[away] = (x[away] - y[away]) / d[away, None]
    return g


def measurement_columns(cand: Candidate, geometry: Mapping[str, Mapping[str, np.ndarray]],
                        order: Sequence[str]) -> tuple[list[np.ndarray], list[float],
                                                       list[float], list[str]]:
    """Linear columns of a non-physical candidate over the stacked residual.

    Parameters
    ----------
    cand : a candidate of :func:`measurement_candidates`
    geometry : position -> {"g": (n, 3) outward directions, "y": (n, 3) closest points on
        the measured skin, mm} of the scored skin nodes
    order : the positions stacked in the residual vector, in order

    Returns
    -------
    columns, lower bounds, upper bounds, parameter labels
    """
    n = [len(geometry[p]["g"]) for p in order]
    offs = np.concatenate([[0], np.cumsum(n)])
    total = int(offs[-1])
    if cand.measurement == "offset":
        col = np.zeros(total)
        for i, p in enumerate(order):
            if p in cand.acts_on:
                col[offs[i]:offs[i + 1]] = -1.0
        return [col], [-MAX_OFFSET_MM], [MAX_OFFSET_MM], ["offset_mm"]
    if cand.measurement != "rigid":
        raise ValueError(f"diagnose: candidate {cand.name!r} has no measurement columns")
    (pos,) = cand.acts_on
    i = list(order).index(pos)
    g, y = geometry[pos]["g"], geometry[pos]["y"]
    c, L = _centre(y)
    rot = np.cross(y - c, g) / L  # d(-g . (theta/L x (y - c)))/d theta = -((y - c) x g) / L
    cols = []
    for k in range(6):
        col = np.zeros(total)
        col[offs[i]:offs[i + 1]] = -(g[:, k] if k < 3 else rot[:, k - 3])
        cols.append(col)
    return cols, [-MAX_RIGID_MM] * 6, [MAX_RIGID_MM] * 6, [f"{p}_mm" for p in _RIGID]


def _centre(y: np.ndarray) -> tuple[np.ndarray, float]:
    c = y.mean(axis=0)
    return c, float(max(np.sqrt(np.mean(np.sum((y - c) ** 2, axis=1))), 1e-9))


def rigid_transform(params: Mapping[str, float], y: np.ndarray) -> dict:
    """The rigid motion of a ``misregistration`` estimate, for people and for re-registering.

    Parameters
    ----------
    params : {"tx_mm", ..., "rz_mm"} as estimated
    y : (n, 3) the scored measured-skin points of the position, mm (centroid, radius)

    Returns
    -------
    dict: ``rotation`` (3, 3) (exact, from the rotation vector), ``translation`` (3,) mm,
    ``centre`` (3,) mm, ``angle_deg``, ``translation_mm`` (norm), ``max_displacement_mm``
    (largest displacement of a scored skin point), so that a measured point p moves to
    ``centre + rotation @ (p - centre) + translation``.
    """
    from scipy.spatial.transform import Rotation

    c, L = _centre(np.asarray(y, float))
    t = np.array([params[f"{k}_mm"] for k in _RIGID[:3]], float)
    w = np.array([params[f"{k}_mm"] for k in _RIGID[3:]], float) / L
    R = Rotation.from_rotvec(w).as_matrix()
    moved = c + (y - c) @ R.T + t
    return {"rotation": R.tolist(), "translation": t.tolist(), "centre": c.tolist(),
            "angle_deg": float(np.degrees(np.linalg.norm(w))),
            "translation_mm": float(np.linalg.norm(t)),
            "max_displacement_mm": float(np.max(np.linalg.norm(moved - y, axis=1)))}
