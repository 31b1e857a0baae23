"""Pluggable sparse direct solvers with a reused symbolic analysis.

``"scipy"``: SuperLU (always available). ``"pardiso"``: MKL PARDISO (the MKL runtime of the
environment, e.g. the ``mkl`` wheel that pypardiso installs, called directly by ctypes):
symmetric indefinite mode on the upper triangle, a single-precision factorisation refined to
double-precision accuracy, analysis redone only when the pattern or the thread count
changes. ``"auto"``: PARDISO when MKL is found, else SuperLU.

PARDISO lives in :mod:`mechanics.pardiso`, the thread counts in :mod:`mechanics.threads`,
the error and cost model the solvers share in :mod:`mechanics.factorization`; this module
holds SuperLU and the choice between them, and names what callers import.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from mechanics.factorization import SingularSystem, factorisation_worth
from mechanics.pardiso import _POOL as _POOL
from mechanics.pardiso import PardisoSolver
from mechanics.pardiso import _Handle as _Handle
from mechanics.system import full_from_upper
from mechanics.threads import THREADS_ENV, machine_cores, resolve_threads, single_thread_blas

__all__ = ["THREADS_ENV", "PardisoSolver", "ScipySolver", "SingularSystem", "full_from_upper",
           "machine_cores", "make_linear_solver", "resolve_threads", "single_thread_blas"]


class ScipySolver:
    """SciPy's SuperLU (one thread; ``threads`` is accepted and has no effect)."""

    name = "scipy"
    threads = 1
    analyses = 0
    analysis_cpu_s = 0.0

    def __init__(self, *, threads: int | None = None):
        self._lu = None
        self.factor_worth = 0.0  # GMRES iterations one factorisation is worth (factorisation_worth)

    def factorize(self, U: sp.csr_matrix, *, symmetric: bool = True) -> None:
        """U: upper triangle if ``symmetric`` else the full matrix."""
        import scipy.sparse.linalg as spla  # here: the PARDISO path never needs it (0.1 s)

        A = full_from_upper(U) if symmetric else U
        try:
            # COLAMD with weak pivoting: measured 8 s vs 60 s (MMD) on the 20k-tet hemisphere.
            self._lu = spla.splu(A.tocsc(), permc_spec="COLAMD", diag_pivot_thresh=0.01)
        except RuntimeError as exc:  # "Factor is exactly singular"
            raise SingularSystem(str(exc)) from None
        # right-looking LU: column j of L (l_j below the diagonal) meets row j of U (u_j);
        # SuperLU builds a copy of L or U at each access, so one at a time
        n = A.shape[0]
        lower = np.diff(self._lu.L.indptr).astype(float) - 1.0  # CSC: per column
        upper = np.bincount(self._lu.U.indices, minlength=n).astype(float) - 1.0  # per row
        flops = 2.0 * float(lower @ upper) + float(lower.sum())
        nnz = float(lower.sum() + upper.sum()) + 2.0 * n
        self.factor_worth = factorisation_worth(self.name, flops, 2.0 * (nnz + A.nnz))

    last_refinements = 0

    def solve(self, b: np.ndarray, tol: float | None = None) -> np.ndarray:
        return self._lu.solve(b)  # a double-precision LU: nothing to refine to ``tol``

    precondition = solve

    def forget_matrix(self) -> None:
        """Nothing to let go of: the LU factors are SuperLU's own copy."""


def make_linear_solver(name: str, *, threads: int | None = None):
    """Return a solver instance for ``name`` in {"auto", "scipy", "pardiso"} on ``threads``
    threads (see :func:`resolve_threads`)."""
    threads = resolve_threads(threads)
    if name == "scipy":
        return ScipySolver(threads=threads)
    if name == "pardiso":
        try:
            return PardisoSolver(threads=threads)
        except ImportError:
            raise ValueError("mechanics: linear_solver='pardiso' needs the pypardiso package "
                             "(pip install pypardiso)") from None
    if name == "auto":
        try:
            return PardisoSolver(threads=threads)
        except (ImportError, OSError):
            return ScipySolver(threads=threads)
    raise ValueError(f"mechanics: unknown linear solver {name!r}; "
                     "choose 'auto', 'scipy' or 'pardiso'")
