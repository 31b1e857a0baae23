"""Geometry of node-to-surface contact: closest facets and the signed gap with derivatives."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices, skew(v) @ u = v x u."""
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def nodal_areas(X: np.ndarray, tri: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """(len(nodes),) tributary areas (one third of each adjacent triangle), mm^2."""
    e1 = X[tri[:, 1]] - X[tri[:, 0]]
    e2 = X[tri[:, 2]] - X[tri[:, 0]]
    A = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    w = np.bincount(tri.ravel(), weights=np.repeat(A / 3.0, 3), minlength=len(X))
    return w[nodes]


def barycentric(q, a, b, c):
    """Barycentric coordinates (u, v, w) of the projections of points q onto the planes of
    triangles (a, b, c); arrays (..., 3) that broadcast together."""
    v0, v1, v2 = b - a, c - a, q - a
    return _barycentric_from_dots(*(np.einsum("...i,...i->...", s, t) for s, t in (
        (v0, v0), (v0, v1), (v1, v1), (v2, v0), (v2, v1))))


def _barycentric_from_dots(d00, d01, d11, d20, d21):
    """:func:`barycentric` from the dot products of the edges ab (0), ac (1) and of q - a
    (2) with them."""
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return 1.0 - v - w, v, w


def closest_facets(p: np.ndarray, x: np.ndarray, tri: np.ndarray, *, k: int = 8,
                   normals: np.ndarray | None = None, min_cos: float = 0.5):
    """Closest triangle of a surface to each point.

    Parameters
    ----------
    p : (S, 3) points, mm
    x : (N, 3) node positions, mm
    tri : (T, 3) surface triangles
    k : candidate triangles per point (nearest centroids)
    normals : (S, 3) unit normals of the points' own surface, oriented as the triangles';
        when given, a triangle facing away (normal . n < ``min_cos``) is a candidate only
        if no candidate faces the point. Where a surface folds (the staircase rim of a
        meshed interface, 90 degree steps), the closest triangle otherwise flips between
        tread and riser from one Newton iteration to the next, and the contact force with
        it (measured on a 20k-tet meshed phantom: gaps jumping to 2-7 mm, no load step
        converging)
    min_cos : see ``normals``

    Returns
    -------
    facet : (S,) index into ``tri``
    bary : (S, 3) barycentric coordinates of the closest point (inside or on the edges)
    dist : (S,) distance, mm
    """
    # imported here: scipy.spatial is 0.2 s of every solver process's start, and only the
    # contact effects need it
    from scipy.spatial import cKDTree

    xt = x[tri]  # (T, 3, 3)
    k = min(k, len(tri))
    _, cand = cKDTree(xt.mean(axis=1)).query(p, k=k)
    cand = np.asarray(cand).reshape(len(p), k)
    d2, ts, bary_plane, (e0, e1) = _candidate_distances(p, xt, cand)
    if normals is not None:
        nt = np.cross(e0, e1)  # (T, 3)
        nt /= np.maximum(np.linalg.norm(nt, axis=1), 1e-300)[:, None]
        away = np.einsum("ski,si->sk", nt[cand], normals) < min_cos
        away &= ~np.all(away, axis=1, keepdims=True)  # none faces the point: keep them all
        d2[away] = np.inf
    flat = d2.reshape(len(p), -1)
    best = np.argmin(flat, axis=1)
    rows = np.arange(len(p))
    kk, mm = np.divmod(best, 4)
    bary = np.zeros((len(p), 3))
    plane = mm == 0
    bary[plane] = bary_plane[rows[plane], kk[plane]]
    for m, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        on = mm == m + 1
        t = ts[rows[on], kk[on], m]
        bary[on, i] = 1.0 - t
        bary[on, j] = t
    return cand[rows, kk], bary, np.sqrt(flat[rows, best])


def _candidate_distances(p: np.ndarray, xt: np.ndarray, cand: np.ndarray):
    """Squared distances (S, k, 4) from points p (S, 3) to their candidate triangles
    ``xt[cand]``: to the plane where the projection falls inside (else inf), then to the
    edges ab, bc, ca; the edges' parameters t (S, k, 3) from their first vertex, the
    projections' barycentric coordinates (S, k, 3) and the triangles' edges ab, ac (T, 3).

    Per triangle: vertex a, edges ab, ac, bc and their dot products; per (point,
    candidate) pair only what involves the point (contiguous gathers: the differences of
    strided views of x[tri][cand] were most of :func:`closest_facets`' time)."""
    a = xt[:, 0]
    e0, e1 = xt[:, 1] - a, xt[:, 2] - a
    ebc = xt[:, 2] - xt[:, 1]
    d00, d01, d11 = (np.einsum("ti,ti->t", u, v) for u, v in ((e0, e0), (e0, e1), (e1, e1)))
    dbc = np.einsum("ti,ti->t", ebc, ebc)
    E0, E1, Ebc = e0[cand], e1[cand], ebc[cand]  # (S, k, 3)
    D00, D01, D11 = d00[cand], d01[cand], d11[cand]
    qa = p[:, None, :] - a[cand]
    d20, d21 = np.einsum("ski,ski->sk", qa, E0), np.einsum("ski,ski->sk", qa, E1)
    bu, bv, bw = _barycentric_from_dots(D00, D01, D11, d20, d21)
    inside = (bu >= 0) & (bv >= 0) & (bw >= 0)

    def sq(r):
        return np.einsum("ski,ski->sk", r, r)

    d2 = np.empty(bu.shape + (4,))  # squared: ordered as their roots
    d2[..., 0] = np.where(inside, sq(qa - bv[..., None] * E0 - bw[..., None] * E1), np.inf)
    ts = np.empty(bu.shape + (3,))
    ts[..., 0] = np.clip(d20 / D00, 0.0, 1.0)
    d2[..., 1] = sq(qa - ts[..., 0, None] * E0)
    qb = qa - E0
    ts[..., 1] = np.clip(np.einsum("ski,ski->sk", qb, Ebc) / dbc[cand], 0.0, 1.0)
    d2[..., 2] = sq(qb - ts[..., 1, None] * Ebc)
    ts[..., 2] = np.clip((D11 - d21) / D11, 0.0, 1.0)
    d2[..., 3] = sq(qa - (1.0 - ts[..., 2, None]) * E1)
    return d2, ts, np.stack([bu, bv, bw], -1), (e0, e1)


def boundary_edges(tri: np.ndarray) -> np.ndarray:
    """(T, 3) bool: the edge of each triangle opposite its vertex i lies on the boundary of
    the surface (it belongs to this triangle only)."""
    tri = np.asarray(tri, np.int64)
    e = np.stack([tri[:, [1, 2]], tri[:, [2, 0]], tri[:, [0, 1]]], axis=1)  # (T, 3, 2)
    e = np.sort(e, axis=2).reshape(-1, 2)
    _, inv, cnt = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    return (cnt[inv.ravel()] == 1).reshape(-1, 3)


def past_boundary(p: np.ndarray, xa: np.ndarray, bedge: np.ndarray, *,
                  tol: float = 0.1) -> np.ndarray:
    """(S,) 1.0 where the projection of a point onto the plane of its closest triangle falls
    outside the triangle across a boundary edge of the surface by more than ``tol`` of the
    triangle's height over that edge (the point has slid past the edge of the surface),
    else 0.0.

    Parameters
    ----------
    p : (S, 3) points, mm
    xa : (S, 3, 3) vertices of each point's closest triangle, mm
    bedge : (S, 3) bool, :func:`boundary_edges` of those triangles
    tol : extension zone, in barycentric units (heights of the edge triangle over that
        edge): the surface reaches that far past its boundary edges (Abaqus extends master
        surfaces by 0.1 of the facet size by default); > 0 keeps the boundary nodes of a
        node-to-surface contact, which lie on the edge, in contact through small slips
    """
    lam = np.stack(barycentric(p, xa[:, 0], xa[:, 1], xa[:, 2]), axis=1)
    return np.any((lam < -tol) & bedge, axis=1).astype(float)


def facet_normals(x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(T, 3) unit normals (right-hand rule)."""
    n = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    return n / np.linalg.norm(n, axis=1)[:, None]


#: Map from q = (x_s, x1, x2, x3) (12) to (d, e1, e2) = (x_s - x1, x2 - x1, x3 - x1) (9).
GAP_EDGES = np.zeros((9, 12))
for _blk, (_plus, _minus) in enumerate(((0, 1), (2, 1), (3, 1))):
    GAP_EDGES[3 * _blk:3 * _blk + 3, 3 * _plus:3 * _plus + 3] = np.eye(3)
    GAP_EDGES[3 * _blk:3 * _blk + 3, 3 * _minus:3 * _minus + 3] -= np.eye(3)


def signed_gap(xs: np.ndarray, xa: np.ndarray, *, hessian: bool = True):
    """Signed distance of points to the planes of triangles, with derivatives.

    Parameters
    ----------
    xs : (S, 3) points, mm
    xa : (S, 3, 3) triangle vertices, mm (normal by the right-hand rule)

    Returns
    -------
    g : (S,) signed distance (positive on the normal's side), mm
    dg : (S, 12) derivative with respect to (x_s, x1, x2, x3)
    d2g : (S, 12, 12) second derivative, 1/mm (None without ``hessian``)
    """
    g, dg9, H9 = signed_gap_edges(xs, xa, hessian=hessian)
    return g, dg9 @ GAP_EDGES, None if H9 is None else GAP_EDGES.T @ H9 @ GAP_EDGES


def signed_gap_edges(xs: np.ndarray, xa: np.ndarray, *, hessian: bool = True):
    """:func:`signed_gap` with its derivatives with respect to (d, e1, e2) = (x_s - x1,
    x2 - x1, x3 - x1): dg (S, 9) and d2g (S, 9, 9); ``GAP_EDGES`` (9, 12) maps them to
    (x_s, x1, x2, x3). A caller with its own map to its dofs composes it with
    ``GAP_EDGES`` once (the 12 x 12 Hessian was a fifth of a sliding contact's time)."""
    d = xs - xa[:, 0]
    e1 = xa[:, 1] - xa[:, 0]
    e2 = xa[:, 2] - xa[:, 0]
    a = np.cross(e1, e2)
    A = np.linalg.norm(a, axis=1)
    ah = a / A[:, None]
    vol = np.einsum("si,si->s", d, a)
    g = vol / A
    dvol = np.concatenate([a, np.cross(e2, d), np.cross(d, e1)], axis=1)  # (S, 9)
    dA = np.concatenate([np.zeros_like(a), np.cross(e2, ah), np.cross(ah, e1)], axis=1)
    dg9 = dvol / A[:, None] - (vol / A**2)[:, None] * dA
    if not hessian:
        return g, dg9, None
    S = len(xs)
    Hv = np.zeros((S, 9, 9))
    Hv[:, 0:3, 3:6] = -skew(e2)
    Hv[:, 0:3, 6:9] = skew(e1)
    Hv[:, 3:6, 6:9] = -skew(d)
    Hv = Hv + Hv.transpose(0, 2, 1)
    Jc = np.concatenate([-skew(e2), skew(e1)], axis=2)  # (S, 3, 6) = da/d(e1, e2)
    Pn = np.eye(3) - np.einsum("si,sj->sij", ah, ah)
    HA6 = Jc.transpose(0, 2, 1) @ Pn @ Jc / A[:, None, None]
    HA6[:, 0:3, 3:6] += -skew(ah)
    HA6[:, 3:6, 0:3] += skew(ah)
    HA = np.zeros((S, 9, 9))
    HA[:, 3:, 3:] = HA6
    outer = np.einsum("si,sj->sij", dvol, dA)
    H9 = (Hv / A[:, None, None] - (outer + outer.transpose(0, 2, 1)) / (A**2)[:, None, None]
          + (2.0 * vol / A**3)[:, None, None] * np.einsum("si,sj->sij", dA, dA)
          - (vol / A**2)[:, None, None] * HA)
    return g, dg9, H9


def coo_blocks(row_dofs: np.ndarray, col_dofs: np.ndarray, K: np.ndarray):
    """COO triplets of per-contact blocks K (S, r, c) at dofs (S, r) x (S, c)."""
    r = np.repeat(row_dofs[:, :, None], col_dofs.shape[1], axis=2)
    c = np.repeat(col_dofs[:, None, :], row_dofs.shape[1], axis=1)
    return r.ravel(), c.ravel(), K.ravel()


def summed_blocks(row_dofs: np.ndarray, col_dofs: np.ndarray, K: np.ndarray, n: int):
    """COO triplets of the sum of per-contact blocks K (S, r, c) at dofs (S, r) x (S, c),
    duplicates summed (each (row, col) once), for an n x n matrix.

    The same matrix as :func:`coo_blocks`, with far fewer triplets: neighbouring contact
    points share nodes, so the 18 x 18 blocks of 2.5k sliding points (0.8M triplets per
    block kind) overlap into ~0.2M distinct entries. Summed as the sparse product
    E_r^T blockdiag(K) E_c (E one-hot dof maps), which sums duplicates without a sort and
    drops exact zeros. Measured on the 20k-tet phantom (2496 points, friction on, a perturbed
    state): 1.66M triplets -> 0.11M; the product costs 0.02 s here, the solver's conversion
    of the effect triplets to its reduced CSR fell from 0.057 s to 0.002 s, and the
    concatenation of the effects' triplets shrank alike. Sorted by row, then column: the
    solver finds such keys in its kept pattern (:mod:`mechanics.pattern`) 2-6x faster.
    """
    S, r, c = K.shape
    if S == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    # csr, not the csc it is built as: SciPy multiplies a csc by a csr by converting the
    # large right factor to csc (7.5 ms of the 20 ms product for 3.8k points of 18 dofs)
    Er_t = sp.csc_matrix((np.ones(S * r), np.asarray(row_dofs).ravel(), np.arange(S * r + 1)),
                         shape=(n, S * r)).tocsr()
    # blockdiag(K) E_c: row (s, i) holds K[s, i, :] at the columns col_dofs[s]
    KEc = sp.csr_matrix((np.ascontiguousarray(K).ravel(),
                         np.broadcast_to(np.asarray(col_dofs)[:, None, :], (S, r, c)).ravel(),
                         np.arange(0, S * r * c + 1, c)), shape=(S * r, n))
    A = (Er_t @ KEc).tocsr()
    A.sort_indices()
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(A.indptr))
    return rows, A.indices.astype(np.int64), A.data


def node_dofs(nodes: np.ndarray) -> np.ndarray:
    """(S, k) nodes -> (S, 3k) dofs."""
    return (3 * nodes[:, :, None] + np.arange(3)).reshape(len(nodes), -1)
