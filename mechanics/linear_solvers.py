"""Pluggable sparse direct solvers with a reused symbolic analysis.

``"scipy"``: SuperLU (always available). ``"pardiso"``: MKL PARDISO through pypardiso
(symmetric indefinite mode on the upper triangle, analysis redone only when the pattern
changes). ``"auto"``: PARDISO when importable, else SuperLU.
"""

from __future__ import annotations

import ctypes
import os
import threading
from ctypes.util import find_library

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from mechanics.system import full_from_upper


class SingularSystem(RuntimeError):
    """The tangent could not be factorised or the solve is meaningless."""


class ScipySolver:
    name = "scipy"

    def __init__(self):
        self._lu = None

    def factorize(self, U: sp.csr_matrix, *, symmetric: bool = True) -> None:
        """U: upper triangle if ``symmetric`` else the full matrix."""
        A = full_from_upper(U) if symmetric else U
        try:
            # COLAMD with weak pivoting: measured 8 s vs 60 s (MMD) on the 20k-tet hemisphere.
            self._lu = spla.splu(A.tocsc(), permc_spec="COLAMD", diag_pivot_thresh=0.01)
        except RuntimeError as exc:  # "Factor is exactly singular"
            raise SingularSystem(str(exc)) from None

    def solve(self, b: np.ndarray) -> np.ndarray:
        return self._lu.solve(b)


_POOL = threading.local()


class PardisoSolver:
    """MKL PARDISO; one handle per thread and matrix type is kept, so that the symbolic
    analysis is reused across solves of the same model (e.g. the many solves of a fit)."""

    name = "pardiso"

    def __init__(self):
        import pypardiso  # noqa: F401  (fail early if missing)

        self._ps = None
        self._mtype = None
        self._pattern = None
        self._A = None

    def _solver(self, mtype: int):
        pool = getattr(_POOL, "handles", None)
        if pool is None:
            pool = _POOL.handles = {}
        if self._ps is None or self._mtype != mtype:
            if mtype in pool:
                self._ps, self._mtype = pool[mtype]["ps"], mtype
                self._pattern = pool[mtype].get("pattern")
                return self._ps
            self._ps = _new_handle(mtype)
            self._ps.set_iparm(1, 1)  # our iparms, not defaults
            self._ps.set_iparm(2, 2)  # METIS nested dissection
            # No iterative refinement unless pivots were perturbed (then PARDISO does two by
            # itself); the caller checks the solve residual. Measured: solve 0.037 -> 0.021 s.
            self._ps.set_iparm(8, 0)
            self._ps.set_iparm(10, 8 if mtype == -2 else 13)  # pivot perturbation 1e-8/1e-13
            self._ps.set_iparm(11, 0 if mtype == -2 else 1)  # scaling
            self._ps.set_iparm(13, 0 if mtype == -2 else 1)  # weighted matching
            self._ps.set_iparm(12, 0)
            self._ps.set_iparm(21, 1)  # Bunch-Kaufman pivoting (symmetric indefinite)
            self._ps.set_iparm(35, 0)  # 1-based indices (pypardiso adds 1)
            self._mtype, self._pattern = mtype, None
            pool[mtype] = {"ps": self._ps}
        return self._ps

    def factorize(self, U: sp.csr_matrix, *, symmetric: bool = True) -> None:
        with _mkl_threads(self._ps or self._solver(-2 if symmetric else 11)):
            self._factorize(U, symmetric=symmetric)

    def _factorize(self, U: sp.csr_matrix, *, symmetric: bool) -> None:
        A = U.tocsr()
        A.sort_indices()
        A.data = np.ascontiguousarray(A.data, dtype=np.float64)
        ps = self._solver(-2 if symmetric else 11)
        pattern = (A.indptr, A.indices)
        same = (self._pattern is not None and np.array_equal(pattern[0], self._pattern[0])
                and np.array_equal(pattern[1], self._pattern[1]))
        b = np.zeros((A.shape[0], 1))
        try:
            if not same:
                ps.set_phase(11)
                ps._call_pardiso(A, b)
                self._pattern = (A.indptr.copy(), A.indices.copy())
                _POOL.handles[self._mtype]["pattern"] = self._pattern
            ps.set_phase(22)
            ps._call_pardiso(A, b)
        except Exception as exc:  # PyPardisoError
            self._pattern = None
            _POOL.handles[self._mtype].pop("pattern", None)
            raise SingularSystem(f"PARDISO: {exc}") from None
        self._A = A

    def solve(self, b: np.ndarray) -> np.ndarray:
        ps = self._ps
        ps.set_phase(33)
        with _mkl_threads(ps):
            x = ps._call_pardiso(self._A, np.asfortranarray(b.reshape(-1, 1)))
        return x.ravel()


#: Threads of MKL inside PARDISO calls (thread-local, restored after each call); 0 leaves
#: MKL's default. Measured on the 2-core machine at 20k tets: on an idle machine 2 threads
#: factorise in 0.23 s against 0.38 s for one; under a load of 8-10 the second thread
#: doubles the CPU time (spin-waiting) for no shorter wall time, so set
#: MECHANICS_PARDISO_THREADS=1 when several solves share the cores.
PARDISO_THREADS = int(os.environ.get("MECHANICS_PARDISO_THREADS", "0"))


class _mkl_threads:
    def __init__(self, ps):
        self.fn = getattr(ps.libmkl, "MKL_Set_Num_Threads_Local", None)
        self.prev = None

    def __enter__(self):
        if self.fn is not None and PARDISO_THREADS > 0:
            self.prev = self.fn(ctypes.c_int(PARDISO_THREADS))

    def __exit__(self, *exc):
        if self.prev is not None:
            self.fn(ctypes.c_int(self.prev))
        return False


def _new_handle(mtype: int):
    """A PyPardisoSolver; the MKL library path is resolved once (pypardiso globs sys.prefix,
    about 1 s, when it is not given)."""
    from pypardiso import PyPardisoSolver

    if "PYPARDISO_MKL_RT" not in os.environ and find_library("mkl_rt") is None:
        probe = PyPardisoSolver(mtype=mtype)
        os.environ["PYPARDISO_MKL_RT"] = probe.libmkl._name
        return probe
    return PyPardisoSolver(mtype=mtype)


def make_linear_solver(name: str):
    """Return a solver instance for ``name`` in {"auto", "scipy", "pardiso"}."""
    if name == "scipy":
        return ScipySolver()
    if name == "pardiso":
        try:
            return PardisoSolver()
        except ImportError:
            raise ValueError("mechanics: linear_solver='pardiso' needs the pypardiso package "
                             "(pip install pypardiso)") from None
    if name == "auto":
        try:
            return PardisoSolver()
        except (ImportError, OSError):
            return ScipySolver()
    raise ValueError(f"mechanics: unknown linear solver {name!r}; "
                     "choose 'auto', 'scipy' or 'pardiso'")
