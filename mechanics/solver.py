"""Newton-Raphson with line search and adaptive load stepping.

The residual is R(x) = f_int(x) (the solid) + sum of every effect's contribution, in mN per
dof (3 * node + component). Dirichlet values of the effects' constraints are scaled by the
load factor and imposed exactly; the Newton correction solves the reduced saddle-point system
of :mod:`mechanics.system`. Convergence: ||R_free|| <= tol * max(||R_fixed||, ||R_free,0||),
i.e. the out-of-balance force relative to the support reactions (or, without supports, to the
step's initial out-of-balance force). Every iteration also records FEBio's displacement and
energy norms; a step that stalls close to convergence is first retried with exact linear solves
and then accepted when those norms hold (``SolverOptions.dtol``, ``etol``, ``accept_residual``),
which the step's log and ``State.stats["convergence"]`` say.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from mechanics.linear_solvers import SingularSystem, make_linear_solver, single_thread_blas
from mechanics.model import Model
from mechanics.solid import InvalidConfiguration, Solid
from mechanics.state import State
from mechanics.system import ReducedSystem

log = logging.getLogger("mechanics.solver")


@dataclass(frozen=True)
class SolverOptions:
    """Options of :func:`solve`.

    tol : relative residual norm at convergence
    max_newton : Newton iterations per load step before the step is cut back
    initial_steps : the first load increment is 1 / initial_steps
    min_step : smallest load increment before giving up
    max_cutbacks : total cut-backs allowed in one solve
    grow_below : grow the increment (x2) after a step that took at most this many iterations
    linear_solver : "auto" (PARDISO if installed, else scipy), "scipy" or "pardiso"
    line_search : Crisfield-type line search on R . du
    reuse_factor : solve with GMRES preconditioned by the last factorisation (that of an
        earlier iteration or load step; an inexact Newton step whose linear tolerance
        follows the nonlinear residual, so convergence stays quadratic), and refactorise
        only if GMRES does not converge; the GMRES iteration budget is what a new
        factorisation would cost in triangular solves, so reuse never costs much more than
        it saves (``bench/vs_febio.py``: at 150k tets one factorisation per solve)
    reuse_below : reuse only once the relative residual is below this; None (default):
        always for a symmetric tangent, below 0.05 for an unsymmetric one (frictional
        sliding, whose tangent changes with the stick/slip state: reused at every residual,
        the 20k-tet phantom's supine solve took 17-27 iterations with 4-7 factorisations,
        once cut back, against 18 iterations and 12 factorisations below 0.05)
    reuse_max_iterations : most GMRES iterations of one reusing solve (each stores a vector
        of the system's size), below the budget above
    stagnate_after, stagnate_above : cut a step back early once it has taken
        ``stagnate_after`` iterations and the relative residual is still above
        ``stagnate_above`` (or, below it, the best residual has not halved in 5 iterations)
        and fell less than 10x over the last 3 iterations, and shows no other progress
        (see ``_progressing``; measured: friction solves leaving their first iterations'
        stick/slip transients were cut back while falling 50x in 3 iterations);
        ``stagnate_after = 0`` turns the check off and leaves only ``max_newton`` (linearly
        converging solves, e.g. friction)
    singular_shift : what to do when the tangent A is singular (its factorisation fails or
        its solve does not satisfy the system): solve the Newton correction with A + rho S,
        rho = min(1, relative residual), S the regularising stiffness that effects offer
        (``regularization(X, x)``: the sliding effect's stick stiffness at contact points
        without pressure, whose friction gives no tangential stiffness at the first iterate
        of a solve), else (or if that is singular too) with A + singular_shift * rho
        |diag(A)| on the displacement block (Levenberg-Marquardt). Only the Newton matrix
        changes, never the residual, so the converged state is the unregularised
        equilibrium. 0 turns both off (a singular tangent then cuts the step back).
    dtol, etol : FEBio's displacement and energy norms (its defaults): at every iteration
        the step's log records ``||eta du|| / ||u - u_step_start||`` (``displacement_norms``)
        and ``|eta du . R_new| / |du_0 . R_0|`` (``energy_norms``), FEBio's
        ``FESolidSolver2`` measures. The residual test (``tol``) decides convergence; a
        step that stagnates (see ``stagnate_after``) even with exact linear solves, or that
        runs out of iterations, is accepted when both norms are below these and the
        relative residual is below ``accept_residual``: what FEBio would call converged
        (it checks no residual by default), with the residual bounded on top. Each
        accepted step says so in its log (``converged_by``) and the solve's
        ``stats["convergence"]`` states the criteria and the last step's norms.
    accept_residual : the largest relative residual of a step accepted by the norms above
        (0: never accept a step by the norms)
    progress : log every Newton iteration at INFO level
    threads : MKL threads of the PARDISO phases; None: the environment variable
        ``BREASTMODEL_THREADS``, else the cores this process may run on (never the load;
        see :func:`mechanics.linear_solvers.resolve_threads`). The Newton loop's own BLAS
        calls (vector operations) run on one thread.
    """

    tol: float = 1e-8
    max_newton: int = 20
    initial_steps: int = 1
    min_step: float = 1e-4
    max_cutbacks: int = 20
    grow_below: int = 6
    linear_solver: str = "auto"
    line_search: bool = True
    reuse_factor: bool = True
    reuse_below: float | None = None
    reuse_max_iterations: int = 100
    stagnate_after: int = 8
    stagnate_above: float = 1e-3
    singular_shift: float = 1e-2
    dtol: float = 1e-3
    etol: float = 1e-2
    accept_residual: float = 1e-3
    progress: bool = False
    threads: int | None = None


class SolverError(RuntimeError):
    """Divergence after the last cut-back, or an unconstrained model.

    ``state`` is the last converged :class:`State` (``converged=False``, its ``load`` < 1).
    ``verdict`` is None for a numerical failure, else a dict that says why the model has no
    equilibrium (see :class:`NoEquilibrium`).
    """

    verdict: dict | None = None

    def __init__(self, message: str, state: State | None = None):
        super().__init__(message)
        self.state = state


class NoEquilibrium(SolverError):
    """A physical verdict, not a stalled Newton: the model as built has no equilibrium (a
    rigid-body mode nothing holds, or a load the supports and structures cannot carry).
    ``verdict``: ``kind`` ("no equilibrium"), ``reason`` and the force budget or the free
    modes behind it."""

    def __init__(self, message: str, state: State | None = None, *, verdict: dict):
        super().__init__(message, state)
        self.verdict = verdict


# -- residual and tangent ------------------------------------------------------------------
def _solid(model: Model, X: np.ndarray) -> Solid:
    return Solid(model.mesh.tets, model.mesh.region, model.materials, X,
                 formulation=model.formulation)


def _effects(model: Model, X, x, load, cpu: dict | None = None):
    """Sum of the effects' forces and tangent triplets; ``cpu`` (effect name -> s) gathers
    each effect's CPU time."""
    force = np.zeros(3 * len(X))
    rows, cols, vals = [], [], []
    for eff in model.effects:
        c0 = time.process_time()
        c = eff.contribute(X, x, load)
        if cpu is not None:
            cpu[eff.name] = cpu.get(eff.name, 0.0) + time.process_time() - c0
        force += np.asarray(c.force, float).reshape(-1)
        if len(c.vals):
            rows.append(np.asarray(c.rows))
            cols.append(np.asarray(c.cols))
            vals.append(np.asarray(c.vals, float))
    if rows:
        return force, np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    return force, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)


