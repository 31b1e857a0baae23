"""Adaptive load stepping of one solve: the load path from 0 to 1 through the effects' path
points, the predictor, the Newton iterations of each step,
growth after easy steps and cut-backs after failed ones, and the end of a solve that runs
out of cut-backs (a numerical failure, or a verdict that the model has no equilibrium)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from mechanics.model import Model
from mechanics.newton.iteration import _newton
from mechanics.newton.options import NoEquilibrium, SolverError, SolverOptions
from mechanics.newton.records import _convergence, _counters, _rss_mb, _stats, _step_costs
from mechanics.newton.verdicts import _crush_hint, _limit_point, _mesh_hint
from mechanics.newton.workspace import _Newton
from mechanics.solid import InvalidConfiguration
from mechanics.state import State

log = logging.getLogger("mechanics.solver")


@dataclass
class _Path:
    """The load path of one solve so far: the last converged load and displacement, the
    next increment, the earlier converged states the predictor and the verdicts read, the
    cut-backs taken and every step's log entry."""

    lam: float
    u: np.ndarray
    dlam: float
    prev: tuple | None = None  # (lam, u) of the converged step before the last one
    first: tuple | None = None  # (lam, u) of the first converged step
    last_ev: object = None
    cutbacks: int = 0
    just_cut: bool = False
    steps: list[dict] = field(default_factory=list)


def _state(nw: _Newton, path: _Path, converged: bool, ev, t_start: float,
           rss_start: float) -> State:
    """The state at the path's last converged load (``ev`` its solid evaluation, or None)."""
    X, u = nw.X, path.u
    if ev is None:
        ev = nw.solid.evaluate(X + u.reshape(-1, 3), tangent=False)
    stress = nw.solid.cauchy_stress(ev)
    J = np.linalg.det(ev.F)
    uu = u.reshape(-1, 3).copy()
    p = ev.p_node if nw.anp else ev.p_elem
    stats = _stats(nw, rss_start, time.perf_counter() - t_start)
    stats["convergence"] = _convergence(nw.opt, path.steps)
    return State(uu, converged, float(path.lam), stress, J, tuple(path.steps),
                 time.perf_counter() - t_start, p.copy(), X.copy(), stats)


def _path_stops(model: Model) -> list[float]:
    """Loads where a path-dependent effect (friction) updates its history, and 1; a step
    never crosses one, so the solution does not depend on how the steps fell."""
    return sorted({float(t) for eff in model.effects for t in eff.path_points()
                   if 0.0 < t < 1.0} | {1.0})


def _next_load(path: _Path, stops: list[float]) -> float:
    """The load the next step aims at: the last one plus the increment, at most the next
    path point (the increment then shrinks to reach it)."""
    lam = path.lam
    path.dlam = min(path.dlam, 1.0 - lam)
    new_lam = 1.0 if lam + path.dlam > 1.0 - 1e-12 else lam + path.dlam
    stop = next(t for t in stops if t > lam + 1e-12)
    if new_lam > stop - 1e-12:
        new_lam, path.dlam = stop, stop - lam  # a cut-back then halves the step taken
    return new_lam


def _predictor(nw: _Newton, path: _Path, new_lam: float, guess, kind: str) -> np.ndarray:
    """The step's first iterate (``kind``, see ``SolverOptions.predictor``): the last
    converged state moved along the initial guess by the load increment (the guess, a nearby
    problem's solution, stands for the path ``load * guess``), or without a guess the
    converged state itself; with "secant" the last two converged states extrapolated; the
    constrained dofs at their scaled targets."""
    lam, u, prev = path.lam, path.u, path.prev
    u_try = u.copy()
    if prev is not None and lam > prev[0] and kind == "secant":
        u_try = u + (new_lam - lam) / (lam - prev[0]) * (u - prev[1])
    elif guess is not None:
        u_try = u + (new_lam - lam) * guess
    u_try[nw.fixed] = new_lam * nw.target[nw.fixed]
    return u_try


def _smaller_start(nw: _Newton, path: _Path, new_lam: float, guess) -> tuple[str, dict]:
    """The predictor ("secant" or "converged") whose first iterate has the smaller residual
    norm on the free dofs at ``new_lam``, and both norms (mN; infinite where the iterate
    inverts an element). Without two converged states the two are one: "converged"."""
    if path.prev is None or path.lam <= path.prev[0]:
        return "converged", {}
    norms = {}
    for kind in ("secant", "converged"):
        try:
            _, R, _ = nw.evaluate(_predictor(nw, path, new_lam, guess, kind), new_lam,
                                  tangent=False)
            norms[kind] = nw.norms(R)[0]
        except InvalidConfiguration:
            norms[kind] = np.inf
    return min(norms, key=norms.get), norms


