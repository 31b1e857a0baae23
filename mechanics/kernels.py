"""Vectorised element kernels for 4-node tetrahedra (no Python loop over elements).

Symbols: X reference and x current node positions (N, 3) mm; per element dN (M, 4, 3) the
reference shape-function gradients (1/mm), V0 (M,) reference volumes (mm^3), F (M, 3, 3).
"""

from __future__ import annotations

import numpy as np

# Gradients of the barycentric shape functions in the unit tet: rows N0..N3, columns xi1..xi3.
_DN_REF = np.array([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def reference_geometry(X: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape-function gradients dN (M, 4, 3) in 1/mm and signed volumes V0 (M,) in mm^3."""
    Xe = X[tets]  # (M, 4, 3)
    Jac = np.einsum("maI,aj->mIj", Xe, _DN_REF)  # dX/dxi (M, 3, 3)
    det = np.linalg.det(Jac)
    V0 = det / 6.0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.linalg.inv(np.where(det[:, None, None] != 0.0, Jac, np.eye(3)))
    dN = np.einsum("aj,mjI->maI", _DN_REF, inv)
    return dN, V0


def tet_volumes(X: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (M,) mm^3 of the tets, those of :func:`reference_geometry` without
    its gradients (20k tets: 2.5 against 23 ms)."""
    e = X[tets[:, 1:]] - X[tets[:, :1]]  # (M, 3, 3): edges from node 0
    return np.einsum("mi,mi->m", e[:, 0], np.cross(e[:, 1], e[:, 2])) / 6.0


def deformation_gradient(x: np.ndarray, tets: np.ndarray, dN: np.ndarray) -> np.ndarray:
    """F (M, 3, 3) with F_iJ = sum_a x_ai dN_aJ."""
    return np.einsum("mai,maJ->miJ", x[tets], dN)


def element_force(P: np.ndarray, dN: np.ndarray, V0: np.ndarray) -> np.ndarray:
    """Internal nodal forces (M, 4, 3) mN: f_ai = V0 P_iJ dN_aJ."""
    return V0[:, None, None] * np.einsum("miJ,maJ->mai", P, dN)


def element_stiffness(A: np.ndarray, dN: np.ndarray, V0: np.ndarray) -> np.ndarray:
    """Element stiffness (M, 12, 12) mN/mm in local dof order 3*a+i from A (M,3,3,3,3)."""
    M = len(dN)
    # T[m, i, a, kL] = sum_J dN[m, a, J] A[m, i, J, kL]
    T = np.matmul(dN[:, None], np.ascontiguousarray(A).reshape(M, 3, 3, 9))  # (M,3,4,9)
    T = T.reshape(M, 36, 3)  # rows (i, a, k), columns L
    K = np.matmul(T, dN.transpose(0, 2, 1))  # (M, 36, 4): [m, (i,a,k), b]
    K = K.reshape(M, 3, 4, 3, 4).transpose(0, 2, 1, 4, 3).reshape(M, 12, 12)
    return K * V0[:, None, None]


def volume_measure(F, dN, V0, linear_mask, *, tangent: bool = True):
    """Current element volume v (M,), its gradient dv/dx (M, 4, 3) and Hessian (M, 12, 12).

    Elements in ``linear_mask`` use the small-strain volume V0 (1 + tr(F - I)), whose
    Hessian vanishes; the others use V0 det F.
    """
    J = np.linalg.det(F)
    with np.errstate(divide="ignore", invalid="ignore"):
        Finv = np.linalg.inv(np.where(J[:, None, None] > 0.0, F, np.eye(3)))
    g = np.einsum("maJ,mJi->mai", dN, Finv)  # spatial gradients of N (1/mm)
    v = V0 * J
    dv = v[:, None, None] * g
    if np.any(linear_mask):
        tr = np.trace(F, axis1=1, axis2=2) - 3.0
        v = np.where(linear_mask, V0 * (1.0 + tr), v)
        dv = np.where(linear_mask[:, None, None], V0[:, None, None] * dN, dv)
    if not tangent:
        return v, dv, None
    M = len(F)
    gg = np.einsum("mai,mbk->maibk", g, g)
    hess = (v * ~linear_mask)[:, None, None, None, None] * (gg - gg.transpose(0, 1, 4, 3, 2))
    return v, dv, hess.reshape(M, 12, 12)


#: Upper-triangle pairs (l1 <= l2) of the local 12 dofs (l = 3 a + i), and their node/comp.
IU, JU = np.triu_indices(12)
A1, I1_, B1, K1 = IU // 3, IU % 3, JU // 3, JU % 3
DIAG_COMP = (I1_ == K1).astype(float)
#: Entries of the swapped product g_bi g_ak: row indices into a (12, M) array of g.
SW1, SW2 = 3 * B1 + I1_, 3 * A1 + K1
#: The 10 node pairs a <= b, and for the 30 upper entries with i == k their row and pair.
PAIR_A, PAIR_B = np.triu_indices(4)
DIAG_ROWS = np.flatnonzero(I1_ == K1)
_PAIR_OF = {(int(a), int(b)): n for n, (a, b) in enumerate(zip(PAIR_A, PAIR_B, strict=True))}
DIAG_PAIR = np.array([_PAIR_OF[(int(A1[r]), int(B1[r]))] for r in DIAG_ROWS])


def pair_dots(dN: np.ndarray) -> np.ndarray:
    """dN_a . dN_b (10, M) for the 10 node pairs a <= b (PAIR_A, PAIR_B) of each tet."""
    return np.einsum("maJ,maJ->am", dN[:, PAIR_A], dN[:, PAIR_B])


def det_inv(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Determinant (M,) and inverse (M, 3, 3) of 3x3 matrices by cofactors (no LAPACK)."""
    a, b, c = F[:, 0, 0], F[:, 0, 1], F[:, 0, 2]
    d, e, f = F[:, 1, 0], F[:, 1, 1], F[:, 1, 2]
    g, h, i = F[:, 2, 0], F[:, 2, 1], F[:, 2, 2]
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g
    J = a * c00 + b * c01 + c * c02
    inv = np.empty_like(F)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = 1.0 / J
    inv[:, 0, 0], inv[:, 1, 0], inv[:, 2, 0] = c00 * r, c01 * r, c02 * r
    inv[:, 0, 1] = (c * h - b * i) * r
    inv[:, 1, 1] = (a * i - c * g) * r
    inv[:, 2, 1] = (b * g - a * h) * r
    inv[:, 0, 2] = (b * f - c * e) * r
    inv[:, 1, 2] = (c * d - a * f) * r
    inv[:, 2, 2] = (a * e - b * d) * r
    return J, inv


def upper_outer(u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(M, 78) upper-triangle entries of u_l1 w_l2 for (M, 4, 3) arrays u, w."""
    M = len(u)
    return u.reshape(M, 12)[:, IU] * w.reshape(M, 12)[:, JU]


def upper_swap(g: np.ndarray) -> np.ndarray:
    """(M, 78) entries g[b, i] g[a, k] for (l1, l2) = (3a+i, 3b+k)."""
    return g[:, B1, I1_] * g[:, A1, K1]


def full_from_upper78(Kup: np.ndarray) -> np.ndarray:
    """(M, 12, 12) symmetric element matrices from their (M, 78) upper triangles."""
    K = np.zeros((len(Kup), 12, 12))
    K[:, IU, JU] = Kup
    K[:, JU, IU] = Kup
    return K
