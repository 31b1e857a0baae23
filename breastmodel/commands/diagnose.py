"""``breastmodel diagnose DIR``: where a run's model fails, and which physical effect is missing.

DIR is the output folder of ``breastmodel run``. Writes ``DIR/diagnosis.json`` and
``DIR/diagnosis.html``: signed skin error maps of every position from anterior, lateral and
inferior views on one colour scale, tables per position and skin region (quadrants,
inframammary fold, nipple area, left/right) with normal and tangential parts and error
against local strain; then every registered effect the model does not use, and every
parameter it holds fixed, ranked by how much of the residual it explains after re-fitting,
with the predicted error per position, the evidence per region, a real check of the best
candidate, and a plain verdict when nothing explains more than the noise floor. Errors of
the measurement are candidates too: a rigid misregistration of each position and an offset
of the measured skin; and so is the mesh (mesh_refinement: the fitted model again on a mesh
of half the edge length, cached in the run; --no-refinement skips it). Every candidate's
score charges its parameters (an information criterion) and is checked on the position the
run held out; every model evaluation has a budget of forward solves and seconds. Where no
candidate is significant on the skin, the internal landmarks (landmarks.csv) are a witness:
the candidates the skin favours are re-fitted, and one that brings the landmarks, which no
fit saw, clearly closer in every position is named.
Model evaluations are stored in ``DIR/diagnosis/evaluations`` (a rerun resumes).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "diagnose",
        help="show where a run fails and rank the physical effects that would fix it",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run_dir", type=Path, metavar="DIR", help="a `breastmodel run` output folder")
    p.add_argument("--workers", type=int, default=0,
                   help="local dask workers for the model evaluations (default 0: in this "
                        "process)")
    p.add_argument("--scheduler", help="address of a running dask scheduler (tcp://host:8786)")
    p.add_argument("--verify-top", type=int, default=1,
                   help="check this many of the best candidates by a real evaluation")
    p.add_argument("--rim-mm", type=float, default=None,
                   help="leave skin nodes this close to the skin's open edge (the field-of-view "
                        "cut) out of the ranking, mm (default 15; 0 keeps all)")
    p.add_argument("--max-solves", type=int, default=None,
                   help="forward solves one model evaluation may spend (default: 3x the fitted "
                        "model's own evaluation, at least 4 more)")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="seconds one model evaluation may spend (default: 3x the fitted "
                        "model's own evaluation, at least 20 s); an evaluation that spends "
                        "its budget fails with the reason and the others still answer")
    p.add_argument("--no-refinement", dest="refine", action="store_false",
                   help="do not probe the mesh (the candidate mesh_refinement: the fitted "
                        "model again on a mesh of half the edge length, about 8x the tets, "
                        "at most about 150k; cached in the run, so a run made with "
                        "[evaluate] refinement = true has it already)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def run(args: argparse.Namespace) -> int:
    from breastmodel.diagnosis.diagnose import diagnose

    d = diagnose(args.run_dir, n_workers=args.workers, scheduler=args.scheduler,
                 verify_top=args.verify_top, rim_mm=args.rim_mm, max_solves=args.max_solves,
                 max_seconds=args.max_seconds, refine=args.refine, progress=not args.quiet)
    m = d["missing"]
    print(m["verdict"])
    print(f"{'#':>3} {'candidate':<40} {'k':>2} {'explained':>9} {'dBIC':>7} {'pred. RMS':>9}"
          "  significant")
    for i, r in enumerate(m["ranking"][:10], 1):
        print(f"{i:3d} {r['name']:<40} {r['n_parameters']:2d} {100 * r['explained']:8.0f}% "
              f"{r['delta_bic']:7.1f} {r['predicted_rms_mm']:9.3f}"
              f"  {'yes' if r['significant'] else 'no'}")
    for f in m["failed"]:
        print(f"failed: {f['name']}: {f['error']}")
    print(f"report: {Path(args.run_dir) / 'diagnosis.html'}")
    return 0
