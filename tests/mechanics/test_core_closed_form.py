"""Homogeneous deformations against closed-form Neo-Hookean and Gent solutions (nu = 0.49),
and the patch test: a linear field on an irregular mesh is reproduced exactly."""

import numpy as np
import pytest
from scipy.optimize import brentq
from zoo import irregular_cube

from mechanics.model import build_model
from mechanics.solver import SolverOptions, residual_and_tangent, solve

E, NU, JM = 2.0, 0.49, 3.0
MU, K = E / (2 * (1 + NU)), E / (3 * (1 - 2 * NU))
TIGHT = SolverOptions(tol=1e-12, linear_solver="scipy")


def cauchy(name: str, F: np.ndarray) -> np.ndarray:
    """Closed-form Cauchy stress of the paper's laws, kPa."""
    J = np.linalg.det(F)
    b = F @ F.T
    I1 = np.trace(b)
    I1bar = J ** (-2 / 3) * I1
    g = 1.0 if name == "neo_hookean" else 1.0 / (1.0 - (I1bar - 3.0) / JM)
    return MU * g / J * J ** (-2 / 3) * (b - I1 / 3 * np.eye(3)) + K * (J - 1) * np.eye(3)


def material(name):
    p = {"name": name, "E": E, "nu": NU}
    if name == "gent":
        p["Jm"] = JM
    return {1: p}


def boundary(mesh):
    X = mesh.nodes
    return np.flatnonzero(np.any((X < 1e-9) | (X > 1 - 1e-9), axis=1))


@pytest.mark.parametrize("formulation", ["anp", "standard"])
@pytest.mark.parametrize("name", ["neo_hookean", "gent"])
def test_uniaxial_stretch_matches_closed_form(name, formulation):
    stretch = 1.5
    mesh = irregular_cube(2, seed=4)
    s = mesh.node_sets
    model = build_model(mesh, material(name), {
        "fixed:x0": {"node_set": "xmin", "components": [0]},
        "fixed:y0": {"node_set": "ymin", "components": [1]},
        "fixed:z0": {"node_set": "zmin", "components": [2]},
        "fixed:pull": {"node_set": "xmax", "components": [0], "values": stretch - 1.0},
    }, formulation=formulation)
    st = solve(model, options=TIGHT)
    # Closed form: lateral stretch with sigma_yy = 0 (uniaxial stress).
    lat = brentq(lambda t: cauchy(name, np.diag([stretch, t, t]))[1, 1], 0.5, 1.0, xtol=1e-15)
    sig = cauchy(name, np.diag([stretch, lat, lat]))
    x = st.x
    assert abs(x[s["ymax"], 1].mean() - lat) <= 1e-10
    assert np.max(np.abs(x - mesh.nodes * [stretch, lat, lat])) <= 1e-10
    # Stress in every element (1e-8 relative to the axial stress).
    assert np.max(np.abs(st.stress - sig)) <= 1e-8 * abs(sig[0, 0])
    # Nodal reaction on the pulled face = sigma_xx * current area.
    R, _ = residual_and_tangent(model, mesh.nodes, x, 1.0)
    force = R.reshape(-1, 3)[s["xmax"], 0].sum()
    assert abs(force - sig[0, 0] * lat * lat) <= 1e-8 * abs(force)


@pytest.mark.parametrize("formulation", ["anp", "standard"])
@pytest.mark.parametrize("name", ["neo_hookean", "gent"])
def test_simple_shear_matches_closed_form(name, formulation):
    gamma = 0.6
    mesh = irregular_cube(3, seed=5)
    Fm = np.eye(3) + gamma * np.outer([1, 0, 0], [0, 1, 0])
    bnd = boundary(mesh)
    u_bnd = mesh.nodes[bnd] @ (Fm - np.eye(3)).T
    model = build_model(mesh, material(name), {"fixed": {"nodes": bnd, "values": u_bnd}},
                        formulation=formulation)
    st = solve(model, options=TIGHT)
    np.testing.assert_allclose(st.x, mesh.nodes @ Fm.T, rtol=0, atol=1e-10)
    sig = cauchy(name, Fm)
    expected_xy = MU * gamma * (1.0 if name == "neo_hookean" else 1 / (1 - gamma**2 / JM))
    assert abs(sig[0, 1] - expected_xy) <= 1e-12 * expected_xy
    assert np.max(np.abs(st.stress - sig)) <= 1e-8 * abs(sig[0, 1])
    # Net force on the top face (y = 1) in x: sigma_xy * area (area unchanged in shear).
    R, _ = residual_and_tangent(model, mesh.nodes, st.x, 1.0)
    top = mesh.node_sets["ymax"]
    assert abs(R.reshape(-1, 3)[top, 0].sum() - sig[0, 1]) <= 1e-8 * sig[0, 1]


@pytest.mark.parametrize("formulation", ["anp", "standard"])
def test_patch_test_linear_field_reproduced_exactly(formulation):
    mesh = irregular_cube(3, seed=6, amplitude=0.3)
    rng = np.random.default_rng(7)
    G = 1e-3 * rng.standard_normal((3, 3))
    c = rng.standard_normal(3)
    bnd = boundary(mesh)
    u_exact = mesh.nodes @ G.T + c
    model = build_model(mesh, {1: {"name": "linear", "E": E, "nu": NU}},
                        {"fixed": {"nodes": bnd, "values": u_exact[bnd]}},
                        formulation=formulation)
    st = solve(model, options=TIGHT)
    interior = np.setdiff1d(np.arange(mesh.n_nodes), bnd)
    assert len(interior) == 8
    np.testing.assert_allclose(st.u, u_exact, rtol=0, atol=1e-13)
    eps = 0.5 * (G + G.T)
    sig = 2 * MU * (eps - np.trace(eps) / 3 * np.eye(3)) + K * np.trace(eps) * np.eye(3)
    assert np.max(np.abs(st.stress - sig)) <= 1e-9 * np.abs(sig).max()


def test_tet_volumes_fill_the_cube_and_match_the_reference_geometry():
    """The volumes gravity weighs (``tet_volumes``) are the solid's (``reference_geometry``)
    to rounding, all positive on a valid mesh, and sum to the unit cube's volume."""
    from mechanics.kernels import reference_geometry, tet_volumes

    mesh = irregular_cube(3, seed=7, amplitude=0.3)
    V = tet_volumes(mesh.nodes, mesh.tets)
    _, V0 = reference_geometry(mesh.nodes, mesh.tets)
    assert np.all(V > 0.0)
    assert np.abs(V - V0).max() <= 1e-14
    assert abs(V.sum() - 1.0) <= 1e-12
