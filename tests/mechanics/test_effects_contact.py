"""Sliding contact in the solver: friction on an incline, a non-matching patch test and a
no-separation interface under a pulling load."""

import numpy as np
import pytest
import scipy.sparse as sp
from breastlike import boundary_faces, breastlike_mesh, paper_model
from zoo import box

from mechanics.effects._interface import split_interface
from mechanics.mesh import Mesh
from mechanics.model import build_model
from mechanics.solver import SolverError, SolverOptions, residual_and_tangent, solve

# The penalty (1e4 kPa/mm against E = 1 kPa) limits the attainable residual to ~1e-9.
OPTS = SolverOptions(tol=1e-8, linear_solver="scipy")
RHO_G = 9.81e-3  # mN/mm^3 for 1000 kg/m^3


def stack(lower, upper, *, extra_nodes=()) -> Mesh:
    """Two separate boxes: ``lower`` (muscle, region 2) under ``upper`` (breast, region 1),
    each (shape, size, origin). The upper bottom face touches the lower top face; the meshes
    do not share nodes (non-matching when the shapes differ)."""
    lo, up = box(*lower), box(*upper)
    n0 = lo.n_nodes
    nodes = np.concatenate([lo.nodes, up.nodes, np.reshape(extra_nodes, (-1, 3))])
    tets = np.concatenate([lo.tets, up.tets + n0])
    region = np.concatenate([np.full(lo.n_tets, 2), np.full(up.n_tets, 1)])
    z_top = lower[2][2] + lower[1][2]
    bl = boundary_faces(lo.tets, np.ones(lo.n_tets, bool))
    bu = boundary_faces(up.tets, np.ones(up.n_tets, bool)) + n0
    master = bl[np.all(np.abs(nodes[bl, 2] - z_top) < 1e-9, axis=1)]  # outward = +z
    slave = bu[np.all(np.abs(nodes[bu, 2] - z_top) < 1e-9, axis=1)][:, ::-1]  # flip to +z
    top = bu[np.all(np.abs(nodes[bu, 2] - nodes[:, 2][bu].max()) < 1e-9, axis=1)]
    sets = {"bottom": lo.node_sets["zmin"], "top": np.unique(top),
            "upper": np.arange(n0, n0 + up.n_nodes)}
    return Mesh(nodes, tets, region, node_sets=sets,
                face_sets={"interface": slave, "interface_muscle": master, "top": top})


def materials(E_lower, E_upper, nu=0.3):
    return {2: {"name": "neo_hookean", "E": E_lower, "nu": nu},
            1: {"name": "neo_hookean", "E": E_upper, "nu": nu}}


@pytest.mark.parametrize("smoothing", [0.0, 0.1])
@pytest.mark.parametrize("tan_a", [0.05, 0.09, 0.11, 0.2])
def test_block_on_incline_sticks_below_and_slides_above_friction(tan_a, smoothing):
    """A stiff block on a plane, gravity tilted by a (tan a vs k = 0.1), held uphill by a
    soft tension-only cable. Sticking (tan a < k): friction carries the downhill load, the
    cable stays (almost) slack. Sliding (tan a > k): the cable carries W (sin a - k cos a)
    and the block slides by that force over the cable stiffness EA/L (closed form, 1%).
    Exact Coulomb corner (smoothing 0) and the default rounded corner (0.1) alike."""
    k = 0.1
    anchor = np.array([[-20.0, 5.0, 4.0]])  # orphan node: held fixed by the solver
    mesh = stack(((12, 3, 1), (60.0, 15.0, 4.0), (-30.0, -2.5, 0.0)),
                 ((2, 2, 1), (10.0, 10.0, 5.0), (0.0, 0.0, 4.0)), extra_nodes=anchor)
    upper = mesh.node_sets["upper"]
    hook = upper[np.all(np.abs(mesh.nodes[upper] - [0.0, 5.0, 4.0]) < 1e-9, axis=1)]
    mesh = Mesh(mesh.nodes, mesh.tets, mesh.region, node_sets=mesh.node_sets,
                face_sets=mesh.face_sets,
                node_pairs={"ligament_lateral": [[hook[0], mesh.n_nodes - 1]]})
    a = np.arctan(tan_a)
    density = 1e4  # kg/m^3: a heavy block makes the slide long compared to elastic slips
    E_cable, area, L = 10.0, 1.0, 20.0
    model = build_model(mesh, materials(1e3, 1e3), {
        "fixed": {"node_set": "bottom"},
        "gravity": {"direction": (np.sin(a), 0.0, -np.cos(a)), "density": density},
        "sliding": {"friction": k, "penalty": 1e3, "tangential_penalty": 1e3,
                    "smoothing": smoothing},
        "ligaments": {"E": E_cable, "area": area},
    })
    st = solve(model, options=SolverOptions(tol=1e-9, linear_solver="scipy", initial_steps=4))
    W = density * 9.81e-6 * 500.0  # mN
    slide = st.u[upper, 0].mean()
    cable = model.effects[3].forces(mesh.nodes, st.x)[0]
    if tan_a < k:
        assert cable <= 1e-3 * W * np.sin(a)
        assert abs(slide) <= 0.01  # mm: elastic deformation of slab, block and penalty only
    else:
        N = W * (np.sin(a) - k * np.cos(a))
        expect = N * L / (E_cable * area)
        assert abs(cable - N) <= 0.01 * N
        assert abs(slide - expect) <= 0.01 * expect


