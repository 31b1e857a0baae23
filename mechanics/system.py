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

# Local (row, col) pairs of the upper triangle of a 12 x 12 element matrix.
_IU, _JU = np.triu_indices(12)


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
        M = len(tets)
        self.free = np.asarray(free, bool)
        fi = np.full(3 * n_nodes, -1, np.int64)
        fi[self.free] = np.arange(int(self.free.sum()))
        self.fi = fi
        self.n_free = int(self.free.sum())
        dofs = (3 * tets[:, :, None] + np.arange(3)).reshape(M, 12)
        fd = fi[dofs]  # (M, 12)
        r, c = fd[:, _IU], fd[:, _JU]  # (M, 78)
        keep_uu = (r >= 0) & (c >= 0)
        lo, hi = np.minimum(r, c), np.maximum(r, c)
        keys = [(lo[keep_uu], hi[keep_uu])]
        if pressure_nodes is not None:
            pidx = np.full(n_nodes, -1, np.int64)
            pidx[pressure_nodes] = self.n_free + np.arange(int(pressure_nodes.sum()))
            self.pidx = pidx
            self.n = self.n_free + int(pressure_nodes.sum())
            ru = np.repeat(fd, 4, axis=1)  # (M, 48): [dof l, node a] as l*4 + a
            cp = np.tile(pidx[tets], (1, 12))
            keep_up = ru >= 0
            keys.append((ru[keep_up], cp[keep_up]))
            pp = np.arange(self.n_free, self.n)
            keys.append((pp, pp))
            self.keep_up = keep_up
        else:
            self.pidx = None
            self.n = self.n_free
            self.keep_up = None
        self.keep_uu = keep_uu
        rows = np.concatenate([k[0] for k in keys])
        cols = np.concatenate([k[1] for k in keys])
        key = rows * self.n + cols
        uniq, inv = np.unique(key, return_inverse=True)
        self.nnz = len(uniq)
        self.indices = (uniq % self.n).astype(np.int32)
        counts = np.bincount(uniq // self.n, minlength=self.n)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
        n_uu = int(keep_uu.sum())
        n_up = 0 if self.keep_up is None else int(self.keep_up.sum())
        # Full-length maps; dropped (constrained) entries go to a spare slot at index nnz.
        map_uu = np.full(keep_uu.size, self.nnz, np.int64)
        map_uu[keep_uu.ravel()] = inv[:n_uu]
        self.map_uu_t = np.ascontiguousarray(map_uu.reshape(M, 78).T).ravel()
        del map_uu
        if self.keep_up is not None:
            self.map_up = np.full(self.keep_up.size, self.nnz, np.int64)
            self.map_up[self.keep_up.ravel()] = inv[n_uu:n_uu + n_up]
        self.map_pp = inv[n_uu + n_up:]

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


def full_from_upper(U: sp.csr_matrix) -> sp.csr_matrix:
    """Symmetric full matrix from its upper triangle."""
    return (U + sp.triu(U, k=1, format="csr").T).tocsr()