def residual_and_tangent(model: Model, X: np.ndarray, x: np.ndarray,
                         load: float) -> tuple[np.ndarray, sp.csr_matrix]:
    """Full residual R (3N,) mN and tangent dR/dx (3N, 3N) mN/mm, no constraints applied.

    The pressure of the "anp" formulation is eliminated (condensed tangent).
    """
    X = np.asarray(X, float)
    x = np.asarray(x, float)
    solid = _solid(model, X)
    ev = solid.evaluate(x)
    f, r, c, v = _effects(model, X, x, load)
    R = ev.force.reshape(-1) + f
    K = solid.condensed_tangent(ev)
    if len(v):
        n = 3 * len(X)
        K = (K + sp.coo_matrix((v, (r, c)), shape=(n, n))).tocsr()
    return R, K


# -- the solve -----------------------------------------------------------------------------
_PATTERN_CACHE: dict = {}


def _system(model: Model, solid: Solid, free: np.ndarray) -> ReducedSystem:
    """Pattern per (topology, free dofs, formulation); reused across solves of one model."""
    key = (id(model.mesh.tets), model.formulation, hash(free.tobytes()))
    hit = _PATTERN_CACHE.get(key)
    if hit is not None and hit[0] is model.mesh.tets:
        return hit[1]
    sysm = ReducedSystem(model.mesh.tets, solid.n_nodes, free,
                         solid.used_nodes if model.formulation == "anp" else None)
    if len(_PATTERN_CACHE) > 8:
        _PATTERN_CACHE.clear()
    _PATTERN_CACHE[key] = (model.mesh.tets, sysm)
    return sysm


def _constraints(model: Model, n_nodes: int, used: np.ndarray):
    fixed = np.zeros(3 * n_nodes, bool)
    target = np.zeros(3 * n_nodes)
    for eff in model.effects:
        for c in eff.constraints():
            nodes = np.asarray(c.nodes, np.int64).reshape(-1)
            comps = tuple(int(k) for k in c.components)
            dofs = (3 * nodes[:, None] + np.asarray(comps)[None, :])
            fixed[dofs.ravel()] = True
            if c.values is not None:
                vals = np.broadcast_to(np.asarray(c.values, float), dofs.shape)
                target[dofs.ravel()] = vals.ravel()
            else:
                target[dofs.ravel()] = 0.0
    # Nodes outside every tet carry no stiffness: hold them where they are.
    orphan = np.repeat(~used, 3)
    fixed |= orphan
    return fixed, target


#: Names of the rigid-body modes of :func:`_check_rigid_modes`, in its order.
_MODES = ("translation along x", "translation along y", "translation along z",
          "rotation about x", "rotation about y", "rotation about z")