def _pressure_loads(mesh, p):
    """Consistent nodal forces (mN) of a uniform pressure p (kPa) on face set 'top'."""
    tri = mesh.face_sets["top"]
    X = mesh.nodes
    A = 0.5 * np.linalg.norm(np.cross(X[tri[:, 1]] - X[tri[:, 0]], X[tri[:, 2]] - X[tri[:, 0]]),
                             axis=1)
    f = np.bincount(tri.ravel(), weights=np.repeat(A / 3, 3), minlength=mesh.n_nodes)
    nodes = np.flatnonzero(f)
    return nodes, -p * f[nodes, None] * [0.0, 0.0, 1.0]


@pytest.mark.parametrize("friction", [0.0, 0.1])
def test_contact_patch_test_non_matching(friction):
    """Uniform pressure on a fine block resting on a coarse block (non-matching interface):
    the contact pressure lumped to the slave nodes and the stress in every element equal the
    applied pressure (1%; Gauss-point-to-surface contact with 3 points per slave face)."""
    p = 1e-3  # kPa: small strains, so the Cauchy stress equals the applied dead load
    mesh = stack(((3, 3, 2), (10.0, 10.0, 4.0), (0.0, 0.0, 0.0)),
                 ((5, 4, 2), (10.0, 10.0, 4.0), (0.0, 0.0, 4.0)))
    X = mesh.nodes
    nodes, forces = _pressure_loads(mesh, p)
    lower_corner = np.flatnonzero(np.all(np.abs(X - [0, 0, 0]) < 1e-9, axis=1))
    lower_x = np.flatnonzero(np.all(np.abs(X - [10, 0, 0]) < 1e-9, axis=1))
    up_corner = np.flatnonzero(np.all(np.abs(X - [0, 0, 8]) < 1e-9, axis=1))
    up_x = np.flatnonzero(np.all(np.abs(X - [10, 0, 8]) < 1e-9, axis=1))
    model = build_model(mesh, materials(1.0, 1.0), {
        "fixed:floor": {"node_set": "bottom", "components": [2]},
        "fixed:a": {"nodes": np.r_[lower_corner, up_corner], "components": [0, 1]},
        "fixed:b": {"nodes": np.r_[lower_x, up_x], "components": [1]},
        "point_load": {"nodes": nodes, "force": forces},
        "sliding": {"friction": friction, "penalty": 1e4},
    })
    st = solve(model, options=OPTS)
    sliding = model.effects[-1]
    np.testing.assert_allclose(sliding.nodal_pressure(X, st.x), p, rtol=0.01)
    np.testing.assert_allclose(st.stress[:, 2, 2], -p, rtol=0.01)
    assert np.abs(st.stress[:, :2, :2]).max() <= 0.01 * p


def test_no_separation_under_pulling_load():
    """Gravity pulling the block away from the slab: the interface holds it in tension
    with the penalty gap of the closed form (weight / (penalty * area))."""
    mesh = stack(((3, 3, 1), (10.0, 10.0, 2.0), (0.0, 0.0, 0.0)),
                 ((4, 4, 2), (10.0, 10.0, 5.0), (0.0, 0.0, 2.0)))
    X = mesh.nodes
    eps = 100.0
    up_corner = np.flatnonzero(np.all(np.abs(X - [0, 0, 2]) < 1e-9, axis=1))[-1:]
    up_x = np.flatnonzero(np.all(np.abs(X - [10, 0, 2]) < 1e-9, axis=1))[-1:]
    model = build_model(mesh, materials(10.0, 10.0), {
        "fixed": {"node_set": "bottom"},
        "fixed:a": {"nodes": up_corner, "components": [0, 1]},
        "fixed:b": {"nodes": up_x, "components": [1]},
        "gravity": {"direction": (0.0, 0.0, 1.0)},
        "sliding": {"friction": 0.1, "penalty": eps},
    })
    st = solve(model, options=OPTS)
    assert st.converged
    sliding = model.effects[-1]
    gap = sliding.gaps(X, st.x)
    W = RHO_G * 500.0
    assert np.all(gap > 0)
    # total normal force = weight (equilibrium), mean gap = W / (eps * area)
    tension = -(sliding.pressure(X, st.x) * sliding.weights(X)).sum()
    assert abs(tension - W) <= 1e-6 * W
    w = sliding.weights(X)
    assert abs((w * gap).sum() / w.sum() - W / (eps * 100.0)) <= 1e-6 * W / (eps * 100.0)
    assert gap.max() <= 1e-3  # mm: held on, not separated


