"""The budget of one model evaluation: forward solves and seconds.

A diagnosis evaluates dozens of model variants; one ill-posed variant (a stress-free inverse
that fails, damps and fails again) must not keep the others' answer waiting. Every
evaluation therefore gets a :class:`Budget`, charged before each forward solve (the
stress-free iterations and every position); once either limit is spent the evaluation stops
with :class:`BudgetExceeded`, whose message says what was spent where, and the diagnosis
lists the candidate as failed with that reason. The seconds also bound each forward solve
from inside: the evaluation hands the solver the budget's deadline
(``SolverOptions.deadline``), checked at every Newton iteration, so an evaluation overruns
its seconds by at most one Newton iteration (measured before, on the adult phantom's 25.6k
tets: the sliding candidate's first forward solve ran 62.8 s against a 20 s budget).
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

__all__ = ["Budget", "BudgetExceeded", "default_budget"]


class BudgetExceeded(RuntimeError):
    """An evaluation spent its forward solves or seconds."""


@dataclass
class Budget:
    """Limits of one evaluation.

    max_solves : forward solves allowed (stress-free iterations, failed ones included, and
        one per position)
    max_seconds : wall-clock seconds allowed, s
    """

    max_solves: int
    max_seconds: float
    solves: int = 0
    t0: float = field(default_factory=time.perf_counter)

    def charge(self, what: str = "a forward solve") -> None:
        """Count one forward solve; raise :class:`BudgetExceeded` when a limit is spent.

        Parameters
        ----------
        what : the solve about to start (for the message)
        """
        spent = time.perf_counter() - self.t0
        if self.solves >= self.max_solves:
            raise BudgetExceeded(
                f"budget: {self.solves} forward solves spent (limit {self.max_solves}) "
                f"before {what}, after {spent:.1f} s")
        if spent > self.max_seconds:
            raise BudgetExceeded(
                f"budget: {spent:.1f} s spent (limit {self.max_seconds:.1f} s) before {what}, "
                f"after {self.solves} forward solves")
        self.solves += 1

    @property
    def deadline(self) -> float:
        """The ``time.perf_counter()`` instant the seconds run out (a solver's deadline)."""
        return self.t0 + self.max_seconds

    @contextmanager
    def solving(self, what: str):
        """A forward solve handed :attr:`deadline`: its stop there (a ``SolverError`` once
        the seconds are spent) becomes :class:`BudgetExceeded`, naming ``what``."""
        from mechanics.solver import SolverError

        try:
            yield
        except SolverError as exc:
            spent = time.perf_counter() - self.t0
            if spent <= self.max_seconds:
                raise
            raise BudgetExceeded(
                f"budget: {spent:.1f} s spent (limit {self.max_seconds:.1f} s) in {what}, "
                f"after {self.solves} forward solves") from exc

    def to_dict(self) -> dict:
        return {"max_solves": int(self.max_solves), "max_seconds": float(self.max_seconds)}


def default_budget(base_solves: int, base_seconds: float, *, factor: float = 3.0,
                   min_seconds: float = 20.0) -> tuple[int, float]:
    """Limits of a variant evaluation from what the fitted model's own evaluation took.

    A variant lies near the fitted model (one parameter 22 % away, or one effect at its probe
    strength), and starts from the fitted model's solution, so it should cost about as much.

    Parameters
    ----------
    base_solves, base_seconds : forward solves and seconds of the fitted model's evaluation
    factor : how many times that a variant may spend
    min_seconds : floor of the seconds (the timing of a small model is noisy), s

    Returns
    -------
    (max_solves, max_seconds)
    """
    solves = max(int(math.ceil(factor * base_solves)), base_solves + 4)
    return solves, max(factor * float(base_seconds), float(min_seconds))
