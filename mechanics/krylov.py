"""Right-preconditioned GMRES for the Newton corrections that reuse an earlier factorisation.

Flexible GMRES (Saad 1993, "A flexible inner-outer preconditioned GMRES algorithm", SIAM J.
Sci. Comput. 14: 461-469) with one cycle: the preconditioned vectors z_k = M v_k are kept,
so the answer y = Z c needs no further solve with the factor, and the residual it monitors is
the true one, |b - A y|. SciPy's ``gmres`` preconditions on the left and, per call, spends
two triangular solves more than the iterations it takes (its outer check of the true
residual, and M z for the answer under right preconditioning); at 20k tets, where a solve
with the factor is 6.5 ms and a Newton solve takes 5 GMRES calls, those were 10 of 40
solves. Written here for that reason; it also spares the solver process the import of
``scipy.sparse.linalg`` (about 0.1 s).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def fgmres(matvec: Callable[[np.ndarray], np.ndarray],
           precondition: Callable[[np.ndarray], np.ndarray],
           b: np.ndarray, rtol: float, maxit: int) -> tuple[np.ndarray | None, int, float]:
    """Solve A y = b to a relative residual |b - A y| / |b| <= ``rtol`` in at most ``maxit``
    iterations (one cycle, zero initial guess). Returns (y, iterations, relative residual
    estimate); y is None when the cycle ended above ``rtol`` (or broke down on a singular
    Hessenberg matrix)."""
    n = len(b)
    beta = float(np.linalg.norm(b))
    if beta == 0.0:
        return np.zeros(n), 0, 0.0
    maxit = max(1, min(int(maxit), n))
    V = np.empty((maxit + 1, n))
    Z = np.empty((maxit, n))
    H = np.zeros((maxit + 1, maxit))  # Hessenberg matrix, rotated into R in place
    cs, sn = np.zeros(maxit), np.zeros(maxit)
    g = np.zeros(maxit + 1)  # rotated right-hand side beta e_1
    g[0] = beta
    V[0] = b / beta
    res, m = 1.0, 0
    for k in range(maxit):
        Z[k] = precondition(V[k])
        w = matvec(Z[k])
        for _ in range(2):  # classical Gram-Schmidt, twice (one BLAS call each way)
            h = V[: k + 1] @ w
            w -= h @ V[: k + 1]
            H[: k + 1, k] += h
        H[k + 1, k] = hk = float(np.linalg.norm(w))
        for i in range(k):  # the earlier Givens rotations on the new column
            H[i, k], H[i + 1, k] = (cs[i] * H[i, k] + sn[i] * H[i + 1, k],
                                    -sn[i] * H[i, k] + cs[i] * H[i + 1, k])
        r = float(np.hypot(H[k, k], H[k + 1, k]))
        m = k + 1
        if r == 0.0:
            return None, m, res
        cs[k], sn[k] = H[k, k] / r, H[k + 1, k] / r
        H[k, k], H[k + 1, k] = r, 0.0
        g[k + 1], g[k] = -sn[k] * g[k], cs[k] * g[k]
        res = abs(g[k + 1]) / beta
        if res <= rtol or hk <= 1e-14 * r:  # converged, or the Krylov space is invariant
            break
        V[k + 1] = w / hk
    c = np.zeros(m)
    for i in range(m - 1, -1, -1):  # back substitution with the triangular R
        c[i] = (g[i] - H[i, i + 1:m] @ c[i + 1:]) / H[i, i]
    y = c @ Z[:m]
    return (y if res <= rtol and np.all(np.isfinite(y)) else None), m, res
