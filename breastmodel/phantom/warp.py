"""Pull-back of points through a solved tetrahedral deformation.

A phantom position is rendered by evaluating the stress-free anatomy at X(p) for every voxel
point p of the deformed body: find the deformed tet that holds p and interpolate the
reference positions with its barycentric coordinates. Points outside every deformed tet keep
their own position (``inside`` tells which were mapped).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, 4) of points (n, 3) in tets with corners (n, 4, 3)."""
    T = (corners[:, 1:] - corners[:, :1]).transpose(0, 2, 1)  # (n, 3, 3) edge columns
    lam = np.linalg.solve(T, (points - corners[:, 0])[..., None])[..., 0]
    return np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)


class PullBack:
    """Map points of a deformed configuration back to the reference configuration.

    Parameters
    ----------
    X : (N, 3) reference node positions, mm
    x : (N, 3) deformed node positions, mm
    tets : (M, 4) node indices
    """

    def __init__(self, X: np.ndarray, x: np.ndarray, tets: np.ndarray):
        self.X = np.asarray(X, np.float64)
        self.x = np.asarray(x, np.float64)
        self.tets = np.asarray(tets, np.int64)
        corners = self.x[self.tets]
        self._tree = cKDTree(corners.mean(axis=1))
        # A point inside a tet is within its circumradius bound of the centroid.
        self._reach = float(np.linalg.norm(corners - corners.mean(axis=1)[:, None], axis=2).max())
        self.lo, self.hi = self.x.min(axis=0), self.x.max(axis=0)

    def __call__(self, points: np.ndarray, *, chunk: int = 200_000,
                 eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        """Reference positions of ``points`` (n, 3) mm and a boolean (n,) ``inside`` mask."""
        p = np.asarray(points, np.float64)
        out = p.copy()
        inside = np.zeros(len(p), bool)
        box = np.all((p >= self.lo - eps) & (p <= self.hi + eps), axis=1)
        todo = np.flatnonzero(box)
        # Most points sit in one of their few nearest tets; the rest get a wider search.
        for k in (8, 32, 128):
            k = min(k, len(self.tets))
            missed = []
            for s in range(0, len(todo), chunk):
                sel = todo[s:s + chunk]
                hit, ref = self._locate(p[sel], k, eps)
                out[sel[hit]] = ref
                inside[sel[hit]] = True
                missed.append(sel[~hit])
            todo = np.concatenate(missed) if missed else todo[:0]
            if not len(todo) or k == len(self.tets):
                break
        return out, inside

    def _locate(self, q: np.ndarray, k: int, eps: float):
        _, cand = self._tree.query(q, k=k, distance_upper_bound=self._reach)
        cand = cand.reshape(len(q), k)
        found = np.full(len(q), -1)
        bary = np.zeros((len(q), 4))
        for j in range(k):
            todo = np.flatnonzero((found < 0) & (cand[:, j] < len(self.tets)))
            if not len(todo):
                continue
            t = cand[todo, j]
            b = barycentric(q[todo], self.x[self.tets[t]])
            ok = np.all(b >= -eps, axis=1)
            found[todo[ok]] = t[ok]
            bary[todo[ok]] = b[ok]
        hit = found >= 0
        return hit, np.einsum("nk,nkd->nd", bary[hit], self.X[self.tets[found[hit]]])
