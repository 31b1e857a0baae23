"""Stress-free (unloaded) geometry: find reference positions X whose loaded shape matches data.

Two methods, compared in ``bench/stress_free.py``:

- :func:`paper_fixed_point` — the paper's algorithm (Mîra et al., after Eiben et al.): simulate
  the loaded position from the current estimate, measure each active skin node's distance to
  the measured surface, impose a fraction ``lam`` of that correction on the estimate as a
  prescribed displacement (a linear-elastic mesh-motion solve moves the interior along),
  repeat while the mean error improves by more than ``min_improvement``.
- :func:`inverse_fixed_point` — the full-field inverse (Sellier's fixed point,
  X <- X + (x_target - x(X))) when every node's loaded position is known, as it is for the
  position the mesh was built from, accelerated with Anderson mixing (Walker & Ni 2011).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mechanics.model import Model, build_model
from mechanics.solver import NoEquilibrium, SolverError, SolverOptions, solve
from mechanics.state import State

log = logging.getLogger("mechanics.stress_free")


@dataclass(frozen=True, eq=False)
class StressFreeResult:
    """X : (N, 3) stress-free positions, mm; state : the loaded solve from X;
    history : per iteration ``{"iteration", "mean_error", "max_error", "newton", "time"}``
    (errors in mm); converged : the stopping criterion was met."""

    X: np.ndarray
    state: State
    history: tuple[dict, ...]
    converged: bool
    method: str


def _forward(model: Model, X: np.ndarray, u0: np.ndarray | None, options: SolverOptions) -> State:
    return solve(model, X=X, u0=u0, options=options)


def _inverted(model: Model, X: np.ndarray) -> bool:
    return bool(np.any(model.mesh.signed_volumes(X) <= 0.0))


def inverse_fixed_point(
    model: Model,
    x_target: np.ndarray,
    *,
    tol: float = 1e-3,
    max_iter: int = 50,
    anderson: int = 5,
    max_failures: int = 3,
    max_total_failures: int = 6,
    max_no_equilibrium: int = 2,
    X0: np.ndarray | None = None,
    u0: np.ndarray | None = None,
    options: SolverOptions = SolverOptions(),
    callback: Callable[[dict], None] | None = None,
    before_solve: Callable[[], None] | None = None,
) -> StressFreeResult:
    """Reference positions whose loaded configuration under ``model`` is ``x_target``.

    Parameters
    ----------
    model : the loaded model (gravity, supports, effects) of the measured position
    x_target : (N, 3) measured loaded node positions, mm (typically ``model.mesh.nodes``)
    tol : stop when the largest nodal mismatch |x(X) - x_target| is below this, mm
    max_iter : forward solves allowed
    anderson : memory of Anderson mixing; 0 gives the plain fixed point
    max_failures : consecutive failed forward solves (each damped half-way back to the last
        good estimate) before giving up: a model with no equilibrium near the target would
        otherwise spend ``max_iter`` full cut-back cascades
    max_total_failures : failed forward solves allowed in all (a model that fails, damps,
        recovers and fails again does not converge either)
    max_no_equilibrium : forward solves ending in the solver's physical verdict (the body
        gives way, :class:`~mechanics.solver.NoEquilibrium`) allowed in all: each costs
        every cut-back, and damping seldom gives the equilibrium back (a soft suite subject
        at 0.18 kPa, supine: 7 of them in 6 minutes, the breast giving way at 0.25-0.72)
    X0, u0 : (N, 3) initial estimate of X and of the displacement, mm (default: ``x_target``
        and none; a nearby model's solution makes a warm start)
    callback : called with each iteration's history row (progress reporting)
    before_solve : called before every forward solve; it may raise to stop the inverse (a
        caller's budget of solves or seconds)
    """
    x_target = np.asarray(x_target, np.float64)
    X = x_target.copy() if X0 is None else np.array(X0, np.float64)
    u = None if u0 is None else np.asarray(u0, np.float64)
    mixing = _Anderson(anderson)
    history: list[dict] = []
    state = None
    X_good = None  # the last estimate whose forward solve converged
    failures = total_failures = verdicts = 0
    t0 = time.perf_counter()
    for it in range(1, max_iter + 1):
        if before_solve is not None:
            before_solve()
        try:
            state = _forward(model, X, u, options)
        except SolverError as exc:
            failures += 1
            total_failures += 1
            verdicts += isinstance(exc, NoEquilibrium)
            if X_good is None or failures > max_failures or total_failures > max_total_failures \
                    or verdicts >= max_no_equilibrium:
                log.warning("inverse: giving up after %d failed forward solves (%d in a row, "
                            "%d without equilibrium)", total_failures, failures, verdicts)
                raise
            # The update went too far: step back half-way to the last good estimate.
            log.warning("inverse: forward solve failed (%s); damping the update", exc)
            X = 0.5 * (X + X_good)
            mixing.reset()
            continue
        X_good = X.copy()
        failures = 0
        u = state.u
        f = (x_target - state.x).reshape(-1)
        row = _row(it, f, state, t0)
        history.append(row)
        if callback:
            callback(row)
        if row["max_error"] < tol:
            return StressFreeResult(X, state, tuple(history), True, "inverse_fixed_point")
        X = _next_estimate(model, X, f, mixing)
    return StressFreeResult(X, state, tuple(history), False, "inverse_fixed_point")


class _Anderson:
    """Anderson mixing (Walker & Ni 2011) of the fixed point X <- X + f(X): the last
    ``memory + 1`` estimates and their mismatches, and the mixed next estimate."""

    def __init__(self, memory: int):
        self.memory = memory
        self.V: list[np.ndarray] = []
        self.F: list[np.ndarray] = []

    def reset(self) -> None:
        """Forget the history (after a damped or inverted step)."""
        self.V.clear()
        self.F.clear()

    def step(self, v: np.ndarray, f: np.ndarray) -> np.ndarray:
        """The next estimate (3N,) from the estimate v and its mismatch f (3N,) mm: v + f,
        mixed with the history when the memory is not 0."""
        V, F = self.V, self.F
        V.append(v.copy())
        F.append(f.copy())
        if len(V) > self.memory + 1:
            V.pop(0)
            F.pop(0)
        new = v + f
        if self.memory and len(V) > 1:
            dF = np.stack([F[i + 1] - F[i] for i in range(len(F) - 1)], axis=1)
            dG = np.stack([(V[i + 1] + F[i + 1]) - (V[i] + F[i]) for i in range(len(V) - 1)],
                          axis=1)
            gamma, *_ = np.linalg.lstsq(dF, f, rcond=None)
            new = new - dG @ gamma
        return new


def _next_estimate(model: Model, X: np.ndarray, f: np.ndarray, mixing: _Anderson) -> np.ndarray:
    """The next reference positions (N, 3) mm: the mixed fixed-point step, or the plain one
    (and a fresh history) where the mixed one inverts an element, halved (at most 5 times)
    while it still does (a breast sliding on a compliant interface: the plain step folded
    a tet at the rim of a suite subject's breast)."""
    v = X.reshape(-1)
    X_new = mixing.step(v, f).reshape(-1, 3)
    if _inverted(model, X_new):
        mixing.reset()
        step = 1.0
        X_new = (v + f).reshape(-1, 3)
        while _inverted(model, X_new) and step > 1.0 / 32:
            step *= 0.5
            X_new = (v + step * f).reshape(-1, 3)
        if step < 1.0:
            log.warning("inverse: the fixed-point step inverts an element; %g of it taken",
                        step)
    return X_new


def _row(it: int, f: np.ndarray, state: State, t0: float) -> dict:
    """One iteration's history row: the mean and largest nodal mismatch |f| (mm)."""
    err = np.linalg.norm(f.reshape(-1, 3), axis=1)
    return {"iteration": it, "mean_error": float(err.mean()), "max_error": float(err.max()),
            "newton": state.newton_iterations, "time": time.perf_counter() - t0}


def paper_fixed_point(
    model: Model,
    target: Callable[[np.ndarray], np.ndarray],
    active: np.ndarray,
    anchored: np.ndarray,
    *,
    X0: np.ndarray | None = None,
    lam: float = 0.5,
    min_improvement: float = 0.01,
    max_iter: int = 30,
    options: SolverOptions = SolverOptions(),
    callback: Callable[[dict], None] | None = None,
    before_solve: Callable[[], None] | None = None,
) -> StressFreeResult:
    """The paper's fixed point on a measured surface (Mîra et al., Fig. 2).

    Parameters
    ----------
    model : loaded model of the measured position (e.g. prone gravity and supports)
    target : maps the (k, 3) simulated positions of the active nodes to their measured
        counterparts, mm: the closest points on the measured skin surface (e.g. an open3d
        ray-casting scene), or the measured node positions where correspondence is known
    active : (k,) indices of the active (skin) nodes
    anchored : (j,) indices of nodes that do not move in the mesh-motion step (fixed chest wall)
    X0 : initial estimate (default the mesh nodes, i.e. the reference-position geometry)
    lam : fraction of the correction imposed per iteration (paper: lambda < 1)
    min_improvement : stop when the mean error improves by less than this, mm (paper: 1 mm)
    before_solve : called before every forward solve; it may raise to stop (a caller's budget)
    """
    if not 0.0 < lam <= 1.0:
        raise ValueError(f"stress-free: lam must be in (0, 1], got {lam}")
    active = np.asarray(active, np.int64)
    anchored = np.setdiff1d(np.asarray(anchored, np.int64), active)
    X = np.array(model.mesh.nodes if X0 is None else X0, np.float64)
    # A compressible linear-elastic solid carries the imposed surface correction smoothly
    # into the interior (the paper's "imposed displacement" step), independent of gravity.
    mover = {int(r): {"name": "linear", "E": 1.0, "nu": 0.3} for r in np.unique(model.mesh.region)}
    history: list[dict] = []
    t0 = time.perf_counter()
    best = (np.inf, X, None)
    u = None
    stuck = False
    for it in range(1, max_iter + 1):
        if before_solve is not None:
            before_solve()
        state = _forward(model, X, u, options)
        u = state.u
        x_act = state.x[active]
        D = target(x_act) - x_act
        err = np.linalg.norm(D, axis=1)
        row = {"iteration": it, "mean_error": float(err.mean()), "max_error": float(err.max()),
               "newton": state.newton_iterations, "time": time.perf_counter() - t0}
        history.append(row)
        if callback:
            callback(row)
        improved = best[0] - row["mean_error"]
        if row["mean_error"] < best[0]:
            best = (row["mean_error"], X, state)
        if improved < min_improvement:
            break
        # Impose a fraction of the correction; halve it while the moved mesh would invert.
        step = lam
        for _ in range(6):
            X_next = _move(model, mover, X, active, step * D, anchored)
            if not _inverted(model, X_next):
                break
            step *= 0.5
        else:
            log.warning("stress-free: every imposed correction inverts the mesh; stopping")
            stuck = True
            break
        X = X_next
    _, X_best, s_best = best
    converged = not stuck and len(history) < max_iter
    return StressFreeResult(X_best, s_best, tuple(history), converged, "paper_fixed_point")


def _move(model: Model, materials: dict, X: np.ndarray, active: np.ndarray, d: np.ndarray,
          anchored: np.ndarray) -> np.ndarray:
    effects = {"fixed:active": {"nodes": active, "values": d},
               "fixed:anchored": {"nodes": anchored}}
    m = build_model(model.mesh, materials, effects, formulation="standard")
    return solve(m, X=X, options=SolverOptions(linear_solver="scipy")).x
