"""The subject pipeline: cached stages, fitting, sweeps, metrics and the report.

- :func:`run_subject` (``breastmodel run``): segment -> register -> measured skins, and the
  reference's mesh beside them -> [fit] -> stress-free geometry -> predict and score every
  position -> outputs.
- :func:`prepare_subject`: the stages up to the problem folder (what fit and sweep need).
- :func:`evaluate_params` / :func:`sweep_point`: the picklable objective.
- :func:`fit_parameters`, :func:`grid_search`, :func:`optimise`, :func:`sensitivity`.
- :func:`load_run_config`, :func:`resolve_config`: the ``run.toml`` config.
"""

from breastmodel.pipeline.config import load_run_config, resolve_config
from breastmodel.pipeline.fit import fit_parameters, grid_search, optimise, sensitivity
from breastmodel.pipeline.problem import evaluate_params, load_problem, sweep_point
from breastmodel.pipeline.run import RunResult, prepare_subject, run_problem, run_subject

__all__ = [
    "RunResult", "evaluate_params", "fit_parameters", "grid_search", "load_problem",
    "load_run_config", "optimise", "prepare_subject", "resolve_config", "run_problem",
    "run_subject",
    "sensitivity", "sweep_point",
]
