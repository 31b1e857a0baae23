"""``breastmodel compare DIR DIR2 [DIR3 ...] --out OUTDIR``: compare runs of one subject.

The runs are model revisions of one subject (same subject, same mesh), oldest first, e.g.
before and after switching an effect on. Writes ``OUTDIR/compare.json`` (per position MHD,
RMSE and p95 of every run with the changes from the previous and the first run, the effects
and parameters of every run's model, RMSE per skin region) and ``OUTDIR/compare.html`` (the
tables, MHD per position against model revision, and the error maps of every run side by
side on one colour scale). Prints the MHD table.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "compare",
        help="compare runs of one subject (model revisions): tables, error maps, MHD per revision",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("runs", type=Path, nargs="+", metavar="DIR",
                   help="run folders (breastmodel run --out), oldest model revision first")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--label", action="append", metavar="TEXT",
                   help="label of a run on the revision axis (once per run, in order; "
                        "default: what changed in the model)")
    return p


def run(args: argparse.Namespace) -> int:
    from breastmodel.diagnosis.compare import format_table, write_compare

    if len(args.runs) < 2:
        raise ValueError("compare: give at least two run folders")
    summary = write_compare(args.runs, args.out, labels=args.label)
    print(format_table(summary))
    print(f"report: {Path(args.out) / 'compare.html'}")
    return 0
