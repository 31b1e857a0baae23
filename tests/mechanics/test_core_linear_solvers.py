"""The reduced saddle-point system and the sparse direct solvers that factorise it."""

import numpy as np
import pytest
import scipy.sparse as sp
from zoo import hemisphere

from mechanics.linear_solvers import PardisoSolver, ScipySolver
from mechanics.model import build_model
from mechanics.solver import _constraints, _solid
from mechanics.system import ReducedSystem, full_from_upper

NH = {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.49}}


def _saddle(n: int = 6, seed: int = 0):
    """Upper-triangle tangent of the hemisphere at a random small deformation, the solid's
    evaluation, its free dofs and the reduced system."""
    mesh = hemisphere(60.0, n)
    model = build_model(mesh, NH, {"gravity": {"direction": (0, 0, -1)},
                                   "fixed": {"node_set": "fixed"}})
    solid = _solid(model, mesh.nodes)
    fixed, _ = _constraints(model, solid.n_nodes, solid.used_nodes)
    rng = np.random.default_rng(seed)
    ev = solid.evaluate(mesh.nodes + 0.05 * rng.standard_normal(mesh.nodes.shape))
    sysm = ReducedSystem(mesh.tets, solid.n_nodes, ~fixed, solid.used_nodes)
    U = sysm.assemble(ev.Kup, ev.dv, -solid.V_node / solid.bulk_node)
    return U, solid, ev, ~fixed, sysm


def test_schur_complement_of_the_saddle_point_is_the_condensed_tangent():
    """Eliminating the nodal pressures of the assembled saddle-point matrix gives the
    solid's condensed tangent (an independent COO assembly) on the free dofs (1e-10)."""
    U, solid, ev, free, sysm = _saddle()
    A = full_from_upper(U)
    nf = sysm.n_free
    Auu, Aup, d = A[:nf, :nf], A[:nf, nf:], A[nf:, nf:].diagonal()
    S = (Auu - Aup @ sp.diags(1.0 / d) @ Aup.T).toarray()
    K = solid.condensed_tangent(ev)[free][:, free].toarray()
    assert np.abs(S - K).max() <= 1e-10 * np.abs(K).max()
    assert np.allclose(S, S.T, rtol=0, atol=1e-12 * np.abs(K).max())


def test_pardiso_single_precision_is_refined_to_double_accuracy():
    """The single-precision factor alone leaves a relative residual far above 1e-9;
    refinement in double brings it below 1e-13, and the solution matches SuperLU (1e-11)."""
    pytest.importorskip("pypardiso")
    U, *_ = _saddle()
    A = full_from_upper(U)
    b = np.random.default_rng(1).standard_normal(A.shape[0])
    lin = PardisoSolver()
    lin.factorize(U, symmetric=True)
    x0 = lin.precondition(b)
    x = lin.solve(b)
    res0 = np.linalg.norm(A @ x0 - b) / np.linalg.norm(b)
    res = np.linalg.norm(A @ x - b) / np.linalg.norm(b)
    assert res0 > 1e-9  # a single-precision solve
    assert res <= 1e-13 and lin.last_refinements >= 1 and lin.fallbacks == 0
    ref = ScipySolver()
    ref.factorize(U, symmetric=True)
    xr = ref.solve(b)
    assert np.abs(x - xr).max() <= 1e-11 * np.abs(xr).max()
    # once the matrix is let go of (the Newton loop's reusing solves), the factor still
    # preconditions, bit for bit, and a refined solve asks for a new factorisation
    lin.forget_matrix()
    assert np.array_equal(lin.precondition(b), x0) and lin.factor_worth > 0.0
    with pytest.raises(RuntimeError, match="factorise again"):
        lin.solve(b)


