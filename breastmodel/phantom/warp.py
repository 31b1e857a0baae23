"""Pull-back of points through a solved tetrahedral deformation.

A phantom position is rendered by evaluating the stress-free anatomy at X(p) for every voxel
point p of the deformed body: find the deformed tet that holds p and interpolate the
reference positions with its barycentric coordinates. Points outside every deformed tet keep
their own position (``inside`` tells which were mapped).
"""

from __future__ import annotations

import numpy as np


def barycentric(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, 4) of points (n, 3) in tets with corners (n, 4, 3)."""
    T = (corners[:, 1:] - corners[:, :1]).transpose(0, 2, 1)  # (n, 3, 3) edge columns
    lam = np.linalg.solve(T, (points - corners[:, 0])[..., None])[..., 0]
    return np.concatenate([1.0 - lam.sum(axis=1, keepdims=True), lam], axis=1)


class PullBack:
    """Map points of a deformed configuration back to the reference configuration.

    The deformed tets are binned on a uniform grid of cells (half a median edge wide) by
    their bounding boxes; a point is tested against every tet of its cell only, which finds
    its tet whenever there is one (no nearest-neighbour guess that can miss a sliver).

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
        # Per-tet inverse edge matrices: barycentric coordinates by one small mat-vec.
        T = (corners[:, 1:] - corners[:, :1]).transpose(0, 2, 1)
        det = np.linalg.det(T)
        ok = np.abs(det) > 1e-12 * np.maximum(1.0, np.abs(T).max(axis=(1, 2)) ** 3)
        self._inv = np.zeros_like(T)
        self._inv[ok] = np.linalg.inv(T[ok])
        self._usable = ok
        self._x0 = corners[:, 0].copy()
        self.lo, self.hi = self.x.min(axis=0), self.x.max(axis=0)
        tlo, thi = corners.min(axis=1), corners.max(axis=1)
        edge = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1)
        self._h = max(0.5 * float(np.median(edge)) if len(edge) else 1.0, 1e-6)
        self._n = np.maximum(1, np.ceil((self.hi - self.lo) / self._h).astype(np.int64) + 1)
        a = self._cell(tlo)
        b = self._cell(thi)
        span = b - a + 1
        count = span.prod(axis=1)
        owner = np.repeat(np.arange(len(self.tets)), count)
        # offsets of each tet's cells within its bounding box of cells
        local = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
        sp = span[owner]
        ijk = a[owner] + np.stack([local % sp[:, 0], (local // sp[:, 0]) % sp[:, 1],
                                   local // (sp[:, 0] * sp[:, 1])], axis=1)
        key = self._key(ijk)
        order = np.argsort(key, kind="stable")
        self._cell_tets = owner[order]
        self._start = np.searchsorted(key[order], np.arange(int(np.prod(self._n)) + 1))

    def _cell(self, p: np.ndarray) -> np.ndarray:
        return np.clip(np.floor((p - self.lo) / self._h).astype(np.int64), 0, self._n - 1)

    def _key(self, ijk: np.ndarray) -> np.ndarray:
        return ijk[:, 0] + self._n[0] * (ijk[:, 1] + self._n[1] * ijk[:, 2])

    def __call__(self, points: np.ndarray, *, chunk: int = 100_000,
                 eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        """Reference positions of ``points`` (n, 3) mm and a boolean (n,) ``inside`` mask."""
        p = np.asarray(points, np.float64)
        out = p.copy()
        inside = np.zeros(len(p), bool)
        box = np.all((p >= self.lo - eps) & (p <= self.hi + eps), axis=1)
        todo = np.flatnonzero(box)
        for s in range(0, len(todo), chunk):
            sel = todo[s:s + chunk]
            hit, ref = self._locate(p[sel], eps)
            out[sel[hit]] = ref
            inside[sel[hit]] = True
        return out, inside

    def _locate(self, q: np.ndarray, eps: float):
        key = self._key(self._cell(q))
        first, count = self._start[key], self._start[key + 1] - self._start[key]
        pt = np.repeat(np.arange(len(q)), count)
        t = self._cell_tets[np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count,
                                                                    count) +
                            np.repeat(first, count)]
        lam = np.einsum("nij,nj->ni", self._inv[t], q[pt] - self._x0[t])
        ok = np.all(lam >= -eps, axis=1) & (lam.sum(axis=1) <= 1.0 + eps) & self._usable[t]
        found = np.full(len(q), -1)
        bary = np.zeros((len(q), 4))
        # one containing tet per point (several on shared faces: any is exact)
        hp, first_hit = np.unique(pt[ok], return_index=True)
        ht, lm = t[ok][first_hit], lam[ok][first_hit]
        found[hp] = ht
        bary[hp, 1:] = lm
        bary[hp, 0] = 1.0 - lm.sum(axis=1)
        hit = found >= 0
        return hit, np.einsum("nk,nkd->nd", bary[hit], self.X[self.tets[found[hit]]])
