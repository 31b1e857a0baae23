"""The result of a solve: a plain, immutable value."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class State:
    """Solved (or last converged) state.

    u : (N, 3) displacements from the reference positions X, mm
    converged : True when the full load was reached
    load : load factor reached, in [0, 1]
    stress : (M, 3, 3) Cauchy stress per element, kPa
    J : (M,) volume ratio per element
    log : per load step a dict with ``load``, ``step``, ``newton`` (iterations),
        ``residuals`` (relative norms), ``converged``, ``cutback`` reason or None,
        ``predictor`` (the step's first iterate: "converged" or "secant", see
        :class:`mechanics.solver.SolverOptions`; with "auto" also ``predictor_residuals``,
        both starts' residual norms, mN),
        wall and CPU time of each cost phase (``t_<phase>``, ``cpu_<phase>``, s; phases:
        ``material`` the solid's forces and element stiffness, ``effects`` the effects'
        forces and tangents, ``assembly`` the sparse matrix, ``factor`` the factorisations
        with their symbolic analyses, ``solve`` the triangular and Krylov solves),
        ``cpu_by_effect`` (effect name -> CPU s), counts of ``evaluations``,
        ``factorizations``, ``analyses``, ``krylov_solves``, ``krylov_iterations``, and
        ``linear``: each linear solve in order (``F`` a factorisation, ``K<n>`` a GMRES solve
        reusing the last factorisation in n iterations, ``k<n>`` one that failed);
        convergence per iteration: ``displacement_norms`` and ``energy_norms`` (FEBio's
        ``||eta du|| / ||u - u_step_start||`` and ``|eta du . R| / |du_0 . R_0|``),
        ``linear_residuals`` (relative, of each Newton direction), ``converged_by``
        ("residual", or "norms": see :class:`mechanics.solver.SolverOptions`), and
        ``exact_linear_from``: the iteration from which a stalling step solved exactly
    wall_time : s
    pressure : (N,) nodal pressure (kPa, formulation "anp") or (M,) per element
    X : (N, 3) reference positions used, mm
    stats : totals of the solve: the phases' times as in ``log``, the counts, ``threads``
        and ``linear_solver`` used, ``unknowns``, ``matrix_nnz_upper``, memory of the
        process (``rss_start_mb``, ``rss_end_mb``, ``peak_rss_mb``: its high-water mark,
        which includes what ran before the solve in the same process) and
        ``linear_solver_mb`` (PARDISO's own account of its factor's memory), MB; ``convergence``:
        the criteria (``residual_tol``, ``dtol``, ``etol``, ``accept_residual``), how many
        steps met each, and the last converged step's norms
    """

    u: np.ndarray
    converged: bool
    load: float
    stress: np.ndarray
    J: np.ndarray
    log: tuple[dict, ...] = ()
    wall_time: float = 0.0
    pressure: np.ndarray | None = None
    X: np.ndarray | None = None
    stats: dict = field(default_factory=dict)

    @property
    def x(self) -> np.ndarray:
        """Current positions (N, 3) mm."""
        return self.X + self.u

    @property
    def newton_iterations(self) -> int:
        return int(sum(e["newton"] for e in self.log))

    @property
    def load_steps(self) -> int:
        return int(sum(1 for e in self.log if e["converged"]))

    def max_displacement(self) -> float:
        """Largest nodal displacement magnitude, mm."""
        return float(np.linalg.norm(self.u, axis=1).max()) if len(self.u) else 0.0
