"""What a solve records: the cost of each load step (time per phase, counts) in its log, and
the totals, memory and convergence criteria of the whole solve in ``State.stats``."""

from __future__ import annotations

import os
import sys
from typing import TYPE_CHECKING

from mechanics.newton.options import SolverOptions

if TYPE_CHECKING:
    from mechanics.newton.workspace import _Newton

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
        # the Newton matrices' kept pattern (mechanics.pattern): how often it grew, how
        # many small effect entries were left out of the matrices (summed over them)
        "pattern_growths": nw.pattern.grown, "entries_left_out": nw.pattern.left_out,
        "krylov_solves": nw.krylov_used, "krylov_iterations": nw.krylov_its,
        "krylov_failed": nw.krylov_failed,
        "refinements": int(getattr(lin, "refinements", 0)),
        "rss_start_mb": rss_start, "rss_end_mb": rss_end,
        "peak_rss_mb": max(_peak_rss_mb(), rss_end),
        # the sparse direct solver's own account of its memory (PARDISO's), part of the peak
        "linear_solver_mb": float(getattr(lin, "memory_mb", float("nan"))),
    }


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


def _counters(nw: _Newton) -> tuple:
    """The solve's running totals before a load step (see :func:`_step_costs`)."""
    return (dict(nw.t), dict(nw.c), nw.n_factor, nw.krylov_used, nw.krylov_its,
            nw.lin.analyses, nw.n_eval, dict(nw.effect_cpu))


def _step_costs(entry: dict, nw: _Newton, before: tuple) -> None:
    """Record in a load step's log entry what the step cost: wall and CPU time per phase,
    factorisations, symbolic analyses, evaluations, CPU time per effect, GMRES solves and
    iterations (the totals now less ``before``, from :func:`_counters`)."""
    t_before, c_before, f_before, k_before, i_before, a_before, e_before, fx_before = before
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
