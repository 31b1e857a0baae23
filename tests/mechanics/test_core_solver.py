"""Solver behaviour: equilibrium of gravity, cut-backs, clear errors, soft tissue at 0.2 kPa."""

import re

import numpy as np
import pytest
from zoo import box, cube6, hemisphere

from mechanics.mesh import Mesh
from mechanics.model import build_model
from mechanics.solver import SolverError, SolverOptions, residual_and_tangent, solve

OPT = SolverOptions(linear_solver="scipy")
NH = {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.49}}


def test_support_reactions_balance_the_weight():
    mesh = hemisphere(60.0, 6)
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 0, -1)},
                                   "fixed": {"node_set": "fixed"}})
    st = solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10))
    assert st.converged and st.load == 1.0
    R, _ = residual_and_tangent(model, mesh.nodes, st.x, 1.0)
    R = R.reshape(-1, 3)
    weight = 1000 * 9.81 * 1e-6 * mesh.signed_volumes().sum()  # mN
    reaction = R[mesh.node_sets["fixed"]].sum(axis=0)  # force of the supports on the body
    np.testing.assert_allclose(reaction, [0, 0, weight], rtol=0, atol=1e-8 * weight)
    # Sags downwards, the flat face stays put, and volume is nearly preserved (nu = 0.49).
    assert st.u[:, 2].min() < -1.0
    assert np.abs(st.u[mesh.node_sets["fixed"]]).max() == 0.0
    vol = Mesh(st.x, mesh.tets, mesh.region).signed_volumes().sum()
    assert abs(vol / mesh.signed_volumes().sum() - 1) < 0.02
    assert st.log[0]["newton"] >= 2 and all(e["residuals"] for e in st.log)


def test_very_soft_tissue_converges_with_cutbacks():
    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": 0.2, "nu": 0.49}},
                        {"gravity": {"direction": (0, 0, -1)}, "fixed": {"node_set": "fixed"}})
    st = solve(model, options=OPT)
    assert st.converged
    assert st.max_displacement() > 30.0  # large sag of a 60 mm hemisphere at 0.2 kPa
    assert np.all(st.J > 0)


def test_a_deadline_stops_the_solve_at_its_next_newton_iteration():
    import time
    from dataclasses import replace

    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": 0.2, "nu": 0.49}},
                        {"gravity": {"direction": (0, 0, -1)}, "fixed": {"node_set": "fixed"}})
    late = replace(OPT, deadline=time.perf_counter() - 1.0)
    with pytest.raises(SolverError, match=r"time budget ran out at load .* \(Newton iteration "
                                          r"0 of the step\)"):
        solve(model, options=late)
    assert solve(model, options=replace(OPT, deadline=time.perf_counter() + 3600)).converged


def test_divergence_keeps_last_converged_state():
    """Squashing a unit cube by 1.5 mm must invert elements somewhere before full load; the
    failure keeps the last converged state and says where its tets have collapsed."""
    mesh = box((2, 2, 2))
    model = build_model(mesh, NH, {
        "fixed:base": {"node_set": "xmin"},
        "fixed:push": {"node_set": "xmax", "values": [-1.5, 0.0, 0.0]},
    })
    with pytest.raises(SolverError, match="last converged load") as info:
        solve(model, options=SolverOptions(linear_solver="scipy", max_cutbacks=6))
    st = info.value.state
    assert st is not None and not st.converged
    assert 0.0 < st.load < 1.0 / 1.5
    np.testing.assert_allclose(st.u[mesh.node_sets["xmax"], 0], -1.5 * st.load)
    assert np.all(st.J > 0)
    crushed = np.flatnonzero(st.J < 0.2)
    assert len(crushed)
    k = crushed[np.argmin(st.J[crushed])]
    at = ", ".join(f"{c:.1f}" for c in mesh.nodes[mesh.tets[k]].mean(axis=0))
    assert (f"{len(crushed)} of {mesh.n_tets} tets have lost more than 80% of their volume (J "
            f"down to {st.J[k]:.2f}, the lowest at ({at}) mm") in str(info.value)