def _check_rigid_modes(X: np.ndarray, fixed: np.ndarray, used: np.ndarray,
                       model: Model) -> None:
    """Fail before the solve, with a plain verdict, when the supports leave a rigid-body
    mode free and no effect can hold the body: no support at all (effects that act between
    parts of the body, such as membranes, cables and contact, cannot hold it), or supports
    that leave a mode free and effects that only load the body."""
    orphans = np.repeat(~used, 3)
    held = fixed & ~orphans
    if held.any() and any(type(e).contribute is not _base_contribute for e in model.effects
                          if not _is_load_only(e)):
        return  # an effect may hold the body (springs, contact): rely on the solve check
    Xc = X[used].mean(axis=0)
    d = X - Xc
    scale = np.abs(d[used]).max() or 1.0
    n = len(X)
    modes = np.zeros((6, n, 3))
    for k in range(3):
        modes[k, :, k] = 1.0
        axis = np.eye(3)[k]
        modes[3 + k] = np.cross(axis, d) / scale
    Rc = modes.reshape(6, -1)[:, held]
    G = Rc @ Rc.T if Rc.size else np.zeros((6, 6))
    w, V = np.linalg.eigh(G)
    free = w <= 1e-10 * max(w.max(), 1.0)
    if not free.any():
        return
    # name the free modes: the basis modes that the free eigenvectors span
    span = np.abs(V[:, free]).sum(axis=1)
    names = [_MODES[i] for i in range(6) if span[i] > 1e-6]
    supports = {e.name: int(sum(len(np.asarray(c.nodes).reshape(-1)) for c in e.constraints()))
                for e in model.effects if e.constraints()}
    where = (", ".join(f"'{k}' holds {v} node(s)" for k, v in supports.items())
             if supports else "no effect sets a support")
    held_set = model.mesh.node_sets.get("fixed")  # the meshing stage's chest-wall node set
    empty = held_set is not None and len(held_set) == 0
    hint = (" The mesh's 'fixed' node set is empty: the meshing stage takes it from the "
            "chest-wall muscle, and a segmentation without muscle leaves none; segment the "
            "muscle, or support the body another way." if empty else "")
    verdict = {"kind": "no equilibrium", "reason": "unsupported",
               "free_modes": int(free.sum()), "modes": names, "supports": supports}
    raise NoEquilibrium(
        f"mechanics: no equilibrium: nothing holds the body against {int(free.sum())} "
        f"rigid-body mode(s) ({', '.join(names)}): {where}.{hint} Add supports (e.g. a "
        "'fixed' effect on a node set) before solving.", verdict=verdict)


from mechanics.effects.base import Effect  # noqa: E402

_base_contribute = Effect.contribute


def _is_load_only(eff) -> bool:
    return bool(getattr(eff, "load_only", False))


