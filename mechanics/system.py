"""The reduced sparse system the Newton solver factorises, with a pattern built once.

Unknowns: the free displacement dofs, then (formulation "anp") one pressure per node that
carries volume. The matrix is the symmetric saddle-point tangent

    [ K_uu   G       ] [du]   [-R_u]
    [ G^T   -V/K     ] [dp] = [  0 ]

whose Schur complement is the condensed tangent K_uu + G diag(K/V) G^T. Keeping p keeps the
sparsity of a linear tet mesh (the condensed matrix couples two rings of neighbours).
Only the upper triangle is stored; entries are scattered with a precomputed index map.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

# Local (row, col) pairs of the upper triangle of a 12 x 12 element matrix, and the 10 node
# pairs a <= b of a tet.
_IU, _JU = np.triu_indices(12)
PAIR_A, PAIR_B = np.triu_indices(4)
_PAIR_OF = {(int(a), int(b)): q for q, (a, b) in enumerate(zip(PAIR_A, PAIR_B, strict=True))}


class ReducedSystem:
    """Sparsity pattern and scatter maps for one mesh topology and one set of free dofs.

    Parameters
    ----------
    tets : (M, 4) int
    n_nodes : int
    free : (3N,) bool, True for unconstrained displacement dofs
    pressure_nodes : (N,) bool nodes that carry a pressure unknown, or None (no pressure)
    """

    def __init__(self, tets: np.ndarray, n_nodes: int, free: np.ndarray,
                 pressure_nodes: np.ndarray | None):
        tets = np.asarray(tets, np.int64)
        M = len(tets)
        self.free = np.asarray(free, bool)
        fi = np.full(3 * n_nodes, -1, np.int64)
        fi[self.free] = np.arange(int(self.free.sum()))
        self.fi = fi
        self.n_free = int(self.free.sum())
        if pressure_nodes is not None:
            pidx = np.full(n_nodes, -1, np.int64)
            pidx[pressure_nodes] = self.n_free + np.arange(int(pressure_nodes.sum()))
            self.pidx = pidx
            self.n = self.n_free + int(pressure_nodes.sum())
        else:
            self.pidx = None
            self.n = self.n_free
        n = self.n
        # The pattern from the unique node pairs of the mesh (a few per node), not from the
        # 126 entries of every element: 150k tets peaked at 2.0 GB in np.unique over the
        # 19M element entries, and take 0.3 GB this way.
        lo = np.minimum(tets[:, PAIR_A], tets[:, PAIR_B])  # (M, 10) node pairs of each tet
        hi = np.maximum(tets[:, PAIR_A], tets[:, PAIR_B])
        pair_key = lo * n_nodes + hi
        del lo, hi
        pairs = _sorted_unique(pair_key.ravel())
        a, b = pairs // n_nodes, pairs % n_nodes
        k3 = np.arange(3)
        r = fi[3 * a[:, None, None] + k3[None, :, None]]  # (U, 3, 1): dofs of a
        c = fi[3 * b[:, None, None] + k3[None, None, :]]  # (U, 1, 3): dofs of b
        r, c = np.broadcast_arrays(r, c)
        ok = (r >= 0) & (c >= 0)
        keys = [np.minimum(r, c)[ok] * n + np.maximum(r, c)[ok]]
        if self.pidx is not None:
            for x, y in ((a, b), (b, a)):  # displacement of x with the pressure of y
                rr = fi[3 * x[:, None] + k3]
                cc = np.broadcast_to(pidx[y][:, None], rr.shape)
                ok = (rr >= 0) & (cc >= 0)
                keys.append(rr[ok] * n + cc[ok])
            pp = pidx[pidx >= 0]
            keys.append(pp * n + pp)
        uniq = _sorted_unique(np.concatenate(keys))
        del keys, ok
        self.nnz = len(uniq)
        self.indices = (uniq % n).astype(np.int32)
        counts = np.bincount(uniq // n, minlength=n)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        # Scatter maps through per-node-pair tables (position of each 3x3 and 3x1 block
        # entry; constrained entries go to a spare slot at index nnz): one search per node
        # pair instead of one per element entry (150k tets: 4.7 s -> about 1 s).
        t_uu = _locate(uniq, r, c, n).ravel()  # (U * 9,): [pair, i of a, k of b]
        del r, c
        pid = np.searchsorted(pairs, pair_key)  # (M, 10)
        del pair_key
        # The stiffness map is element-last (78, M), as the solid stores Kup.
        self.map_uu_t = np.empty((78, M), np.int64)
        for j in range(78):
            (na, i), (nb, k) = divmod(int(_IU[j]), 3), divmod(int(_JU[j]), 3)
            base = 9 * pid[:, _PAIR_OF[na, nb]]
            swap = tets[:, na] > tets[:, nb]
            self.map_uu_t[j] = t_uu[base + np.where(swap, 3 * k + i, 3 * i + k)]
        self.map_uu_t = self.map_uu_t.ravel()
        if self.pidx is not None:
            t_up = np.stack([_locate(uniq, fi[3 * a[:, None] + k3], pidx[b][:, None], n),
                             _locate(uniq, fi[3 * b[:, None] + k3], pidx[a][:, None], n)],
                            axis=1).ravel()  # (U * 6,): [pair, lower node's dof?, i]
            self.map_up = np.empty((M, 48), np.int64)
            for j in range(48):  # column l * 4 + a: displacement dof l with pressure of node a
                (nd, i), npr = divmod(j // 4, 3), j % 4
                base = 6 * pid[:, _PAIR_OF[min(nd, npr), max(nd, npr)]]
                upper = tets[:, nd] > tets[:, npr]  # the displacement node is the pair's b
                self.map_up[:, j] = t_up[base + 3 * upper + i]
            self.map_up = self.map_up.ravel()
            self.map_pp = np.searchsorted(uniq, pp * n + pp)

    def assemble(self, Kup: np.ndarray, dv: np.ndarray | None = None,
                 pp_diag: np.ndarray | None = None) -> sp.csr_matrix:
        """Upper triangle (csr, n x n) from element stiffness (M,78), dv (M,4,3) and the
        pressure block diagonal (n_p,) (negative compliance -V/K)."""
        # The solid stores Kup as (78, M) (element index last), so the map is kept in that
        # order: no copy of Kup here.
        data = np.bincount(self.map_uu_t, weights=np.ascontiguousarray(Kup.T).ravel(),
                           minlength=self.nnz + 1)
        if self.pidx is not None:
            M = len(Kup)
            g = np.repeat(dv.reshape(M, 12) * 0.25, 4, axis=1)
            data += np.bincount(self.map_up, weights=g.ravel(), minlength=self.nnz + 1)
            data[self.map_pp] += pp_diag
        data = data[: self.nnz]
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))

    def extra_upper(self, rows, cols, vals, *, symmetric: bool) -> sp.csr_matrix | None:
        """Effect tangent entries (dof numbering) restricted to free dofs.

        Symmetric: the upper triangle only; else the full matrix (both in reduced numbering).
        """
        if len(vals) == 0:
            return None
        r, c = self.fi[np.asarray(rows)], self.fi[np.asarray(cols)]
        keep = (r >= 0) & (c >= 0)
        r, c, v = r[keep], c[keep], np.asarray(vals, float)[keep]
        if symmetric:
            up = r <= c
            r, c, v = r[up], c[up], v[up]
        return sp.coo_matrix((v, (r, c)), shape=(self.n, self.n)).tocsr()


def _sorted_unique(x: np.ndarray) -> np.ndarray:
    """np.unique by sorting (numpy 2.4's default hash-based unique took 2.5 s of the 3.8 s
    pattern build at 150k tets, the sort 0.35 s)."""
    x = np.sort(x)
    return x[np.concatenate(([True], x[1:] != x[:-1]))] if x.size else x


def _locate(uniq: np.ndarray, r: np.ndarray, c: np.ndarray, n: int) -> np.ndarray:
    """Positions in the sorted keys ``uniq`` of the upper-triangle entries (r, c); nnz
    (the spare slot) where r or c is constrained (< 0)."""
    r, c = np.broadcast_arrays(r, c)
    ok = (r >= 0) & (c >= 0)
    key = np.minimum(r, c) * n + np.maximum(r, c)
    return np.where(ok, np.searchsorted(uniq, np.where(ok, key, 0)), len(uniq))


def full_from_upper(U: sp.csr_matrix) -> sp.csr_matrix:
    """Symmetric full matrix from its upper triangle.

    The solver calls this at every evaluation of an unsymmetric model (friction) with
    matrices of one pattern: from the second call with an equal pattern on, the full pattern
    and the gather map from the upper entries are reused and each call is one comparison of
    the index arrays and one gather (measured 20k tets: 9 ms -> 2 ms).
    """
    plan = next((c[2] for c in _FULL_CACHE if len(c[1]) == U.nnz and len(c[0]) == len(U.indptr)
                 and np.array_equal(c[0], U.indptr) and np.array_equal(c[1], U.indices)), None)
    if plan is None:
        if len(_FULL_CACHE) > 4:
            _FULL_CACHE.clear()
        _FULL_CACHE.append((U.indptr.copy(), U.indices.copy(), []))  # map at the 2nd sighting
        return (U + sp.triu(U, k=1, format="csr").T).tocsr()
    if not plan:
        rows = np.repeat(np.arange(U.shape[0]), np.diff(U.indptr))
        if np.any(U.indices < rows):  # not an upper triangle: no map
            return (U + sp.triu(U, k=1, format="csr").T).tocsr()
        Up = sp.csr_matrix((np.arange(1, U.nnz + 1, dtype=float), U.indices, U.indptr),
                           shape=U.shape)
        F = (Up + sp.triu(Up, k=1, format="csr").T).tocsr()
        F.sort_indices()
        # every full entry is one upper entry (diagonal, upper, or mirrored strict upper)
        plan.extend((F.data.astype(np.int64) - 1, F.indices, F.indptr))
    take, indices, indptr = plan
    return sp.csr_matrix((U.data[take], indices, indptr), shape=U.shape)


#: full_from_upper's patterns: (upper indptr, upper indices, [gather map, full indices,
#: full indptr], empty until the pattern comes a second time)
_FULL_CACHE: list = []