@pytest.mark.parametrize("supports", [{}, {"fixed": {"nodes": [0]}},
                                      {"fixed": {"nodes": [0, 1], "components": [0, 1, 2]}}])
def test_unconstrained_model_is_reported(supports):
    mesh = cube6()
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 0, -1)}, **supports})
    with pytest.raises(SolverError, match="rigid-body"):
        solve(model, options=OPT)


def test_inverted_reference_mesh_is_reported():
    mesh = cube6()
    tets = mesh.tets.copy()
    tets[2, [0, 1]] = tets[2, [1, 0]]
    bad = Mesh(mesh.nodes, tets, mesh.region, node_sets=mesh.node_sets)
    model = build_model(bad, NH, {"fixed": {"node_set": "zmin"}})
    with pytest.raises(ValueError, match="inverted or degenerate mesh: 1 of 6"):
        solve(model, options=OPT)


def test_bad_inputs_have_clear_messages():
    mesh = cube6()
    with pytest.raises(ValueError, match="outside"):
        build_model(mesh, {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.5}}, {})
    with pytest.raises(ValueError, match="unknown material"):
        build_model(mesh, {1: {"name": "mooney", "E": 1.0}}, {})
    with pytest.raises(ValueError, match="regions \\[1\\]"):
        build_model(mesh, {2: {"name": "linear"}}, {})
    with pytest.raises(ValueError, match="no node set 'wall'"):
        build_model(mesh, NH, {"fixed": {"node_set": "wall"}})


def test_initial_guess_and_options_agree_with_default():
    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 1, 0)},
                                   "fixed": {"node_set": "fixed"}})
    ref = solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10))
    warm = solve(model, u0=ref.u * 1.05, options=SolverOptions(linear_solver="scipy",
                                                               tol=1e-10))
    stepped = solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10,
                                                 initial_steps=4, grow_below=0))
    # a guess is a nearby solution at full load: the first step takes the whole load from it,
    # whatever the increments asked for without one
    conv = {"linear_solver": "scipy", "tol": 1e-10, "initial_steps": 4, "grow_below": 0,
            "predictor": "converged"}
    cold_stepped = solve(model, options=SolverOptions(**conv))
    warm_stepped = solve(model, u0=ref.u * 1.05, options=SolverOptions(**conv))
    assert warm.newton_iterations < ref.newton_iterations
    assert stepped.load_steps == 4 and warm_stepped.load_steps == 1
    assert warm_stepped.newton_iterations < cold_stepped.newton_iterations
    for other in (warm, stepped, cold_stepped, warm_stepped):
        np.testing.assert_allclose(other.u, ref.u, atol=1e-7 * np.abs(ref.u).max())


def test_a_guess_from_a_ten_times_stiffer_model_takes_the_whole_load_in_one_step():
    """The 0.1 kPa hemisphere (145 mm sag; 28 Newton iterations in 3 steps from rest at
    initial_steps = 4) from the 1 kPa solution: one step of 11 iterations, the same state."""
    mesh = hemisphere(60.0, 4)

    def model(e):
        return build_model(mesh, {1: {"name": "neo_hookean", "E": e, "nu": 0.49}},
                           {"gravity": {"direction": (0, 0, -1)}, "fixed": {"node_set": "fixed"}})

    opt = SolverOptions(linear_solver="scipy", tol=1e-10, initial_steps=4)
    cold = solve(model(0.1), options=opt)
    warm = solve(model(0.1), u0=solve(model(1.0), options=opt).u, options=opt)
    assert cold.load_steps > 1 and warm.load_steps == 1 and warm.converged
    assert warm.newton_iterations < cold.newton_iterations
    np.testing.assert_allclose(warm.u, cold.u, atol=1e-8 * np.abs(cold.u).max())