class _Newton:
    """One solve's working data (not public)."""

    def __init__(self, model: Model, X: np.ndarray, options: SolverOptions):
        self.model, self.X, self.opt = model, X, options
        self.solid = _solid(model, X)
        self.n = len(X)
        self.fixed, self.target = _constraints(model, self.n, self.solid.used_nodes)
        self.free = ~self.fixed
        _check_rigid_modes(X, self.fixed, self.solid.used_nodes, model)
        self.sys = _system(model, self.solid, self.free)
        self.symmetric = all(getattr(e, "symmetric", True) for e in model.effects)
        self.lin = make_linear_solver(options.linear_solver, threads=options.threads)
        self.anp = model.formulation == "anp"
        if self.anp:
            sel = self.solid.used_nodes
            self.pp_diag = -self.solid.V_node[sel] / self.solid.bulk_node[sel]
        else:
            self.pp_diag = None
        # wall and CPU time (all threads) of: the solid's forces and element stiffness, the
        # effects' forces and tangents, the sparse assembly (pattern scatter and the effect
        # entries), the factorisations (symbolic analysis included), the solves
        self.t = dict.fromkeys(_PHASES, 0.0)
        self.c = dict.fromkeys(_PHASES, 0.0)
        self.effect_cpu: dict[str, float] = {}
        self.n_eval = 0
        self.factored = False
        self.n_factor = 0
        self.krylov_used = 0
        self.krylov_its = 0
        self.krylov_failed = 0  # reusing solves that did not converge (a factorisation followed)
        self.trace: list[str] = []  # linear solves of the current step: F, K<its>, k<its> (failed)
        # exact linear solves (a fresh double-precision factorisation at every iteration):
        # switched on for the rest of a step that stagnates, so that neither a reused factor
        # (GMRES to the forcing term) nor a single-precision one caps the residual Newton
        # can reach
        self.exact = False
        self.exact_steps = 0
        self.last_linear_residual = float("nan")  # relative, of the last Newton direction

    def _lap(self, phase: str, t0: float, c0: float) -> tuple[float, float]:
        t1, c1 = time.perf_counter(), time.process_time()
        self.t[phase] += t1 - t0
        self.c[phase] += c1 - c0
        return t1, c1

    def evaluate(self, u: np.ndarray, load: float, *, tangent: bool):
        t0, c0 = time.perf_counter(), time.process_time()
        self.n_eval += 1
        x = self.X + u.reshape(-1, 3)
        ev = self.solid.evaluate(x, tangent=tangent)
        t0, c0 = self._lap("material", t0, c0)
        f, r, c, v = _effects(self.model, self.X, x, load, self.effect_cpu)
        t0, c0 = self._lap("effects", t0, c0)
        R = ev.force.reshape(-1) + f
        if not np.all(np.isfinite(R)):
            raise InvalidConfiguration("the residual is not finite")
        A = None
        if tangent:
            A = self.sys.assemble(ev.Kup, ev.dv, self.pp_diag)
            extra = self.sys.extra_upper(r, c, v, symmetric=self.symmetric)
            if not self.symmetric:
                from mechanics.system import full_from_upper

                A = full_from_upper(A)
            if extra is not None:
                A = (A + extra).tocsr()
            # The element stiffness (78 doubles per tet) is in A now: the line search keeps
            # up to three evaluations, and at 150k tets each Kup is 100 MB.
            ev = replace(ev, Kup=None)
            self._lap("assembly", t0, c0)
        return ev, R, A

    def norms(self, R):
        rf = float(np.linalg.norm(R[self.free]))
        rc = float(np.linalg.norm(R[self.fixed]))
        return rf, rc

    def _matvec(self, A):
        if not self.symmetric:
            return A.__matmul__
        d = A.diagonal()
        At = A.T  # csc view of the lower triangle, no copy
        return lambda y: A @ y + At @ y - d * y

    def effect_shift(self, A, u: np.ndarray, mu: float):
        """A + mu S, S the effects' regularising stiffness (``regularization(X, x)`` COO
        triplets, e.g. the stick stiffness of frictional contact at zero pressure); None
        when no effect offers one."""
        x = self.X + u.reshape(-1, 3)
        parts = [eff.regularization(self.X, x) for eff in self.model.effects
                 if hasattr(eff, "regularization")]
        parts = [p for p in parts if len(p[2])]
        if not parts:
            return None
        r, c, v = (np.concatenate(q) for q in zip(*parts, strict=True))
        return (A + self.sys.extra_upper(r, c, mu * v, symmetric=self.symmetric)).tocsr()

    def regularized(self, A, u: np.ndarray, rel: float):
        """Newton matrices to try when A is singular, in order: A + min(1, rel) S (see
        :meth:`effect_shift`), then A + mu |diag(A)| on the displacement block
        (Levenberg-Marquardt, mu = singular_shift * min(1, rel))."""
        mu = min(1.0, rel)
        A_eff = self.effect_shift(A, u, mu)
        if A_eff is not None:
            yield A_eff
        nf = self.sys.n_free
        d = np.zeros(self.sys.n)
        d[:nf] = np.abs(A.diagonal()[:nf])
        d[:nf] = np.where(d[:nf] > 0.0, d[:nf], d[:nf].max(initial=0.0) or 1.0)
        yield (A + sp.diags(self.opt.singular_shift * mu * d, format="csr")).tocsr()

    def direction(self, A, R, rel: float, *, fresh: bool = False) -> np.ndarray:
        b = np.zeros(self.sys.n)
        b[: self.sys.n_free] = -R[self.free]
        matvec = self._matvec(A)
        y = None
        # GMRES iterations a new factorisation is worth, from the operation counts of the
        # last one (not from measured times: those follow the load, and two runs of one
        # model would then take different paths to slightly different answers)
        budget = int(0.8 * getattr(self.lin, "factor_worth", 0.0))
        below = self.opt.reuse_below
        if below is None:
            below = np.inf if self.symmetric else 0.05
        fresh = fresh or self.exact
        if self.exact and getattr(self.lin, "precision", "double") != "double":
            self.lin.precision = "double"  # PARDISO: this and the later factorisations
        if self.opt.reuse_factor and self.factored and rel < below \
                and budget >= 3 and not fresh:
            its0 = self.krylov_its
            y = self._krylov(matvec, b, rel, min(budget, self.opt.reuse_max_iterations))
            self.krylov_used += y is not None
            self.krylov_failed += y is None
            self.trace.append(f"{'K' if y is not None else 'k'}{self.krylov_its - its0}")
        if y is None:
            t0, c0 = time.perf_counter(), time.process_time()
            self.lin.factorize(A, symmetric=self.symmetric)
            self.factored = True
            self.n_factor += 1
            self.trace.append("F")
            t1, c1 = time.perf_counter(), time.process_time()
            y = self.lin.solve(b)
            self.t["factor"] += t1 - t0
            self.t["solve"] += time.perf_counter() - t1
            self.c["factor"] += c1 - c0
            self.c["solve"] += time.process_time() - c1
            # Backstop for singular tangents that the factorisation let through (perturbed
            # pivots): the solve must satisfy the system it was given.
            err = np.linalg.norm(matvec(y) - b) / max(np.linalg.norm(b), 1e-300)
            if not np.isfinite(err) or err > 1e-6:
                self.factored = False
                raise SingularSystem(f"linear solve residual {err:.2e}")
            self.last_linear_residual = float(err)
        du = np.zeros(3 * self.n)
        du[self.free] = y[: self.sys.n_free]
        return du

    def _krylov(self, matvec, b, rel, maxit):
        """GMRES on the new tangent, right-preconditioned by the previous factorisation:
        GMRES on A M z = b, y = M z. Its residual is the true one, so it stops at the
        forcing term itself (SciPy preconditions on the left and stops its inner iterations
        on the preconditioned residual: with one restart cycle that gave up after 3-4
        iterations at 150k tets when the true residual was still above the forcing term,
        and a factorisation followed)."""
        import scipy.sparse.linalg as spla

        t0, c0 = time.perf_counter(), time.process_time()
        n = len(b)
        pre = self.lin.precondition
        op = spla.LinearOperator((n, n), matvec=lambda v: matvec(pre(v)), dtype=float)
        # Forcing term: the linear residual need only be as small as the nonlinear one (keeps
        # Newton's quadratic rate), and never much below what the tolerance asks for.
        eta = min(0.1, max(0.1 * rel, 0.2 * self.opt.tol / max(rel, 1e-300)))
        its = [0]

        def count(_):
            its[0] += 1

        z, info = spla.gmres(op, b, rtol=eta, atol=0.0, restart=maxit, maxiter=1,
                             callback=count, callback_type="pr_norm")
        self.krylov_its += its[0]
        y = pre(z) if info == 0 else z
        self._lap("solve", t0, c0)
        if info != 0 or not np.all(np.isfinite(y)):
            return None
        err = np.linalg.norm(matvec(y) - b) / max(np.linalg.norm(b), 1e-300)
        self.last_linear_residual = float(err)
        return y if err <= max(eta, 1e-12) * 1.01 else None


def solve(model: Model, *, X: np.ndarray | None = None, u0: np.ndarray | None = None,
          options: SolverOptions = SolverOptions()) -> State:
    """Static equilibrium of ``model`` under its effects at full load.

    Parameters
    ----------
    model : Model
    X : (N, 3) reference (stress-free) positions, mm; default ``model.mesh.nodes``
    u0 : (N, 3) initial guess of the displacement at full load, mm (e.g. a previous solution)
    options : SolverOptions

    Returns
    -------
    State at load 1.

    Raises
    ------
    ValueError : inverted reference mesh, missing material, bad input shapes
    SolverError : unconstrained model, or divergence after the last cut-back; ``.state``
        holds the last converged state
    """
    with single_thread_blas():
        return _solve(model, X, u0, options)


