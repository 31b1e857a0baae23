"""Point-to-triangle-surface distances and closest points (open3d ray-casting scene).

open3d's :class:`open3d.t.geometry.RaycastingScene` finds, through its BVH, the nearest
triangle of every query point; it works in float32 only. So the coordinates are centred before
the float32 conversion, and the closest point on the triangle that open3d picked is then
recomputed here in float64 (Ericson's region test). Distances are exact in float64 for the
chosen triangle; the choice itself can be wrong only between triangles whose distances differ
by less than the float32 rounding (about 1e-7 times the size of the scene), which bounds the
error.

Sign convention: negative inside, positive outside.

* A closed (watertight) surface: every edge shared by exactly two triangles. The sign is
  open3d's ``compute_signed_distance`` (ray-crossing parity, odd number of rays); it does not
  depend on the triangle orientation.
* An open surface (a skin patch): inside/outside is not defined, so the sign is that of
  ``(p - closest) . n`` with ``n`` the normal of the nearest triangle from its vertex order
  (right-hand rule, ``(b - a) x (c - a)``): positive on the side the normals point to. Orient
  the triangles outwards to get "positive = outside". Where the closest point lies on an edge
  or a vertex shared with a triangle bent the other way (a concave crease), this face normal
  can give the wrong sign for points off that crease; the magnitude is unaffected.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "TriangleSurface",
    "boundary_distance",
    "boundary_edges",
    "closest_point_on_triangles",
    "is_closed",
    "point_to_surface",
]


def _as_points(a, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"evaluation: {what} must have shape (n, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"evaluation: {what} contain NaN or infinite coordinates")
    return a


def _as_triangles(t, n_vertices: int) -> np.ndarray:
    t = np.asarray(t)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise ValueError(f"evaluation: triangles must have shape (k >= 1, 3), got {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"evaluation: triangles must be integer indices, got {t.dtype}")
    if t.min() < 0 or t.max() >= n_vertices:
        raise ValueError(
            f"evaluation: triangle indices must lie in [0, {n_vertices}), "
            f"got [{t.min()}, {t.max()}]"
        )
    return t.astype(np.int64)


def is_closed(triangles) -> bool:
    """Whether every edge of a triangle mesh is shared by exactly two triangles (watertight).

    Parameters
    ----------
    triangles : (k, 3) int array

    Returns
    -------
    bool
    """
    _, counts = _edge_counts(triangles)
    return bool(np.all(counts == 2))


def _edge_counts(triangles) -> tuple[np.ndarray, np.ndarray]:
    """The distinct edges (e, 2) of a triangle mesh, vertex pairs sorted, and how many
    triangles hold each."""
    t = np.asarray(triangles, dtype=np.int64)
    edges = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    codes = edges[:, 0] * (int(t.max()) + 1) + edges[:, 1]  # 1-D: np.unique(axis=0) is slow
    _, first, counts = np.unique(codes, return_index=True, return_counts=True)
    return edges[first], counts


def closest_point_on_triangles(p, a, b, c) -> np.ndarray:
    """Closest point of each triangle ``(a[i], b[i], c[i])`` to ``p[i]`` (float64).

    Voronoi-region test of Ericson, *Real-Time Collision Detection* (2005), sec. 5.1.5,
    vectorised; degenerate (zero-area) triangles fall back to their edges.

    Parameters
    ----------
    p, a, b, c : (n, 3) float arrays, mm

    Returns
    -------
    (n, 3) float64 array, mm
    """
    p, a, b, c = (np.asarray(x, dtype=np.float64) for x in (p, a, b, c))

    def dot(u, v):
        return np.einsum("ij,ij->i", u, v)

    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

    out = np.empty_like(p)
    todo = np.ones(len(p), dtype=bool)

    def assign(mask, value_fn):
        m = todo & mask
        if m.any():
            out[m] = value_fn(m)
            todo[m] = False

    with np.errstate(divide="ignore", invalid="ignore"):
        assign((d1 <= 0) & (d2 <= 0), lambda m: a[m])
        assign((d3 >= 0) & (d4 <= d3), lambda m: b[m])
        assign((vc <= 0) & (d1 >= 0) & (d3 <= 0) & (d1 - d3 > 0),
               lambda m: a[m] + (d1[m] / (d1[m] - d3[m]))[:, None] * ab[m])
        assign((d6 >= 0) & (d5 <= d6), lambda m: c[m])
        assign((vb <= 0) & (d2 >= 0) & (d6 <= 0) & (d2 - d6 > 0),
               lambda m: a[m] + (d2[m] / (d2[m] - d6[m]))[:, None] * ac[m])
        e1, e2 = d4 - d3, d5 - d6
        assign((va <= 0) & (e1 >= 0) & (e2 >= 0) & (e1 + e2 > 0),
               lambda m: b[m] + (e1[m] / (e1[m] + e2[m]))[:, None] * (c[m] - b[m]))
        denom = va + vb + vc
        assign(denom > 0, lambda m: a[m] + (vb[m] / denom[m])[:, None] * ab[m]
               + (vc[m] / denom[m])[:, None] * ac[m])
    if todo.any():  # degenerate triangles whose region tests all failed: nearest edge point
        idx = np.flatnonzero(todo)
        cands = [_closest_on_segment(p[idx], s, e)
                 for s, e in ((a[idx], b[idx]), (b[idx], c[idx]), (c[idx], a[idx]))]
        dists = np.stack([np.linalg.norm(q - p[idx], axis=1) for q in cands])
        best = np.argmin(dists, axis=0)
        out[idx] = np.stack(cands)[best, np.arange(len(idx))]
    return out


def boundary_edges(triangles) -> np.ndarray:
    """(b, 2) vertex pairs of the edges that belong to one triangle only (the rim of an open
    surface; none for a closed one)."""
    edges, counts = _edge_counts(triangles)
    return edges[counts == 1]


def boundary_distance(vertices, triangles, points, *, spacing_mm: float = 0.25) -> np.ndarray:
    """Distance (mm) from each point to the rim of an open triangle surface (its boundary
    edges), to within ``spacing_mm / 2`` (the rim is sampled every ``spacing_mm``); infinite
    for a closed surface. Used to fade out the fit's residuals whose closest point lies on
    the rim, where the sign of a point-to-surface distance is not defined."""
    from scipy.spatial import cKDTree

    v = _as_points(vertices, "vertices")
    p = _as_points(points, "query points")
    e = boundary_edges(_as_triangles(triangles, len(v)))
    if len(e) == 0:
        return np.full(len(p), np.inf)
    a, b = v[e[:, 0]], v[e[:, 1]]
    n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / spacing_mm).astype(int), 1)
    k = np.repeat(np.arange(len(e)), n)
    t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
    samples = np.concatenate([a[k] + t[:, None] * (b - a)[k], b])
    return cKDTree(samples).query(p)[0]


def _closest_on_segment(p, s, e):
    d = e - s
    dd = np.einsum("ij,ij->i", d, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dd > 0, np.einsum("ij,ij->i", p - s, d) / dd, 0.0)
    return s + np.clip(t, 0.0, 1.0)[:, None] * d


class TriangleSurface:
    """A triangle surface ready for repeated distance queries (builds the BVH once).

    Parameters
    ----------
    vertices : (m, 3) float array, mm
    triangles : (k, 3) int array, indices into ``vertices``

    Inputs are copied; the surface is immutable.
    """

    def __init__(self, vertices, triangles):
        import open3d as o3d

        self.vertices = _as_points(vertices, "surface vertices").copy()
        self.triangles = _as_triangles(triangles, len(self.vertices)).copy()
        self.vertices.flags.writeable = False
        self.triangles.flags.writeable = False
        self.closed = is_closed(self.triangles)
        # Centre before float32 so that rounding scales with the surface size, not its offset.
        self._origin = 0.5 * (self.vertices.min(axis=0) + self.vertices.max(axis=0))
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(self.vertices - self._origin, np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(self.triangles, np.uint32)),
        )
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        self.face_normals = np.cross(b - a, c - a)  # area-weighted, orientation from order
        self.face_normals.flags.writeable = False

    def _query32(self, points):
        import open3d as o3d

        return o3d.core.Tensor(np.ascontiguousarray(points - self._origin, np.float32))

    def closest(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Closest surface point of each query point and the triangle it lies on.

        Parameters
        ----------
        points : (n, 3) float array, mm

        Returns
        -------
        closest : (n, 3) float64 array, mm
        triangle_ids : (n,) int64 array
        """
        points = _as_points(points, "query points")
        if len(points) == 0:
            return np.empty((0, 3)), np.empty(0, dtype=np.int64)
        ans = self._scene.compute_closest_points(self._query32(points))
        tri = ans["primitive_ids"].numpy().astype(np.int64)
        corners = [self.vertices[self.triangles[tri, i]] for i in range(3)]
        return closest_point_on_triangles(points, *corners), tri

    def distance(self, points, *, signed: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Distances from points to the surface, and the closest points.

        Parameters
        ----------
        points : (n, 3) float array, mm
        signed : bool
            Negative inside, positive outside (see the module notes for open surfaces).

        Returns
        -------
        distances : (n,) float64 array, mm
        closest : (n, 3) float64 array, mm
        """
        points = _as_points(points, "query points")
        closest, tri = self.closest(points)
        d = np.linalg.norm(points - closest, axis=1)
        if signed and len(points):
            if self.closed:
                # 3 rays (odd) guard against a ray grazing an edge or a vertex.
                s = self._scene.compute_signed_distance(self._query32(points), nsamples=3)
                sign = np.where(s.numpy() < 0, -1.0, 1.0)
            else:
                side = np.einsum("ij,ij->i", points - closest, self.face_normals[tri])
                sign = np.where(side < 0, -1.0, 1.0)
            d = sign * d
        return d, closest


def point_to_surface(points, vertices, triangles, *, signed: bool = False):
    """Point-to-triangle distances from points to a triangle surface, and the closest points.

    Parameters
    ----------
    points : (n, 3) float array, mm
        Query points.
    vertices : (m, 3) float array, mm
    triangles : (k, 3) int array
        The surface; it need not be closed.
    signed : bool
        If True, distances are negative inside and positive outside. A closed (watertight)
        surface gets its sign from ray parity (open3d ``compute_signed_distance``); an open
        one from the normal of the nearest triangle (vertex order, right-hand rule).

    Returns
    -------
    distances : (n,) float64 array, mm
    closest : (n, 3) float64 array, mm
        The closest point of the surface to each query point.
    """
    return TriangleSurface(vertices, triangles).distance(points, signed=signed)