def test_newton_matrices_without_tensile_pressure_stiffness_reach_the_same_equilibrium():
    """Away from equilibrium the Newton matrix may leave out the geometric stiffness of
    tensile pressure (SolverOptions.tensile_pressure_stiffness_below): the solid's forces are
    unchanged and its stiffness differs only in elements with p > 0; a 0.3 kPa hemisphere
    (5184 tets, 60 mm sag) reaches the exact tangent's equilibrium in 8 Newton iterations
    against 36."""
    from mechanics.solid import Solid

    mesh = hemisphere(60.0, 12)
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": 0.3, "nu": 0.49}},
                        {"gravity": {"direction": (0, 0, -1)}, "fixed": {"node_set": "fixed"}})
    modified = solve(model, options=SolverOptions(tol=1e-10))
    exact = solve(model, options=SolverOptions(tol=1e-10, tensile_pressure_stiffness_below=0))
    assert modified.newton_iterations < exact.newton_iterations
    np.testing.assert_allclose(modified.u, exact.u, atol=1e-9 * np.abs(exact.u).max())

    solid = Solid(mesh.tets, mesh.region, model.materials, mesh.nodes, formulation="anp")
    x = mesh.nodes + 0.5 * exact.u  # half way: pressures of both signs
    full = solid.evaluate(x)
    part = solid.evaluate(x, tensile_pressure_stiffness=False)
    np.testing.assert_array_equal(part.force, full.force)
    changed = np.any(part.Kup != full.Kup, axis=1)
    assert changed.any() and not changed[full.p_elem <= 0.0].any()


def test_a_step_whose_first_direction_inverts_an_element_is_cut_to_what_it_allows():
    """A 60 mm hemisphere at 0.1 kPa sags 145 mm: the full load's first Newton direction
    inverts an element unless halved, so with ``first_inversion_shrink`` the step is cut back
    at once to a quarter of the load (not after Newton fails), and with predictor
    "converged" each later step starts from the converged state. Measured: 21 Newton
    iterations in 4 steps, against 73 in 9 (4 failed after 8-18 iterations) with the
    secant predictor, halving only after a failure."""
    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": 0.1, "nu": 0.49}},
                        {"gravity": {"direction": (0, 0, -1)}, "fixed": {"node_set": "fixed"}})
    st = solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10,
                                            predictor="converged", first_inversion_shrink=0.5))
    first = st.log[0]
    assert not first["converged"] and first["newton"] == 1
    assert re.fullmatch(r"the first Newton direction inverts an element unless scaled by 0\.5",
                        first["cutback"])
    assert st.log[1]["load"] == 0.25 and st.log[1]["converged"]
    assert st.converged and st.max_displacement() > 100.0 and np.all(st.J > 0)
    before = solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10,
                                                predictor="secant"))
    assert before.converged
    assert st.newton_iterations < 0.6 * before.newton_iterations
    np.testing.assert_allclose(st.u, before.u, atol=1e-6 * np.abs(st.u).max())
    with pytest.raises(ValueError,
                       match="predictor must be 'auto', 'converged' or 'secant', got 'x'"):
        solve(model, options=SolverOptions(predictor="x"))


def test_the_auto_predictor_starts_each_step_from_the_smaller_residual():
    """The 0.1 kPa hemisphere (145 mm sag) from rest at full load: the step fails, the step
    to 0.5 converges; from there the extrapolation of (0, 0.5) to full load leaves a residual
    137x that of the converged state, so "auto" starts from the converged state and
    converges in one more step (measured: 35 Newton iterations in 3 load steps, one cut
    back, against 73 in 9, four cut back, from the extrapolation alone), at the same
    equilibrium."""
    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": 0.1, "nu": 0.49}},
                        {"gravity": {"direction": (0, 0, -1)}, "fixed": {"node_set": "fixed"}})
    auto, secant = (solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10,
                                                       predictor=p))
                    for p in ("auto", "secant"))
    assert auto.converged and secant.converged
    # before a step has converged the two starts are one (the state at rest)
    assert [e["load"] for e in auto.log[:2]] == [1.0, 0.5]
    for entry in auto.log[:2]:
        assert entry["predictor"] == "converged" and "predictor_residuals" not in entry
    later = auto.log[2:]
    assert later
    for entry in later:  # two converged states: both starts measured, the smaller taken
        norms = entry["predictor_residuals"]
        assert set(norms) == {"secant", "converged"}
        assert entry["predictor"] == min(norms, key=norms.get) == "converged"
        assert norms["converged"] < 0.1 * norms["secant"]
    assert auto.newton_iterations < 0.6 * secant.newton_iterations
    np.testing.assert_allclose(auto.u, secant.u, atol=1e-6 * np.abs(secant.u).max())