def _solve(model: Model, X, u0, options: SolverOptions) -> State:
    t_start = time.perf_counter()
    rss_start = _rss_mb()
    X = np.array(model.mesh.nodes if X is None else X, dtype=np.float64)
    if X.shape != model.mesh.nodes.shape:
        raise ValueError(f"mechanics: X must be {model.mesh.nodes.shape}, got {X.shape}")
    nw = _Newton(model, X, options)
    opt = options
    n3 = 3 * nw.n
    guess = None
    if u0 is not None:
        guess = np.asarray(u0, float).reshape(-1)
        if guess.shape != (n3,):
            raise ValueError(f"mechanics: u0 must be {X.shape}, got {np.shape(u0)}")

    lam, u = 0.0, np.zeros(n3)
    prev = None  # (lam, u) of the converged step before the last one
    first = None  # (lam, u) of the first converged step
    last_ev = None
    dlam = 1.0 / max(1, int(opt.initial_steps))
    cutbacks = 0
    just_cut = False
    steps: list[dict] = []
    step_no = 0

    def state(converged: bool, ev) -> State:
        if ev is None:
            ev = nw.solid.evaluate(X + u.reshape(-1, 3), tangent=False)
        stress = nw.solid.cauchy_stress(ev)
        J = np.linalg.det(ev.F)
        uu = u.reshape(-1, 3).copy()
        p = ev.p_node if nw.anp else ev.p_elem
        stats = _stats(nw, rss_start, time.perf_counter() - t_start)
        stats["convergence"] = _convergence(opt, steps)
        return State(uu, converged, float(lam), stress, J, tuple(steps),
                     time.perf_counter() - t_start, p.copy(), X.copy(), stats)

    # Path points: loads where a path-dependent effect (friction) updates its history; a
    # step never crosses one, so the solution does not depend on how the steps fell.
    stops = sorted({float(t) for eff in model.effects for t in eff.path_points()
                    if 0.0 < t < 1.0} | {1.0})
    while lam < 1.0 - 1e-12:
        dlam = min(dlam, 1.0 - lam)
        new_lam = 1.0 if lam + dlam > 1.0 - 1e-12 else lam + dlam
        stop = next(t for t in stops if t > lam + 1e-12)
        if new_lam > stop - 1e-12:
            new_lam, dlam = stop, stop - lam  # a cut-back then halves the step taken
        step_no += 1
        x_conv = X + u.reshape(-1, 3)
        for eff in model.effects:
            eff.begin_step(X, x_conv, lam)
        t_before, c_before = dict(nw.t), dict(nw.c)
        f_before, k_before, i_before = nw.n_factor, nw.krylov_used, nw.krylov_its
        a_before, e_before, fx_before = nw.lin.analyses, nw.n_eval, dict(nw.effect_cpu)
        entry = {"step": step_no, "load": new_lam, "newton": 0, "residuals": [],
                 "converged": False, "cutback": None}
        nw.trace = entry["linear"] = []
        # Predictor: extrapolate the last two converged states, else scale the guess.
        u_try = u.copy()
        if prev is not None and lam > prev[0]:
            u_try = u + (new_lam - lam) / (lam - prev[0]) * (u - prev[1])
        elif guess is not None:
            u_try = guess * new_lam
        u_try[nw.fixed] = new_lam * nw.target[nw.fixed]
        try:
            ev, R, A = nw.evaluate(u_try, new_lam, tangent=True)
        except InvalidConfiguration:
            u_try = u.copy()
            u_try[nw.fixed] = new_lam * nw.target[nw.fixed]
            try:
                ev, R, A = nw.evaluate(u_try, new_lam, tangent=True)
            except InvalidConfiguration as exc:
                ev = None
                entry["cutback"] = f"predictor invalid: {exc}"
        ok = False
        if ev is not None:
            ok, u_try, ev, reason = _newton(nw, u_try, new_lam, ev, R, A, entry, u)
            entry["cutback"] = None if ok else reason
        for k in nw.t:
            entry[f"t_{k}"] = nw.t[k] - t_before[k]
            entry[f"cpu_{k}"] = nw.c[k] - c_before[k]
        entry["factorizations"] = nw.n_factor - f_before
        entry["analyses"] = nw.lin.analyses - a_before
        entry["evaluations"] = nw.n_eval - e_before
        entry["cpu_by_effect"] = {k: v - fx_before.get(k, 0.0)
                                  for k, v in nw.effect_cpu.items()}
        entry["krylov_solves"] = nw.krylov_used - k_before
        entry["krylov_iterations"] = nw.krylov_its - i_before
        entry["converged"] = ok
        steps.append(entry)
        if opt.progress:
            log.info("step %d load %.4f: %s after %d iterations", step_no, new_lam,
                     "converged" if ok else f"cut back ({entry['cutback']})", entry["newton"])
        if ok:
            prev = (lam, u)
            lam, u, last_ev = new_lam, u_try, ev
            if first is None:
                first = (lam, u)
            if entry["newton"] <= opt.grow_below and not just_cut:
                dlam *= 2.0
            just_cut = False
            continue
        just_cut = True
        if lam == 0.0 and (entry["cutback"] or "").startswith("singular"):
            raise SolverError(f"mechanics: {entry['cutback']} at the first load step"
                              f"{_mesh_hint(model.mesh)}", state(False, None))
        cutbacks += 1
        dlam *= 0.5
        if dlam < opt.min_step or cutbacks > opt.max_cutbacks:
            st = state(False, last_ev)
            verdict = _limit_point(nw, first, prev, lam, u)
            if verdict is not None:
                raise NoEquilibrium(
                    f"mechanics: no equilibrium beyond load {lam:.4g}: "
                    f"{verdict['message']} (Newton stopped at load {new_lam:.4g} after "
                    f"{cutbacks} cut-back(s); last reason: {entry['cutback']})",
                    st, verdict=verdict)
            raise SolverError(
                f"mechanics: Newton diverged at load {new_lam:.4g} after {cutbacks} cut-back(s) "
                f"(last reason: {entry['cutback']}); last converged load {lam:.4g}"
                f"{_mesh_hint(model.mesh) if lam == 0.0 else ''}",
                st,
            )
    st = state(True, last_ev)
    wall = time.perf_counter() - t_start
    return replace(st, wall_time=wall, stats={**st.stats, "wall_s": wall})


