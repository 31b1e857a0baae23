"""The right-preconditioned GMRES that the Newton corrections use with a stale factor."""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from mechanics.krylov import fgmres


def _system(n=400, seed=0):
    """A sparse, unsymmetric, well-posed matrix and a stale factor of a nearby one (the
    situation of a Newton step that reuses an earlier tangent's factorisation)."""
    rng = np.random.default_rng(seed)
    L = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n), format="csr")
    A = (L + sp.random(n, n, density=0.01, random_state=seed) * 0.3).tocsc()
    stale = spla.splu((L + 0.2 * sp.eye(n)).tocsc())
    return A, stale.solve, rng.standard_normal(n)


def test_it_reaches_the_true_residual_it_was_asked_for():
    A, pre, b = _system()
    for rtol in (1e-2, 1e-6, 1e-10):
        y, its, est = fgmres(A.__matmul__, pre, b, rtol, 200)
        true = np.linalg.norm(b - A @ y) / np.linalg.norm(b)
        assert true <= rtol * 1.01, (rtol, true)
        assert est <= rtol and abs(true - est) <= 1e-3 * rtol + 1e-13  # estimate is the truth
        assert 1 < its < 200


def test_an_exact_preconditioner_takes_one_iteration():
    A, _, b = _system()
    lu = spla.splu(A.tocsc())
    y, its, _ = fgmres(A.__matmul__, lu.solve, b, 1e-10, 50)
    assert its == 1 and np.allclose(A @ y, b, rtol=0, atol=1e-9 * np.linalg.norm(b))


def test_a_budget_too_small_gives_no_answer():
    A, pre, b = _system()
    y, its, est = fgmres(A.__matmul__, pre, b, 1e-12, 2)
    assert y is None and its == 2 and est > 1e-12


def test_a_zero_right_hand_side_is_the_zero_solution():
    A, pre, _ = _system()
    y, its, est = fgmres(A.__matmul__, pre, np.zeros(A.shape[0]), 1e-8, 10)
    assert its == 0 and est == 0.0 and not y.any()
