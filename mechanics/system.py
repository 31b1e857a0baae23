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

import time

import numpy as np
import scipy.sparse as sp

# Local (row, col) pairs of the upper triangle of a 12 x 12 element matrix, and the 10 node
# pairs a <= b of a tet.
_IU, _JU = np.triu_indices(12)
PAIR_A, PAIR_B = np.triu_indices(4)
_PAIR_OF = {(int(a), int(b)): q for q, (a, b) in enumerate(zip(PAIR_A, PAIR_B, strict=True))}
#: Each upper-triangle entry j of a 12 x 12 element matrix (rows i, k): its node pair q,
#: the flag that the element has the pair's nodes in the other order (row q of the block's
#: (10, k) flags), its place in the pair's 3 x 3 table, and the step to its place there
#: when the flag is set (the transposed entry).
_UU = [(_PAIR_OF[i // 3, k // 3], _PAIR_OF[i // 3, k // 3], 3 * (i % 3) + k % 3,
        3 * (k % 3) + i % 3 - 3 * (i % 3) - k % 3)
       for i, k in zip(_IU.tolist(), _JU.tolist(), strict=True)]
#: Each pressure coupling entry l * 4 + a (displacement dof l = 3 * d + i of node d, the
#: pressure of node a): its node pair, the flag that d's node number is above a's (row
#: 4 * d + a of the block's (16, k) flags: d is then the pair's second node), its place in
#: the pair's table of 6 for a first node d, and the step to the second node's place.
_UP = [(_PAIR_OF[min(j // 12, j % 4), max(j // 12, j % 4)], 4 * (j // 12) + j % 4,
        (j // 4) % 3, 3) for j in range(48)]
#: A mesh of at most BLOCK elements is evaluated and scattered whole, with stored scatter
#: maps (fastest: the 20k-tet hemisphere's evaluation and assembly 43 ms, in blocks of 16384
#: 56-67 ms); a larger one streams through blocks of STREAM elements, so that its
#: temporaries are a block's (78 x 16384 doubles, 10 MB), not the mesh's (150k tets: 100
#: MB). Measured at 150k tets: blocks of 16384 against 32768, evaluation and assembly
#: 551-563 against 594-605 ms, the solve's peak 939 against 976 MB.
BLOCK = 32768
STREAM = 16384


def blocks(M: int) -> list[slice]:
    """The element blocks of a mesh of M elements: the whole, or STREAM elements each."""
    step = max(1, M if M <= BLOCK else STREAM)
    return [slice(s, min(M, s + step)) for s in range(0, M, step)]


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
        self._tets = tets
        self._t_uu = _locate(uniq, r, c, n).ravel().astype(np.int32)  # (U*9,): [pair, i, k]
        del r, c
        self._pid = np.searchsorted(pairs, pair_key).astype(np.int32)  # (M, 10)
        del pair_key
        self._t_up = None
        if self.pidx is not None:
            self._t_up = np.stack([_locate(uniq, fi[3 * a[:, None] + k3], pidx[b][:, None], n),
                                   _locate(uniq, fi[3 * b[:, None] + k3], pidx[a][:, None], n)],
                                  axis=1).ravel().astype(np.int32)  # (U*6,): [pair, b's?, i]
        # A mesh of one block keeps its element maps (int64: with int32 maps the 20k-tet
        # hemisphere's scatter measured 7-50 % slower); a larger one makes each block's from
        # the tables as it is scattered (150k tets: the maps were 78 MB of the solve's peak,
        # the tables and the pair ids are 20 MB).
        self.map_uu = self.map_up = None
        if M <= BLOCK:
            self.map_uu = self.stiffness_map(slice(None)).astype(np.int64)
            if self.pidx is not None:
                self.map_up = self.pressure_map(slice(None)).astype(np.int64)
            self._t_uu = self._t_up = self._pid = self._tets = None
        if self.pidx is not None:
            self.map_pp = np.searchsorted(uniq, pp * n + pp)

    def stiffness_map(self, cols) -> np.ndarray:
        """Where the upper-triangle stiffness entries of the elements ``cols`` (a slice or an
        index array) go in the matrix's entries: (78, k), element-last as the solid's
        stiffness blocks come."""
        if self.map_uu is not None:
            return self.map_uu[:, cols]
        t = self._tets[cols]
        swap = np.ascontiguousarray((t[:, PAIR_A] > t[:, PAIR_B]).T)  # (10, k)
        return self._from_tables(self._t_uu, 9, cols, swap, _UU)

    def pressure_map(self, cols) -> np.ndarray:
        """Where the pressure coupling entries of the elements ``cols`` go: (48, k),
        element-last; row l * 4 + a, displacement dof l with the pressure of node a."""
        if self.map_up is not None:
            return self.map_up[:, cols]
        t = self._tets[cols]
        upper = np.ascontiguousarray((t[:, :, None] > t[:, None, :]).reshape(-1, 16).T)
        return self._from_tables(self._t_up, 6, cols, upper, _UP)

    def _from_tables(self, table, width, cols, flag, entries) -> np.ndarray:
        """Element entries' positions from a per-node-pair ``table`` (``width`` entries a
        pair): entry j of element e reads table[width * pair + plain + flag * step] with
        (pair, flag row, plain, step) = entries[j] (13 ms for 32768 tets' stiffness)."""
        base = np.ascontiguousarray((width * self._pid[cols]).T)  # (10, k)
        out = np.empty((len(entries), base.shape[1]), np.int32)
        tmp = np.empty(base.shape[1], np.int32)
        for j, (q, f, plain, step) in enumerate(entries):
            np.multiply(flag[f], step, out=tmp)
            tmp += base[q]
            tmp += plain
            np.take(table, tmp, out=out[j])
        return out

    def start(self) -> Assembly:
        """An empty Newton matrix to fill block by block (see :class:`Assembly`)."""
        return Assembly(self)

    def assemble(self, Kup: np.ndarray, dv: np.ndarray | None = None,
                 pp_diag: np.ndarray | None = None) -> sp.csr_matrix:
        """Upper triangle (csr, n x n) from element stiffness (M,78), dv (M,4,3) and the
        pressure block diagonal (n_p,) (negative compliance -V/K)."""
        asm = self.start()
        for sl in blocks(len(Kup)):
            asm.add_stiffness(sl, Kup[sl].T)
        return asm.matrix(dv, pp_diag)


class Assembly:
    """The upper-triangle entries of one Newton matrix, summed block by block of elements,
    so that no mesh-sized array of element matrices exists (150k tets: the (78, M) element
    stiffness and the (M, 48) pressure coupling were 160 MB at the solve's peak). The
    solid hands its stiffness blocks to :meth:`add_stiffness` as it computes them; the wall
    and CPU time spent here are kept apart (``wall``, ``cpu``) for the solve's phase times."""

    def __init__(self, system: ReducedSystem):
        self.sys = system
        self.data = None  # (nnz + 1,): the last slot takes constrained entries
        self.wall = self.cpu = 0.0

    def add_stiffness(self, cols, KT: np.ndarray) -> None:
        """Add element stiffness (78, k), upper triangles of the elements ``cols`` (a slice
        or an index array) in the order of their element-last columns."""
        t0, c0 = time.perf_counter(), time.process_time()
        self._scatter(self.sys.stiffness_map(cols), KT)
        self.wall += time.perf_counter() - t0
        self.cpu += time.process_time() - c0

    def _scatter(self, where: np.ndarray, values: np.ndarray) -> None:
        """Add ``values`` at the positions ``where`` (the same 2-D shape) into the entries,
        in place: at once where both are contiguous, else row by row. Unlike a
        bincount over nnz per block, no nnz-sized sum, no int64 copy of an int32 map and
        no copy of a strided slice exists (a bincount on a synthetic 32768-tet block of the
        150k mesh's size: 53 MB of temporaries, 22.6 against 16.4 ms)."""
        if self.data is None:
            self.data = np.zeros(self.sys.nnz + 1)
        if where.flags.c_contiguous and values.flags.c_contiguous:
            np.add.at(self.data, where.ravel(), values.ravel())
        else:
            for w, v in zip(where, values, strict=True):
                np.add.at(self.data, w, v)

    def matrix(self, dv: np.ndarray | None, pp_diag: np.ndarray | None) -> sp.csr_matrix:
        """The assembled upper triangle (csr, n x n), with the pressure coupling dv (M, 4,
        3) and the pressure block's diagonal (n_p,) where the system has pressures."""
        t0, c0 = time.perf_counter(), time.process_time()
        s = self.sys
        if self.data is None:
            self.data = np.zeros(s.nnz + 1)
        if s.pidx is not None:
            for sl in blocks(len(dv)):  # entry (l * 4 + a) of an element: dv_l / 4
                g = np.repeat(0.25 * dv[sl].reshape(-1, 12).T, 4, axis=0)
                self._scatter(s.pressure_map(sl), g)
            self.data[s.map_pp] += pp_diag
        A = sp.csr_matrix((self.data[: s.nnz], s.indices, s.indptr), shape=(s.n, s.n))
        self.data = None
        self.wall += time.perf_counter() - t0
        self.cpu += time.process_time() - c0
        return A


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
    """Symmetric full matrix from its upper triangle (SuperLU factorises the full matrix)."""
    return (U + sp.triu(U, k=1, format="csr").T).tocsr()