#: Cost phases of a solve (wall and CPU time in each step's log and in ``State.stats``).
_PHASES = ("material", "effects", "assembly", "factor", "solve")


def _rss_mb() -> float:
    """Resident memory of this process now (MB), NaN where /proc is not available."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):  # pragma: no cover
        return float("nan")


def _peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB): ``ru_maxrss``."""
    try:
        import resource
    except ImportError:  # pragma: no cover (not on Windows)
        return float("nan")
    kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0 if sys.platform != "darwin" else kb / 2**20


def _stats(nw: _Newton, rss_start: float, wall: float) -> dict:
    """Totals of one solve: time per phase, counts, threads, memory."""
    lin = nw.lin
    rss_end = _rss_mb()
    return {
        "wall_s": wall,
        **{f"t_{k}": nw.t[k] for k in _PHASES},
        **{f"cpu_{k}": nw.c[k] for k in _PHASES},
        "cpu_by_effect": dict(nw.effect_cpu),
        "cpu_analysis": float(getattr(lin, "analysis_cpu_s", 0.0)),
        "linear_solver": lin.name, "threads": int(lin.threads),
        "unknowns": int(nw.sys.n), "matrix_nnz_upper": int(nw.sys.nnz),
        "evaluations": nw.n_eval, "factorizations": nw.n_factor,
        "analyses": int(getattr(lin, "analyses", 0)),
        "krylov_solves": nw.krylov_used, "krylov_iterations": nw.krylov_its,
        "krylov_failed": nw.krylov_failed,
        "refinements": int(getattr(lin, "refinements", 0)),
        "rss_start_mb": rss_start, "rss_end_mb": rss_end,
        "peak_rss_mb": max(_peak_rss_mb(), rss_end),
    }


#: A solve that fails after its last cut-back is at a limit point (no equilibrium along the
#: load path) when its last converged step moved the body this many times more per unit
#: load than its first step did (the structure has lost its stiffness against the load), or
#: when, at the last step's rate, the body would move more than LIMIT_REACH times its size
#: by full load (it was never held: a breast sliding off a flat slab in the tilted position,
#: 236 mm per unit load at the last step and 308 at the first, on a 200 mm slab).
#: Either way, the motion must be one of the whole part (its mean over its nodes at least
#: LIMIT_COHERENCE of their mean magnitude): a part that gives way moves away as a body,
#: one that sags or spreads in place under a stalled Newton does not.
LIMIT_SOFTENING = 10.0
LIMIT_REACH = 0.5
LIMIT_COHERENCE = 0.5