def test_pardiso_falls_back_to_double_precision_when_refinement_stalls():
    """A dense symmetric indefinite matrix with a condition number of 3e8, beyond what a
    single-precision factor resolves (eps 6e-8; 1e7 still refines, slowly): the solver
    refactorises in double precision and returns a backward-stable solution (normwise
    backward error 1e-14; measured 3e-17)."""
    pytest.importorskip("pypardiso")
    rng = np.random.default_rng(2)
    n = 60
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    d = np.logspace(-8.5, 0, n) * np.where(np.arange(n) % 2, 1.0, -1.0)
    A = (Q * d) @ Q.T
    A = 0.5 * (A + A.T)
    U = sp.triu(sp.csr_matrix(A), format="csr")
    b = rng.standard_normal(n)
    lin = PardisoSolver()
    lin.factorize(U, symmetric=True)
    x = lin.solve(b)
    backward = np.linalg.norm(A @ x - b) / (np.linalg.norm(A, 2) * np.linalg.norm(x)
                                            + np.linalg.norm(b))
    assert backward <= 1e-14
    assert lin.fallbacks == 1 and lin.precision == "double"


def test_pardiso_analyses_again_for_another_thread_count(tmp_path):
    """A factorisation that reuses an analysis must run on the analysis's thread count (MKL
    crashes otherwise: phase 22 on 1 thread after an analysis on 2, a segmentation fault).
    Solvers of different counts share one handle per pattern, so a new count analyses
    again. Run in a child process, which a crash would kill."""
    import subprocess
    import sys
    from pathlib import Path

    pytest.importorskip("pypardiso")
    root = Path(__file__).resolve().parents[2]
    script = tmp_path / "alternate.py"
    script.write_text(f"""
import sys
sys.path[:0] = [{str(root)!r}, {str(root / "tests")!r}, {str(Path(__file__).parent)!r}]
import numpy as np
import mechanics.linear_solvers as L
from test_core_linear_solvers import _saddle

U = _saddle(10)[0]
b = np.ones(U.shape[0])
for i in range(6):
    for n in (2, 1):
        s = L.PardisoSolver(threads=n)
        Ui = U * (1.0 + 0.01 * i)
        s.factorize(Ui)
        s.factorize(Ui)  # the same pattern and count: no new analysis
        x = s.solve(b)
        assert s._h.threads == n and s.analyses == 1, (s._h.threads, s.analyses)
        r = L.full_from_upper(Ui) @ x - b
        assert np.linalg.norm(r) <= 1e-8 * np.linalg.norm(b)
print("ok")
""")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
    assert done.stdout.strip().endswith("ok")


def test_pardiso_reports_each_analysed_matrix_s_own_factor():
    """The factor's nonzeros and operation count (which price a factorisation against GMRES
    iterations, ``factor_worth``) are those of the matrix last analysed, not of the first
    one the handle saw: a small, a large and the small system again, each against a
    handle of its own."""
    pytest.importorskip("pypardiso")
    import mechanics.pardiso as P

    small, large = _saddle(4)[0], _saddle(8)[0]
    seen = []
    for U in (small, large, small):
        lin = PardisoSolver(threads=1)
        lin.factorize(U)
        seen.append((lin._h.factor_nonzeros, lin._h.factor_flops, lin.factor_worth))
    P._POOL.handles = {}  # fresh handles: one analysis each
    alone = []
    for U in (small, large):
        lin = PardisoSolver(threads=1)
        lin.factorize(U)
        alone.append((lin._h.factor_nonzeros, lin._h.factor_flops, lin.factor_worth))
        P._POOL.handles = {}
    assert seen == [alone[0], alone[1], alone[0]]
    assert alone[1][0] > 2 * alone[0][0]