def _load_step(nw: _Newton, path: _Path, new_lam: float, guess, kind: str):
    """One load step from the path's last converged state to ``new_lam``: the effects'
    ``begin_step``, the predictor ``kind`` (the converged state itself where the predictor
    inverts an element), the Newton iterations; its log entry (with
    ``predictor``) is added to the path. Returns (ok, u, ev, entry)."""
    model, X = nw.model, nw.X
    x_conv = X + path.u.reshape(-1, 3)
    for eff in model.effects:
        eff.begin_step(X, x_conv, path.lam)
    before = _counters(nw)
    entry = {"step": len(path.steps) + 1, "load": new_lam, "newton": 0, "residuals": [],
             "converged": False, "cutback": None}
    nw.trace = entry["linear"] = []
    if kind == "auto":
        kind, norms = _smaller_start(nw, path, new_lam, guess)
        if norms:
            entry["predictor_residuals"] = norms
    entry["predictor"] = kind
    u_try = _predictor(nw, path, new_lam, guess, kind)
    start = []  # [ev, R, A] at u_try, handed over to (and emptied by) the iterations
    try:
        start[:] = nw.evaluate(u_try, new_lam, tangent=True)
    except InvalidConfiguration:
        u_try = path.u.copy()
        u_try[nw.fixed] = new_lam * nw.target[nw.fixed]
        try:
            start[:] = nw.evaluate(u_try, new_lam, tangent=True)
        except InvalidConfiguration as exc:
            entry["cutback"] = f"predictor invalid: {exc}"
    ok, ev = False, None
    if start:
        ok, u_try, ev, reason = _newton(nw, u_try, new_lam, start, entry, path.u)
        entry["cutback"] = None if ok else reason
    _step_costs(entry, nw, before)
    entry["converged"] = ok
    path.steps.append(entry)
    if nw.opt.progress:
        log.info("step %d load %.4f: %s after %d iterations", entry["step"], new_lam,
                 "converged" if ok else f"cut back ({entry['cutback']})", entry["newton"])
    return ok, u_try, ev, entry


def _advance(path: _Path, new_lam: float, u, ev, entry: dict, opt: SolverOptions) -> None:
    """A converged step: the path moves on, and the increment doubles after a step that took
    at most ``grow_below`` iterations (not right after a cut-back)."""
    path.prev = (path.lam, path.u)
    path.lam, path.u, path.last_ev = new_lam, u, ev
    if path.first is None:
        path.first = (path.lam, path.u)
    if entry["newton"] <= opt.grow_below and not path.just_cut:
        path.dlam *= 2.0
    path.just_cut = False


def _cut_back(nw: _Newton, path: _Path, new_lam: float, entry: dict, t_start: float,
              rss_start: float) -> None:
    """A failed step: halve the increment, or raise when that is no longer allowed (a
    singular tangent at the first step, the smallest increment, the last cut-back): a
    :class:`NoEquilibrium` verdict where the path shows a limit point, else a
    :class:`SolverError`; both carry the last converged state."""
    opt, model, lam = nw.opt, nw.model, path.lam
    path.just_cut = True
    if lam == 0.0 and (entry["cutback"] or "").startswith("singular"):
        raise SolverError(f"mechanics: {entry['cutback']} at the first load step"
                          f"{_mesh_hint(model.mesh)}",
                          _state(nw, path, False, None, t_start, rss_start))
    path.cutbacks += 1
    path.dlam *= entry.get("shrink", 0.5)
    if path.dlam >= opt.min_step and path.cutbacks <= opt.max_cutbacks:
        return
    cutbacks = path.cutbacks
    st = _state(nw, path, False, path.last_ev, t_start, rss_start)
    verdict = _limit_point(nw, path.first, path.prev, lam, path.u)
    if verdict is not None:
        raise NoEquilibrium(
            f"mechanics: no equilibrium beyond load {lam:.4g}: "
            f"{verdict['message']} (Newton stopped at load {new_lam:.4g} after "
            f"{cutbacks} cut-back(s); last reason: {entry['cutback']})",
            st, verdict=verdict)
    raise SolverError(
        f"mechanics: Newton diverged at load {new_lam:.4g} after {cutbacks} cut-back(s) "
        f"(last reason: {entry['cutback']}); last converged load {lam:.4g}"
        f"{_mesh_hint(model.mesh) if lam == 0.0 else _crush_hint(nw, st.J)}",
        st,
    )