def test_friction_from_exactly_zero_pressure_sticks_on_an_incline():
    """The interface lies exactly in z = 0, so at the first iterate every gap and every contact
    pressure is exactly zero: friction gives no tangential stiffness and the downhill mode of
    the block is free (singular tangent). The solver's regularisation (the sliding effect's
    stick stiffness, only in the Newton matrix) gets past it, and the converged state is the
    unregularised equilibrium: friction carries W sin a (tan a = 0.05 < k = 0.1, 1%), the
    block does not slide, and the exact residual vanishes."""
    mesh = stack(((6, 3, 1), (30.0, 15.0, 4.0), (-15.0, -7.5, -4.0)),
                 ((2, 2, 1), (10.0, 10.0, 5.0), (-5.0, -5.0, 0.0)))
    a = np.arctan(0.05)
    density = 1e4
    model = build_model(mesh, materials(1e3, 1e3), {
        "fixed": {"node_set": "bottom"},
        "gravity": {"direction": (np.sin(a), 0.0, -np.cos(a)), "density": density},
        "sliding": {"friction": 0.1, "penalty": 1e3, "tangential_penalty": 1e3},
    })
    sliding = model.effects[-1]
    X = mesh.nodes
    sliding.begin_step(X, X.copy())
    assert np.all(sliding.gaps(X, X) == 0.0)  # the premise: exactly zero pressure
    with pytest.raises(SolverError, match="singular"):
        solve(model, options=SolverOptions(tol=1e-9, linear_solver="scipy", singular_shift=0.0))
    st = solve(model, options=SolverOptions(tol=1e-9, linear_solver="scipy"))
    assert any(e.get("shifted", 0) for e in st.log)
    W = density * 9.81e-6 * 500.0  # mN
    _, t, _ = sliding.tangential_state(X, st.x)
    assert abs(t[:, 0].sum() - W * np.sin(a)) <= 0.01 * W * np.sin(a)
    assert abs(st.u[mesh.node_sets["upper"], 0].mean()) <= 0.01  # mm: elastic only
    R, _ = residual_and_tangent(model, X, st.x, 1.0)
    free = np.ones(mesh.n_nodes, bool)
    free[mesh.node_sets["bottom"]] = False
    assert np.linalg.norm(R.reshape(-1, 3)[free]) <= 1e-7 * W


def test_regularization_is_the_stick_stiffness_of_unloaded_points():
    """The regularising stiffness is symmetric positive semi-definite, covers exactly the
    points without compressive pressure, and is absent without friction."""
    mesh = stack(((3, 3, 1), (10.0, 10.0, 2.0), (0.0, 0.0, 0.0)),
                 ((2, 2, 1), (10.0, 10.0, 4.0), (0.0, 0.0, 2.0)))
    X = mesh.nodes
    eff = build_model(mesh, materials(1.0, 1.0), {"sliding": {"friction": 0.1}}).effects[0]
    x = X.copy()
    x[mesh.node_sets["upper"], 2] += 0.01  # pulled apart: tension, zero friction bound
    eff.begin_step(X, X.copy())
    r, c, v = eff.regularization(X, x)
    n = 3 * mesh.n_nodes
    S = np.zeros((n, n))
    np.add.at(S, (r, c), v)
    np.testing.assert_allclose(S, S.T, atol=1e-12)
    ev = np.linalg.eigvalsh(S)
    assert ev.min() >= -1e-9 * ev.max() and ev.max() > 0
    # stiffness of a rigid tangential slide of the upper block = eps_T * interface area
    d = np.zeros((mesh.n_nodes, 3))
    d[mesh.node_sets["upper"], 0] = 1.0
    expect = eff.values["tangential_penalty"] * 100.0  # kPa/mm * mm^2
    assert abs(d.ravel() @ S @ d.ravel() - expect) <= 1e-9 * expect
    x[mesh.node_sets["upper"], 2] -= 0.02  # pressed together: no regularisation
    assert len(eff.regularization(X, x)[2]) == 0
    off = build_model(mesh, materials(1.0, 1.0), {"sliding": {"friction": 0.0}}).effects[0]
    assert len(off.regularization(X, x)[2]) == 0


