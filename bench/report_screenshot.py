"""Render a run's report.html with headless Chromium, to look at it as a reader would.

Writes ``bench/results/report.png`` (the whole page) and prints its size. Without a report,
runs the pipeline on the small 2 mm phantom of ``tests/breastmodel/test_pipeline.py`` first
(about a minute on 2 cores).

Run: ``.venv/bin/python bench/report_screenshot.py [RUN_DIR] [--out PNG]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

_HERE = Path(__file__).resolve().parent
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir", nargs="?", type=Path, help="a finished run folder")
    p.add_argument("--out", type=Path, default=_HERE / "results" / "report.png")
    args = p.parse_args()
    from breastmodel.pipeline.report import screenshot

    run_dir = args.run_dir
    if run_dir is None:
        from breastmodel.phantom import make_phantom
        from breastmodel.pipeline import resolve_config, run_subject

        root = Path(tempfile.mkdtemp(prefix="report-bench-"))
        subj = make_phantom(root / "subject", seed=3, small=True, voxel_size=2.0,
                            progress=False)
        cfg = resolve_config({
            "segment": {"labels": str(subj) + "_truth"},
            "register": {"shrink": [2, 1], "smooth_mm": [2.0, 0.0], "iterations": 30},
            "mesh": {"size_mm": 12.0}, "surface": {"edge_mm": 4.0},
            "stress_free": {"tol_mm": 0.2, "max_iter": 10}})
        run_dir = root / "run"
        run_subject(subj, cfg, run_dir, progress=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    png = screenshot(run_dir / "report.html", args.out)
    from PIL import Image

    w, h = Image.open(png).size
    print(f"{png}: {w} x {h} px from {run_dir / 'report.html'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
