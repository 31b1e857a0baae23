"""The displacement field u(x) of one solved position over a whole image volume.

:func:`position_deformation` gives :func:`~breastmodel.phantom.writer.make_phantom`'s
``deformation`` contract for a :class:`~breastmodel.phantom.simulated.SimulatedPosition`:
the tet pull-back inside the deformed mesh, the displacement of the closest deformed surface
point outside it (:func:`closest_on_triangles`), and air where the tissue has moved away.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from breastmodel.phantom.anatomy import FAT, GLAND, MUSCLE, SKIN, Anatomy
from breastmodel.phantom.warp import PullBack

if TYPE_CHECKING:
    from breastmodel.phantom.simulated import SimulatedPosition

__all__ = ["AIR_POINT", "closest_on_triangles", "position_deformation"]

#: Tissue that the mesh carries: far outside the deformed mesh such a code means "moved away".
_MESHED = np.array([FAT, MUSCLE, GLAND, SKIN])
#: A patient-frame point far in front of the body: air for any anatomy (outside every
#: primitive), used as the material point of voxels the tissue has left.
AIR_POINT = np.array([0.0, -1.0e5, 0.0])


def _boundary_faces(tets: np.ndarray) -> np.ndarray:
    """(F, 3) faces used by one tet only (the outer surface, and both interface sides of a
    split mesh)."""
    f = tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3)
    _, inv, cnt = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True,
                            return_counts=True)
    return f[cnt[inv.ravel()] == 1]


def closest_on_triangles(p: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each of k candidate triangles to each point.

    Parameters
    ----------
    p : (n, 3) points, mm
    tri : (n, k, 3, 3) candidate triangle corners, mm

    Returns
    -------
    d2 : (n, k) squared distances, mm^2
    bary : (n, k, 3) barycentric coordinates of the closest points
    """
    A, e0, e1 = tri[..., 0, :], tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]
    v = p[:, None, :] - A
    d00, d01, d11 = (np.einsum("nki,nki->nk", a, b) for a, b in ((e0, e0), (e0, e1), (e1, e1)))
    d20, d21 = np.einsum("nki,nki->nk", v, e0), np.einsum("nki,nki->nk", v, e1)
    den = d00 * d11 - d01 * d01
    den = np.where(den > 0, den, np.inf)
    b1, b2 = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    bary = np.stack([1.0 - b1 - b2, b1, b2], axis=-1)
    # Projection inside the triangle: it is the closest point; otherwise the closest point
    # lies on one of the three edges.
    best_d2 = np.full(b1.shape, np.inf)
    best_b = np.zeros(bary.shape)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        P, Q = tri[..., i, :], tri[..., j, :]
        e = Q - P
        ee = np.einsum("nki,nki->nk", e, e)
        t = np.clip(np.einsum("nki,nki->nk", p[:, None, :] - P, e) / np.maximum(ee, 1e-300),
                    0.0, 1.0)
        d2 = np.sum((P + t[..., None] * e - p[:, None, :]) ** 2, axis=-1)
        better = d2 < best_d2
        best_d2 = np.where(better, d2, best_d2)
        b = np.zeros(bary.shape)
        b[..., i], b[..., j] = 1.0 - t, t
        best_b = np.where(better[..., None], b, best_b)
    inside = np.all(bary >= 0.0, axis=-1)
    q = A + b1[..., None] * e0 + b2[..., None] * e1
    d2_plane = np.sum((q - p[:, None, :]) ** 2, axis=-1)
    return (np.where(inside, d2_plane, best_d2),
            np.where(inside[..., None], bary, best_b))


