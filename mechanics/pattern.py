"""One sparsity pattern for the Newton matrices of a solve.

PARDISO analyses a matrix afresh (its METIS ordering and symbolic factorisation) whenever the
pattern differs from the last one's. A sliding contact pairs its points with other muscle
triangles as the breast slides, and its friction entries vanish where the pressure does, so
the effects' entries change at nearly every evaluation: on the 20k-tet phantom with every
effect on, all 9 factorisations of the tilted solve were analysed afresh (90 ms each beside
130 ms of numerical factorisation), and the union of the patterns seen grew at each of them
by 18-111 entries.

:class:`KeptPattern` puts the matrices of one solve on one pattern: the mesh's and the
effects' entries seen so far, explicit zeros where a matrix has none. An evaluation whose
effect entries fall outside it grows it (PARDISO then analyses once more), unless they are
a small part of their effect's tangent (``drop_below``, relative 2-norm of the values): then
they are left out of the Newton matrix, a modified Newton step whose residual is exact.
Measured on that phantom: the entries outside were 8e-6 to 4e-4 of their effect's tangent
(27-1521 entries of 155-167k) except when friction first engages or the pairing moves by a
triangle (2e-3, 3798-5283 entries), the Newton iterations were those of the exact matrices
(10 / 13 / 12, prone / supine / tilted) with 1 / 1 / 3 analyses instead of 5 / 8 / 9. A
step that stagnates solves exactly (``exact``): nothing is left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from mechanics.system import ReducedSystem, _sorted_unique


@dataclass
class _Seen:
    """One effect's last triplets: their rows and columns (dof numbering), which of them are
    entries (``keep``), those entries' keys, and their positions in the pattern (its size
    where left out; None until located)."""

    rows: np.ndarray
    cols: np.ndarray
    keep: np.ndarray
    keys: np.ndarray
    at: np.ndarray | None = None


class KeptPattern:
    """The pattern of one solve's Newton matrices on ``system`` (the upper triangle when
    ``symmetric``, else the full matrix), and the matrices put on it."""

    def __init__(self, system: ReducedSystem, symmetric: bool, drop_below: float = 0.0):
        self.sys, self.symmetric, self.drop_below = system, symmetric, drop_below
        self.keys = None  # sorted row * n + col of the pattern's entries
        self.indptr = self.indices = None
        self.grown = 0  # patterns made: the first and each growth
        self.left_out = 0  # effect entries left out of the Newton matrices
        self._seen: dict[int, _Seen] = {}  # by the effect's index in ``parts``
        # where the mesh's upper entries (and, unsymmetric, the mirrors of its strict upper
        # ones, ``_strict``) go: made with the pattern, none for a solve without effect
        # entries (a 150k-tet hemisphere's would hold 300 MB)
        self._at_upper = self._at_lower = self._strict = None

    def _keys(self, rows, cols, reduced: bool):
        """Which triplets (rows, cols) in dof numbering (or the reduced one) are entries (free
        dofs; the upper triangle when symmetric), and their keys."""
        r, c = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        if not reduced:
            r, c = self.sys.fi[r], self.sys.fi[c]
        keep = (r >= 0) & (c >= 0)
        if self.symmetric:
            keep &= r <= c
        return keep, r[keep] * self.sys.n + c[keep]

    def _locate(self, keys: np.ndarray):
        """Positions of ``keys`` in the pattern (its size where absent) and the absent mask."""
        if self.keys is None:
            return np.zeros(len(keys), np.int64), np.ones(len(keys), bool)
        return _find(self.keys, keys)

    def _grow(self, new: np.ndarray) -> None:
        """Add the keys ``new``, none of them in the pattern; the first time with the
        mesh's entries."""
        if self.keys is None:
            self._mesh_entries()
            for h in self._seen.values():
                if h.at is not None:
                    h.at = _find(self.keys, h.keys)[0]
            new = new[_find(self.keys, new)[1]]
        keys = self.keys
        if len(new):  # the old entries move up by the new ones before them, the spare slot too
            new = _sorted_unique(new)
            keys = np.insert(keys, np.searchsorted(keys, new), new)
            moved = np.arange(len(self.keys) + 1) + np.searchsorted(
                new, np.append(self.keys, np.iinfo(np.int64).max))
            self._at_upper = moved[self._at_upper]
            if self._at_lower is not None:
                self._at_lower = moved[self._at_lower]
            for h in self._seen.values():
                if h.at is not None:
                    h.at = moved[h.at]
                    out = h.at == len(keys)  # left out before: perhaps in now
                    if out.any():
                        h.at[out] = _find(keys, h.keys[out])[0]
        self._set(keys)

    def _mesh_entries(self) -> None:
        """The pattern of the mesh's entries alone: the system's upper triangle, and its
        mirror when unsymmetric."""
        s = self.sys
        rows = np.repeat(np.arange(s.n, dtype=np.int64), np.diff(s.indptr))
        upper = rows * s.n + s.indices
        parts = [upper]
        if not self.symmetric:
            strict = s.indices != rows
            self._strict = np.flatnonzero(strict)
            parts.append(s.indices[strict].astype(np.int64) * s.n + rows[strict])
        del rows
        self.keys = _sorted_unique(np.concatenate(parts))
        self._at_upper = np.searchsorted(self.keys, upper)
        if not self.symmetric:
            self._at_lower = np.searchsorted(self.keys, parts[1])

    def _set(self, keys: np.ndarray) -> None:
        n = self.sys.n
        self.keys = keys
        self.indices = (keys % n).astype(np.int32)
        self.indptr = np.concatenate(
            [[0], np.cumsum(np.bincount(keys // n, minlength=n))]).astype(np.int32)
        self.grown += 1

    def _csr(self, data: np.ndarray) -> sp.csr_matrix:
        n = self.sys.n
        A = sp.csr_matrix((data, self.indices, self.indptr), shape=(n, n))
        A.has_sorted_indices = True
        return A

    def matrix(self, base: sp.csr_matrix, parts, *, exact: bool = False) -> sp.csr_matrix:
        """The Newton matrix on the kept pattern: the mesh's part ``base`` (the upper triangle
        on the system's pattern) plus each effect's triplets ``parts`` [(rows, cols, vals)]
        (dof numbering); ``exact``: leave nothing out. An effect whose rows and columns are
        those of its last call (a membrane's) keeps their positions."""
        if not parts and self.symmetric and (self.keys is None or len(self.keys) == base.nnz):
            return base  # the mesh's pattern, nothing added: no copy (150k tets: 80 MB)
        at = []
        for i, (r, c, _) in enumerate(parts):
            h = self._seen.get(i)
            if h is None or not (np.array_equal(h.rows, r) and np.array_equal(h.cols, c)):
                h = self._seen[i] = _Seen(np.array(r), np.array(c), *self._keys(r, c, False))
            at.append(h)
        vals = [np.asarray(p[2], float)[h.keep] for h, p in zip(at, parts, strict=True)]
        new = []
        for h, v in zip(at, vals, strict=True):
            if h.at is None:
                h.at, out = self._locate(h.keys)
            else:  # left out before, maybe too large now
                out = h.at == len(self.keys)
            if not out.any():
                continue
            if exact or self.keys is None or \
                    np.linalg.norm(v[out]) > self.drop_below * np.linalg.norm(v):
                new.append(h.keys[out])
            else:
                self.left_out += int(out.sum())
        if new or self.keys is None:
            self._grow(np.concatenate(new or [np.zeros(0, np.int64)]))  # moves those found
        m = len(self.keys)
        data = np.zeros(m) if not at else np.bincount(
            np.concatenate([h.at for h in at]), weights=np.concatenate(vals), minlength=m + 1)[:m]
        data[self._at_upper] += base.data
        if not self.symmetric:
            data[self._at_lower] += base.data[self._strict]
        return self._csr(data)

    def plus(self, A: sp.csr_matrix, rows, cols, vals, *, reduced: bool = False):
        """A (a matrix of :meth:`matrix`) plus triplets in dof numbering (``reduced``: in the
        reduced system's), on the kept pattern (grown where they fall outside)."""
        keep, keys = self._keys(rows, cols, reduced)
        v = np.asarray(vals, float)[keep]
        pos, out = self._locate(keys)
        if out.any():
            self._grow(keys[out])
            pos = _find(self.keys, keys)[0]
        data = A.data
        if len(A.data) != len(self.keys):  # made before the pattern grew
            n = self.sys.n
            rows_a = np.repeat(np.arange(n, dtype=np.int64), np.diff(A.indptr))
            data = np.zeros(len(self.keys))
            data[np.searchsorted(self.keys, rows_a * n + A.indices)] = A.data
        return self._csr(data + np.bincount(pos, weights=v, minlength=len(self.keys)))


def _find(pattern: np.ndarray, keys: np.ndarray):
    """Positions of ``keys`` in the sorted ``pattern`` (its length where absent) and the
    absent mask."""
    pos = np.searchsorted(pattern, keys)
    pos[pos == len(pattern)] = 0
    out = pattern[pos] != keys
    pos[out] = len(pattern)
    return pos, out
