"""MKL PARDISO called directly by ctypes (the MKL runtime of the environment, e.g. the
``mkl`` wheel that pypardiso installs): one handle per Python thread, matrix type and
precision keeps its symbolic analysis, redone only when the pattern or the thread count
changes; symmetric indefinite mode on the upper triangle; a single-precision factorisation
refined to double-precision accuracy, with a double-precision fallback."""

from __future__ import annotations

import ctypes
import functools
import os
import threading
import time

import numpy as np
import scipy.sparse as sp

from mechanics.factorization import SingularSystem, factorisation_worth
from mechanics.threads import resolve_threads

# Intel OpenMP threads spin 200 ms after each parallel region by default, holding the cores
# that the Newton loop's numpy and OpenBLAS calls need next (measured on the 2-core machine:
# a vector norm right after a 2-thread PARDISO solve took 6.5 ms instead of 0.03 ms). Read
# when MKL's OpenMP runtime starts, i.e. at the first PARDISO call.
os.environ.setdefault("KMP_BLOCKTIME", "0")


_POOL = threading.local()

#: iparm (1-based index: value) of each PARDISO configuration; everything else is 0.
#: "single": single-precision factorisation (iparm 28), half the memory and about half the
#: time of double (150k-tet hemisphere, 105k unknowns, 99M entries in L, one thread: 3.0 s
#: against 5.5 s), refined to double accuracy in :meth:`PardisoSolver.solve`; for the
#: symmetric saddle-point tangent 1x1 diagonal pivots (iparm 21 = 0): with K_uu positive
#: definite and a negative pressure block the matrix is quasi-definite, so LDL^T exists in
#: any order, and Bunch-Kaufman's 2x2 pivots cost 30 % more time for the same fill.
#: For the unsymmetric tangent of frictional contact the single-precision factorisation
#: skips scaling and weighted matching (iparm 11, 13): the matching is most of the symbolic
#: analysis, which the contact's changing pattern makes PARDISO redo at nearly every
#: factorisation (20k-tet phantom's supine tangent, 18.9k unknowns, 2 threads: analysis
#: 167 -> 115 ms, factorisation 130 -> 123 ms); the refinement below checks every solve.
#: "double": the robust fallback (Bunch-Kaufman; scaling and weighted matching for
#: unsymmetric matrices), used when a single-precision solve cannot be refined.
#: iparm 2 = 3: METIS's nested dissection run on the MKL threads (the same ordering as the
#: serial one, 2 threads: the analysis above 167 -> 136 ms; with no matching 88 ms).
#: iparm 18 and 19 < 0: report the factor's nonzeros and its factorisation's Mflops.
_COMMON = {1: 1, 2: 3, 8: 0, 18: -1, 19: -1, 35: 1}  # ours; parallel METIS; no PARDISO
# refinement; 0-based
_IPARM = {
    ("single", -2): {**_COMMON, 10: 8, 21: 0, 28: 1},
    ("double", -2): {**_COMMON, 10: 8, 21: 1},
    ("single", 11): {**_COMMON, 10: 13, 28: 1},
    ("double", 11): {**_COMMON, 10: 13, 11: 1, 13: 1},
}


