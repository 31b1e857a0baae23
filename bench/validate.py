"""The validation suite: subjects whose truth FEBio computed, through the whole pipeline.

    python bench/validate.py                       # 12 small subjects, seeds 0-11
    python bench/validate.py --size full --subjects 12 --work /data/validation
    python bench/validate.py --seeds 3,7 --force   # redo two subjects
    python bench/validate.py --band soft --seeds 0,3,8 --json bench/results/validate_soft.json

Each subject is drawn from the phantom family (``breastmodel.phantom.family``: field of view,
anatomy, voxels, contrast, motion, tilt, all from the seed), its truth deformation computed by
FEBio 4 (``--febio`` or ``$FEBIO``, else ``../shared/febio/febio4``) on a finer mesh than the
fitted one, then run twice through ``breastmodel run`` (own segmentation; truth labels).
``--band soft`` draws the same subjects with the soft band's breast moduli
(``breastmodel.phantom.family.MODULUS_BANDS``: twice the sag), named ``small-soft-<seed>``.
Prints a table and writes ``--json`` (default ``bench/results/validate.json``) plus one
result per subject under ``--work``/results (a rerun resumes: finished subjects are read
back; truths and pipeline stages are cached too).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# bench/ holds scripts named like the packages (bench/meshing.py): not on the import path
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)


def _size(text: str) -> float | str:
    return "auto" if text == "auto" else float(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subjects", type=int, default=12, help="seeds 0..N-1 (default 12)")
    ap.add_argument("--seeds", default=None, help="comma-separated seeds (overrides --subjects)")
    ap.add_argument("--size", choices=("small", "full"), default="small")
    ap.add_argument("--band", choices=("standard", "soft"), default="standard",
                    help="the breast modulus' band of the family (default standard)")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "validation_work")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "results" / "validate.json")
    ap.add_argument("--febio", default=None, help="FEBio 4 executable (default $FEBIO, then "
                    "../shared/febio/febio4)")
    ap.add_argument("--arms", default="pipeline,truth_labels",
                    help="comma-separated: pipeline, truth_labels, reference_truth (the "
                         "reference's truth label map alone, the other positions segmented)")
    ap.add_argument("--mesh-size", type=_size, default="auto",
                    help="fitted model's tet edge, mm, or auto (the pipeline's default)")
    ap.add_argument("--force", action="store_true",
                    help="re-evaluate finished subjects (the pipeline's stage cache under "
                         "WORK/runs is keyed by inputs and settings, not by code: delete it "
                         "to rerun stages after a code change)")
    ap.add_argument("--markdown", action="store_true", help="print the table as markdown")
    ap.add_argument("--progress", action="store_true")
    ap.add_argument("--register", default="{}",
                    help='JSON: [register] keys over the run\'s defaults, e.g. '
                         '\'{"require_fiducials": false}\'')
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    os.environ.setdefault("OMP_NUM_THREADS", "2")

    from breastmodel.febio import find_febio
    from breastmodel.validation import family_maker, format_table, run_suite

    try:
        febio = str(find_febio(args.febio))
    except (FileNotFoundError, ValueError) as exc:
        print(f"validate: {exc}", file=sys.stderr)
        return 2
    register = json.loads(args.register)
    seeds = ([int(s) for s in args.seeds.split(",")] if args.seeds
             else list(range(args.subjects)))
    tag = "" if args.band == "standard" else f"{args.band}-"
    names = [f"{args.size}-{tag}{s:03d}" for s in seeds]
    make = family_maker(size=args.size, febio=febio, cache=args.work / "truth_cache",
                        band=args.band)
    t0 = time.perf_counter()

    def show(res):
        print(format_table([res]), flush=True)

    results = run_suite(names, make, args.work, arms=args.arms.split(","),
                        mesh_size_mm=args.mesh_size, force=args.force, progress=args.progress,
                        on_result=show, register=register)
    print()
    print(format_table(results, markdown=args.markdown))
    met = [t for r in results for t in r.get("targets", [])]
    summary = {}
    for t in met:
        k = f"{t['arm']}:{t['figure']} ({'<=' if t['kind'] == 'max' else '>='} {t['bound']})"
        s = summary.setdefault(k, {"met": 0, "missed": 0, "no figure": 0, "issue": t["issue"]})
        s["met" if t["met"] else ("no figure" if t["met"] is None else "missed")] += 1
    print("\ntargets (subjects met / missed / no figure):")
    for k, s in summary.items():
        print(f"  issue {s['issue']}: {k}: {s['met']} / {s['missed']} / {s['no figure']}")
    from breastmodel.config import write_json

    args.json.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.json, {"size": args.size, "band": args.band, "seeds": seeds,
                           "register": register,
                           "wall_s": time.perf_counter() - t0,
                           "targets": summary, "subjects": results})
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
