"""Registration on the validation suite: each position's chest-wall TRE against the truth for
the transform the stage uses, the correlation's (refined) and the markers' (fiducial-only).

    python bench/register_suite.py --work bench/validation_work           # seeds 0-11
    python bench/register_suite.py --size full --seeds 0 --arms truth_labels,pipeline
    python bench/register_suite.py --seeds 7,10 --register '{"base_margin_mm": 0}'
    python bench/register_suite.py --family '{"snr": 10000, "bias": 0}' --work W2 \
        --cache bench/validation_work/truth_cache                 # clean images, same truth

``--seed-study K`` measures the refinement's sampling instead: each position registered
once per sampling seed (``[register] repeats = 1``, seeds 20211 ... 20211 + K - 1, the
pipeline arm on its first run's segmentation), with each seed's chest-wall TRE (max), their
mean, and the TRE of the mean transform of the first 3 and of all K seeds
(:func:`registration.repeats.mean_transform`): what ``repeats`` buys on this suite.

``--family`` overrides fields of the drawn subjects (``breastmodel.phantom.family.draw_spec``):
with the noise and the bias field taken out (the same anatomy, motions and FEBio truth), what
is left of the TRE is the anatomy's own deformation between positions and the partial-volume
images, the floor of a rigid registration of what the scans show.

Subjects come from the phantom family as in ``bench/validate.py`` (their FEBio truth cached
under ``--work``/truth_cache; the same ``--work`` reuses them). Arms: ``truth_labels`` (the
chest-wall mask from the truth's label maps) and ``pipeline`` (from ``segment``'s). The
default ``[register]`` config, except ``require_fiducials = false`` so that every position
is measured. Prints a table and writes ``--json`` (default
``bench/results/register_suite.json``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# bench/ holds scripts named like the packages (bench/meshing.py): not on the import path
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)


def position_row(entry: dict, truth_tfm, points: np.ndarray) -> dict:
    """TRE (mean, max, mm) of the used, refined and fiducial-only transforms of one
    ``registration.json`` entry against the truth at ``points``, with the chest-wall figures
    its checks hold (the two transforms' difference, its expected size and null spread)."""
    from registration.qa import target_registration_error
    from registration.transforms import matrix_to_transform

    row = {"status": entry["status"], "seed_spread_mm": entry.get("seed_spread_mm")}
    checks = entry.get("checks") or {}
    for key in ("chest_wall_shift_mm", "expected_tre_mm", "chest_wall_null_mm"):
        if key in checks:                   # what the fallback decided on (rigid._checked)
            row[key] = {k: round(float(v), 3) for k, v in checks[key].items()}
    for key, what in (("matrix", "used"), ("refined_matrix", "refined"),
                      ("fiducial_only_matrix", "fiducials")):
        if entry.get(key) is None:
            row[what] = None
            continue
        tre = target_registration_error(matrix_to_transform(np.asarray(entry[key])),
                                        truth_tfm, points)
        row[what] = {"mean": round(float(tre.mean()), 3), "max": round(float(tre.max()), 3)}
    return row


def register_one(name: str, make, work: Path, arm: str, config: dict | None = None) -> dict:
    """Every position of subject ``name`` registered in ``arm`` (``config``: more
    ``[register]`` keys): {position: row}."""
    from breastmodel.pipeline.register import _truth_points, register_subject, truth_transform

    subject, truth, _ = make(name, work / "subjects" / name)
    out = work / "register_suite" / arm / name
    rep = register_subject(subject, out, truth=truth,
                           seg_dir=truth if arm == "truth_labels" else None,
                           config={"require_fiducials": False, **(config or {})})
    points = _truth_points(truth, rep["reference"])
    return {p: position_row(e, truth_transform(truth, rep["reference"], p), points)
            for p, e in rep["positions"].items()}


def seed_study(name: str, make, work: Path, arm: str, k: int,
               config: dict | None = None) -> dict:
    """Every position of ``name`` registered once per sampling seed (one repeat each):
    {position: {"seeds": [max TRE], "mean_of_seeds", "mean_transform_3", "mean_transform"}}."""
    from breastmodel.pipeline.register import _truth_points, register_subject, truth_transform
    from registration.qa import target_registration_error
    from registration.repeats import mean_transform
    from registration.transforms import matrix_to_transform

    subject, truth, _ = make(name, work / "subjects" / name)
    base = work / "seed_study" / arm / name
    seg = truth if arm == "truth_labels" else None
    reps = []
    for s in range(20211, 20211 + k):
        out = base / str(s)
        reps.append(register_subject(subject, out, truth=truth, seg_dir=seg, config={
            "require_fiducials": False, **(config or {}), "repeats": 1, "seed": s}))
        seg = seg or out / "segmentation"
    ref = reps[0]["reference"]
    points = _truth_points(truth, ref)
    rows = {}
    for p in reps[0]["positions"]:
        t = truth_transform(truth, ref, p)
        tfms = [matrix_to_transform(np.asarray(r["positions"][p]["refined_matrix"]))
                for r in reps]

        def tre(x, t=t):
            return round(float(target_registration_error(x, t, points).max()), 3)

        each = [tre(x) for x in tfms]
        centre = np.zeros(3)
        rows[p] = {"seeds": each, "mean_of_seeds": round(float(np.mean(each)), 3),
                   "mean_transform_3": tre(mean_transform(tfms[:3], centre)),
                   "mean_transform": tre(mean_transform(tfms, centre))}
    return rows


def _spread(s: dict | None) -> str:
    """The repeats' standard error on the chest wall (mm), or "-"."""
    return "-" if not s else f"{s['standard_error']:.2f}"


def _seed_study_main(args, make, extra: dict, family: dict) -> int:
    """``--seed-study``: the table of each position's single-seed TREs and their means, a
    summary over every registration, and the JSON."""
    from breastmodel.config import write_json

    k, rows = args.seed_study, []
    print(f"{'subject':10s} {'arm':12s} {'position':18s} max TRE (mm): each of {k} seeds | "
          "their mean | mean transform of 3 | of all")
    for seed in (int(s) for s in args.seeds.split(",")):
        name = f"{args.size}-{seed:03d}"
        for arm in args.arms.split(","):
            for pos, r in seed_study(name, make, args.work, arm, k, extra).items():
                rows.append({"subject": name, "arm": arm, "position": pos, **r})
                print(f"{name:10s} {arm:12s} {pos:18s} "
                      + " ".join(f"{v:.2f}" for v in r["seeds"])
                      + f" | {r['mean_of_seeds']:.2f} | {r['mean_transform_3']:.2f} | "
                      f"{r['mean_transform']:.2f}", flush=True)
    summary = {key: round(float(np.mean([r[key] for r in rows])), 3)
               for key in ("mean_of_seeds", "mean_transform_3", "mean_transform")}
    summary["mean_transform_no_worse"] = sum(r["mean_transform"] <= r["mean_of_seeds"]
                                             for r in rows)
    summary["registrations"] = len(rows)
    print("over every registration, mean of the max TRE (mm): one seed "
          f"{summary['mean_of_seeds']:.3f}, the mean transform of 3 seeds "
          f"{summary['mean_transform_3']:.3f}, of {k} {summary['mean_transform']:.3f}; the mean "
          f"transform no worse than the seeds' mean on {summary['mean_transform_no_worse']} "
          f"of {len(rows)}")
    write_json(args.json, {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                           "size": args.size, "register": extra, "family": family,
                           "seed_study": k, "summary": summary, "rows": rows})
    print(f"wrote {args.json}")
    return 0


def _cell(t: dict | None) -> str:
    return "-" if t is None else f"{t['mean']:.2f}/{t['max']:.2f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default=",".join(str(s) for s in range(12)))
    ap.add_argument("--size", choices=("small", "full"), default="small")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "validation_work")
    ap.add_argument("--arms", default="truth_labels")
    ap.add_argument("--febio", default=None)
    ap.add_argument("--register", default="{}",
                    help='JSON: more [register] keys, e.g. \'{"base_margin_mm": 0}\'')
    ap.add_argument("--cache", type=Path, default=None,
                    help="truth cache (default WORK/truth_cache)")
    ap.add_argument("--family", default="{}",
                    help='JSON: fields of the drawn subjects, e.g. \'{"snr": 10000, "bias": 0}\'')
    ap.add_argument("--seed-study", type=int, default=0, metavar="K",
                    help="register each position once per sampling seed, K seeds (see above)")
    ap.add_argument("--json", type=Path,
                    default=ROOT / "bench" / "results" / "register_suite.json")
    args = ap.parse_args(argv)
    extra = json.loads(args.register)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    os.environ.setdefault("OMP_NUM_THREADS", "2")
    from breastmodel.config import write_json
    from breastmodel.febio import find_febio
    from breastmodel.validation import family_maker

    family = json.loads(args.family)
    make = family_maker(size=args.size, febio=str(find_febio(args.febio)),
                        cache=args.cache or args.work / "truth_cache", **family)
    if args.seed_study:
        return _seed_study_main(args, make, extra, family)
    rows = []
    print(f"{'subject':10s} {'arm':12s} {'position':18s} {'status':10s} "
          f"{'TRE used':>12s} {'refined':>12s} {'fiducials':>12s} {'seeds se':>10s}"
          "   (mean/max mm)")
    for seed in (int(s) for s in args.seeds.split(",")):
        name = f"{args.size}-{seed:03d}"
        for arm in args.arms.split(","):
            try:
                got = register_one(name, make, args.work, arm, extra)
            except Exception as exc:  # noqa: BLE001  (a subject that fails is a row)
                rows.append({"subject": name, "arm": arm, "error": f"{type(exc).__name__}: "
                             f"{exc}"[:200]})
                print(f"{name:10s} {arm:12s} {rows[-1]['error']}")
                continue
            for pos, r in got.items():
                rows.append({"subject": name, "arm": arm, "position": pos, **r})
                print(f"{name:10s} {arm:12s} {pos:18s} {r['status']:10s} "
                      f"{_cell(r['used']):>12s} {_cell(r['refined']):>12s} "
                      f"{_cell(r['fiducials']):>12s} {_spread(r['seed_spread_mm']):>10s}",
                      flush=True)
    write_json(args.json, {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                           "size": args.size, "register": extra, "family": family,
                           "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