@pytest.mark.slow
def test_soft_breast_supine_with_friction_converges():
    """The paper-like model at the soft corner of the search box (breast 0.1, skin 20, fascia
    80 kPa), supine, friction 0.1 with the default stick penalty: converges (it cycled with a
    100 kPa/mm stick spring), and friction holds the interface back: its mean tangential
    slide is smaller than without friction."""
    mesh = split_interface(breastlike_mesh())
    nodes = np.unique(mesh.face_sets["interface"])
    slide = {}
    for k in (0.1, 0.0):
        st = solve(paper_model(mesh, 0.1, 20.0, 80.0, "supine", sliding={"friction": k}),
                   options=SolverOptions(max_newton=30))
        assert st.converged and st.load == 1.0
        slide[k] = np.linalg.norm(st.u[nodes][:, [0, 2]], axis=1).mean()
    assert slide[0.1] < slide[0.0]


def test_begin_step_updates_once_per_converged_state():
    """A cut-back calls begin_step again at the same converged x: the friction anchors and the
    augmented multipliers must come out as after one call (they used to be updated again,
    relaxing the friction forces and growing the multipliers at every retry)."""
    mesh = stack(((3, 3, 1), (10.0, 10.0, 2.0), (0.0, 0.0, 0.0)),
                 ((2, 2, 1), (10.0, 10.0, 4.0), (0.0, 0.0, 2.0)))
    X = mesh.nodes
    eff = build_model(mesh, materials(1.0, 1.0), {
        "sliding": {"friction": 0.1, "method": "augmented"}}).effects[0]
    eff.begin_step(X, X.copy())
    x = X.copy()
    up = mesh.node_sets["upper"]
    x[up, 2] -= 0.01  # pressed on: a friction bound
    x[up, 0] += 0.5  # sheared far beyond it: every point slips
    eff.begin_step(X, x.copy())
    once = (eff.multiplier.copy(), eff.anchor_bary.copy(), eff.anchor_facet.copy())
    assert np.abs(once[0]).max() > 0  # the premise: the update did something
    for _ in range(3):
        eff.begin_step(X, x.copy())
    np.testing.assert_array_equal(eff.multiplier, once[0])
    np.testing.assert_array_equal(eff.anchor_bary, once[1])
    np.testing.assert_array_equal(eff.anchor_facet, once[2])


@pytest.mark.parametrize("smoothing", [0.0, 0.1, 0.3])
def test_anchor_update_keeps_the_friction_force_of_a_converged_state(smoothing):
    """Re-anchoring at the start of a load step moves only the slipping points' anchors and
    leaves every contact force at x unchanged, so a converged state stays in equilibrium (a
    law below the stick line everywhere relaxed every force at each step). Shear growing
    along x: sticking, rounded and slipping points alike."""
    mesh = stack(((4, 4, 1), (20.0, 20.0, 2.0), (-5.0, -5.0, 0.0)),
                 ((4, 4, 1), (10.0, 10.0, 4.0), (0.0, 0.0, 2.0)))
    X = mesh.nodes
    eff = build_model(mesh, materials(1.0, 1.0), {
        "sliding": {"friction": 0.1, "smoothing": smoothing}}).effects[0]
    eff.begin_step(X, X.copy())
    x = X.copy()
    up = mesh.node_sets["upper"]
    x[up, 2] -= 0.02 + 0.01 * X[up, 1] / 10.0  # pressure varying along y
    x[up, 0] += 0.05 * X[up, 0]  # shear growing along x
    _, _, stick = eff.tangential_state(X, x)
    assert 0 < stick.sum() < len(stick)  # the premise: both states present
    before = eff.contribute(X, x, 1.0).force
    eff.begin_step(X, x.copy())
    after = eff.contribute(X, x, 1.0).force
    tol = 1e-9 * np.abs(before).max()
    # breast side node by node; the muscle side takes the reaction at the anchor, which moves
    # with the slip, so only its resultant is unchanged
    np.testing.assert_allclose(after[up], before[up], atol=tol)
    np.testing.assert_allclose(after.sum(axis=0), before.sum(axis=0), atol=tol)


def _mound_model(position_gravity, effects):
    from breastmodel.phantom.mounds import mound_mesh

    mesh = split_interface(mound_mesh(cells=(8, 6, 3, 2), gland=False))
    nh = {"name": "neo_hookean", "nu": 0.49}
    mats = {1: {**nh, "E": 1.0}, 3: {**nh, "E": 1.0}, 2: {**nh, "E": 10.0}}
    eff = {"supports": {}, "skin": {"E": 4.0}, **effects,
           "gravity": {"direction": position_gravity}}
    return mesh, build_model(mesh, mats, eff)


