"""Every effect's residual is the derivative of its energy, and its tangent is the derivative
of its residual, both checked by central finite differences (relative error < 1e-6)."""

import numpy as np
import pytest
import scipy.sparse as sp
from breastlike import breastlike_mesh

from mechanics.effects import EFFECTS
from mechanics.effects._contact import signed_gap
from mechanics.effects._interface import split_interface
from mechanics.mesh import Mesh

# Central differences with h = 1e-6 mm on mm-sized coordinates have a truncation error
# ~h^2 * third derivative ~1e-12 and a round-off error ~1e-16 / 1e-6 relative: 1e-6 is safe.
H = 1e-6
TOL = 1e-6


def _tangent(eff, X, x, load=1.0):
    c = eff.contribute(X, x, load)
    n = 3 * len(x)
    K = sp.coo_matrix((c.vals, (c.rows, c.cols)), shape=(n, n)).toarray()
    return np.asarray(c.force).reshape(-1), K


def _fd_check(eff, X, x, dofs):
    """Max relative error of the tangent columns ``dofs`` against central differences."""
    _, K = _tangent(eff, X, x)
    err, scale = 0.0, np.abs(K).max()
    assert scale > 0
    for d in dofs:
        xp, xm = x.copy().reshape(-1), x.copy().reshape(-1)
        xp[d] += H
        xm[d] -= H
        fp = np.asarray(eff.contribute(X, xp.reshape(-1, 3), 1.0).force).reshape(-1)
        fm = np.asarray(eff.contribute(X, xm.reshape(-1, 3), 1.0).force).reshape(-1)
        err = max(err, np.abs((fp - fm) / (2 * H) - K[:, d]).max())
    return err / scale


