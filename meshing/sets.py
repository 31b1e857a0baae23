"""Named node sets, face sets and ligament node pairs of a tagged tet mesh."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mechanics.mesh import BREAST_REGIONS, REGIONS
from meshing.labels import Grid, TissueMasks
from meshing.surface import fov_faces, triangle_normals

#: Local faces of a positively oriented tet, ordered so their normal points out of it.
OUTWARD_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def tet_faces(tets: np.ndarray):
    """Boundary faces and shared (internal) faces of a tet mesh.

    Returns
    -------
    boundary : (b, 3) int, outward-oriented faces used by one tet
    boundary_owner : (b,) int, the tet of each boundary face
    shared : (s, 3) int, faces used by two tets, oriented out of ``shared_owner[:, 0]``
    shared_owner : (s, 2) int, the two tets of each shared face
    """
    faces = tets[:, OUTWARD_FACES].reshape(-1, 3)
    owner = np.repeat(np.arange(len(tets)), 4)
    _, first, inv, cnt = np.unique(
        np.sort(faces, axis=1), axis=0, return_index=True, return_inverse=True,
        return_counts=True,
    )
    inv = inv.ravel()
    once = cnt[inv] == 1
    twice = np.flatnonzero(cnt[inv] == 2)
    order = twice[np.argsort(inv[twice], kind="stable")].reshape(-1, 2)
    return faces[once], owner[once], faces[order[:, 0]], owner[order]


#: The named sets' version, part of the pipeline's mesh stage key so that a cached mesh made
#: before a set was added is made again: 2 added ``cut_breast`` and ``cut_muscle``.
SETS_VERSION = 2


def _fixed_faces(nodes, faces, masks: TissueMasks, grid: Grid) -> np.ndarray:
    """(k,) bool over exposed muscle faces: those facing the thorax interior.

    A muscle layer that wraps around the thorax has its voxel centroid inside the thorax
    cavity: a face is on the thorax side when its normal points towards that centroid in the
    axial (x, y) plane. A flat layer (centroid inside tissue) faces the thorax posteriorly
    (+y in LPS).
    """
    n = triangle_normals(nodes, faces)
    c = nodes[faces].mean(1)
    kji = np.argwhere(masks.muscle)
    centre = grid.to_physical(kji[:, ::-1].mean(0, keepdims=True))[0]
    ijk = np.round(grid.to_index(centre[None])[0]).astype(int)
    inside_grid = np.all((ijk >= 0) & (ijk < np.asarray(grid.size)))
    in_tissue = inside_grid and masks.union[ijk[2], ijk[1], ijk[0]]
    if in_tissue or not inside_grid:
        return n[:, 1] > 0.5
    to_axis = centre[None, :2] - c[:, :2]
    return (np.einsum("ij,ij->i", n[:, :2], to_axis) > 0) & (np.abs(n[:, 2]) < 0.7)


def _end_bands(nodes, ids, side_of, band_mm):
    """Nodes of ``ids`` within ``band_mm`` of the superior / inferior end, per breast side."""
    sup, inf = [], []
    for s in (True, False):
        k = ids[side_of[ids] == s]
        if len(k) == 0:
            continue
        z = nodes[k, 2]
        sup.append(k[z >= z.max() - band_mm])
        inf.append(k[z <= z.min() + band_mm])
    cat = lambda a: np.unique(np.concatenate(a)) if a else np.zeros(0, np.int64)  # noqa: E731
    return cat(sup), cat(inf)


def _ligament_pairs(nodes, skin_ids, iface_faces, muscle_only, left, x_mid):
    """(breast node, muscle node) pairs at the inframammary, medial and lateral zones.

    Per breast, the footprint is the part of the interface where the tissue above it is
    thick (the breast mound rather than the thin layer around it); breast anchors are the
    footprint's boundary nodes, sorted into zones by their direction from its centre in the
    coronal (x, z) plane. Each gets the nearest muscle-only node as its partner.
    """
    out = {k: [] for k in ("inframammary", "medial", "lateral")}
    if len(muscle_only) == 0 or len(skin_ids) == 0 or len(iface_faces) == 0:
        return {f"ligament_{k}": np.zeros((0, 2), np.int64) for k in out}
    muscle_tree = cKDTree(nodes[muscle_only])
    for side in (True, False):
        fs = iface_faces[left[iface_faces].all(1) == side]
        sk = skin_ids[left[skin_ids] == side]
        if len(fs) == 0 or len(sk) == 0:
            continue
        ids = np.unique(fs)
        thick, _ = cKDTree(nodes[sk]).query(nodes[ids])
        p10, p95 = np.percentile(thick, [10, 95])
        foot = np.zeros(len(nodes), bool)
        foot[ids[thick > p10 + 0.25 * (p95 - p10)]] = True
        # boundary: footprint nodes on an interface edge that leaves the footprint, or on
        # the rim of the interface itself
        edges = np.sort(fs[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
        e, cnt = np.unique(edges, axis=0, return_counts=True)
        bnd = np.zeros(len(nodes), bool)
        leave = foot[e[:, 0]] != foot[e[:, 1]]
        bnd[e[leave].ravel()] = True
        bnd[e[cnt == 1].ravel()] = True
        anchors = np.flatnonzero(bnd & foot)
        if len(anchors) == 0:
            continue
        centre = nodes[foot].mean(0)
        dx = nodes[anchors, 0] - centre[0]
        dz = nodes[anchors, 2] - centre[2]
        medial_sign = np.sign(x_mid - centre[0]) or 1.0
        zone = {
            "inframammary": dz < -np.abs(dx),
            "medial": dx * medial_sign > np.abs(dz),
            "lateral": -dx * medial_sign > np.abs(dz),
        }
        for k, sel in zone.items():
            b = anchors[sel]
            if len(b):
                _, j = muscle_tree.query(nodes[b])
                out[k].append(np.column_stack([b, muscle_only[j]]))
    return {
        f"ligament_{k}": (np.vstack(v) if v else np.zeros((0, 2), np.int64)) for k, v in out.items()
    }


def named_sets(nodes, tets, region, *, grid: Grid, masks: TissueMasks, x_mid: float,
               size_mm: float) -> dict:
    """Every named set the model needs, as ``Mesh`` keyword arguments.

    Parameters
    ----------
    nodes : (N, 3) mm; tets : (M, 4); region : (M,) codes of ``REGIONS``
    grid : the label map's grid (to recognise field-of-view cut planes)
    masks : the tissue masks (to find the thorax side of the muscle)
    x_mid : physical x of the left/right split, mm
    size_mm : element size, mm (width of the superior/inferior end bands)

    Returns
    -------
    dict with ``node_sets``, ``face_sets``, ``node_pairs``
    """
    breast_tet = np.isin(region, BREAST_REGIONS)
    muscle_tet = region == REGIONS["muscle"]
    bfaces, bowner, sfaces, sowner = tet_faces(tets)
    cut = fov_faces(nodes, bfaces, grid)
    skin = bfaces[breast_tet[bowner] & ~cut]
    exposed = bfaces[muscle_tet[bowner] & ~cut]
    fixed_faces = exposed[_fixed_faces(nodes, exposed, masks, grid)] if len(exposed) else exposed

    b0, b1 = breast_tet[sowner[:, 0]], breast_tet[sowner[:, 1]]
    m0, m1 = muscle_tet[sowner[:, 0]], muscle_tet[sowner[:, 1]]
    # oriented out of the muscle tet = from muscle into breast
    iface = np.vstack([sfaces[m0 & b1], sfaces[b0 & m1][:, ::-1]])

    skin_ids = np.unique(skin)
    iface_ids = np.unique(iface)
    left = nodes[:, 0] > x_mid
    extent = np.ptp(nodes[:, 2]) if len(nodes) else 0.0
    band = max(float(size_mm), 0.05 * float(extent))
    skin_sup, skin_inf = _end_bands(nodes, skin_ids, left, band)
    fas_sup, fas_inf = _end_bands(nodes, iface_ids, left, band)
    in_breast = np.zeros(len(nodes), bool)
    in_breast[tets[breast_tet].ravel()] = True
    muscle_only = np.setdiff1d(np.unique(tets[muscle_tet]), np.flatnonzero(in_breast))
    pairs = _ligament_pairs(nodes, skin_ids, iface, muscle_only, left, x_mid)
    return {
        "node_sets": {
            "fixed": np.unique(fixed_faces),
            "skin": skin_ids,
            "interface": iface_ids,
            "skin_superior": skin_sup,
            "skin_inferior": skin_inf,
            "fascia_superior": fas_sup,
            "fascia_inferior": fas_inf,
            "cut_breast": np.unique(bfaces[breast_tet[bowner] & cut]),
            "cut_muscle": np.unique(bfaces[muscle_tet[bowner] & cut]),
        },
        "face_sets": {"skin": skin, "interface": iface},
        "node_pairs": pairs,
    }