def position_deformation(anatomy: Anatomy, sim: SimulatedPosition, *,
                         field_box: tuple | None = None, band_mm: float = 6.0, candidates: int = 8,
                         chunk: int = 50_000) -> Callable[[np.ndarray], np.ndarray]:
    """The ``u(x)`` of :func:`make_phantom`'s ``deformation`` contract for one position.

    Inside the deformed mesh, X(x) comes from the tet pull-back (exact on the mesh).
    Outside it, x takes the displacement of its closest point on the deformed mesh surface
    (interpolated on that triangle), so u is continuous across the surface: the skin layer
    and the markers just outside the (voxel-smoothed) mesh surface move with it, and the
    fixed-point solve of marker positions in :func:`make_phantom` converges. Where the
    tissue has moved away, this extrapolation maps x to air in the reference anatomy; where
    a point farther than ``band_mm`` from the deformed surface (beyond the skin layer and
    markers that the voxel-smoothed mesh surface may leave outside) still lands on tissue
    that the mesh carries (fat, gland, skin, muscle) inside the meshed box, that tissue has
    left x, so x must render as air: it is mapped to ``AIR_POINT``, a point far in front of
    the body that every anatomy classifies as air.

    Parameters
    ----------
    anatomy
        The anatomy the mesh was made from.
    sim
        A solved position.
    field_box
        (lo, hi) patient-frame box, mm, in which the mesh holds all carried tissue (default
        the anatomy's field of view); outside it the extrapolated field is used as is.
    band_mm
        Distance outside the deformed surface within which the extrapolation is trusted, mm
        (markers reach 2 r + gap = 4.5 mm out; the mesh surface lies up to ~1 mm inside).
    candidates
        Surface triangles (nearest centroids) searched per point.
    chunk
        Points per batch of the closest-point search (bounds memory).
    """
    mesh, X, x = sim
    pull = PullBack(X, x, mesh.tets)
    surface = _DeformedSurface.of(X, x, mesh.tets, candidates=candidates, chunk=chunk)
    node_tree = cKDTree(x[np.unique(surface.faces)])
    edge = _longest_edge(x, mesh.tets)
    all_tree = cKDTree(x)
    reach = band_mm + edge
    lo, hi = (np.asarray(b, float) for b in (field_box or anatomy.body_box))

    def u(points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float)
        # Only points within an element edge of a node can lie in a tet; the pull-back's
        # search is costly for the many points (air, thorax) that lie in no tet.
        dn_all, _ = all_tree.query(p, k=1, distance_upper_bound=edge)
        maybe = np.flatnonzero(dn_all <= edge)
        ref, hit = pull(p[maybe])
        inside = np.zeros(len(p), bool)
        inside[maybe[hit]] = True
        disp = np.zeros_like(p)
        disp[maybe[hit]] = p[maybe[hit]] - ref[hit]
        out = np.flatnonzero(~inside)
        # Points far from the surface (beyond the band by more than an element) keep u = 0:
        # only the air check below concerns them.
        dn, _ = node_tree.query(p[out], k=1, distance_upper_bound=reach)
        near = out[dn <= reach]
        dist2 = np.full(len(out), np.inf)
        disp[near], dist2[dn <= reach] = surface.extrapolate(p[near])
        in_box = np.all((p[out] >= lo) & (p[out] <= hi), axis=1) & (dist2 > band_mm**2)
        _air_where_tissue_left(anatomy, p, disp, out[in_box])
        return disp

    return u


def _longest_edge(x: np.ndarray, tets) -> float:
    """Longest edge of the deformed tets, mm."""
    tet_x = x[np.asarray(tets)]
    return float(max(np.linalg.norm(tet_x[:, i] - tet_x[:, j], axis=1).max()
                     for i in range(4) for j in range(i + 1, 4)))


@dataclass(frozen=True, eq=False)
class _DeformedSurface:
    """The deformed mesh surface with its nodal displacements, searched by triangle centroid.

    ``faces`` (F, 3) node indices, ``corners`` (F, 3, 3) deformed corners mm, ``u_nodes``
    (N, 3) nodal displacements mm, ``k`` candidate triangles per point, ``chunk`` points per
    batch of the search.
    """

    faces: np.ndarray
    corners: np.ndarray
    tree: cKDTree
    u_nodes: np.ndarray
    k: int
    chunk: int

    @classmethod
    def of(cls, X: np.ndarray, x: np.ndarray, tets, *, candidates: int,
           chunk: int) -> _DeformedSurface:
        faces = _boundary_faces(np.asarray(tets, np.int64))
        corners = x[faces]  # (F, 3, 3)
        return cls(faces, corners, cKDTree(corners.mean(axis=1)), x - X,
                   min(int(candidates), len(faces)), chunk)

    def extrapolate(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (n, 3) mm of each point's closest surface point (interpolated on its
        triangle) and the squared distance (n,) mm^2 to it."""
        disp, dist2 = np.empty((len(q), 3)), np.empty(len(q))
        for s in range(0, len(q), self.chunk):
            qs = q[s:s + self.chunk]
            _, cand = self.tree.query(qs, k=self.k)
            cand = cand.reshape(len(qs), self.k)
            d2, bary = closest_on_triangles(qs, self.corners[cand])
            j = np.argmin(d2, axis=1)
            rows = np.arange(len(qs))
            dist2[s:s + self.chunk] = d2[rows, j]
            f = self.faces[cand[rows, j]]  # (n, 3) nodes of the closest triangle
            disp[s:s + self.chunk] = np.einsum("nc,ncd->nd", bary[rows, j], self.u_nodes[f])
        return disp, dist2


def _air_where_tissue_left(anatomy: Anatomy, p: np.ndarray, disp: np.ndarray,
                           chk: np.ndarray) -> None:
    """Map the points ``chk`` whose material point lands on tissue the mesh carries to
    :data:`AIR_POINT` (that tissue has moved away from them); ``disp`` is updated in place."""
    if len(chk):
        code = anatomy.classify(p[chk] - disp[chk])
        gone = chk[np.isin(code, _MESHED)]
        disp[gone] = p[gone] - AIR_POINT
