"""``breastmodel fit SUBJECT --config run.toml --out DIR``: fit material parameters.

Runs (or reuses) the preparation stages of ``breastmodel run`` in ``DIR/cache``, then fits
the ``[fit.parameters]`` of the config (e.g. ``"materials.breast_left.E" = {min = 0.1,
max = 4.0, step = 0.1}``): ``--method grid`` evaluates the whole grid on a dask cluster (the
paper's calibration), ``--method optimizer`` runs a bounded Nelder-Mead in log-parameter
space within ``--budget`` simulations. The objective is the mean modified Hausdorff distance
of the calibration positions (``[fit] calibrate``, default prone and the reference) after the
stress-free estimate; the other positions are scored as held out. Writes ``DIR/fit.json``
(best, history, sensitivity) and ``DIR/params.json``. Every evaluation is stored as it
finishes: a killed fit resumes.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "fit",
        help="fit material parameters (grid on dask, or an optimiser)",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("subject", type=Path, help="subject folder")
    p.add_argument("--config", type=Path, required=True, help="run config with [fit.parameters]")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--method", choices=["grid", "optimizer"], help="override [fit] method")
    p.add_argument("--budget", type=int, help="override [fit] budget (optimizer evaluations)")
    p.add_argument("--scheduler", help="dask scheduler address (grid; default a local cluster)")
    p.add_argument("--workers", type=int, help="local dask workers (grid; default [fit] n_workers)")
    p.add_argument("--no-sensitivity", action="store_true", help="skip the sensitivity analysis")
    return p


def run(args: argparse.Namespace) -> int:
    from breastmodel.config import ConfigError, write_json
    from breastmodel.pipeline import fit_parameters, load_run_config, prepare_subject
    from breastmodel.pipeline.config import get_param, set_params
    from breastmodel.pipeline.fit import fit_work_dir
    from breastmodel.pipeline.problem import fit_settings

    cfg = load_run_config(args.config)
    fit = dict(cfg["fit"])
    if not fit["parameters"]:
        raise ConfigError(f"fit: {args.config} has no [fit.parameters]")
    for key, val in (("method", args.method), ("budget", args.budget),
                     ("scheduler", args.scheduler), ("n_workers", args.workers)):
        if val is not None:
            fit[key] = val
    if args.no_sensitivity:
        fit["sensitivity"] = False
    prep = prepare_subject(args.subject, cfg, args.out, command="fit")
    settings = fit_settings(cfg, prep.positions, prep.subject.reference)
    work = fit_work_dir(Path(args.out) / "fit", prep.problem_dir, settings)
    res = fit_parameters(prep.problem_dir, settings, fit, work_dir=work)
    write_json(Path(args.out) / "fit.json", res)
    model = set_params(cfg["model"], res["best"]["params"])
    write_json(Path(args.out) / "params.json", {
        "parameters": {p: get_param(model, p) for p in fit["parameters"]},
        "model": model, "fitted": True,
        "fit": {k: res[k] for k in ("method", "best", "n_simulations", "calibrate", "evaluate")},
    })
    b = res["best"]
    print(f"fit ({res['method']}): best mean MHD {b['objective']:.4f} mm after "
          f"{res['n_simulations']} simulations ({res['n_failed']} failed)")
    for k, v in b["params"].items():
        print(f"  {k} = {v:.4g}")
    return 0