def test_two_mounds_tilted_slide_held_by_ligaments():
    """The paper's model on the two-mound mesh (breast 1, muscle 10, skin 4, fascia 120 kPa,
    friction 0.1, ligaments 100 kPa on 10 mm^2) tilted 45 deg: converges, and the breast's
    lateral balance holds: the weight's x component equals the friction resultant plus the
    ligaments' x pull (no support acts in x; 1e-6), with friction at Coulomb's capacity
    k x (normal resultant) within the rounding of the corner (10 %), since 0.1 < tan 45."""
    g = (np.sqrt(0.5), np.sqrt(0.5), 0.0)
    mesh, model = _mound_model(g, {"fascia": {"E": 120.0}, "ligaments": {"area": 10.0},
                                   "sliding": {"friction": 0.1}})
    st = solve(model, options=SolverOptions(linear_solver="scipy"))
    X, x = mesh.nodes, st.x
    eff = {e.name: e for e in model.effects}
    breast = np.unique(mesh.tets[mesh.region != 2])
    W = RHO_G * np.abs(np.linalg.det(X[mesh.tets[mesh.region != 2]][:, 1:]
                                     - X[mesh.tets[mesh.region != 2]][:, :1])).sum() / 6
    lig = eff["ligaments"].contribute(X, x, 1.0).force[breast].sum(axis=0)
    slide = eff["sliding"].contribute(X, x, 1.0).force[breast].sum(axis=0)
    assert abs(lig[0] + slide[0] - W * g[0]) <= 1e-6 * W  # residual sign: resisting > 0
    _, t, _ = eff["sliding"].tangential_state(X, x)
    fN = -(eff["sliding"].pressure(X, x) * eff["sliding"].weights(X))  # < 0 compression
    cap = 0.1 * np.maximum(-fN, 0).sum()
    assert 0.9 * cap <= abs(t[:, 0].sum()) <= cap * (1 + 1e-9)
    assert lig[0] > 0.5 * W * g[0]  # the ligaments, not friction, hold most of it


@pytest.mark.parametrize("path_steps", [1, 2])
def test_friction_path_is_set_by_path_steps_not_by_the_solver_steps(path_steps):
    """The tilted two-mound model with friction, solved in one load step and in five solver
    steps (initial_steps 5): the friction history moves only at the path points k /
    path_steps, which every solve converges, so both give one solution (to the Newton
    tolerance); a different path gives another (0.13 mm from 4 path steps with 1, 0.06 with
    2). Without held pairings: a pairing held across a crease until a solver step ends
    leaves the converged state in equilibrium for that pairing, which moved it by up to
    0.013 mm (1 path step) and 0.053 mm (2) between the two stepping schemes."""
    g = (np.sqrt(0.5), np.sqrt(0.5), 0.0)
    sliding = {"friction": 0.1, "path_steps": path_steps, "hold_flipping": False}
    mesh, model = _mound_model(g, {"fascia": {"E": 120.0}, "ligaments": {"area": 10.0},
                                   "sliding": sliding})
    points = {k / path_steps for k in range(1, path_steps + 1)}
    sols = []
    for steps in (1, 5):
        # grow_below 0: the five steps stay five (fast steps would grow the increment)
        st = solve(model, options=SolverOptions(linear_solver="scipy", initial_steps=steps,
                                                grow_below=0))
        loads = {round(e["load"], 12) for e in st.log if e["converged"]}
        assert points <= loads and len(loads) >= (5 if steps == 5 else len(points))
        sols.append(st.u)
    scale = np.abs(sols[0]).max()
    assert np.abs(sols[1] - sols[0]).max() <= 1e-6 * scale
    _, other = _mound_model(g, {"fascia": {"E": 120.0}, "ligaments": {"area": 10.0},
                                "sliding": {**sliding, "path_steps": 3 - path_steps}})
    u_other = solve(other, options=SolverOptions(linear_solver="scipy")).u
    assert np.abs(u_other - sols[0]).max() > 1e-3 * scale


@pytest.mark.parametrize("gy", [-1.0, 1.0])
def test_two_mounds_prone_and_supine_slide_on_friction_alone(gy):
    """Skin, supports and sliding with friction 0.1 on the two-mound mesh (the diagnosis's
    sliding truth) converge prone and supine; the mesh is mirror-symmetric in x, so the
    friction resultant in x vanishes (1e-6 of the weight) while the two breasts slide apart
    or together."""
    mesh, model = _mound_model((0.0, gy, 0.0), {"sliding": {"friction": 0.1}})
    st = solve(model, options=SolverOptions(linear_solver="scipy"))
    X = mesh.nodes
    breast = np.unique(mesh.tets[mesh.region != 2])
    W = RHO_G * np.abs(np.linalg.det(X[mesh.tets[mesh.region != 2]][:, 1:]
                                     - X[mesh.tets[mesh.region != 2]][:, :1])).sum() / 6
    slide = model.effects[-2].contribute(X, st.x, 1.0).force[breast].sum(axis=0)
    assert abs(slide[0]) <= 1e-6 * W
    left = breast[X[breast, 0] > 0]
    assert np.abs(st.u[left, 0]).max() > 0.1  # mm: the interface does slide


