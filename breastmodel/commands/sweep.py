"""``breastmodel sweep SUBJECT --config run.toml --out DIR``: a parameter grid on dask.

Evaluates every point of the ``[fit.parameters]`` grid (``{min, max, step}`` or ``{values}``
per parameter path; the paper's grid is in ``examples/run.toml``) on a dask cluster: a local
one with ``--workers`` processes by default, or the scheduler at ``--scheduler ADDRESS``.
Each finished point is stored atomically in ``DIR/fit/<hash>/grid/points/<key>.json``; a killed
sweep resumes, and a point on a worker lost mid-sweep is recomputed. Failed simulations are
NaN points. Writes ``DIR/sweep.json`` (every point, the best one) and prints the best.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "sweep",
        help="evaluate a grid of material parameters on a dask cluster (resumable)",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("subject", type=Path, help="subject folder")
    p.add_argument("--config", type=Path, required=True, help="run config with [fit.parameters]")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--scheduler", help="dask scheduler address (default: a local cluster)")
    p.add_argument("--workers", type=int, default=2, help="local dask workers (default 2)")
    return p


def run(args: argparse.Namespace) -> int:
    from breastmodel.config import ConfigError, write_json
    from breastmodel.pipeline import grid_search, load_run_config, prepare_subject
    from breastmodel.pipeline.fit import fit_work_dir
    from breastmodel.pipeline.problem import fit_settings

    cfg = load_run_config(args.config)
    if not cfg["fit"]["parameters"]:
        raise ConfigError(f"sweep: {args.config} has no [fit.parameters]")
    prep = prepare_subject(args.subject, cfg, args.out, command="sweep")
    settings = fit_settings(cfg, prep.positions, prep.subject.reference)
    res = grid_search(prep.problem_dir, settings, cfg["fit"]["parameters"],
                      work_dir=fit_work_dir(Path(args.out) / "fit", prep.problem_dir, settings),
                      scheduler=args.scheduler,
                      n_workers=args.workers)
    write_json(Path(args.out) / "sweep.json", res)
    b = res["best"]
    print(f"sweep: {res['n_simulations']} points ({res['n_failed']} failed); best mean MHD "
          f"{b['objective']:.4f} mm at " + ", ".join(f"{k} = {v:.4g}"
                                                   for k, v in b["params"].items()))
    return 0
