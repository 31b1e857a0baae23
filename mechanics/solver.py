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

The parts live in :mod:`mechanics.newton`: its options and errors (``options``), the residual
and tangent (``residual``), one solve's working data (``workspace``) and its linear algebra
(``directions``), the Newton iterations of a load step (``iteration``), the load stepping
(``stepping``), the records of a solve (``records``) and the no-equilibrium verdicts
(``verdicts``). This module is the public entry and names what callers import.
"""

from __future__ import annotations

import logging

import numpy as np

from mechanics.linear_solvers import single_thread_blas
from mechanics.model import Model
from mechanics.newton.iteration import _progressing as _progressing
from mechanics.newton.options import NoEquilibrium, SolverError, SolverOptions
from mechanics.newton.residual import _constraints as _constraints
from mechanics.newton.residual import _solid as _solid
from mechanics.newton.residual import residual_and_tangent
from mechanics.newton.stepping import _solve
from mechanics.newton.verdicts import LIMIT_COHERENCE, LIMIT_REACH, LIMIT_SOFTENING
from mechanics.newton.workspace import _Newton as _Newton
from mechanics.state import State

__all__ = ["LIMIT_COHERENCE", "LIMIT_REACH", "LIMIT_SOFTENING", "NoEquilibrium", "SolverError",
           "SolverOptions", "residual_and_tangent", "solve"]

log = logging.getLogger("mechanics.solver")


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