class _Handle:
    """One PARDISO instance (internal memory pointer, iparm, analysed pattern)."""

    def __init__(self, lib, mtype: int, precision: str):
        self.lib, self.mtype, self.precision = lib, mtype, precision
        self.dtype = np.float32 if precision == "single" else np.float64
        self.pt = np.zeros(64, np.int64)
        self.iparm = np.zeros(64, np.int32)
        for k, v in _IPARM[(precision, mtype)].items():
            self.iparm[k - 1] = v
        self.ia = self.ja = None
        self.a = None
        self.n = 0
        self.threads = 0  # MKL threads of the current analysis
        self.analyses = 0  # symbolic analyses (phase 11) made by this handle
        self.analysis_cpu_s = 0.0  # their CPU time (all threads), s

    def call(self, phase: int, b: np.ndarray | None = None) -> np.ndarray | None:
        n = self.n
        err = ctypes.c_int32(0)
        if b is None:
            rhs = x = np.zeros(1, self.dtype)
        else:
            rhs = np.ascontiguousarray(b, dtype=self.dtype)
            x = np.empty_like(rhs)
        i32 = ctypes.POINTER(ctypes.c_int32)
        perm = np.zeros(1, np.int32)
        self.lib.pardiso(
            self.pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
            ctypes.byref(ctypes.c_int32(1)), ctypes.byref(ctypes.c_int32(1)),
            ctypes.byref(ctypes.c_int32(self.mtype)), ctypes.byref(ctypes.c_int32(phase)),
            ctypes.byref(ctypes.c_int32(n)), self.a.ctypes.data_as(ctypes.c_void_p),
            self.ia.ctypes.data_as(i32), self.ja.ctypes.data_as(i32), perm.ctypes.data_as(i32),
            ctypes.byref(ctypes.c_int32(1)), self.iparm.ctypes.data_as(i32),
            ctypes.byref(ctypes.c_int32(0)), rhs.ctypes.data_as(ctypes.c_void_p),
            x.ctypes.data_as(ctypes.c_void_p), ctypes.byref(err))
        if err.value != 0:
            raise SingularSystem(f"PARDISO error {err.value} in phase {phase} "
                                 f"({_ERRORS.get(err.value, 'see the MKL manual')})")
        return None if b is None else x

    def factorize(self, A: sp.csr_matrix, threads: int) -> None:
        """Phase 22, after phase 11 when the pattern or the thread count is new."""
        same = (self.ia is not None and self.n == A.shape[0] and self.threads == threads
                and np.array_equal(self.ia, A.indptr) and np.array_equal(self.ja, A.indices))
        self.a = np.ascontiguousarray(A.data, dtype=self.dtype)
        if not same:
            if self.ia is not None:
                self.release()
            self.n = A.shape[0]
            # no copy where the pattern is int32 already (the reduced system's arrays,
            # which nothing changes in place): 12 MB at 150k tets
            self.ia = A.indptr.astype(np.int32, copy=False)
            self.ja = A.indices.astype(np.int32, copy=False)
            self.threads = threads
            # conditional numerical reproducibility on this many threads: without it two
            # factorisations of one matrix on 2 threads differ in their last bits (measured:
            # 2 distinct solutions in 30, 2e-6 apart on a 47k-unknown Laplacian), which the
            # Newton and stress-free loops carry into 2e-5 mm node differences between two
            # runs of one subject; with it they are bitwise equal, for 0-15 % more time
            self.iparm[33] = threads
            self.analyses += 1
            # iparm 18 and 19 report only when negative on input, and the report makes them
            # positive: without this every later analysis of the handle kept the first
            # matrix's figures (a 2k- and a 20k-unknown matrix analysed in turn both
            # reported 41832 nonzeros), and factor_worth priced the GMRES budget of every
            # later solve of the process by the first model's factorisation
            self.iparm[17] = self.iparm[18] = -1
            t0 = time.process_time()
            try:
                with _mkl_threads(self.lib, self.threads):
                    self.call(11)
            except SingularSystem:
                self.ia = self.ja = None
                raise
            finally:
                self.analysis_cpu_s += time.process_time() - t0
        with _mkl_threads(self.lib, self.threads):
            self.call(22)

    @property
    def factor_flops(self) -> float:
        """Operations of one numerical factorisation (iparm 19, in Mflops)."""
        return 1e6 * float(self.iparm[18])

    @property
    def factor_nonzeros(self) -> int:
        """Nonzeros of the factor (iparm 18): L for a symmetric matrix, L and U else."""
        return int(self.iparm[17])

    @property
    def memory_mb(self) -> float:
        """PARDISO's own peak memory (MB): max(analysis peak, permanent + factorisation and
        solve), iparm 15-17 in KB."""
        return max(float(self.iparm[14]), float(self.iparm[15] + self.iparm[16])) / 1024.0

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Phase 33 (forward and backward substitution) with the analysis's threads."""
        with _mkl_threads(self.lib, self.threads):
            return self.call(33, b)

    def release(self) -> None:
        if self.ia is not None and self.a is not None:
            try:
                self.call(-1)
            except SingularSystem:
                pass
        self.ia = self.ja = None
        self.pt[:] = 0

    @property
    def perturbed_pivots(self) -> int:
        return int(self.iparm[13])