def test_the_auto_predictor_follows_a_path_that_ends_without_equilibrium_once_more(
        monkeypatch):
    """Where the smaller-residual path ends in an error that carries a state (a fold where
    the other friction branch goes on, seen on the 17k-tet suite mesh's softest corner in
    supine), the whole solve runs once more from the extrapolation; the abandoned path is in
    ``stats["abandoned_path"]`` and the wall time counts both. The first path's failure is
    made here: its state at load 0.5, raised as a solver error."""
    from dataclasses import replace

    import mechanics.newton.stepping as stepping
    from mechanics.newton.options import SolverError

    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 0, -1)},
                                   "fixed": {"node_set": "fixed"}})
    real, calls = stepping._solve_path, []

    def first_path_folds(model, X, u0, options, *, again=True):
        calls.append(options.predictor)
        st = real(model, X, u0, options)
        if options.predictor == "auto" or not again:
            raise SolverError("mechanics: no equilibrium beyond load 0.5 (made)",
                              replace(st, converged=False, load=0.5))
        return st

    monkeypatch.setattr(stepping, "_solve_path", first_path_folds)
    opts = SolverOptions(linear_solver="scipy", tol=1e-10, predictor="auto")
    st = solve(model, options=opts)
    assert calls == ["auto", "secant"] and st.converged
    first = st.stats["abandoned_path"]
    assert first["predictor"] == "auto" and first["load"] == 0.5
    assert first["reason"] == "mechanics: no equilibrium beyond load 0.5 (made)"
    assert first["newton"] > 0 and 0.0 < first["wall_s"] < st.wall_time
    assert st.stats["wall_s"] == st.wall_time
    secant = solve(model, options=replace(opts, predictor="secant"))
    np.testing.assert_allclose(st.u, secant.u, atol=1e-9 * np.abs(secant.u).max())
    # the second path fails too: its error carries the abandoned path
    calls.clear()
    monkeypatch.setattr(stepping, "_solve_path",
                        lambda *a: first_path_folds(*a, again=False))
    with pytest.raises(SolverError) as exc:
        solve(model, options=opts)
    assert calls == ["auto", "secant"]
    assert exc.value.state.stats["abandoned_path"]["load"] == 0.5
    # an error without a state (an unconstrained model, a time budget) is not retried
    calls.clear()

    def no_state(model, X, u0, options):
        calls.append(options.predictor)
        raise SolverError("mechanics: the caller's time budget is spent")

    monkeypatch.setattr(stepping, "_solve_path", no_state)
    with pytest.raises(SolverError, match="time budget"):
        solve(model, options=opts)
    assert calls == ["auto"]


def test_pardiso_and_scipy_agree():
    pytest.importorskip("pypardiso")
    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 0, -1)},
                                   "fixed": {"node_set": "fixed"}})
    a = solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10))
    b = solve(model, options=SolverOptions(linear_solver="pardiso", tol=1e-10))
    np.testing.assert_allclose(b.u, a.u, atol=1e-8 * np.abs(a.u).max())


def test_progress_that_the_stagnation_check_leaves_alone():
    """Residual histories measured on the 20k-tet phantom (rounded): a transient that ends
    with a halving of the best residual, and a steady damped descent, are progress; an
    oscillation and a crawl are not."""
    from mechanics.solver import _progressing

    assert _progressing([1.0, 1.39, 0.94, 0.93, 0.74, 0.78, 1.5, 0.97, 0.13])  # tilted
    assert _progressing([1.0, 2.33, 2.24, 2.09, 2.04, 1.88, 1.36, 1.03, 0.91])  # supine
    assert not _progressing([1.0, 0.98, 4.42, 3.94, 4.12, 3.97, 3.55, 6.45, 6.38])
    assert not _progressing([1.0, 0.5, 0.49, 0.48, 0.47, 0.46])  # < 25 % in three


