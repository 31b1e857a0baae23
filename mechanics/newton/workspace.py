"""One solve's working data (:class:`_Newton`): the solid, the constraints and the reduced
system's pattern, the linear solver, the evaluation of residual and tangent at a
displacement, and the counters and timers that the step log and the stats report."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from mechanics.linear_solvers import make_linear_solver
from mechanics.model import Model
from mechanics.newton.directions import _Directions
from mechanics.newton.options import SolverOptions
from mechanics.newton.records import _PHASES
from mechanics.newton.residual import _constraints, _effects, _solid, _system
from mechanics.newton.verdicts import _check_rigid_modes
from mechanics.pattern import KeptPattern
from mechanics.solid import InvalidConfiguration


class _Newton(_Directions):
    """One solve's working data (not public)."""

    def __init__(self, model: Model, X: np.ndarray, options: SolverOptions):
        if options.predictor not in ("auto", "converged", "secant"):
            raise ValueError(f"mechanics: predictor must be 'auto', 'converged' or 'secant', "
                             f"got {options.predictor!r}")
        self.model, self.X, self.opt = model, X, options
        self.solid = _solid(model, X)
        self.n = len(X)
        self.fixed, self.target = _constraints(model, self.n, self.solid.used_nodes)
        self.free = ~self.fixed
        _check_rigid_modes(X, self.fixed, self.solid.used_nodes, model)
        self.sys = _system(model, self.solid, self.free)
        self.symmetric = all(getattr(e, "symmetric", True) for e in model.effects)
        self.pattern = KeptPattern(self.sys, self.symmetric, options.pattern_drop_below)
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
        self.reused = False  # the last direction came from a reused factorisation
        self.krylov_its = 0
        self.krylov_failed = 0  # reusing solves that did not converge (a factorisation followed)
        self.trace: list[str] = []  # linear solves of the current step: F, K<its>, k<its> (failed)
        # exact linear solves (a fresh double-precision factorisation at every iteration):
        # switched on for the rest of a step that stagnates, so that neither a reused factor
        # (GMRES to the forcing term) nor a single-precision one caps the residual Newton
        # can reach
        self.exact = False
        self.exact_steps = 0
        # Newton matrices without the tensile pressure's geometric stiffness (SolverOptions.
        # tensile_pressure_stiffness_below), set by the iterations of a step
        self.no_pressure_stiffness = False
        self.exact_tangent = False  # the rest of the step uses the exact tangent
        self.last_linear_residual = float("nan")  # relative, of the last Newton direction

    def _lap(self, phase: str, t0: float, c0: float) -> tuple[float, float]:
        t1, c1 = time.perf_counter(), time.process_time()
        self.t[phase] += t1 - t0
        self.c[phase] += c1 - c0
        return t1, c1

    def evaluate(self, u: np.ndarray, load: float, *, tangent: bool):
        """Solid evaluation, residual R (3N,) mN and, with ``tangent``, the assembled Newton
        matrix at the displacement u (3N,) mm and load factor ``load``; raises
        :class:`InvalidConfiguration` where an element inverts or R is not finite."""
        t0, c0 = time.perf_counter(), time.process_time()
        self.n_eval += 1
        x = self.X + u.reshape(-1, 3)
        # On a mesh of more than one block the bulk's element stiffness goes into the matrix
        # block by block as it is computed (150k tets: peak 1494 -> 1345-1361 MB); a smaller one
        # is scattered after its evaluation, which measured faster (20k: 30 against 47 ms).
        stream = tangent and len(self.solid.blocks) > 1  # the solid's blocks (system.blocks)
        asm = self.sys.start() if stream else None
        ev = self.solid.evaluate(x, tangent=tangent, sink=asm.add_stiffness if stream else None,
                                 tensile_pressure_stiffness=not self.no_pressure_stiffness)
        t0, c0 = self._lap("material", t0, c0)
        if asm is not None:  # the scatter ran inside the solid's evaluation: assembly's time
            for acc, spent in ((self.t, asm.wall), (self.c, asm.cpu)):
                acc["material"] -= spent
                acc["assembly"] += spent
        f, parts = _effects(self.model, self.X, x, load, self.effect_cpu)
        t0, c0 = self._lap("effects", t0, c0)
        R = ev.force.reshape(-1) + f
        if not np.all(np.isfinite(R)):
            raise InvalidConfiguration("the residual is not finite")
        A = None
        if tangent:
            A = asm.matrix(ev.dv, self.pp_diag) if stream else \
                self.sys.assemble(ev.Kup, ev.dv, self.pp_diag)
            # both in A now; the line search keeps up to three evaluations (150k tets: the
            # element stiffness is 100 MB, dv 16 MB)
            ev = replace(ev, Kup=None, dv=None)
            A = self.pattern.matrix(A, parts, exact=self.exact)
            self._lap("assembly", t0, c0)
        return ev, R, A

    def norms(self, R):
        """||R|| on the free dofs and on the constrained ones (the reactions), mN."""
        rf = float(np.linalg.norm(R[self.free]))
        rc = float(np.linalg.norm(R[self.fixed]))
        return rf, rc
