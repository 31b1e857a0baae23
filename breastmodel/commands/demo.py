"""``breastmodel demo``: the main job end to end on built-in demo data (a phantom subject).

Makes a synthetic subject, validates it, then runs the cached subject pipeline on it
(segment -> register -> mesh -> stress-free geometry -> predict every position -> metrics ->
report). A rerun reuses every finished stage.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger("breastmodel.demo")


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo",
        help="run the whole pipeline on a built-in phantom subject",
        description=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--seed", type=int, default=0, help="phantom seed (default 0)")
    p.add_argument(
        "--full",
        action="store_true",
        help="full-size phantom (default: the small, fast phantom)",
    )
    p.add_argument("--config", type=Path, help="run config (TOML); default: built-in defaults")
    return p


def run(args: argparse.Namespace) -> int:
    from breastmodel.commands import info
    from breastmodel.phantom import make_phantom
    from breastmodel.pipeline import load_run_config, run_subject

    out: Path = args.out
    subject = out / "subject"
    if not (subject / "subject.toml").exists():
        log.info("demo: writing the phantom subject to %s", subject)
        make_phantom(subject, seed=args.seed, small=not args.full)
    if info.main_info(subject) != 0:
        return 1
    res = run_subject(subject, load_run_config(args.config), out / "run", progress=True)
    print(f"\ndemo finished in {res['wall_s']:.1f} s; outputs in {(out / 'run').resolve()}")
    for pos, m in res["metrics"]["positions"].items():
        print(f"  {pos:>14}: MHD {m['mhd_mm']:.2f} mm, Hausdorff {m['hausdorff_mm']:.2f} mm, "
              f"RMSE {m['rmse_mm']:.2f} mm")
    print(f"  report: {(out / 'run' / 'report.html').resolve()}")
    return 0