def test_a_slow_step_from_rest_near_equilibrium_gets_twice_the_iterations():
    """The first ten residuals of a step from rest measured on the suite's small-000
    (breast 0.1, skin 20, fascia 80 kPa, prone; rounded): at 9 iterations it is at 1.4e-2,
    between ``stagnate_above`` and 0.1, so it is not stagnating before 16 (it converged at
    19; here it goes on crawling at 1.2-1.5e-2, made up, and is cut back at 16); the same
    crawl in a later step, or far from equilibrium (0.3-0.5: the 17k mesh's softest corner's
    step to full load), is stagnating at 8, and below ``stagnate_above`` the rule is
    unchanged."""
    from mechanics.newton.iteration import _stagnating

    opt = SolverOptions()
    near = [1.0, 0.91, 0.81, 0.85, 0.30, 0.27, 0.039, 0.018, 0.026, 0.014]
    near += [0.015, 0.013, 0.014, 0.012, 0.013, 0.012, 0.012]
    far = [1.0, 0.996, 0.557, 0.477, 0.405, 0.392, 0.422, 0.389, 0.327]
    assert not _stagnating(opt, near[:10], 9, near[9], None, True)
    assert not _stagnating(opt, near[:16], 15, near[15], None, True)
    assert _stagnating(opt, near, 16, near[16], None, True)
    assert _stagnating(opt, near[:10], 9, near[9], None, False)
    assert _stagnating(opt, far, 8, far[8], None, True)
    floor = [1.0, 0.1, 1e-2, 1e-3] + [1e-5] * 6
    assert _stagnating(opt, floor, 9, floor[9], None, True)
    assert not _stagnating(SolverOptions(stagnate_after=0), near, 16, near[16], None, True)


def test_stagnation_cutback_is_configurable():
    """A step that stops making progress is cut back early as stagnating, after
    ``stagnate_after`` iterations (and 4 more with exact linear solves); the check switched
    off leaves only ``max_newton``, and gives the default's solution where the step
    converges. A tolerance below the rounding
    floor makes the residual stall there."""
    mesh = hemisphere(60.0, 4)
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 0, -1)},
                                   "fixed": {"node_set": "fixed"}})
    ref = solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10))
    assert max(e["newton"] for e in ref.log) >= 2
    # accept_residual=0: no step is accepted by FEBio's norms (tests/mechanics/
    # test_solver_converge.py: with them, this rounding floor is a converged state)
    unreachable = {"linear_solver": "scipy", "tol": 1e-30, "max_cutbacks": 0, "max_newton": 20,
                   "accept_residual": 0.0}
    with pytest.raises(SolverError, match="stagnating") as info:
        solve(model, options=SolverOptions(stagnate_after=4, **unreachable))
    after = int(re.search(r"stagnating \(relative residual \S+ after (\d+)\)",
                          str(info.value)).group(1))
    assert 4 <= after < 20
    # before the cut-back, the step retried with exact linear solves (fresh factorisations)
    assert "exact_linear_from" in info.value.state.log[-1]
    with pytest.raises(SolverError, match="no convergence in 20 iterations"):
        solve(model, options=SolverOptions(stagnate_after=0, **unreachable))
    off = solve(model, options=SolverOptions(linear_solver="scipy", tol=1e-10,
                                             stagnate_after=0))
    np.testing.assert_allclose(off.u, ref.u, atol=1e-8 * np.abs(ref.u).max())


