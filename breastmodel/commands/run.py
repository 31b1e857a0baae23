"""``breastmodel run SUBJECT --config run.toml --out DIR``: the cached subject pipeline.

segment -> register -> measured skins (the reference's mesh made beside them) -> [fit] ->
stress-free geometry -> predict every position -> metrics -> report. Writes
``DIR/metrics.json`` (per position: modified Hausdorff distance, Hausdorff, RMSE, p95 of
node-to-surface distances on the skin, per skin region, landmark errors where
``landmarks.csv`` exists), ``DIR/<position>_predicted.ply`` (reference frame),
``DIR/params.json``, ``DIR/report.html``, ``DIR/stages.json`` and the resolved config.
Stages are cached in ``DIR/cache`` by a hash of their inputs and settings: a rerun skips what
is done, a killed run resumes, a changed parameter recomputes only what depends on it.
See ``examples/run.toml`` for the config.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "run",
        help="run the whole cached pipeline on a subject (metrics, predicted surfaces, report)",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("subject", type=Path, help="subject folder (subject.toml + volumes)")
    p.add_argument("--config", type=Path, help="run config (TOML); default: built-in defaults")
    p.add_argument("--out", type=Path, required=True, help="output folder (cache inside)")
    p.add_argument("--quiet", action="store_true", help="no per-stage progress lines")
    p.add_argument("--add-effect", action="append", default=[], metavar="NAME",
                   help="switch a candidate effect on (a name from `breastmodel diagnose`, "
                        "e.g. skin, sliding, strain_stiffening:fascia, ligaments:medial) and "
                        "fit its parameters too; repeatable")
    p.add_argument("--from", dest="from_run", type=Path, metavar="DIR",
                   help="a finished run (a previous model revision): its stage cache is "
                        "shared (same segmentation, registration and mesh), its fitted model "
                        "and config start this run unless --config is given, and with "
                        "--add-effect its diagnosis' estimates start the refit")
    return p


def from_run_config(run_dir: Path) -> dict:
    """A finished run's config with its fitted model as the new starting point."""
    import json

    from breastmodel.pipeline import load_run_config, resolve_config

    cfg = load_run_config(run_dir / "config.toml", drop=("subject",))
    params = run_dir / "params.json"
    if params.is_file():
        cfg["model"] = json.loads(params.read_text())["model"]
    return resolve_config(cfg, where=f"run --from {run_dir}")


def add_effect(cfg: dict, name: str, from_run: Path | None) -> dict:
    """``cfg`` with candidate ``name`` switched on; start values from ``from_run``'s
    diagnosis (its estimate for that candidate) when there is one."""
    import json

    from breastmodel.diagnosis.candidates import add_to_config, candidate_by_name

    start = None
    diag = from_run / "diagnosis.json" if from_run else None
    if diag is not None and diag.is_file():
        ranking = json.loads(diag.read_text())["missing"]["ranking"]
        start = next((r["estimate"] for r in ranking if r["name"] == name), None)
    return add_to_config(cfg, candidate_by_name(cfg["model"], name), start=start)


def run(args: argparse.Namespace) -> int:
    from breastmodel.pipeline import load_run_config, run_subject

    cfg = load_run_config(args.config)
    if args.from_run and not args.config:
        cfg = from_run_config(args.from_run)
    for name in args.add_effect:
        cfg = add_effect(cfg, name, args.from_run)
    cache = None
    if args.from_run:
        from breastmodel.pipeline.run import cache_of

        cache = cache_of(args.from_run)
    res = run_subject(args.subject, cfg, args.out, progress=not args.quiet, cache=cache)
    ran = sum(s["status"] == "ran" for s in res["stages"])
    print(f"run: {ran} stage(s) computed, {len(res['stages']) - ran} cached, "
          f"{res['wall_s']:.1f} s")
    for pos, m in res["metrics"]["positions"].items():
        print(f"  {pos:>14}: MHD {m['mhd_mm']:.3f} mm, Hausdorff {m['hausdorff_mm']:.3f} mm, "
              f"RMSE {m['rmse_mm']:.3f} mm, p95 {m['p95_mm']:.3f} mm, over the skin both "
              f"show {m.get('mhd_overlap_mm', float('nan')):.3f} mm"
              + ("" if m.get("converged", True) else "  (NOT converged)"))
    print(f"report: {Path(args.out) / 'report.html'}")
    return 0
