"""Membranes and cables against closed-form solutions; supports, stiffening and regions."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from breastlike import breastlike_mesh

from mechanics.effects import EFFECTS, MaterialSpec
from mechanics.effects._contact import skew
from mechanics.effects._interface import split_interface
from mechanics.effects.ligaments import cable_terms
from mechanics.effects.membrane import NU_MEMBRANE
from mechanics.mesh import REGIONS, Mesh
from mechanics.model import build_model


def icosphere(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere: nodes (N, 3), outward triangles (T, 3)."""
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t),
         (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    nodes = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = np.array(f)
    for _ in range(level):
        cache, new = {}, []

        def mid(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = nodes[a] + nodes[b]
                nodes.append(m / np.linalg.norm(m))
                cache[key] = len(nodes) - 1
            return cache[key]

        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = np.array(new)
    return np.array(nodes), faces


def closed_form_pressure(lam, E, H, R0, law, Jm=np.inf):
    """Inflation pressure of a thin incompressible sphere at stretch lam, kPa."""
    mu = E / (2 * (1 + NU_MEMBRANE))
    p = 2 * H * mu / R0 * (1 / lam - lam**-7)
    if law == "gent":
        p = p / (1 - (2 * lam**2 + lam**-4 - 3) / Jm)
    return p


def inflate(eff, X, tri, pressure, steps=4):
    """Newton equilibrium of the membrane under a follower pressure. Returns positions."""
    n = len(X)
    x = X.copy()
    for lam_load in np.linspace(0, 1, steps + 1)[1:]:
        p = pressure * lam_load
        for _ in range(30):
            c = eff.contribute(X, x, 1.0)
            K = sp.coo_matrix((c.vals, (c.rows, c.cols)), shape=(3 * n, 3 * n)).tocsr()
            xt = x[tri]
            a = np.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])
            fext = np.zeros((n, 3))
            np.add.at(fext, tri.ravel(), np.repeat(p / 6 * a, 3, axis=0))
            R = np.asarray(c.force).reshape(-1) - fext.reshape(-1)
            # d(a)/dx1 = [x3 - x2]x, cyclic; every node of a triangle gets p/6 a
            blocks = [skew(xt[:, 2] - xt[:, 1]), skew(xt[:, 0] - xt[:, 2]),
                      skew(xt[:, 1] - xt[:, 0])]
            rows, cols, vals = [], [], []
            for i in range(3):
                for j in range(3):
                    r = 3 * tri[:, i, None, None] + np.arange(3)[None, :, None]
                    cc = 3 * tri[:, j, None, None] + np.arange(3)[None, None, :]
                    rows.append(np.broadcast_to(r, blocks[j].shape).ravel())
                    cols.append(np.broadcast_to(cc, blocks[j].shape).ravel())
                    vals.append((-p / 6 * blocks[j]).ravel())
            K = K + sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows),
                                   np.concatenate(cols))), shape=K.shape)
            # A tiny shift of the tangent (no change of the residual) removes the six rigid
            # modes; the residual of a closed pressurised membrane has no rigid component.
            K = K + 1e-9 * abs(K.diagonal()).max() * sp.identity(3 * n)
            du = spla.spsolve(K.tocsc(), -R)
            if np.linalg.norm(R) < 1e-10 * np.linalg.norm(fext):
                break
            x = x + du.reshape(-1, 3)
        else:
            raise AssertionError("membrane inflation did not converge")
    return x


@pytest.mark.parametrize("law,Jm,target", [("neo_hookean", np.inf, 1.15),
                                          ("neo_hookean", np.inf, 1.3),
                                          ("gent", 3.0, 1.2)])