def _overhang(friction=0.1):
    """A block (x in [4, 14]) resting on a slab (x in [0, 10]): its bottom overhangs the slab's
    edge x = 10 by 4 mm; the slab's top triangles are 10/3 mm wide, and the slab's surface
    extends 0.1 of that past its edge."""
    mesh = stack(((3, 3, 1), (10.0, 10.0, 2.0), (0.0, 0.0, 0.0)),
                 ((5, 4, 2), (10.0, 10.0, 4.0), (4.0, 0.0, 2.0)))
    eff = build_model(mesh, materials(1.0, 1.0), {
        "sliding": {"friction": friction, "penalty": 50.0, "tangential_penalty": 20.0,
                    "edge_extension": 0.1}}).effects[0]
    return mesh, eff


def test_points_past_the_edge_of_the_muscle_surface_are_released():
    """Contact points whose projection falls past the slab's edge (beyond the extension zone of
    0.1 of the edge triangle's height, here 1/3 mm) are released: zero pressure, no force, no
    stiffness; every point over the slab carries the penalty pressure of the penetration (it
    used to be held by the extended plane of the edge triangles, under empty space)."""
    mesh, eff = _overhang()
    X = mesh.nodes
    up = mesh.node_sets["upper"]
    eff.begin_step(X, X.copy())
    x = X.copy()
    x[up, 2] -= 0.01  # pressed 0.01 mm into the slab
    xp = eff.contact_points(x)
    off = eff.released(X, x)
    assert np.all(xp[off, 0] > 10.0) and np.all(off[xp[:, 0] > 10.0 + 10.0 / 3 * 0.1 + 1e-9])
    assert off.any() and (~off).any()
    p = eff.pressure(X, x)
    np.testing.assert_allclose(p[~off], 50.0 * 0.01, rtol=1e-9)
    assert np.all(p[off] == 0.0)
    # the released points add nothing: forces on the nodes that only they touch vanish
    c = eff.contribute(X, x, 1.0)
    only_off = np.setdiff1d(np.unique(eff.sconn[off]), np.unique(eff.sconn[~off]))
    assert only_off.size and np.all(c.force[only_off] == 0.0)
    n = 3 * mesh.n_nodes
    K = sp.coo_matrix((c.vals, (c.rows, c.cols)), shape=(n, n)).tocsr()
    dofs = (3 * only_off[:, None] + np.arange(3)).ravel()
    assert abs(K[dofs]).sum() == 0.0


def test_sliding_tangent_with_released_points():
    """Finite-difference check (central, h = 1e-6 mm, 1e-6 relative) of the tangent at a state
    with released points, slipping points and points in compression and tension."""
    mesh, eff = _overhang()
    X = mesh.nodes
    up = mesh.node_sets["upper"]
    rng = np.random.default_rng(7)
    x = X + 0.002 * rng.normal(size=X.shape)
    x[up, 2] -= 0.01 + 0.002 * (X[up, 1] - 5.0)  # compression, tension at y = 10
    eff.begin_step(X, x.copy())
    x[up, 0] += 0.3  # slip past the anchors
    off = eff.released(X, x)
    p = eff.pressure(X, x)
    assert off.any() and (p[~off] > 0).any() and (p[~off] < 0).any()
    c = eff.contribute(X, x, 1.0)
    n = 3 * mesh.n_nodes
    K = sp.coo_matrix((c.vals, (c.rows, c.cols)), shape=(n, n)).toarray()
    nodes = np.concatenate([eff.slaves, np.unique(eff.master)])
    dofs = rng.choice((3 * nodes[:, None] + np.arange(3)).ravel(), 30, replace=False)
    h, err = 1e-6, 0.0
    for d in dofs:
        xp_, xm_ = x.copy().reshape(-1), x.copy().reshape(-1)
        xp_[d] += h
        xm_[d] -= h
        fp = eff.contribute(X, xp_.reshape(-1, 3), 1.0).force.reshape(-1)
        fm = eff.contribute(X, xm_.reshape(-1, 3), 1.0).force.reshape(-1)
        err = max(err, np.abs((fp - fm) / (2 * h) - K[:, d]).max())
    assert err <= 1e-6 * np.abs(K).max()


