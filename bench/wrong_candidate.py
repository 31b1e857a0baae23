"""Benchmark: does the held-out position tell a right effect from a wrong one?

Issue 16 asks that adding a wrong candidate and refitting does not improve the position
that was not fitted, shown with a deliberately wrong candidate of the same parameter count
as the right one. This bench takes finished runs of ``bench/diagnosis_matrix.py --suite
febio`` (FEBio truths with a known hidden effect, or none) and refits each with candidates
switched on, the way a user does (``breastmodel run --from RUN --add-effect NAME``: the
run's own fit, calibrated on its calibration positions, the others predicted), and reports
per refit the held-out positions' MHD before and after and the worst MHD over every scored
position. A candidate "improves" the held-out position when it lowers its MHD by more than
0.02 mm (the diagnosis' least drop, ``SIGNIFICANT_MIN_MM``).

    python bench/diagnosis_matrix.py --suite febio --cases regions:asymmetry,none \
        --seeds 3,8,0 --out M --results M/matrix.json
    python bench/wrong_candidate.py --runs M/regions_asymmetry-3/run,... \
        --right regions:asymmetry --wrong strain_stiffening,parameter:materials.muscle.E

A run whose truth is "none" (the folder's name starts ``none``) has no right candidate:
every candidate is wrong there. Prints a table and writes ``--json`` (default
``bench/results/wrong_candidate.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from breastmodel.commands.run import add_effect, from_run_config  # noqa: E402
from breastmodel.config import write_json  # noqa: E402
from breastmodel.diagnosis import load_run  # noqa: E402
from breastmodel.diagnosis.scoring import SIGNIFICANT_MIN_MM  # noqa: E402
from breastmodel.pipeline.run import cache_of, run_problem  # noqa: E402


def _mhd(metrics: dict) -> dict:
    return {p: m.get("mhd_mm") for p, m in metrics["positions"].items()}


def _n_fitted(cfg: dict) -> int:
    return len(cfg["fit"]["parameters"]) if cfg["fit"].get("enabled") else 0


def refit(run, name: str, out: Path) -> dict:
    """The finished ``run``'s model with candidate ``name`` switched on, refitted as the run
    was."""
    base = from_run_config(run.out)
    cfg = add_effect(base, name, run.out)
    t0 = time.perf_counter()
    res = run_problem(run.problem_dir, cfg, out, progress=False, cache=cache_of(run.out))
    params = json.loads((out / "params.json").read_text())
    return {"candidate": name, "added_parameters": _n_fitted(cfg) - _n_fitted(base),
            "mhd_mm": _mhd(res["metrics"]), "params": params.get("parameters"),
            "fit_termination": (params.get("fit") or {}).get("termination"),
            "seconds": time.perf_counter() - t0}


def study(run_dir: Path, names: list[str], right: str | None, work: Path) -> dict:
    run = load_run(run_dir)
    held = list(run.config["fit"].get("evaluate") or [])
    before = _mhd(run.metrics)
    rows = []
    for name in names:
        r = refit(run, name, work / f"{run_dir.parent.name}-{name.replace(':', '_')}")
        r["right"] = name == right
        r["held_out"] = {p: {"before_mm": before[p], "after_mm": r["mhd_mm"][p]} for p in held
                         if p in before and p in r["mhd_mm"]}
        r["improves_held_out"] = bool(r["held_out"]) and all(
            v["after_mm"] < v["before_mm"] - SIGNIFICANT_MIN_MM for v in r["held_out"].values())
        r["worst_before_mm"] = max(before.values())
        r["worst_after_mm"] = max(r["mhd_mm"].values())
        rows.append(r)
        h = next(iter(r["held_out"].values()), {"before_mm": float("nan"),
                                                 "after_mm": float("nan")})
        print(f"{run_dir.parent.name:<24} {name:<30} {'right' if r['right'] else 'wrong':<5} "
              f"{r['added_parameters']:>3} {h['before_mm']:7.3f} -> {h['after_mm']:6.3f} "
              f"{r['worst_before_mm']:7.3f} -> {r['worst_after_mm']:6.3f} "
              f"{'yes' if r['improves_held_out'] else 'no':>4} {r['seconds']:6.0f}", flush=True)
    return {"run": str(run_dir), "held_out": held, "right": right, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, help="comma list of finished run folders")
    ap.add_argument("--right", required=True,
                    help="the candidate the hidden effect calls for (runs named none-*: none)")
    ap.add_argument("--wrong", required=True, help="comma list of wrong candidates")
    ap.add_argument("--work", type=Path, default=Path("/tmp/wrong_candidate"))
    ap.add_argument("--json", type=Path, default=_HERE / "results" / "wrong_candidate.json")
    args = ap.parse_args(argv)
    wrong = [w for w in args.wrong.split(",") if w]
    runs = [Path(r) for r in args.runs.split(",") if r]
    missing = [str(r) for r in runs if not (r / "params.json").is_file()]
    if missing:
        ap.error(f"not finished runs (no params.json): {missing}")
    print(f"{'run':<24} {'candidate':<30} {'':<5} {'+k':>3} {'held-out MHD mm':>17} "
          f"{'worst MHD mm':>17} {'impr':>4} {'s':>6}")
    studies = []
    for r in runs:
        none = r.parent.name.startswith("none")
        right = None if none else args.right
        names = [args.right] + [w for w in wrong if w != args.right]
        studies.append(study(r, names, right, args.work))
        write_json(args.json, {"studies": studies, "least_drop_mm": SIGNIFICANT_MIN_MM,
                               "machine": platform.node(), "cpus": os.cpu_count(),
                               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())})
    rows = [x for s in studies for x in s["rows"]]
    right_ok = [x["improves_held_out"] for x in rows if x["right"]]
    wrong_bad = [x["improves_held_out"] for x in rows if not x["right"]]
    print(f"right candidates improving the held-out position: {sum(right_ok)} of "
          f"{len(right_ok)}; wrong ones: {sum(wrong_bad)} of {len(wrong_bad)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
