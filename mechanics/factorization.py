"""What the sparse direct solvers of :mod:`mechanics.linear_solvers` share: the error of a
system that cannot be factorised or solved, and the cost model that says how many GMRES
iterations a factorisation is worth (from operation counts, never timings)."""

from __future__ import annotations

#: Time of one flop of a substitution over one of a factorisation (BLAS-3 supernodes against
#: memory-bound triangular solves and a sparse product), measured on the 2-core machine with
#: the hemisphere's saddle-point tangent: PARDISO on 2 threads 3.4-7.8 (637 to 48k unknowns,
#: growing with the size), SuperLU 1.0-8.5. Fixed, so that what a factorisation is worth
#: (:func:`factorisation_worth`) depends on the matrix only, never on the load: two runs take
#: one path.
_SOLVE_FLOP_COST = {"pardiso": 6.0, "scipy": 4.0}


def factorisation_worth(name: str, factor_flops: float, iteration_flops: float) -> float:
    """How many preconditioned GMRES iterations (a substitution with the factor and a product
    with the matrix) cost as much as one factorisation, from operation counts."""
    return factor_flops / (_SOLVE_FLOP_COST[name] * max(iteration_flops, 1.0))


class SingularSystem(RuntimeError):
    """The tangent could not be factorised or the solve is meaningless."""