def test_overhanging_block_carries_its_load_on_the_slab_only():
    """Uniform pressure on the overhanging block: the solve converges, the released points carry
    nothing and the contact resultant equals the applied load (equilibrium, 1e-6)."""
    mesh, _ = _overhang()
    X = mesh.nodes
    p = 1e-3
    nodes, forces = _pressure_loads(mesh, p)
    corner = np.flatnonzero(np.all(np.abs(X - [4, 0, 2]) < 1e-9, axis=1))[-1:]
    xdir = np.flatnonzero(np.all(np.abs(X - [14, 0, 2]) < 1e-9, axis=1))[-1:]
    model = build_model(mesh, materials(1.0, 1.0), {
        "fixed": {"node_set": "bottom"},
        "fixed:a": {"nodes": corner, "components": [0, 1]},
        "fixed:b": {"nodes": xdir, "components": [1]},
        "point_load": {"nodes": nodes, "force": forces},
        "sliding": {"friction": 0.1, "penalty": 1e3, "edge_extension": 0.1},
    })
    st = solve(model, options=OPTS)
    eff = model.effects[-1]
    off = eff.released(X, st.x)
    assert off.any()
    fN = eff.pressure(X, st.x) * eff.weights(X)
    assert np.all(fN[off] == 0.0)
    load = -forces[:, 2].sum()
    assert abs(fN.sum() - load) <= 1e-6 * load


def test_summed_blocks_equal_the_plain_triplets():
    """summed_blocks (duplicates summed by a sparse product) is the matrix of coo_blocks."""
    from mechanics.effects._contact import coo_blocks, summed_blocks

    rng = np.random.default_rng(1)
    rd, cd = rng.integers(0, 40, (30, 6)), rng.integers(0, 40, (30, 9))
    K = rng.normal(size=(30, 6, 9))
    a = sp.coo_matrix((K.ravel(), (coo_blocks(rd, cd, K)[:2])), shape=(40, 40)).toarray()
    r, c, v = summed_blocks(rd, cd, K, 40)
    assert len(np.unique(r * 40 + c)) == len(r)  # each entry once
    np.testing.assert_allclose(sp.coo_matrix((v, (r, c)), shape=(40, 40)).toarray(), a,
                               atol=1e-13)


def test_default_edge_extension_is_one_triangle_height():
    """By default the muscle surface extends one edge-triangle height (10/3 mm here) past its
    edge, standing in for the chest wall beyond the muscle; points further out are released."""
    mesh = stack(((3, 3, 1), (10.0, 10.0, 2.0), (0.0, 0.0, 0.0)),
                 ((5, 4, 2), (10.0, 10.0, 4.0), (4.0, 0.0, 2.0)))
    eff = build_model(mesh, materials(1.0, 1.0), {"sliding": {}}).effects[0]
    X = mesh.nodes
    x = X.copy()
    x[mesh.node_sets["upper"], 2] -= 0.01
    xp = eff.contact_points(x)
    off = eff.released(X, x)
    np.testing.assert_array_equal(off, xp[:, 0] > 10.0 + 10.0 / 3)
    assert off.any() and (xp[~off, 0] > 10.0).any()
    with pytest.raises(ValueError, match="edge_extension"):
        build_model(mesh, materials(1.0, 1.0), {"sliding": {"edge_extension": -1.0}})


@pytest.mark.parametrize("hold", [False, True])
def test_a_pairing_that_flips_back_across_a_crease_is_held_until_the_step_ends(hold):
    """A point whose closest muscle triangle goes A -> B -> A across a crease within one
    load step keeps B for the rest of the step (``hold_flipping``); flips between coplanar
    triangles (a continuous force) and points that move on are paired afresh; the next step
    pairs every point afresh."""
    from mechanics.effects import EFFECTS

    mesh = stack(((4, 4, 1), (4.0, 4.0, 1.0), (0, 0, 0)), ((3, 3, 1), (4.0, 4.0, 1.0), (0, 0, 1)))
    X = mesh.nodes.copy()
    lower_top = (np.arange(len(X)) < 50) & (np.abs(X[:, 2] - 1.0) < 1e-9)
    X[lower_top, 2] += 0.2 * np.maximum(X[lower_top, 0] - 2.0, 0.0)  # an 11 degree crease
    mesh = Mesh(X, mesh.tets, mesh.region, node_sets=mesh.node_sets, face_sets=mesh.face_sets)
    eff = EFFECTS["sliding"](mesh, friction=0.0, hold_flipping=hold)
    moved, far = X.copy(), X.copy()
    moved[mesh.node_sets["upper"], 0] += 1.5  # more than a muscle triangle, over the crease
    far[mesh.node_sets["upper"], 0] += 3.0

    def pairing(x):
        return eff._normal(X, x)[0][:, -3:]  # the muscle nodes each point is paired with

    eff.begin_step(X, X)
    at_rest = pairing(X)
    at_moved = pairing(moved)
    back = pairing(X)  # where it was: every point that changed triangle flips back
    changed = np.any(at_rest != at_moved, axis=1)
    held = np.any(back != at_rest, axis=1)
    if hold:
        assert 0 < held.sum() < changed.sum()  # some flips cross the crease, some do not
        assert np.array_equal(back[held], at_moved[held])
        assert np.array_equal(pairing(far)[held], at_moved[held])
    else:
        assert changed.any() and not held.any()
    eff.begin_step(X, X)
    assert np.array_equal(pairing(X), at_rest)


