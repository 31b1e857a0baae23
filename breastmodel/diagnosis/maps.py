"""Where the model fails: skin regions, per-node error maps and per-region tables.

Compute only (pictures are in :mod:`breastmodel.diagnosis.views`). Coordinates are LPS mm in
the reference frame: x to the patient's left, y posterior (anterior is -y), z superior.

Skin regions (:func:`skin_regions`) are Lagrangian: masks over the skin nodes
(``np.unique(mesh.face_sets["skin"])``) defined once on one configuration of the nodes, so the
same node keeps its region in every position and every model revision of a subject.

* ``left`` / ``right``: the breast of the tet the node belongs to (regions 1, 4 left and
  3, 5 right, :func:`breastmodel.pipeline.problem.skin_node_regions`); a skin node of no
  breast tet takes the side of its nearest breast skin node. The two partition the skin.
* ``<side>.upper_outer``, ``upper_inner``, ``lower_outer``, ``lower_inner``: relative to that
  breast's nipple, its most anterior skin node (smallest y). Upper: z >= z_nipple; outer:
  away from the midline, x >= x_nipple on the left breast, x <= x_nipple on the right. The
  four partition the breast.
* ``<side>.nipple_area``: within ``nipple_radius_mm`` (default 20 mm) of the nipple.
* ``<side>.inframammary_fold``: the crease where the breast meets the chest wall below the
  nipple. Tissue thickness t of a skin node = its distance to the nearest chest-wall node
  (the ``interface`` face set; without one, its anterior projection from the most posterior
  skin node of that breast). The fold candidates are the nodes of the inferior sector below
  the nipple (z < z_nipple and |x - x_nipple| <= z_nipple - z, i.e. within 45 degrees of
  straight down in the coronal plane) that are thin: t <= ``fold_fraction`` * t_nipple
  (default 1/3). The fold is where these start: the candidates within ``fold_band_mm``
  (default 20 mm) below the highest candidate, so that a breast region running on down the
  abdomen does not count as fold.

Strain (:func:`failure_map`) is the largest principal Green-Lagrange strain of the tets
around a node, from the stress-free nodes X to the predicted nodes x, averaged per node
weighted by the tets' stress-free volumes (dimensionless; 0.1 = 10% stretch squared minus
one over two), and ``stretch`` = sqrt(1 + 2 E_max) - 1, the largest principal stretch minus 1.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["QUADRANTS", "failure_map", "failure_tables", "node_strain", "skin_regions"]

QUADRANTS = ("upper_outer", "upper_inner", "lower_outer", "lower_inner")
_SIDES = {"left": (1, 4), "right": (3, 5)}
_TABLE_KEYS = ("mean_signed_mm", "mean_abs_mm", "rmse_mm", "p95_mm", "max_mm",
               "normal_rms_mm", "tangential_rms_mm", "mean_strain")


def _skin(mesh) -> tuple[np.ndarray, np.ndarray]:
    """Skin node ids (sorted) and the skin faces renumbered into them."""
    if "skin" not in mesh.face_sets or len(mesh.face_sets["skin"]) == 0:
        raise ValueError("diagnose: the mesh has no 'skin' face set")
    faces = np.asarray(mesh.face_sets["skin"], np.int64)
    nodes = np.unique(faces)
    remap = np.full(mesh.n_nodes, -1, np.int64)
    remap[nodes] = np.arange(len(nodes))
    return nodes, remap[faces]


def skin_regions(mesh, X: np.ndarray | None = None, *, nipple_radius_mm: float = 20.0,
                 fold_fraction: float = 1.0 / 3.0,
                 fold_band_mm: float = 20.0) -> dict[str, np.ndarray]:
    """Named boolean masks over the skin nodes (see the module notes for the definitions).

    Parameters
    ----------
    mesh : mechanics.mesh.Mesh
        With a ``skin`` face set (and ideally an ``interface`` face set for the chest wall).
    X : (N, 3) float array, mm, optional
        The node positions the regions are defined on (the stress-free geometry of a run);
        default ``mesh.nodes`` (the reference position).
    nipple_radius_mm : radius of the nipple area, mm
    fold_fraction : the fold's tissue thickness relative to the nipple's (0..1)
    fold_band_mm : height of the fold band below its highest node, mm

    Returns
    -------
    dict
        ``{"left", "right", "<side>.<quadrant>", "<side>.inframammary_fold",
        "<side>.nipple_area"}`` -> (n_skin,) bool, in the order of
        ``np.unique(mesh.face_sets["skin"])``. A side without breast nodes has all-False
        masks.
    """
    from scipy.spatial import cKDTree

    from breastmodel.pipeline.problem import skin_node_regions

    X = np.asarray(mesh.nodes if X is None else X, np.float64)
    if X.shape != (mesh.n_nodes, 3):
        raise ValueError(f"diagnose: node positions must be ({mesh.n_nodes}, 3), got {X.shape}")
    nodes, _ = _skin(mesh)
    P = X[nodes]
    code = skin_node_regions(mesh)[nodes]
    side = {s: np.isin(code, c) for s, c in _SIDES.items()}
    breast = side["left"] | side["right"]
    if not breast.any():
        raise ValueError("diagnose: no skin node belongs to a breast region (1, 3, 4, 5)")
    if not breast.all():  # skin of no breast tet: the side of the nearest breast skin node
        _, j = cKDTree(P[breast]).query(P[~breast])
        lab = side["left"][breast][j]
        side["left"][~breast], side["right"][~breast] = lab, ~lab
    iface = mesh.face_sets.get("interface")
    wall = cKDTree(X[np.unique(iface)]) if iface is not None and len(iface) else None
    out: dict[str, np.ndarray] = {"left": side["left"], "right": side["right"]}
    for s, sgn in (("left", 1.0), ("right", -1.0)):
        m = side[s]
        names = [*QUADRANTS, "inframammary_fold", "nipple_area"]
        if not m.any():
            out.update({f"{s}.{k}": np.zeros(len(nodes), bool) for k in names})
            continue
        ids = np.flatnonzero(m)
        nip = P[ids[np.argmin(P[ids, 1])]]  # most anterior: smallest y
        upper = P[:, 2] >= nip[2]
        outer = sgn * (P[:, 0] - nip[0]) >= 0
        out[f"{s}.upper_outer"] = m & upper & outer
        out[f"{s}.upper_inner"] = m & upper & ~outer
        out[f"{s}.lower_outer"] = m & ~upper & outer
        out[f"{s}.lower_inner"] = m & ~upper & ~outer
        if wall is not None:
            t = wall.query(P)[0]
            t_nip = wall.query(nip)[0]
        else:
            back = P[ids, 1].max()
            t, t_nip = back - P[:, 1], back - nip[1]
        below = nip[2] - P[:, 2]
        cand = m & (below > 0) & (np.abs(P[:, 0] - nip[0]) <= below) & (
            t <= fold_fraction * t_nip)
        fold = np.zeros(len(nodes), bool)
        if cand.any():
            top = P[cand, 2].max()
            fold = cand & (P[:, 2] >= top - fold_band_mm)
        out[f"{s}.inframammary_fold"] = fold
        out[f"{s}.nipple_area"] = m & (np.linalg.norm(P - nip, axis=1) <= nipple_radius_mm)
    return out


def node_strain(tets: np.ndarray, X: np.ndarray, x: np.ndarray,
                nodes: np.ndarray | None = None) -> np.ndarray:
    """Largest principal Green-Lagrange strain per node, averaged over the tets around it.

    Parameters
    ----------
    tets : (M, 4) int
    X : (N, 3) float array, mm; stress-free (reference) node positions
    x : (N, 3) float array, mm; deformed node positions
    nodes : (n,) int, optional; the nodes wanted (default all)

    Returns
    -------
    (n,) float array (dimensionless): sum over the tets containing the node of
    ``|V_t| * max eig(E_t)`` divided by the sum of ``|V_t|`` (stress-free volumes), with
    ``E = (F^T F - I) / 2`` and ``F`` the constant deformation gradient of a linear tet.
    NaN for a node in no tet.
    """
    tets = np.asarray(tets, np.int64)
    X, x = np.asarray(X, np.float64), np.asarray(x, np.float64)
    nodes = np.arange(len(X)) if nodes is None else np.asarray(nodes, np.int64)
    want = np.zeros(len(X), bool)
    want[nodes] = True
    t = tets[want[tets].any(axis=1)]  # only the tets that touch a wanted node
    Dm = np.transpose(X[t[:, 1:]] - X[t[:, :1]], (0, 2, 1))  # columns: edge vectors
    Ds = np.transpose(x[t[:, 1:]] - x[t[:, :1]], (0, 2, 1))
    F = Ds @ np.linalg.inv(Dm)
    E = 0.5 * (np.transpose(F, (0, 2, 1)) @ F - np.eye(3))
    emax = np.linalg.eigvalsh(E)[:, -1]
    vol = np.abs(np.linalg.det(Dm)) / 6.0
    num, den = np.zeros(len(X)), np.zeros(len(X))
    np.add.at(num, t.ravel(), np.repeat(vol * emax, 4))
    np.add.at(den, t.ravel(), np.repeat(vol, 4))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (num / den)[nodes]


def _area(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1)


def failure_map(run, position: str, *, regions: Mapping[str, np.ndarray] | None = None) -> dict:
    """Per skin node error and strain of one position of a run.

    Parameters
    ----------
    run : breastmodel.diagnosis.RunData
    position : a predicted position of the run
    regions : :func:`skin_regions` masks to carry along (default: computed on ``run.X``)

    Returns
    -------
    dict of arrays over the n skin nodes (order ``np.unique(mesh.face_sets["skin"])``):

    ``skin_nodes`` (n,) int; ``faces`` (m, 3) skin triangles indexing the skin nodes;
    ``points`` (n, 3) predicted skin, mm; ``X`` (n, 3) stress-free skin, mm;
    ``signed_error`` (n,) mm, predicted node to the measured skin surface, positive outside
    (:class:`breastmodel.evaluation.TriangleSurface`); ``closest`` (n, 3) the closest measured
    point, mm; ``error_vector`` (n, 3) = points - closest, mm; ``normals`` (n, 3) unit outward
    normals of the predicted skin; ``normal`` (n,) mm, signed ``error_vector . normal``;
    ``tangential`` (n,) mm, the magnitude of the rest; ``strain`` (n,) largest principal
    Green-Lagrange strain X -> x (module notes); ``stretch`` (n,) largest principal stretch
    minus 1; ``skin_area_change`` (n,) skin area ratio x/X minus 1 of the triangles around the
    node (area-weighted); ``measured`` (vertices (k, 3) mm, triangles (l, 3)); ``regions``
    name -> (n,) bool; ``position``.
    """
    from breastmodel.evaluation import TriangleSurface, normal_tangential, vertex_normals

    if position not in run.x:
        raise ValueError(f"diagnose: position {position!r} is not among the run's predicted "
                         f"positions {sorted(run.x)} ({run.out})")
    from breastmodel.pipeline.problem import mesh_of, skin_nodes

    X = np.asarray(run.X, np.float64)
    x = np.asarray(run.x[position], np.float64)
    if x.shape != X.shape:
        raise ValueError(f"diagnose: {run.out}: node arrays {X.shape}, {x.shape} differ")
    # A sliding model runs on the split mesh: its skin nodes, in the conforming order.
    mesh = mesh_of(run.problem, len(x))
    _, faces = _skin(run.problem.mesh)
    nodes = skin_nodes(run.problem, len(x))
    pts = x[nodes]
    mv, mf = run.problem.skins[position]
    d, closest = TriangleSurface(mv, mf).distance(pts, signed=True)
    ev = pts - closest
    normals = vertex_normals(pts, faces)
    nrm, tan = normal_tangential(ev, np.where(np.linalg.norm(normals, axis=1)[:, None] > 0,
                                              normals, [0.0, 0.0, 1.0]))
    strain = node_strain(mesh.tets, X, x, nodes)
    ratio = _area(pts, faces) / _area(X[nodes], faces)
    a0 = _area(X[nodes], faces)
    num, den = np.zeros(len(nodes)), np.zeros(len(nodes))
    np.add.at(num, faces.ravel(), np.repeat(a0 * (ratio - 1.0), 3))
    np.add.at(den, faces.ravel(), np.repeat(a0, 3))
    if regions is None:
        regions = skin_regions(run.problem.mesh, X[:run.problem.mesh.n_nodes])
    return {
        "position": position, "skin_nodes": nodes, "faces": faces, "points": pts,
        "X": X[nodes], "signed_error": d, "closest": closest, "error_vector": ev,
        "normals": normals, "normal": nrm, "tangential": tan, "strain": strain,
        "stretch": np.sqrt(np.maximum(1.0 + 2.0 * strain, 0.0)) - 1.0,
        "skin_area_change": num / den, "measured": (np.asarray(mv), np.asarray(mf)),
        "regions": dict(regions),
    }


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def region_stats(fm: Mapping[str, Any], mask: np.ndarray) -> dict:
    """Error statistics of the nodes of one mask of a :func:`failure_map` (mm; strain
    dimensionless). Empty masks give ``n = 0`` and None values."""
    mask = np.asarray(mask, bool)
    n = int(mask.sum())
    if n == 0:
        return {"n": 0, **{k: None for k in _TABLE_KEYS}}
    d = np.asarray(fm["signed_error"])[mask]
    a = np.abs(d)
    return {
        "n": n, "mean_signed_mm": _num(d.mean()), "mean_abs_mm": _num(a.mean()),
        "rmse_mm": _num(np.sqrt(np.mean(d**2))), "p95_mm": _num(np.percentile(a, 95)),
        "max_mm": _num(a.max()),
        "normal_rms_mm": _num(np.sqrt(np.mean(np.asarray(fm["normal"])[mask] ** 2))),
        "tangential_rms_mm": _num(np.sqrt(np.mean(np.asarray(fm["tangential"])[mask] ** 2))),
        "mean_strain": _num(np.nanmean(np.asarray(fm["strain"])[mask])),
    }


def error_vs_strain(fm: Mapping[str, Any], *, n_bins: int = 5) -> dict:
    """How the skin error goes with the local strain of one position.

    Returns
    -------
    dict
        ``spearman_abs``/``pearson_abs``: correlation of |error| with strain;
        ``spearman_signed``/``pearson_signed``: of the signed error (None where undefined,
        e.g. constant strain); ``bins``: strain quantile bins ``[{"strain_lo", "strain_hi",
        "n", "mean_abs_mm", "mean_signed_mm"}]`` (fewer than ``n_bins`` when quantiles tie).
    """
    from scipy import stats

    s = np.asarray(fm["strain"], float)
    d = np.asarray(fm["signed_error"], float)
    ok = np.isfinite(s) & np.isfinite(d)
    s, d = s[ok], d[ok]
    out: dict[str, Any] = {"measure": "max principal Green-Lagrange strain", "n": int(len(s))}

    def flat(a):  # constant up to round-off (a rigid motion, a homogeneous stretch)
        return np.ptp(a) <= 1e-9 * max(1.0, float(np.abs(a).max()))

    def corr(fn, a, b):
        if len(a) < 3 or flat(a) or flat(b):
            return None
        return _num(fn(a, b)[0])

    out["spearman_abs"] = corr(stats.spearmanr, s, np.abs(d))
    out["pearson_abs"] = corr(stats.pearsonr, s, np.abs(d))
    out["spearman_signed"] = corr(stats.spearmanr, s, d)
    out["pearson_signed"] = corr(stats.pearsonr, s, d)
    bins = []
    if len(s):
        edges = np.unique(np.quantile(s, np.linspace(0.0, 1.0, n_bins + 1)))
        if flat(s):
            edges = np.array([s.min(), s.max()])
        idx = np.clip(np.searchsorted(edges, s, side="right") - 1, 0, len(edges) - 2)
        for b in range(len(edges) - 1):
            sel = idx == b
            if sel.any():
                bins.append({"strain_lo": _num(edges[b]), "strain_hi": _num(edges[b + 1]),
                             "n": int(sel.sum()), "mean_abs_mm": _num(np.abs(d[sel]).mean()),
                             "mean_signed_mm": _num(d[sel].mean())})
    out["bins"] = bins
    return out


def failure_tables(run, *, maps: Mapping[str, Mapping[str, Any]] | None = None,
                   regions: Mapping[str, np.ndarray] | None = None) -> dict:
    """Per position and per skin region error tables of a run (JSON-ready).

    Parameters
    ----------
    run : breastmodel.diagnosis.RunData
    maps : position -> :func:`failure_map` (computed when not given)
    regions : :func:`skin_regions` masks (default: on the run's stress-free ``X``)

    Returns
    -------
    dict
        ``{"units", "regions": {name: n_nodes}, "positions": {position: {"regions": {name:
        {"n", "mean_signed_mm", "mean_abs_mm", "rmse_mm", "p95_mm", "max_mm",
        "normal_rms_mm", "tangential_rms_mm", "mean_strain"}}, "error_vs_strain": {...}}}}``
        with region ``"all"`` first (every skin node), then those of :func:`skin_regions`.
    """
    if regions is None:
        regions = skin_regions(run.problem.mesh, run.X[:run.problem.mesh.n_nodes])
    n = len(next(iter(regions.values())))
    masks = {"all": np.ones(n, bool), **regions}
    out: dict[str, Any] = {
        "units": "errors mm (+ = predicted skin outside the measured one); strain "
                 "dimensionless (max principal Green-Lagrange, stress-free -> predicted)",
        "regions": {k: int(np.sum(m)) for k, m in masks.items()},
        "positions": {},
    }
    for pos in run.x:
        fm = maps[pos] if maps is not None and pos in maps else failure_map(run, pos,
                                                                            regions=regions)
        out["positions"][pos] = {
            "regions": {k: region_stats(fm, m) for k, m in masks.items()},
            "error_vs_strain": error_vs_strain(fm),
        }
    return out