def _limit_point(nw: _Newton, first, prev, lam: float, u: np.ndarray) -> dict | None:
    """Verdict of a failed solve whose load-displacement path flattens (see
    :data:`LIMIT_SOFTENING`), with the force budget of the breast (the body where the mesh
    has no breast region) at the last converged load: its load along the load direction,
    and what the solid, each effect and the supports carry of it (mN; they sum to the
    load). None when the path does not flatten (a numerical failure, not a verdict)."""
    if first is None or prev is None or lam <= prev[0] or first[0] <= 0.0:
        return None
    from mechanics.mesh import BREAST_REGIONS

    model, X = nw.model, nw.X
    tets = model.mesh.tets
    in_breast = np.isin(model.mesh.region, np.asarray(BREAST_REGIONS))
    part = "breast" if in_breast.any() else "body"
    nodes = np.unique(tets[in_breast] if in_breast.any() else tets)
    U, U0 = u.reshape(-1, 3)[nodes], prev[1].reshape(-1, 3)[nodes]
    rate = np.linalg.norm(U - U0, axis=1).max() / (lam - prev[0])  # mm per unit load
    softening = rate / max(np.linalg.norm(first[1].reshape(-1, 3)[nodes], axis=1).max()
                           / first[0], 1e-300)
    # the displacement at full load if the last step's rate held, against the part's size
    extent = float(np.linalg.norm(np.ptp(X[nodes], axis=0)))
    reach = (np.linalg.norm(U, axis=1).max() + (1.0 - lam) * rate) / extent
    # how much of the last step's motion is one motion of the whole part (1: a rigid
    # translation, sliding away; near 0: sagging or spreading in place)
    dU = U - U0
    coherence = float(np.linalg.norm(dU.mean(0)) / max(np.linalg.norm(dU, axis=1).mean(),
                                                      1e-300))
    log.debug("limit point check: softening %.3g, reach %.3g, coherence %.3g", softening,
              reach, coherence)
    if not ((softening >= LIMIT_SOFTENING or reach >= LIMIT_REACH)
            and coherence >= LIMIT_COHERENCE):
        return None
    x = X + u.reshape(-1, 3)
    load = np.zeros(3)
    carried: dict[str, np.ndarray] = {}
    for eff in model.effects:
        f = np.asarray(eff.contribute(X, x, lam).force, float).reshape(-1, 3)[nodes].sum(0)
        if _is_load_only(eff):
            load -= f  # the force the load applies (residual = internal - external)
        else:
            carried[eff.name] = f
    if not np.any(load):
        return None
    ev = nw.solid.evaluate(x, tangent=False)
    carried["solid"] = ev.force.reshape(-1, 3)[nodes].sum(0)
    R = ev.force.reshape(-1) + _effects(model, X, x, lam)[0]
    fixed = nw.fixed.reshape(-1, 3)[nodes]
    carried["supports"] = -np.where(fixed, R.reshape(-1, 3)[nodes], 0.0).sum(0)
    # the budget along the way the part gives way (its mean motion over the last step),
    # where the load pushes that way; else along the load
    move = (U - U0).mean(0)
    move = move / max(np.linalg.norm(move), 1e-300)
    d = move if load @ move > 0.05 * np.linalg.norm(load) else load / np.linalg.norm(load)
    shares = {k: float(v @ d) for k, v in carried.items() if abs(float(v @ d)) > 1e-9}
    along = float(load @ d)
    budget = ", ".join(f"{k} {v:.0f}" for k, v in sorted(shares.items(), key=lambda kv: -kv[1]))
    message = (
        f"the {part} gives way along ({', '.join(f'{c:.2f}' for c in move)}): over the last "
        f"converged step it moved {rate:.0f} mm per unit load ({softening:.1f}x the first "
        f"step's rate; {reach:.1f}x its size by full load). At load {lam:.3g} the load pushes "
        f"it {along:.0f} mN along ({', '.join(f'{c:.2f}' for c in d)}) (at full load "
        f"{along / lam:.0f} mN), carried by: {budget} mN; the supports hold "
        f"{int(np.any(nw.fixed.reshape(-1, 3)[nw.solid.used_nodes], axis=1).sum())} of "
        f"{int(nw.solid.used_nodes.sum())} nodes. Nothing in the model holds the "
        f"rest in this position: add support along that direction (e.g. hold the skin's "
        "lateral cut), or stiffen what carries it (ligaments, skin, fascia, friction)")
    return {"kind": "no equilibrium", "reason": "limit point", "load": float(lam),
            "softening": float(softening), "mm_per_unit_load": float(rate),
            "reach": float(reach), "coherence": coherence, "part": part,
            "part_size_mm": extent,
            "budget_direction": d.tolist(), "load_mN": along, "load_at_full_mN": along / lam,
            "carried_mN": shares, "motion_direction": move.tolist(),
            "message": message}


def _convergence(opt: SolverOptions, steps: list[dict]) -> dict:
    """The convergence criteria of a solve and how its steps met them: the residual test
    (``tol``: ||R_free|| relative to the reactions or the step's first residual) or FEBio's
    displacement and energy norms (``dtol``, ``etol``) with the residual below
    ``accept_residual``; the norms of the last converged step."""
    done = [e for e in steps if e["converged"]]
    last = done[-1] if done else None

    def final(key):
        return float(last[key][-1]) if last is not None and last.get(key) else None

    return {
        "residual_tol": opt.tol, "dtol": opt.dtol, "etol": opt.etol,
        "accept_residual": opt.accept_residual,
        "steps_by_residual": sum(e.get("converged_by") == "residual" for e in done),
        "steps_by_norms": sum(e.get("converged_by") == "norms" for e in done),
        "steps_with_exact_linear_solves": sum("exact_linear_from" in e for e in steps),
        "last_step": None if last is None else {
            "load": float(last["load"]), "converged_by": last.get("converged_by"),
            "residual": final("residuals"), "displacement": final("displacement_norms"),
            "energy": final("energy_norms"), "linear_residual": final("linear_residuals")},
    }


def _mesh_hint(mesh) -> str:
    """Why a solve may fail from its very first load step, when the mesh shows it: tets that
    hang on the rest by an edge or a vertex (a free rotation). Computed only on failure."""
    from mechanics.mesh import hinged_tets

    bad = hinged_tets(mesh.tets)
    if len(bad) == 0:
        return ""
    shown = ", ".join(str(int(t)) for t in bad[:5]) + (", ..." if len(bad) > 5 else "")
    return (f"; the mesh has {len(bad)} tet(s) that meet the rest only at an edge or a vertex "
            f"(tets {shown}): they rotate freely; remove them or re-mesh (the meshing stage "
            "keeps only the face-connected body)")


def _progressing(res: list[float]) -> bool:
    """True when a Newton step's relative residuals show progress that the stagnation check
    must not cut short: the last iteration halved the best residual so far, or the last
    three each fell, by a quarter in all (a damped, line-searched approach to a large
    deformation).

    Measured on the 20k-tet phantom with every effect on: 45 deg tilted went 0.97 -> 0.13 at
    iteration 8 and supine fell steadily from 2.3 to 0.91 over iterations 1-8; both were cut
    back there and took 27-36 iterations in two load steps; left alone they converged at
    iterations 15 and 18."""
    last = res[-1]
    if last <= 0.5 * min(res[:-1]):
        return True
    tail = res[-4:]
    return len(tail) == 4 and all(b < a for a, b in zip(tail, tail[1:])) \
        and last <= 0.75 * tail[0]


def _accepted_by_norms(opt: SolverOptions, entry: dict) -> bool:
    """FEBio's displacement and energy tests on the last iteration, with the relative
    residual below ``accept_residual`` (see :class:`SolverOptions`)."""
    d, e = entry["displacement_norms"], entry["energy_norms"]
    return bool(opt.accept_residual > 0.0 and d and entry["residuals"][-1] <= opt.accept_residual
                and d[-1] <= opt.dtol and e[-1] <= opt.etol)


