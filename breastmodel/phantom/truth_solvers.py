"""How one position of a simulated phantom is solved: by our solver or by FEBio.

:func:`solve_position` times one solve and records its statistics; ``"ours"`` is
:func:`mechanics.solver.solve`, ``"febio"`` is :func:`breastmodel.febio.solve_with_febio`
(locking-free UT4 tets), an FE code independent of ours, so that a truth does not share our
solver's errors.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from breastmodel.phantom.truth_model import TruthModel

__all__ = ["FEBIO_APPROXIMATED", "FEBIO_ELEMENT", "FEBIO_MAX_REFS", "FEBIO_SOFT_BELOW_KPA",
           "FEBIO_STEPS", "TRUTH_SOLVERS",
           "find_febio_for_truth", "solve_position", "truth_solver_executable"]

log = logging.getLogger("breastmodel.phantom")

#: Truth solvers of :func:`simulate_positions`.
TRUTH_SOLVERS = ("ours", "febio")
#: Load steps of an FEBio truth. FEBio's UT4 tets cost ~15x its standard tets per iteration;
#: two steps reach the same equilibrium as ten (to 1e-13 mm on a small subject) at a fifth of
#: the time, and FEBio's time stepper halves a step that fails to converge.
FEBIO_STEPS = 2
#: A family subject whose breast is softer than the standard band (adult 1.5 kPa) starts from
#: ``FEBIO_STEPS * ceil(1.5 kPa / its adult-size modulus)`` steps (``load_steps`` of its
#: truth model): a half-size torso (seed 3) at 0.3 kPa in 2 steps had FEBio retry its
#: supine position through negative Jacobians for over 10 minutes (the first step from rest
#: cut 6 times); at 0.5 kPa in 4 steps the three positions took 105, 184 and 236 s.
FEBIO_SOFT_BELOW_KPA = 1.5
#: Newton iterations FEBio may spend on one time step of a truth before it cuts the step
#: (its own default and :data:`mechanics.febio.TOLERANCES`: 25). On Gent breast tissue
#: FEBio's Newton converges linearly near full load (the displacement norm halves each
#: iteration): a small subject's prone position (seed 3, Jm 1) needed 30 iterations in its
#: second step and converged in 115 s with 60, where with 25 the retries crawled from load
#: 0.94 to 0.98 in 10 minutes. Converging solves are unchanged (the limit is not reached).
FEBIO_MAX_REFS = 60
#: FEBio's element for truths: its locking-free UT4 tet. ``bench/truth_refinement.py`` sets
#: "tet10" (quadratic tets on the same mesh) to tell the element's error from the mesh's.
FEBIO_ELEMENT = "ut4"
#: Effects for which a truth is written with FEBio approximations allowed: the wrinkling skin,
#: written as shells that carry compression (without it, any approximation is refused before
#: FEBio runs). What the file approximated is recorded with each truth, in its own words.
FEBIO_APPROXIMATED = ("skin",)


def solve_position(model, name: str, tm: TruthModel, truth_solver: str, *, febio_path,
                   cache_dir, work_dir, progress: bool) -> tuple[np.ndarray, dict]:
    """Displacement (N, 3) mm of position ``name`` solved by ``truth_solver``, and its info:
    the solver's statistics, ``solver``, ``wall_time_s`` and ``max_displacement_mm`` (logged
    at INFO level with ``progress``, else DEBUG)."""
    t0 = time.perf_counter()
    if truth_solver == "febio":
        u, info = _solve_febio(model, name, tm, febio_path, cache_dir=cache_dir,
                               work_dir=work_dir)
    else:
        u, info = _solve_ours(model, name, tm)
    dt = time.perf_counter() - t0
    info.update(solver=truth_solver, wall_time_s=dt,
                max_displacement_mm=float(np.linalg.norm(u, axis=1).max()))
    say = log.info if progress else log.debug
    say("phantom: %s solved by %s in %.1f s, max displacement %.1f mm", name,
        truth_solver, dt, info["max_displacement_mm"])
    return u, info


def _solve_ours(model, name: str, tm: TruthModel) -> tuple[np.ndarray, dict]:
    """Displacement (N, 3) mm and info of one position solved by :func:`mechanics.solver.solve`."""
    from mechanics.solver import SolverError, SolverOptions, solve

    try:
        state = solve(model, options=SolverOptions(initial_steps=2))
    except SolverError as exc:
        raise RuntimeError(f"phantom: simulation of position {name!r} with truth "
                           f"model {tm.name!r} failed: {exc}") from None
    info = {"converged": bool(state.converged), "load_steps": state.load_steps,
            "newton_iterations": state.newton_iterations}
    return state.u, info


def truth_solver_executable(truth_solver: str, febio) -> Path | None:
    """Check a truth solver's name; the FEBio executable for ``"febio"``, else None.

    Raises
    ------
    ValueError
        An unknown truth solver.
    RuntimeError
        FEBio missing (says how to give it).
    """
    if truth_solver not in TRUTH_SOLVERS:
        raise ValueError(f"phantom: unknown truth solver {truth_solver!r}; use one of "
                         f"{TRUTH_SOLVERS}")
    return find_febio_for_truth(febio) if truth_solver == "febio" else None


def find_febio_for_truth(febio):
    """The FEBio executable, or a RuntimeError saying how to give one."""
    try:
        from breastmodel.febio import find_febio
    except ImportError as exc:
        raise RuntimeError(f"phantom: the FEBio truth solver is not available in this build "
                           f"({exc})") from None
    try:
        return find_febio(febio)
    except Exception as exc:  # noqa: BLE001 - re-raised with the stage and the remedy
        raise RuntimeError(f"phantom: truth solver 'febio' needs FEBio 4: {exc} (pass "
                           "--febio PATH or set $FEBIO)") from None


def _solve_febio(model, name: str, tm, febio_path, *, cache_dir, work_dir):
    """Displacement (N, 3) mm and info of one position solved by FEBio."""
    import tempfile

    from breastmodel.febio import solve_with_febio

    febio_cache = Path(cache_dir) / "febio" if cache_dir is not None else None
    approximate = bool(set(tm.effects) & set(FEBIO_APPROXIMATED))
    with tempfile.TemporaryDirectory(prefix=f"febio-{name}-") as tmp:
        wd = Path(work_dir) / name if work_dir is not None else Path(tmp)
        try:
            run = solve_with_febio(model, work_dir=wd, febio=febio_path, element=FEBIO_ELEMENT,
                                   threads=1, cache_dir=febio_cache,
                                   steps=tm.load_steps or FEBIO_STEPS,
                                   approximate=approximate, max_refs=FEBIO_MAX_REFS)
        except Exception as exc:  # noqa: BLE001 - re-raised naming the position and model
            raise RuntimeError(f"phantom: FEBio truth of position {name!r} with truth model "
                               f"{tm.name!r} failed: {exc}") from None
    if not run.converged:
        tail = "\n".join(str(run.log_tail).splitlines()[-8:])
        raise RuntimeError(f"phantom: FEBio did not converge for position {name!r} with "
                           f"truth model {tm.name!r}; log tail:\n{tail}")
    info = {"converged": True, "febio_wall_s": float(run.wall_s),
            "cached": bool(getattr(run, "cached", False)), "element": FEBIO_ELEMENT,
            "febio_approximations": list(run.approximations)}
    return np.asarray(run.displacement, float), info
