"""The pattern a solve's Newton matrices share (mechanics.pattern): the same matrices as a
plain sum, a pattern that grows only where it must, and small entries left out only where
the solve allows it."""

import numpy as np
import pytest
import scipy.sparse as sp
from zoo import hemisphere

from mechanics.model import build_model
from mechanics.pattern import KeptPattern
from mechanics.solver import _constraints, _solid
from mechanics.system import ReducedSystem, full_from_upper

NH = {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.49}}


def _system():
    mesh = hemisphere(60.0, 6)
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 0, -1)},
                                   "fixed": {"node_set": "fixed"}})
    solid = _solid(model, mesh.nodes)
    fixed, _ = _constraints(model, solid.n_nodes, solid.used_nodes)
    ev = solid.evaluate(mesh.nodes)
    sysm = ReducedSystem(mesh.tets, solid.n_nodes, ~fixed, solid.used_nodes)
    return sysm, sysm.assemble(ev.Kup, ev.dv, -solid.V_node / solid.bulk_node), 3 * solid.n_nodes


def _plain(sysm, U, triplets, symmetric):
    """The Newton matrix summed directly: the mesh's part and the triplets on free dofs."""
    A = (U if symmetric else full_from_upper(U)).toarray()
    r, c, v = (np.concatenate(q) for q in zip(*triplets, strict=True))
    r, c = sysm.fi[r], sysm.fi[c]
    keep = (r >= 0) & (c >= 0) & ((r <= c) if symmetric else True)
    np.add.at(A, (r[keep], c[keep]), v[keep])
    return A


@pytest.mark.parametrize("symmetric", [True, False])
def test_kept_pattern_matrices_are_the_plain_sums(symmetric):
    """With nothing left out, every matrix equals the mesh's part plus the effects'
    triplets, summed directly: an effect whose entries stay (a membrane's), one whose
    entries move at every evaluation (a contact's), an addition to a matrix made before the
    pattern grew; the pattern grows only when an entry falls outside it."""
    sysm, U, n3 = _system()
    rng = np.random.default_rng(0)
    kp = KeptPattern(sysm, symmetric, 0.0)
    still = (rng.integers(0, n3, 500), rng.integers(0, n3, 500), rng.standard_normal(500))
    older = None
    for _ in range(6):
        m = int(rng.integers(50, 400))
        moving = (rng.integers(0, n3, m), rng.integers(0, n3, m), rng.standard_normal(m))
        grown = kp.grown
        A = kp.matrix(U, [still, moving])
        ref = _plain(sysm, U, [still, moving], symmetric)
        np.testing.assert_allclose(A.toarray(), ref, rtol=0, atol=1e-12)
        again = kp.matrix(U, [still, moving])
        assert np.array_equal(again.indices, A.indices) and kp.grown == grown + 1  # once
        extra = (rng.integers(0, n3, 30), rng.integers(0, n3, 30), rng.standard_normal(30))
        np.testing.assert_allclose(kp.plus(A, *extra).toarray(),
                                   _plain(sysm, U, [still, moving, extra], symmetric),
                                   rtol=0, atol=1e-12)
        if older is not None:  # a matrix of the pattern before it grew
            np.testing.assert_allclose(kp.plus(older[0], *extra).toarray(),
                                       older[1] + _plain(sysm, 0 * U, [extra], symmetric),
                                       rtol=0, atol=1e-12)
        older = (A, ref)
    assert kp.left_out == 0


def test_small_entries_outside_the_pattern_are_left_out_unless_exact():
    """An effect entry outside the pattern whose share of its effect's tangent (2-norm) is
    at most ``drop_below`` is left out of the matrix and the pattern stays; a larger one
    grows the pattern, and so does any in an exact solve."""
    sysm, U, n3 = _system()
    free = np.flatnonzero(sysm.free)
    r0, c0 = free[:200], free[1:201]
    v0 = np.ones(200)
    kp = KeptPattern(sysm, False, 1e-3)
    kp.matrix(U, [(r0, c0, v0)])
    keys = kp.keys.copy()
    far = (np.concatenate([r0, [free[0]]]), np.concatenate([c0, [free[-1]]]),
           np.concatenate([v0, [1e-3]]))  # 1e-3 / sqrt(200): small
    A = kp.matrix(U, [far])
    assert np.array_equal(kp.keys, keys) and kp.left_out == 1
    np.testing.assert_allclose(A.toarray(), _plain(sysm, U, [(r0, c0, v0)], False), atol=1e-12)
    big = (far[0], far[1], np.concatenate([v0, [1.0]]))
    kp.matrix(U, [big])
    assert len(kp.keys) == len(keys) + 1  # grown: the entry is now in the pattern
    kp2 = KeptPattern(sysm, False, 1e-3)
    kp2.matrix(U, [(r0, c0, v0)])
    np.testing.assert_allclose(kp2.matrix(U, [far], exact=True).toarray(),
                               _plain(sysm, U, [far], False), rtol=0, atol=1e-12)
    assert kp2.left_out == 0


def test_full_from_upper_is_the_symmetric_matrix():
    """The full matrix SuperLU and the unsymmetric pattern start from: U + strict_upper(U)^T
    exactly, call after call on one pattern."""
    rng = np.random.default_rng(2)
    U = sp.triu(sp.random(50, 50, density=0.2, random_state=3), format="csr")
    for _ in range(3):
        V = sp.csr_matrix((rng.normal(size=U.nnz), U.indices.copy(), U.indptr.copy()),
                          shape=U.shape)
        ref = (V + sp.triu(V, k=1).T).toarray()
        np.testing.assert_array_equal(full_from_upper(V).toarray(), ref)