def test_pardiso_on_two_threads_gives_the_same_bits_every_time(monkeypatch):
    """Same matrix, same thread count, same solution to the last bit (MKL's conditional
    numerical reproducibility, iparm 34): without it, 30 factorisations of this Laplacian
    on 2 threads gave 2 distinct solutions, 2e-6 apart, and two runs of one subject
    differed by 2e-5 mm. Each repetition analyses anew, as a new run does."""
    pytest.importorskip("pypardiso")
    import mechanics.linear_solvers as L

    n = 36
    eye, d = sp.identity(n), sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    lap = (sp.kron(sp.kron(d, eye), eye) + sp.kron(sp.kron(eye, d), eye)
           + sp.kron(sp.kron(eye, eye), d)).tocsr()
    rng = np.random.default_rng(0)
    U = sp.triu(lap + sp.diags(0.1 * rng.random(lap.shape[0]))).tocsr()
    b = rng.random(lap.shape[0])
    solutions = set()
    for _ in range(12):
        monkeypatch.setattr(L._POOL, "handles", {}, raising=False)
        s = L.PardisoSolver(threads=2)
        s.factorize(U)
        solutions.add(s.precondition(b).tobytes())  # the factor's own bits, unrefined
        s._h.release()
    assert len(solutions) == 1


def test_thread_count_comes_from_the_setting_the_environment_or_the_cores(monkeypatch):
    """Explicit count first, then BREASTMODEL_THREADS, then the cores of the process; never
    the load average."""
    import os

    from mechanics.linear_solvers import THREADS_ENV, machine_cores, resolve_threads

    monkeypatch.delenv(THREADS_ENV, raising=False)
    assert resolve_threads(None) == machine_cores() == len(os.sched_getaffinity(0))
    monkeypatch.setattr(os, "getloadavg", lambda: (99.0, 99.0, 99.0))
    assert resolve_threads(None) == machine_cores()
    monkeypatch.setenv(THREADS_ENV, "3")
    assert resolve_threads(None) == 3
    assert resolve_threads(1) == 1
    for bad in ("0", "two", "-1"):
        monkeypatch.setenv(THREADS_ENV, bad)
        with pytest.raises(ValueError, match=THREADS_ENV):
            resolve_threads(None)
    with pytest.raises(ValueError, match="threads"):
        resolve_threads(0)


