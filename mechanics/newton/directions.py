"""Newton directions of one solve (a mixin of :class:`mechanics.newton.workspace._Newton`):
the linear solve of the correction, by GMRES preconditioned with the last factorisation
where that costs less than a new one, else by a new factorisation checked against the
system it was given; and the regularised matrices that stand in for a singular tangent."""

from __future__ import annotations

import time

import numpy as np

from mechanics.krylov import fgmres
from mechanics.linear_solvers import SingularSystem


class _Directions:
    """Linear algebra of the Newton correction. Reads the working data of
    :class:`mechanics.newton.workspace._Newton` (``sys``, ``free``, ``lin``, ``opt``,
    ``symmetric``, the counters and timers) and updates its counters."""

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
        return self.pattern.plus(A, r, c, mu * v)

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
        at = np.flatnonzero(d)
        yield self.pattern.plus(A, at, at, self.opt.singular_shift * mu * d[at], reduced=True)

    def direction(self, A, R, rel: float, *, fresh: bool = False) -> np.ndarray:
        """The Newton correction du (3N,) mm for the residual R and Newton matrix A (the
        reduced system's upper triangle, or the full matrix when unsymmetric): GMRES
        preconditioned by the last factorisation where reuse is allowed (``reuse_factor``,
        below ``reuse_below``, not ``fresh``, not exact), else a new factorisation, whose
        solve must satisfy the system (else :class:`SingularSystem`)."""
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
            self.reused = y is not None
            self.krylov_used += y is not None
            self.krylov_failed += y is None
            self.trace.append(f"{'K' if y is not None else 'k'}{self.krylov_its - its0}")
        if y is None:
            self.reused = False
            t0, c0 = time.perf_counter(), time.process_time()
            self.lin.factorize(A, symmetric=self.symmetric)
            self.factored = True
            self.n_factor += 1
            self.trace.append("F")
            t1, c1 = time.perf_counter(), time.process_time()
            # refined to 1e-10, below any forcing term (>= 0.1 sqrt(2 tol)) and the backstop's
            # 1e-6; to the rounding floor only for an exact Newton step (20k tets: one
            # refinement instead of three)
            y = self.lin.solve(b, tol=None if self.exact else 1e-10)
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
            self.lin.forget_matrix()  # from here the factor only preconditions
        du = np.zeros(3 * self.n)
        du[self.free] = y[: self.sys.n_free]
        return du

    def _krylov(self, matvec, b, rel, maxit):
        """GMRES on the new tangent, right-preconditioned by the previous factorisation
        (:func:`mechanics.krylov.fgmres`): its residual is the true one, so it stops at the
        forcing term itself (SciPy's left-preconditioned GMRES stopped its inner iterations
        on the preconditioned residual: with one restart cycle that gave up after 3-4
        iterations at 150k tets when the true residual was still above the forcing term,
        and a factorisation followed)."""
        t0, c0 = time.perf_counter(), time.process_time()
        # Forcing term: the linear residual need only be as small as the nonlinear one (keeps
        # Newton's quadratic rate), and never much below what the tolerance asks for.
        eta = min(0.1, max(0.1 * rel, 0.2 * self.opt.tol / max(rel, 1e-300)))
        y, its, _ = fgmres(matvec, self.lin.precondition, b, eta, maxit)
        self.krylov_its += its
        self._lap("solve", t0, c0)
        if y is None:
            return None
        err = np.linalg.norm(matvec(y) - b) / max(np.linalg.norm(b), 1e-300)
        self.last_linear_residual = float(err)
        return y if err <= max(eta, 1e-12) * 1.01 else None