def _block_on_slab():
    """A 10 x 10 x 5 mm block on a 30 x 15 x 4 mm slab (split interface): the mesh, the
    block's base nodes, the slab's node under each (the two grids coincide on the
    interface) and the base nodes' tributary areas (mm^2)."""
    from mechanics.effects._contact import nodal_areas

    mesh = stack(((6, 3, 1), (30.0, 15.0, 4.0), (-15.0, 0.0, 0.0)),
                 ((2, 2, 1), (10.0, 10.0, 5.0), (0.0, 0.0, 4.0)))
    upper, faces = mesh.node_sets["upper"], mesh.face_sets["interface"]
    base = np.unique(faces)
    w = nodal_areas(mesh.nodes, faces, base)
    under = np.argmin(np.linalg.norm(mesh.nodes[base][:, None] - mesh.nodes[None], axis=2)
                      + 1e9 * np.isin(np.arange(mesh.n_nodes), upper)[None], axis=1)
    assert np.allclose(mesh.nodes[under], mesh.nodes[base]) and w.sum() == pytest.approx(100.0)
    return mesh, base, under, w


@pytest.mark.parametrize("shear", [0.1, 1.0])
def test_compliant_interface_shears_by_the_traction_over_its_stiffness(shear):
    """A stiff block on a stiff slab, gravity tilted by 30 deg, held by the compliant
    interface alone: the block's base slides over the slab by the downhill traction over
    ``shear`` and sinks into it by the normal traction over ``penalty`` (area-weighted mean
    gaps, exact by equilibrium when the springs split normal and shear right); tied, it
    slides by the traction over the penalty only."""
    mesh, base, under, w = _block_on_slab()
    a, density, penalty = np.radians(30.0), 1e4, 1e3
    gravity = {"direction": (np.sin(a), 0.0, -np.cos(a)), "density": density}
    W = density * 9.81e-6 * 500.0  # mN over the block's 100 mm^2
    for name, table in (("compliant_interface", {"shear": shear, "penalty": penalty}),
                        ("tied", {"penalty": penalty})):
        model = build_model(mesh, materials(1e3, 1e3), {
            "fixed": {"node_set": "bottom"}, "gravity": gravity, name: table})
        st = solve(model, options=OPTS)
        gap = w @ (st.u[base] - st.u[under]) / w.sum()
        slide = W * np.sin(a) / 100.0 / (shear if name != "tied" else penalty)
        assert gap[0] == pytest.approx(slide, rel=1e-6) and abs(gap[1]) < 1e-9 * slide
        assert -gap[2] == pytest.approx(W * np.cos(a) / 100.0 / penalty, rel=1e-6)


def test_compliant_interface_stress_free_inverse_slides_the_reference_back():
    """The measured configuration (the mesh) is loaded: the stress-free inverse of the block
    sliding on a compliant interface converges, and its reference has the block's base moved
    uphill from the slab by the slide (the layer unsheared there, sheared in the mesh)."""
    from mechanics.stress_free import inverse_fixed_point

    mesh, base, under, w = _block_on_slab()
    a, density, shear = np.radians(30.0), 1e4, 0.1
    model = build_model(mesh, materials(1e3, 1e3), {
        "fixed": {"node_set": "bottom"},
        "gravity": {"direction": (np.sin(a), 0.0, -np.cos(a)), "density": density},
        "compliant_interface": {"shear": shear}})
    res = inverse_fixed_point(model, mesh.nodes, tol=1e-5, options=OPTS)
    assert res.converged and len(res.history) <= 10
    slide = density * 9.81e-6 * 500.0 * np.sin(a) / 100.0 / shear  # 2.45 mm
    gap = w @ (res.X[base] - res.X[under]) / w.sum()
    assert gap[0] == pytest.approx(-slide, rel=1e-3) and abs(gap[1]) < 1e-6


def test_compliant_interface_is_not_written_to_febio_as_tied():
    from mechanics.febio import FebioUnsupported, feb_text

    mesh = stack(((2, 2, 1), (10.0, 10.0, 4.0), (0.0, 0.0, 0.0)),
                 ((2, 2, 1), (10.0, 10.0, 5.0), (0.0, 0.0, 4.0)))
    model = build_model(mesh, materials(1e3, 1e3), {"fixed": {"node_set": "bottom"},
                                                    "compliant_interface": {"shear": 0.1}})
    with pytest.raises(FebioUnsupported, match="'compliant_interface'.*one penalty"):
        feb_text(model, approximate=True)