@pytest.mark.parametrize("formulation", ["anp", "standard"])
def test_streamed_assembly_equals_the_whole_mesh_one(monkeypatch, formulation):
    """A solid evaluated block by block, its element stiffness handed to the matrix as it
    is computed (the path of meshes above one block; here blocks of 50 tets, maps per block),
    gives the matrix, forces and energy of the whole-mesh evaluation and assembly, bit for
    bit up to summation order, with a closed-form law (Neo-Hookean) and a generic,
    geometrically linear one (linear) side by side."""
    import mechanics.system as system_mod

    mesh = hemisphere(60.0, 6)
    region = np.where(np.arange(mesh.n_tets) % 3 == 0, 2, 1)
    mats = {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.49},
            2: {"name": "linear", "E": 3.0, "nu": 0.45}}
    model = build_model(type(mesh)(mesh.nodes, mesh.tets, region, node_sets=mesh.node_sets),
                        mats, {"gravity": {"direction": (0, 0, -1)},
                               "fixed": {"node_set": "fixed"}}, formulation=formulation)
    solid = _solid(model, mesh.nodes)
    fixed, _ = _constraints(model, solid.n_nodes, solid.used_nodes)
    x = mesh.nodes + 0.05 * np.random.default_rng(1).standard_normal(mesh.nodes.shape)
    pp = -solid.V_node / solid.bulk_node if formulation == "anp" else None
    whole = ReducedSystem(mesh.tets, solid.n_nodes, ~fixed,
                          solid.used_nodes if formulation == "anp" else None)
    ev = solid.evaluate(x)
    A = whole.assemble(ev.Kup, ev.dv, pp)
    monkeypatch.setattr(system_mod, "BLOCK", 50)
    monkeypatch.setattr(system_mod, "STREAM", 50)
    blocks = ReducedSystem(mesh.tets, solid.n_nodes, ~fixed,
                           solid.used_nodes if formulation == "anp" else None)
    # above one block the maps are made per block from the node-pair tables: the same
    # positions as the whole mesh's stored maps, for a slice and for an index array
    assert blocks.map_uu is None and whole.map_uu.dtype == np.int64
    some = np.flatnonzero(region == 2)
    for cols in (slice(None), slice(50, 100), some):
        assert np.array_equal(blocks.stiffness_map(cols), whole.stiffness_map(cols))
        if formulation == "anp":
            assert np.array_equal(blocks.pressure_map(cols), whole.pressure_map(cols))
    streamed = _solid(model, mesh.nodes)
    assert len(solid.blocks) == 1 and len(streamed.blocks) == -(-mesh.n_tets // 50)
    asm = blocks.start()
    seen = []
    ev2 = streamed.evaluate(x, sink=lambda cols, KT: (seen.append(KT.shape[1]),
                                                      asm.add_stiffness(cols, KT)))
    B = asm.matrix(ev2.dv, pp)
    assert ev2.Kup is None and len(seen) > mesh.n_tets // 50
    # the blocks, then the linear law's elements (and, "standard", their volumetric term)
    n_lin = int((region == 2).sum())
    assert sum(seen) == mesh.n_tets + n_lin * (2 if formulation == "standard" else 1)
    assert np.array_equal(A.indptr, B.indptr) and np.array_equal(A.indices, B.indices)
    assert np.abs(A.data - B.data).max() <= 1e-12 * np.abs(A.data).max()
    # the nodal forces summed block by block: the same up to summation order
    assert np.abs(ev.force - ev2.force).max() <= 1e-12 * np.abs(ev.force).max()
    assert abs(ev.energy - ev2.energy) <= 1e-12 * abs(ev.energy)
    for a, b in ((ev.F, ev2.F), (ev.P_dev, ev2.P_dev), (ev.dv, ev2.dv)):
        assert np.array_equal(a, b)
    # "anp": the nodal volumes summed block by block
    assert np.abs(ev.p_elem - ev2.p_elem).max() <= 1e-12 * np.abs(ev.p_elem).max()
    # without a sink the blocks' stiffness is gathered into the whole mesh's
    assert np.abs(streamed.evaluate(x).Kup - ev.Kup).max() <= 1e-14 * np.abs(ev.Kup).max()


def test_a_solve_streamed_in_blocks_matches_the_whole_mesh_one(monkeypatch):
    """A Newton solve whose solid and assembly go block by block (the path of meshes above
    one block of 32768 tets; here blocks of 100 tets) reaches the solution of the whole-mesh
    path, with two closed-form laws side by side in every block (Neo-Hookean, and Gent with
    its q q stiffness term)."""
    import mechanics.system as system_mod
    from mechanics.solver import SolverOptions, solve

    mesh = hemisphere(60.0, 6)
    region = np.where(np.arange(mesh.n_tets) % 4 == 0, 2, 1)
    mats = {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.49},
            2: {"name": "gent", "E": 2.0, "nu": 0.49, "Jm": 5.0}}
    model = build_model(type(mesh)(mesh.nodes, mesh.tets, region, node_sets=mesh.node_sets),
                        mats, {"gravity": {"direction": (0, 0, -1)},
                               "fixed": {"node_set": "fixed"}})
    opt = SolverOptions(tol=1e-10, threads=1)
    whole = solve(model, options=opt)
    monkeypatch.setattr(system_mod, "BLOCK", 100)
    monkeypatch.setattr(system_mod, "STREAM", 70)
    assert len(_solid(model, mesh.nodes).blocks) == -(-mesh.n_tets // 70) > 1
    streamed = solve(model, options=opt)
    assert whole.converged and streamed.converged
    scale = np.abs(whole.u).max()
    assert scale > 1.0  # mm: the hemisphere hangs
    assert np.abs(streamed.u - whole.u).max() <= 1e-8 * scale
    assert np.abs(streamed.stress - whole.stress).max() <= 1e-8 * np.abs(whole.stress).max()
