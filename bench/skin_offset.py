"""Does the fit's reported sensitivity to a segmentation bias hold? The measured skin of every
position of a finished run's problem moved along its normal by a known offset, the fit redone
(``breastmodel.pipeline.run.run_problem``), the change of the least squares' optimum set
beside the change the unmoved fit predicted (``params.json`` > ``fit.skin_offset_sensitivity``,
per mm), and the change of the value the fit reports (its best evaluation by MHD, up to a
Jacobian step from the optimum).

    python bench/validate.py --seeds 3 --arms truth_labels --work W   # makes W/runs/...
    python bench/skin_offset.py --runs W/runs/small-003/truth_labels --offsets=-1,1

Prints a table and writes ``--json`` (default ``bench/results/skin_offset.json``). Each run
must be a least-squares fit (the default ``run.toml``); three fits per run, each a few tens
of seconds on a small suite subject.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# bench/ holds scripts named like the packages (bench/meshing.py): not on the import path
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)


def _problem_dir(run: Path) -> Path:
    """The problem folder a finished run used: its ``stages.json``'s problem stage, in the
    run's cache (``cache/problem/<key>``)."""
    stages = json.loads((run / "stages.json").read_text()) if (run / "stages.json").is_file() \
        else {}
    keys = [s["key"] for s in stages.get("stages", []) if s.get("name") == "problem"]
    cache = Path(stages.get("cache") or run / "cache")
    if not keys or not (cache / "problem" / keys[-1] / "problem.json").is_file():
        raise SystemExit(f"skin_offset: {run} is not a finished run with its problem folder "
                         "in its cache (stages.json, cache/problem/<key>/problem.json)")
    return cache / "problem" / keys[-1]


def _fit(problem: Path, cfg: dict, out: Path) -> dict:
    """The fit block of ``params.json`` after :func:`run_problem` on ``problem``."""
    from breastmodel.pipeline.run import run_problem

    run_problem(problem, cfg, out, progress=False)
    return json.loads((out / "params.json").read_text())["fit"]


def offset_row(run: Path, offsets: list[float], scratch: Path) -> dict:
    """Fitted parameters at offset 0 and at each of ``offsets`` (mm, outward), with the
    change the offset-0 fit predicted."""
    from breastmodel.config import load_toml
    from breastmodel.evaluation.metrics import vertex_normals
    from breastmodel.pipeline.config import resolve_config
    from breastmodel.pipeline.problem import move_measured_skin

    raw = load_toml(run / "config.toml")
    raw.pop("subject", None)  # the run's record of its input, not a table
    cfg = resolve_config(raw)
    src = _problem_dir(run)
    positions = list(json.loads((src / "problem.json").read_text())["gravity"])
    t0 = time.perf_counter()
    if not cfg["fit"]["parameters"] or cfg["fit"]["method"] != "least_squares":
        raise SystemExit(f"skin_offset: {run} has no least-squares fit ([fit] method "
                         f"{cfg['fit']['method']!r}); the sensitivity comes with it only")
    base = _fit(src, cfg, scratch / "offset_0")
    # the least squares' optimum (where the sensitivity is computed), not the best
    # evaluation by MHD beside it (up to a Jacobian step, 5 %, away)
    p0, sens = base["optimum"], base.get("skin_offset_sensitivity") or {}
    row = {"run": str(run), "params": p0, "best": base["best"]["params"],
           "sensitivity_per_mm": sens, "offsets": {}}
    for s in offsets:
        prob = scratch / f"problem_{s:g}"
        shutil.copytree(src, prob)
        for p in positions:
            move_measured_skin(prob, p, lambda v, t, s=s: v + s * vertex_normals(v, t))
        fit = _fit(prob, cfg, scratch / f"offset_{s:g}")
        row["offsets"][f"{s:g}"] = {
            "termination": fit.get("termination"), "n_simulations": fit.get("n_simulations"),
            "params": {k: {"fitted": fit["optimum"][k], "best": fit["best"]["params"][k],
                           "change_pct": 100.0 * (fit["optimum"][k] / p0[k] - 1.0),
                           "predicted_pct": (100.0 * s * sens[k] / p0[k]) if k in sens
                           else None} for k in p0}}
    row["termination"], row["n_simulations"] = base.get("termination"), base.get("n_simulations")
    row["wall_s"] = round(time.perf_counter() - t0, 1)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, help="comma-separated finished run folders")
    ap.add_argument("--offsets", default="-1,1", help="outward offsets, mm")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "results" / "skin_offset.json")
    args = ap.parse_args(argv)
    offsets = [float(v) for v in args.offsets.split(",")]
    from breastmodel.config import write_json

    rows = []
    for run in [Path(r) for r in args.runs.split(",")]:
        with tempfile.TemporaryDirectory(prefix="skin_offset_") as tmp:
            rows.append(offset_row(run, offsets, Path(tmp)))
        args.json.parent.mkdir(parents=True, exist_ok=True)  # after each run (atomic)
        write_json(args.json, {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                               "rows": rows})
    print(f"{'run':32s} {'parameter':24s} {'optimum':>8s} {'offset':>7s} {'change %':>9s} "
          f"{'predicted %':>12s} {'best by MHD: change %':>22s}")
    for r in rows:
        for k, v in r["params"].items():
            for s, o in r["offsets"].items():
                q = o["params"][k]
                pred = q["predicted_pct"]
                best = 100.0 * (q["best"] / r["best"][k] - 1.0)
                print(f"{r['run'][-32:]:32s} {k[-24:]:24s} {v:8.4g} {s:>7s} "
                      f"{q['change_pct']:+9.2f} "
                      f"{'-' if pred is None else format(pred, '+.2f'):>12s} {best:+22.2f}")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
