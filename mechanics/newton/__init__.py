"""The Newton solver behind :func:`mechanics.solver.solve`, one module per part: options and
errors, residual and tangent, one solve's working data and its linear algebra, the Newton
iterations of a load step, the load stepping, the records and the no-equilibrium verdicts.
Callers import from :mod:`mechanics.solver`."""