_ERRORS = {-1: "input inconsistent", -2: "not enough memory", -3: "reordering problem",
           -4: "zero pivot, numerical factorization or iterative refinement problem",
           -5: "unclassified (internal) error", -6: "reordering failed",
           -7: "diagonal matrix is singular", -8: "32-bit integer overflow",
           -9: "not enough memory for OOC", -10: "error opening OOC files",
           -11: "read/write error with OOC files"}


#: A refinement that stalls below this relative residual has reached the rounding floor of
#: double precision (measured 1e-14 to 1e-13 on the hemisphere), not a bad factor.
_ACCURATE = 1e-9


class PardisoSolver:
    """MKL PARDISO on ``threads`` MKL threads (see :func:`resolve_threads`). Handles (one
    per Python thread, matrix type and precision) are kept, so the symbolic analysis is
    reused across solves of the same model and thread count (e.g. the many solves of a fit).

    ``precision="single"`` (default): single-precision factor, and :meth:`solve` refines
    its solution with the double-precision matrix to a relative residual of ``refine_tol``
    (or its rounding floor); when the refinement stalls above 1e-9 (perturbed pivots, a
    singular or badly conditioned tangent) the matrix is factorised again in double
    precision with Bunch-Kaufman pivoting, and so are the later matrices given to this
    instance (one instance serves one solve).
    """

    name = "pardiso"

    def __init__(self, *, precision: str = "single", refine_tol: float = 1e-14,
                 threads: int | None = None):
        _mkl()  # fail early (ImportError or OSError) without MKL

        self.threads = resolve_threads(threads)  # MKL threads of every PARDISO phase

        if precision not in ("single", "double"):
            raise ValueError(f"mechanics: PARDISO precision must be 'single' or 'double', "
                             f"got {precision!r}")
        self.precision = precision
        self.refine_tol = refine_tol
        self._h = None
        self._A = None
        self._nnz = 0
        self._matvec = None
        self.fallbacks = 0  # double-precision refactorisations after a stalled refinement
        self.refinements = 0  # refinement steps (extra triangular solves)
        self.last_refinements = 0  # ... of the last call of solve
        self.analyses = 0  # symbolic analyses this instance needed (a reused one: none)
        self.analysis_cpu_s = 0.0  # their CPU time, s

    def _handle(self, mtype: int, precision: str) -> _Handle:
        pool = getattr(_POOL, "handles", None)
        if pool is None:
            pool = _POOL.handles = {}
        key = (mtype, precision)
        if key not in pool:
            pool[key] = _Handle(_mkl(), mtype, precision)
        return pool[key]

    def factorize(self, U: sp.csr_matrix, *, symmetric: bool = True) -> None:
        """Factorise U: the upper triangle if ``symmetric`` else the full matrix."""
        A = U.tocsr()
        if not A.has_sorted_indices:
            A = A.copy()
            A.sort_indices()
        self._A, self._nnz = A, A.nnz
        self._mtype = -2 if symmetric else 11
        if symmetric:
            d = A.diagonal()
            At = A.T
            self._matvec = lambda y: A @ y + At @ y - d * y
        else:
            self._matvec = A.__matmul__
        self._factor(self.precision)

    def _factor(self, precision: str) -> None:
        h = self._handle(self._mtype, precision)
        n0, c0 = h.analyses, h.analysis_cpu_s
        h.factorize(self._A, self.threads)
        self.analyses += h.analyses - n0
        self.analysis_cpu_s += h.analysis_cpu_s - c0
        self._h = h

    @property
    def factor_worth(self) -> float:
        """GMRES iterations that cost as much as one factorisation (:func:`factorisation_worth`)."""
        if self._h is None:
            return 0.0
        # a substitution reads the factor twice: L and L^T (symmetric), or L and U once each
        per = (4 if self._mtype == -2 else 2) * self._h.factor_nonzeros
        return factorisation_worth(self.name, self._h.factor_flops, per + 2.0 * self._nnz
                      * (2 if self._mtype == -2 else 1))

    @property
    def memory_mb(self) -> float:
        """The current factor's memory as PARDISO reports it (MB); 0 before the first."""
        return 0.0 if self._h is None else self._h.memory_mb

    def forget_matrix(self) -> None:
        """Let go of the factorised matrix, which only :meth:`solve` reads (its refinement
        and a double-precision fallback); the factor stays, for :meth:`precondition`. The
        Newton loop's later solves with this factor only precondition (150k tets: 24 MB of
        the solve's peak)."""
        self._A = self._matvec = None

    def precondition(self, b: np.ndarray) -> np.ndarray:
        """One solve with the factor as it is (no refinement): a preconditioner."""
        return self._h.solve(b).astype(np.float64)

    def solve(self, b: np.ndarray, tol: float | None = None) -> np.ndarray:
        """Solution of A x = b, refined in double precision to a relative residual of
        ``tol`` (default ``refine_tol``) or until the residual stops falling 4x a step (the
        rounding floor, about 1e-14 for the hemisphere; a double-precision factor usually
        needs no step).
        A single-precision factor whose refinement stalls above 1e-9 is replaced by a
        double-precision one."""
        if self._A is None:
            raise RuntimeError("mechanics: PARDISO solve without its matrix (forgotten "
                               "after the last factorisation); factorise again")
        b = np.asarray(b, dtype=np.float64).ravel()
        x = self.precondition(b)
        self.last_refinements = 0
        nb = np.linalg.norm(b)
        if nb == 0.0:
            return x
        prev = np.inf
        for _ in range(12):
            r = b - self._matvec(x)
            err = np.linalg.norm(r) / nb
            if not np.isfinite(err) or err <= (self.refine_tol if tol is None else tol):
                break
            if err > 0.25 * prev:  # stalls
                if self._h.precision == "double" or err <= _ACCURATE:
                    break
                self.fallbacks += 1
                self.precision = "double"
                self._factor("double")
                x, prev = self.precondition(b), np.inf
                continue
            prev = err
            x += self.precondition(r)
            self.refinements += 1
            self.last_refinements += 1
        return x