def test_a_tet_hanging_by_an_edge_is_named_when_the_first_step_fails():
    """A tet that meets the mesh only at an edge rotates freely about it: the tangent is
    singular and no load step converges. The failure names the tet (the meshing stage drops
    such tets; a mesh from elsewhere may have them)."""
    from mechanics.mesh import Mesh, hinged_tets, orient_tets

    mesh = box(shape=(6, 6, 2), size=(30.0, 30.0, 10.0))
    top = np.flatnonzero(mesh.nodes[:, 2] == 10.0)
    a = int(top[np.lexsort(mesh.nodes[top].T)][0])  # a corner edge of the top face
    b = int(np.flatnonzero(np.all(mesh.nodes == mesh.nodes[a] + [5.0, 0.0, 0.0], axis=1))[0])
    nodes = np.vstack([mesh.nodes, [[2.5, -4.0, 14.0], [2.5, 3.0, 16.0]]])
    n = len(mesh.nodes)
    tets = orient_tets(nodes, np.vstack([mesh.tets, [a, b, n, n + 1]]))
    hinged = Mesh(nodes, tets, np.ones(len(tets), np.int32), node_sets=dict(mesh.node_sets))
    assert hinged_tets(hinged.tets).tolist() == [len(tets) - 1]
    assert len(hinged_tets(mesh.tets)) == 0
    model = build_model(hinged, NH, {"gravity": {"direction": (0.0, 1.0, 0.0)},
                                     "fixed": {"node_set": "zmin"}})
    with pytest.raises(SolverError, match=rf"1 tet\(s\) that meet the rest only at an edge "
                                          rf"or a vertex \(tets {len(tets) - 1}\)"):
        solve(model, options=SolverOptions(linear_solver="scipy", max_cutbacks=3))


@pytest.mark.parametrize("threads", [1, 3])
def test_thread_setting_reaches_every_pardiso_call(monkeypatch, threads):
    """``SolverOptions.threads`` (and, unset, BREASTMODEL_THREADS) is the MKL thread count in
    force during every PARDISO phase (asked of MKL itself inside the call); OpenBLAS runs on
    one thread inside the solve and gets its own count back afterwards; the solve reports
    the count and its phases' costs."""
    pytest.importorskip("pypardiso")
    threadpoolctl = pytest.importorskip("threadpoolctl")
    import mechanics.linear_solvers as L
    import mechanics.solver as S

    seen, blas = [], []
    call = L._Handle.call

    def spy(self, phase, b=None):
        seen.append((phase, int(self.lib.MKL_Get_Max_Threads())))
        return call(self, phase, b)

    def spy_eval(self, *a, **k):
        blas.extend(p["num_threads"] for p in threadpoolctl.threadpool_info()
                    if p["internal_api"] == "openblas")
        return evaluate(self, *a, **k)

    evaluate = S._Newton.evaluate
    monkeypatch.setattr(L._Handle, "call", spy)
    monkeypatch.setattr(S._Newton, "evaluate", spy_eval)
    mesh = hemisphere(60.0, 6)
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 0, -1)},
                                   "fixed": {"node_set": "fixed"}})
    before = [p["num_threads"] for p in threadpoolctl.threadpool_info()
              if p["internal_api"] == "openblas"]
    monkeypatch.setenv("BREASTMODEL_THREADS", "2")
    st = solve(model, options=SolverOptions(linear_solver="pardiso", threads=threads))
    assert st.converged and st.stats["threads"] == threads
    phases = {p for p, _ in seen}
    assert {11, 22, 33} <= phases and {n for p, n in seen if p > 0} == {threads}
    assert blas and set(blas) == {1}
    assert [p["num_threads"] for p in threadpoolctl.threadpool_info()
            if p["internal_api"] == "openblas"] == before
    seen.clear()
    st = solve(model, options=SolverOptions(linear_solver="pardiso"))  # from the environment
    assert st.stats["threads"] == 2 and {n for p, n in seen if p > 0} == {2}
    for k in ("material", "effects", "assembly", "factor", "solve"):
        assert st.stats[f"cpu_{k}"] >= 0.0 and all(f"t_{k}" in e for e in st.log)
    assert st.stats["factorizations"] >= 1 and st.stats["peak_rss_mb"] > 0
    # PARDISO's own account of its memory, a part of the process's peak
    assert 0 < st.stats["linear_solver_mb"] < st.stats["peak_rss_mb"]
    assert set(st.stats["cpu_by_effect"]) == {"gravity", "fixed"}