def test_spherical_membrane_matches_closed_form(law, Jm, target):
    """Pressure-stretch of an inflated sphere within 1% (faceting of a 1280-triangle
    icosphere changes area/volume by ~0.3%; the closed form is exact for a smooth sphere)."""
    R0, H, E = 50.0, 2.0, 4.0
    unit, tri = icosphere(3)
    X = R0 * unit
    mesh = Mesh(X, np.zeros((0, 4), int), np.zeros(0, int), face_sets={"skin": tri})
    kw = {"E": E, "thickness": H, "law": law}
    if law == "gent":
        kw["Jm"] = Jm
    eff = EFFECTS["skin"](mesh, **kw)
    p = closed_form_pressure(target, E, H, R0, law, Jm)
    x = inflate(eff, X, tri, p)
    r = np.linalg.norm(x - x.mean(axis=0), axis=1)
    lam = r.mean() / R0
    assert np.ptp(r) / r.mean() < 0.01  # stays spherical
    assert abs(closed_form_pressure(lam, E, H, R0, law, Jm) - p) <= 0.01 * p


@pytest.mark.parametrize("law", ["linear", "neo_hookean"])
def test_cable_closed_form_tension_and_zero_compression(law):
    rng = np.random.default_rng(0)
    P = 50
    X = rng.normal(size=(2 * P, 3)) * 10
    pairs = np.arange(2 * P).reshape(P, 2)
    L = np.linalg.norm(X[1::2] - X[0::2], axis=1)
    lam = rng.uniform(0.5, 1.8, P)
    d = rng.normal(size=(P, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    x = X.copy()
    x[1::2] = x[0::2] + (lam * L)[:, None] * d  # rotated and stretched
    EA = np.full(P, 100.0 * 2.0)
    N, fe, _ = cable_terms(x, pairs, L, EA, law=law)
    expect = EA * (lam - 1) if law == "linear" else EA / 3 * (lam - lam**-2)
    expect = np.where(lam > 1, expect, 0.0)
    np.testing.assert_allclose(N, expect, rtol=1e-12, atol=1e-12)
    # force on the muscle end pulls it back towards the breast end along the cable
    np.testing.assert_allclose(fe[:, 1], N[:, None] * d, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fe[:, 0], -fe[:, 1], rtol=0, atol=0)
    assert np.all(N[lam <= 1] == 0) and np.all(N[lam > 1] > 0)


@pytest.fixture(scope="module")
def mesh():
    return breastlike_mesh(cells=(6, 4, 2, 2))


def test_ligament_groups_switch_separately(mesh):
    full = EFFECTS["ligaments"](mesh)
    one = EFFECTS["ligaments"](mesh, groups=["medial"], E_by_group={"medial": 150.0})
    assert len(full.pairs) == sum(len(v) for v in mesh.node_pairs.values())
    np.testing.assert_array_equal(one.pairs, mesh.node_pairs["ligament_medial"])
    assert np.all(one.E == 150.0) and np.all(full.E == 100.0)
    with pytest.raises(ValueError, match="unknown group"):
        EFFECTS["ligaments"](mesh, groups=["cranial"])


def test_supports_constrain_the_paper_sets(mesh):
    c = EFFECTS["supports"](mesh).constraints()
    s = mesh.node_sets
    assert c[0].components == (0, 1, 2) and set(c[0].nodes) == set(s["fixed"])
    assert c[1].components == (2,)
    assert set(c[1].nodes) == set(s["fascia_superior"]) | set(s["fascia_inferior"])
    assert c[2].components == (1,)
    assert set(c[2].nodes) == set(s["skin_superior"]) | set(s["skin_inferior"])
    assert len(EFFECTS["supports"](mesh, skin_ends=False, fascia_ends=False).constraints()) == 1
    lateral = EFFECTS["supports"](mesh, skin_lateral=True).constraints()[3]
    assert lateral.components == (0,) and set(lateral.nodes) == set(s["skin_lateral"])
    x = mesh.nodes[s["skin_lateral"], 0]
    assert len(x) > 0 and np.allclose(np.abs(x), np.abs(mesh.nodes[:, 0]).max())


def test_strain_stiffening_and_regions_modify_materials(mesh):
    mats = {r: {"name": "neo_hookean", "E": 0.5, "nu": 0.49} for r in (1, 2, 3, 4, 5)}
    model = build_model(mesh, mats, {
        "regions": {"E_left": 0.3, "E_right": 0.7, "E_gland": 2.0},
        "strain_stiffening": {"Jm": 5.0, "Jm_by_region": {"gland_left": 20.0}},
    })
    m = model.materials
    assert m[REGIONS["muscle"]] == MaterialSpec("neo_hookean", mats[2]) or \
        (m[2].name == "neo_hookean" and m[2].params["E"] == 0.5)
    assert m[1].name == "gent" and m[1].params["E"] == 0.3 and m[1].params["Jm"] == 5.0
    assert m[3].params["E"] == 0.7 and m[4].params["E"] == 2.0 and m[4].params["Jm"] == 20.0
    no_gland = EFFECTS["regions"](mesh, E_left=0.3, E_right=0.7, gland=False).moduli()
    assert no_gland[4] == 0.3 and no_gland[5] == 0.7
    with pytest.raises(ValueError, match="outside"):
        EFFECTS["regions"](mesh, E_left=5.0)


def test_every_effect_has_doc_and_bounded_params():
    for name in ("skin", "fascia", "ligaments", "sliding", "tied", "supports",
                 "strain_stiffening", "regions"):
        cls = EFFECTS[name]
        assert cls.doc and "\n" not in cls.doc
        for p in cls.params:
            assert p.unit and p.lower <= p.default <= p.upper


def test_split_interface_duplicates_breast_side(mesh):
    s = split_interface(mesh)
    shared = np.unique(mesh.face_sets["interface"])
    assert s.n_nodes == mesh.n_nodes + len(shared)
    np.testing.assert_array_equal(s.face_sets["interface_muscle"], mesh.face_sets["interface"])
    np.testing.assert_allclose(s.nodes[s.face_sets["interface"]],
                               mesh.nodes[mesh.face_sets["interface"]])
    breast = s.region != REGIONS["muscle"]
    muscle_nodes, breast_nodes = np.unique(s.tets[~breast]), np.unique(s.tets[breast])
    assert np.intersect1d(muscle_nodes, breast_nodes).size == 0
    assert np.all(np.isin(s.face_sets["interface"], breast_nodes))
    assert np.all(np.isin(s.face_sets["skin"], breast_nodes))
    assert np.all(np.isin(s.node_pairs["ligament_medial"][:, 0], breast_nodes))
    assert np.all(np.isin(s.node_sets["fixed"], muscle_nodes))
    np.testing.assert_allclose(s.signed_volumes(), mesh.signed_volumes())
    assert "interface_muscle" not in mesh.face_sets  # input untouched


@pytest.mark.parametrize("width", [0.5, 0.9])
def test_wrinkled_membrane_carries_uniaxial_tension_only(width):
    """A membrane stretched by lam along x and narrowed below its natural width lam^-1/2
    wrinkles: its stress is the uniaxial nominal stress mu (lam - lam^-2) along x, nothing
    across; squeezed in both directions it is slack. Without the relaxation (wrinkling
    "none") the narrowed membrane carries a compressive transverse stress."""
    from mechanics.effects.membrane import membrane_energy_terms, reference_triangles

    X = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [1.0, 3.0, 0.0]])
    tri = np.array([[0, 1, 2]])
    G, A0 = reference_triangles(X, tri)
    E, H, lam = 4.0, 2.0, 1.3
    mu = E / (2 * (1 + NU_MEMBRANE))
    x = X * np.array([lam, width * lam**-0.5, 1.0])
    W, fe, _ = membrane_energy_terms(x, tri, G, A0, H, E)
    V = H * A0[0]
    P = np.zeros((3, 2))
    P[0, 0] = mu * (lam - lam**-2)  # uniaxial nominal stress, kPa
    assert np.allclose(fe[0], V * G[0] @ P.T, rtol=1e-12, atol=1e-12 * abs(fe).max())
    assert W[0] == pytest.approx(V * mu / 2 * (lam**2 + 2 / lam - 3), rel=1e-12)
    _, fe_plain, _ = membrane_energy_terms(x, tri, G, A0, H, E, wrinkling="none")
    assert np.abs(fe_plain[0][:, 1]).max() > 0.1 * np.abs(fe[0][:, 0]).max()
    Ws, fs, Ks = membrane_energy_terms(X * np.array([0.95, width, 1.0]), tri, G, A0, H, E)
    assert Ws[0] == 0.0 and not fs.any() and not Ks.any()