class _mkl_threads:
    """MKL's thread-local thread count set to ``n`` (> 0) inside the block.

    One PARDISO analysis keeps one count for all its phases (``_Handle.threads``): a
    numerical factorisation with another count than its analysis crashes MKL (reproduced:
    analysis on 2 threads, phase 22 on 1, a segmentation fault), so a handle asked for
    another count analyses again."""

    def __init__(self, lib, n: int):
        self.fn = getattr(lib, "MKL_Set_Num_Threads_Local", None)
        self.n = int(n)
        self.prev = None

    def __enter__(self):
        if self.fn is not None and self.n > 0:
            self.prev = self.fn(ctypes.c_int(self.n))

    def __exit__(self, *exc):
        if self.prev is not None:
            self.fn(ctypes.c_int(self.prev))
        return False


@functools.cache
def _mkl():
    """The MKL runtime library, one search per process: ``$PYPARDISO_MKL_RT``, else
    ``libmkl_rt`` in the environment's ``lib/`` (where the pip ``mkl`` wheel puts it), else
    pypardiso's own search (``find_library`` and a recursive glob of ``sys.prefix``: about
    0.7 s of a 2 s run at 20k tets)."""
    import sys

    env = os.environ.get("PYPARDISO_MKL_RT")
    names = ("libmkl_rt.so.3", "libmkl_rt.so.2", "libmkl_rt.so", "libmkl_rt.dylib")
    cands = [env] if env else []
    cands += [os.path.join(sys.prefix, "lib", n) for n in names]
    for path in cands:
        if path and os.path.exists(path):
            try:
                lib = ctypes.CDLL(path)
                lib.pardiso  # noqa: B018  (fails if this is not the MKL runtime)
                return lib
            except (OSError, AttributeError):
                continue
    from pypardiso.scipy_aliases import pypardiso_solver  # created (library found) on import

    return pypardiso_solver.libmkl