def _newton(nw: _Newton, u, lam, ev, R, A, entry, u_start):
    """Newton iterations of one load step from ``u`` (the predictor; ``u_start`` the
    converged displacement the step starts from). Returns (ok, u, ev, reason)."""
    opt = nw.opt
    rf, rc = nw.norms(R)
    r0 = rf
    entry["displacement_norms"], entry["energy_norms"] = [], []
    energy0 = None  # |du_0 . R_0|, FEBio's reference of the energy norm
    exact_from = None  # iteration from which the step's linear solves are exact
    nw.exact = False

    def stop_early(reason: str):
        """A step that stalls: accepted when FEBio's norms say it converged."""
        if _accepted_by_norms(opt, entry):
            entry["converged_by"] = "norms"
            return True, u, ev, None
        return False, u, ev, reason

    for it in range(opt.max_newton + 1):
        ref = max(rc, r0, 1e-300)
        rel = rf / ref
        entry["residuals"].append(rel)
        if opt.progress:
            log.info("  load %.4f iteration %d: relative residual %.3e", lam, it, rel)
        if rel <= opt.tol:
            entry["converged_by"] = "residual"
            return True, u, ev, None
        if it == opt.max_newton:
            return stop_early(f"no convergence in {opt.max_newton} iterations")
        if rf > 1e6 * max(r0, 1e-300) and it > 0:
            return False, u, ev, "residual diverged"
        res = entry["residuals"]
        if opt.stagnate_after and it >= opt.stagnate_after \
                and (exact_from is None or it >= exact_from + 4) \
                and rel > 0.1 * res[max(it - 3, 0)] and not _progressing(res) \
                and (rel > opt.stagnate_above
                     or min(res[it - 4:]) > 0.5 * min(res[:max(it - 4, 1)])):
            # also below stagnate_above when the best residual has not halved in the last
            # 5 iterations (friction states cycling: 20k-tet prone ran 20 iterations at 1e-4).
            reason = f"stagnating (relative residual {rel:.1e} after {it})"
            if exact_from is not None or rel > opt.stagnate_above:
                return stop_early(reason)
            # Close to convergence: first rule out the linear solver (a reused or
            # single-precision factor) as what holds the residual up.
            exact_from = entry["exact_linear_from"] = it
            nw.exact = True
            nw.exact_steps += 1
        try:
            A_first = None
            if it == 0 and opt.singular_shift > 0.0 and not np.any(u[nw.free]):
                # From rest every contact gap is zero: frictional sliding gives no tangential
                # stiffness and a body held by friction alone has an exactly singular but
                # consistent tangent, which some factorisations solve without complaint,
                # adding an arbitrary rigid slide (measured: 107 mm with scipy on the
                # two-mound model, diverged). The first correction from rest therefore always
                # uses the effects' regularisation (what a detected singular tangent gets).
                A_first = nw.effect_shift(A, u, 1.0)
            du = nw.direction(A if A_first is None else A_first, R, rel,
                              fresh=A_first is not None)
            if A_first is not None:
                entry["shifted"] = entry.get("shifted", 0) + 1
        except SingularSystem as exc:
            du = None
            if opt.singular_shift > 0.0:
                for A_reg in nw.regularized(A, u, rel):
                    try:
                        du = nw.direction(A_reg, R, rel, fresh=True)
                    except SingularSystem:
                        continue
                    entry["shifted"] = entry.get("shifted", 0) + 1
                    break
            if du is None:
                return False, u, ev, f"singular tangent ({exc}); is the model constrained?"
        entry["newton"] += 1
        if energy0 is None:
            R0_free = R[nw.free].copy()
        entry.setdefault("linear_residuals", []).append(nw.last_linear_residual)
        s0 = float(R @ du)
        eta, accepted = 1.0, None
        for _ls in range(8):
            try:
                ev1, R1, A1 = nw.evaluate(u + eta * du, lam, tangent=True)
            except InvalidConfiguration:
                eta *= 0.5
                continue
            if not opt.line_search or s0 >= 0.0:
                accepted = (eta, ev1, R1, A1)
                break
            s1 = float(R1 @ du)
            if abs(s1) <= 0.9 * abs(s0) or accepted is not None:
                accepted = (eta, ev1, R1, A1)
                break
            accepted = (eta, ev1, R1, A1)  # keep as fallback, try one secant step
            r = s0 / (s0 - s1)  # root of the linear interpolation of s(eta) / eta
            if not (0.0 < r < 1.0) or abs(r - 1.0) < 0.05:
                break
            new_eta = max(0.1, min(1.0, r)) * eta
            try:
                ev2, R2, A2 = nw.evaluate(u + new_eta * du, lam, tangent=True)
            except InvalidConfiguration:
                break
            if np.linalg.norm(R2[nw.free]) < np.linalg.norm(R1[nw.free]) or \
                    abs(float(R2 @ du)) < abs(s1):
                accepted = (new_eta, ev2, R2, A2)
            break
        if accepted is None:
            return False, u, ev, "element inversion (J <= 0) along the Newton direction"
        eta, ev, R, A = accepted
        u = u + eta * du
        if energy0 is None:
            energy0 = abs(float(du[nw.free] @ R0_free))
        step = eta * du[nw.free]
        total = float(np.linalg.norm((u - u_start)[nw.free]))
        entry["displacement_norms"].append(float(np.linalg.norm(step)) / max(total, 1e-300))
        entry["energy_norms"].append(abs(float(step @ R[nw.free])) / max(energy0, 1e-300))
        rf, rc = nw.norms(R)
        if not np.isfinite(rf):
            return False, u, ev, "residual is not finite"
    return False, u, ev, "no convergence"