def _active_dofs(nodes, rng, k=40):
    dofs = (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()
    return rng.choice(dofs, size=min(k, len(dofs)), replace=False)


@pytest.fixture(scope="module")
def mesh():
    return breastlike_mesh(cells=(6, 4, 2, 2))


@pytest.fixture(scope="module")
def split(mesh):
    return split_interface(mesh)


def _deformed(X, rng, scale=1.0):
    """A smooth finite deformation plus noise (mm)."""
    x = X.copy()
    x[:, 0] += 0.05 * X[:, 1] + 0.002 * X[:, 2] ** 2 / 10
    x[:, 1] *= 1.15
    x[:, 2] += 0.1 * X[:, 0]
    return x + scale * rng.normal(size=X.shape)


@pytest.mark.parametrize("name,kw", [
    ("skin", {}),
    ("skin", {"law": "gent", "Jm": 3.0}),
    ("fascia", {"E": 200.0}),
    ("fascia", {"law": "gent", "Jm": 2.0}),
])
def test_membrane_tangent(mesh, name, kw):
    rng = np.random.default_rng(0)
    eff = EFFECTS[name](mesh, **kw)
    X = mesh.nodes
    x = _deformed(X, rng, 0.3)
    assert _fd_check(eff, X, x, _active_dofs(np.unique(eff.tri), rng)) < TOL


def test_membrane_energy_gradient(mesh):
    rng = np.random.default_rng(1)
    eff = EFFECTS["skin"](mesh)
    X = mesh.nodes
    x = _deformed(X, rng, 0.3)
    f = np.asarray(eff.contribute(X, x, 1.0).force).reshape(-1)
    for d in _active_dofs(np.unique(eff.tri), rng, 10):
        xp, xm = x.copy().reshape(-1), x.copy().reshape(-1)
        xp[d] += 1e-4
        xm[d] -= 1e-4
        fd = (eff.energy(X, xp.reshape(-1, 3)) - eff.energy(X, xm.reshape(-1, 3))) / 2e-4
        assert abs(fd - f[d]) <= 1e-6 * np.abs(f).max()


@pytest.mark.parametrize("law", ["linear", "neo_hookean"])
def test_ligament_tangent(mesh, law):
    rng = np.random.default_rng(2)
    eff = EFFECTS["ligaments"](mesh, law=law)
    X = mesh.nodes
    x = X.copy()
    # stretch every cable by 10-30 % along a random-ish direction, one pair in compression
    b, m = eff.pairs[:, 0], eff.pairs[:, 1]
    x[b] += (X[b] - X[m]) * rng.uniform(0.1, 0.3, (len(b), 1)) + rng.normal(size=(len(b), 3))
    x[b[0]] = X[m[0]] + 0.5 * (X[b[0]] - X[m[0]])
    lam = np.linalg.norm(x[m] - x[b], axis=1) / eff.lengths(X)
    N = eff.forces(X, x)
    assert (lam < 1).any() and (lam > 1).any()
    assert np.all(N[lam < 1] == 0) and np.all(N[lam > 1] > 0)
    assert _fd_check(eff, X, x, _active_dofs(np.unique(eff.pairs), rng, 60)) < TOL


def test_signed_gap_derivatives():
    rng = np.random.default_rng(3)
    xs, xa = rng.normal(size=(5, 3)), rng.normal(size=(5, 3, 3))
    g, dg, d2g = signed_gap(xs, xa)
    q = np.concatenate([xs, xa.reshape(5, 9)], axis=1)
    for k in range(12):
        qp, qm = q.copy(), q.copy()
        qp[:, k] += H
        qm[:, k] -= H
        gp, dgp, _ = signed_gap(qp[:, :3], qp[:, 3:].reshape(5, 3, 3))
        gm, dgm, _ = signed_gap(qm[:, :3], qm[:, 3:].reshape(5, 3, 3))
        assert np.allclose((gp - gm) / (2 * H), dg[:, k], atol=TOL * np.abs(dg).max())
        assert np.allclose((dgp - dgm) / (2 * H), d2g[:, :, k], atol=TOL * np.abs(d2g).max())


def _contact_state(split, rng):
    """Breast side pushed into the muscle (compression) and sheared along x."""
    X = split.nodes
    x = X + 0.01 * rng.normal(size=X.shape)
    breast = np.unique(split.tets[split.region != 2])
    x[breast, 1] += 0.05  # penetration: breast moves posteriorly into the muscle
    return X, x, breast


@pytest.mark.parametrize("points,smoothing", [(0, 0.0), (3, 0.0), (3, 0.2)])
@pytest.mark.parametrize("friction,shift", [(0.0, 0.3), (0.1, 0.3), (2.0, 0.03)])
def test_sliding_tangent(split, friction, shift, points, smoothing):
    """k = 0 frictionless; k = 0.1: every node slips; k = 2 with a small shear: all stick."""
    rng = np.random.default_rng(4)
    eff = EFFECTS["sliding"](split, friction=friction, penalty=50.0, tangential_penalty=20.0,
                             points=points, smoothing=smoothing)
    X, x, breast = _contact_state(split, rng)
    eff.begin_step(X, x)
    x2 = x.copy()
    x2[breast, 0] += shift  # tangential slip from the anchors
    if friction > 0:
        _, t, _ = eff._trial(X, x2)
        bound = friction * np.maximum(eff.pressure(X, x2) * eff.weights(X), 0)
        slipping = np.linalg.norm(t, axis=1) > bound
        assert slipping.all() if friction < 1 else not slipping.any()
    assert eff.symmetric == (friction == 0.0)
    dofs = _active_dofs(np.concatenate([eff.slaves, np.unique(eff.master)]), rng, 24)
    assert _fd_check(eff, X, x2, dofs) < TOL


def test_sliding_tangent_with_points_off_their_anchor_triangle(split):
    """A shear that carries some contact points onto other muscle triangles than their
    friction anchors': their friction blocks sit on other dofs than their normal blocks
    (scattered on their own), the others' are added to the normal blocks; both in one
    tangent, which must still be the residual's derivative."""
    rng = np.random.default_rng(5)
    eff = EFFECTS["sliding"](split, friction=0.1, penalty=50.0, tangential_penalty=20.0)
    X, x, breast = _contact_state(split, rng)
    eff.begin_step(X, x)
    x2 = x.copy()
    # a shear ramp of 0 to 10 mm along x (the muscle triangles' edges are about 32 mm)
    x2[breast, 0] += 10.0 * (X[breast, 0] - X[breast, 0].min()) / np.ptp(X[breast, 0])
    paired = eff._normal(X, x2, hessian=False)[0][:, 3:]  # the muscle triangles' nodes
    anchored = eff.master[eff.anchor_facet]
    moved = np.any(paired != anchored, axis=1)
    assert moved.any() and not moved.all()
    dofs = _active_dofs(np.concatenate([eff.slaves, np.unique(eff.master)]), rng, 24)
    assert _fd_check(eff, X, x2, dofs) < TOL


@pytest.mark.parametrize("smoothing", [0.0, 0.2])
def test_sliding_tangent_smooth_bound_across_zero_pressure(split, smoothing):
    """Regularised friction bound (pressure_smoothing): the normal gap changes sign along x,
    so contact points in compression, near zero pressure and in tension are all present;
    the coupling of friction to the smoothed pressure must be in the tangent."""
    rng = np.random.default_rng(6)
    eff = EFFECTS["sliding"](split, friction=0.3, penalty=50.0, tangential_penalty=20.0,
                             smoothing=smoothing, pressure_smoothing=1.0)
    X, x, breast = _contact_state(split, rng)
    x[breast, 1] -= 0.05
    span = np.ptp(X[:, 0])
    x[breast, 1] += 0.05 * np.sin(2 * np.pi * (X[breast, 0] - X[:, 0].min()) / span)
    eff.begin_step(X, x)
    x2 = x.copy()
    x2[breast, 0] += 0.1
    p = eff.pressure(X, x2)
    assert (p > 1.0).any() and (p < -1.0).any() and (np.abs(p) < 1.0).any()
    dofs = _active_dofs(np.concatenate([eff.slaves, np.unique(eff.master)]), rng, 24)
    assert _fd_check(eff, X, x2, dofs) < TOL


def test_friction_bound_smooth_ramp():
    """The smoothed bound is within k w p_eps / 2 of Coulomb's, exact far from p = 0, and
    its derivative matches finite differences."""
    from mechanics.effects.sliding import friction_bound

    fN = np.linspace(-5.0, 5.0, 101)
    w = np.full_like(fN, 2.0)
    b0, _ = friction_bound(fN, w, 0.1, 0.0)
    b, db = friction_bound(fN, w, 0.1, 0.5)
    assert np.all(b >= b0) and np.abs(b - b0).max() <= 0.1 * 2.0 * 0.5 / 2 + 1e-15
    far = np.abs(fN) > 4.0
    assert np.abs(b - b0)[far].max() <= 0.1 * (2.0 * 0.5) ** 2 / (4 * 4.0)
    h = 1e-6
    fd = (friction_bound(fN + h, w, 0.1, 0.5)[0] - friction_bound(fN - h, w, 0.1, 0.5)[0]) / 2 / h
    np.testing.assert_allclose(db, fd, atol=1e-8)


def test_sliding_augmented_tangent(split):
    rng = np.random.default_rng(5)
    eff = EFFECTS["sliding"](split, method="augmented", friction=0.0)
    X, x, _ = _contact_state(split, rng)
    eff.begin_step(X, x)
    assert np.abs(eff.multiplier).max() > 0
    dofs = _active_dofs(np.concatenate([eff.slaves, np.unique(eff.master)]), rng, 40)
    assert _fd_check(eff, X, x, dofs) < TOL


def test_tied_tangent(split):
    rng = np.random.default_rng(6)
    eff = EFFECTS["tied"](split)
    X, x, _ = _contact_state(split, rng)
    dofs = _active_dofs(np.concatenate([eff.slaves, np.unique(eff.master)]), rng, 40)
    assert _fd_check(eff, X, x, dofs) < TOL


def test_tied_adds_nothing_on_conforming_mesh(mesh):
    c = EFFECTS["tied"](mesh).contribute(mesh.nodes, mesh.nodes + 1.0, 1.0)
    assert np.all(np.asarray(c.force) == 0) and len(c.vals) == 0


def test_sliding_refuses_conforming_mesh(mesh):
    with pytest.raises(ValueError, match="interface_muscle"):
        EFFECTS["sliding"](mesh)
    shared = Mesh(mesh.nodes, mesh.tets, mesh.region,
                  face_sets={"interface": mesh.face_sets["interface"],
                             "interface_muscle": mesh.face_sets["interface"]})
    with pytest.raises(ValueError, match="split the interface"):
        EFFECTS["sliding"](shared)


def _triangle_states(seed=3):
    """Separate triangles, each under a homogeneous stretch chosen to be taut, wrinkled
    (width below the natural width lam^-1/2) or slack, with a random rotation and shear."""
    from mechanics.effects.membrane import reference_triangles

    rng = np.random.default_rng(seed)
    stretches = [(1.3, 1.1), (1.2, 1.0), (1.4, 0.6), (1.1, 0.5), (1.25, 0.2), (0.9, 0.8),
                 (0.95, 0.3)]
    X, x, tri = [], [], []
    for k, (l1, l2) in enumerate(stretches):
        ref = np.array([[0.0, 0.0, 0.0], [3.0, 0.5, 0.0], [0.7, 2.5, 0.0]]) + 5.0 * k
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        A = np.diag([l1, l2, 1.0]) @ np.array([[1.0, 0.2, 0.0], [0.0, 1.0, 0.0], [0, 0, 1]])
        X.append(ref)
        x.append((ref - ref[0]) @ (Q @ A).T + ref[0] + 1.0)
        tri.append(np.arange(3) + 3 * k)
    X, x, tri = np.vstack(X), np.vstack(x), np.array(tri)
    G, A0 = reference_triangles(X, tri)
    return X, x, tri, G, A0


@pytest.mark.parametrize("law,Jm", [("neo_hookean", np.inf), ("gent", 4.0)])
def test_tension_field_membrane_tangent_and_energy(law, Jm):
    """The relaxed (tension-field) membrane in taut, wrinkled and slack states: forces are
    the energy's gradient and the stiffness the forces' derivative."""
    from mechanics.effects.membrane import _relax, membrane_energy_terms

    X, x, tri, G, A0 = _triangle_states()

    def terms(y, tangent=True):
        return membrane_energy_terms(y, tri, G, A0, 2.0, 4.0, law=law, Jm=Jm, tangent=tangent)

    # the chosen stretches cover all three states
    F = np.einsum("tai,taA->tiA", x[tri], G)
    C = np.einsum("tiA,tiB->tAB", F, F)
    c = np.linalg.det(C)
    I1 = C[:, 0, 0] + C[:, 1, 1] + 1 / c
    relaxed, *_ = _relax(C, c, I1, np.zeros((7, 2, 2)), np.zeros((7, 2, 2, 2, 2)))
    assert np.sum(relaxed == I1) >= 2 and np.sum(relaxed == 3.0) >= 2
    assert np.sum((relaxed != I1) & (relaxed != 3.0)) >= 2
    W, fe, Ke = terms(x)
    y = x.reshape(-1)
    err_f = err_k = 0.0
    for d in range(y.size):
        yp, ym = y.copy(), y.copy()
        yp[d] += H
        ym[d] -= H
        Wp, fp, _ = terms(yp.reshape(-1, 3), False)
        Wm, fm, _ = terms(ym.reshape(-1, 3), False)
        t, loc = divmod(d // 3, 3)
        comp = d % 3
        err_f = max(err_f, abs((Wp.sum() - Wm.sum()) / (2 * H) - fe[t, loc, comp]))
        col = (fp[t] - fm[t]).reshape(-1) / (2 * H)
        err_k = max(err_k, np.abs(col - Ke[t][:, 3 * loc + comp]).max())
    assert err_f < TOL * np.abs(fe).max()
    assert err_k < TOL * np.abs(Ke).max()