def _solve(model: Model, X, u0, options: SolverOptions) -> State:
    """:func:`mechanics.solver.solve` inside its single-threaded BLAS context. With the
    "auto" predictor a path that ends without equilibrium is followed once more from the
    extrapolation (``predictor = "secant"``) before the solve gives up: with friction the
    two starts can follow different equilibrium branches, and the smaller residual's can end
    at a fold where the other reaches full load (the 17k-tet suite mesh's softest corner in
    supine: "no equilibrium" at load 0.86 after 240 Newton iterations; from the
    extrapolation, full load in 160). The abandoned path is in ``stats["abandoned_path"]``
    (its reason, load reached, Newton iterations, seconds); the state's wall time counts
    both."""
    if options.predictor != "auto":
        return _solve_path(model, X, u0, options)
    t0 = time.perf_counter()
    try:
        return _solve_path(model, X, u0, options)
    except SolverError as exc:
        if exc.state is None:  # an unconstrained model, or the caller's time budget
            raise
        first = {"predictor": "auto", "reason": str(exc), "load": float(exc.state.load),
                 "newton": exc.state.newton_iterations, "cutbacks": sum(
                     1 for e in exc.state.log if not e["converged"]),
                 "wall_s": time.perf_counter() - t0}
    log.info("mechanics: the smaller-residual starts ended at load %.4g; the whole solve once "
             "more from the extrapolation", first["load"])
    try:
        st = _solve_path(model, X, u0, replace(options, predictor="secant"))
    except SolverError as exc:
        if exc.state is not None:
            exc.state = replace(exc.state, stats={**exc.state.stats, "abandoned_path": first})
        raise
    wall = time.perf_counter() - t0
    return replace(st, wall_time=wall,
                   stats={**st.stats, "wall_s": wall, "abandoned_path": first})


def _solve_path(model: Model, X, u0, options: SolverOptions) -> State:
    """One solve along one load path (see :func:`_solve`)."""
    t_start = time.perf_counter()
    rss_start = _rss_mb()
    X = np.array(model.mesh.nodes if X is None else X, dtype=np.float64)
    if X.shape != model.mesh.nodes.shape:
        raise ValueError(f"mechanics: X must be {model.mesh.nodes.shape}, got {X.shape}")
    nw = _Newton(model, X, options)
    n3 = 3 * nw.n
    guess = None
    if u0 is not None:
        guess = np.asarray(u0, float).reshape(-1)
        if guess.shape != (n3,):
            raise ValueError(f"mechanics: u0 must be {X.shape}, got {np.shape(u0)}")
    # A guess is a nearby problem's solution at full load: the first step takes the whole
    # load from it, and a cut-back falls back on the path's increments (measured on the
    # suite's full-000, 46k tets: the stress-free inverse's warm solves 10-18 -> 1-4 Newton
    # iterations each at initial_steps = 2; the inverse of the fit's first, cold evaluation
    # 26 -> 17 s).
    first = 1.0 if guess is not None else 1.0 / max(1, int(options.initial_steps))
    path = _Path(0.0, np.zeros(n3), first)
    stops = _path_stops(model)
    while path.lam < 1.0 - 1e-12:
        new_lam = _next_load(path, stops)
        ok, u_try, ev, entry = _load_step(nw, path, new_lam, guess, options.predictor)
        if not ok and options.predictor == "converged" and path.prev is not None:
            # the same step once more from the extrapolation before cutting back: the
            # converged state is the better start on the softest moduli, the extrapolation
            # near a Gent fascia's limit stretch (bench/step_control.py). Not with "auto":
            # measured on the 17k-tet mesh's softest corner in supine, such retries won 2 of
            # 14 failed steps and took the solve 240 -> 354 iterations
            ok, u_try, ev, entry = _load_step(nw, path, new_lam, guess, "secant")
        if ok:
            _advance(path, new_lam, u_try, ev, entry, options)
        else:
            _cut_back(nw, path, new_lam, entry, t_start, rss_start)
    st = _state(nw, path, True, path.last_ev, t_start, rss_start)
    wall = time.perf_counter() - t_start
    return replace(st, wall_time=wall, stats={**st.stats, "wall_s": wall})
