"""How far the pipeline's own segmentation puts the measured skin from the truth labels', and
what that does to the fitted modulus: per subject and position, the mean signed distance of
the pipeline arm's measured skin from the truth-labels arm's (mm, + outside; over the skin
both show: closest points on the truth's rim, ``COVERAGE_RIM_MM``, left out), times the
pipeline fit's own sensitivity to a skin offset (``fit.skin_offset_sensitivity``, per mm),
beside the two arms' fitted moduli.

    python bench/validate.py --seeds 1,9 --arms pipeline --work P
    python bench/validate.py --seeds 1,9 --arms truth_labels --work T
    python bench/skin_bias.py --pipeline P --truth-labels T --subjects small-001,small-009

Prints a table and writes ``--json`` (default ``bench/results/skin_bias.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)

import numpy as np  # noqa: E402


def _skin(path: Path):
    import pyvista as pv

    m = pv.read(str(path))
    return np.asarray(m.points, float), np.asarray(m.faces.reshape(-1, 4)[:, 1:])


def signed_offset(skin: Path, truth_skin: Path) -> float:
    """Mean signed distance (mm, + outside) of ``skin``'s vertices from ``truth_skin``."""
    from scipy.spatial import cKDTree

    from breastmodel.evaluation.metrics import (
        COVERAGE_RIM_MM,
        TriangleSurface,
        boundary_distance,
        vertex_normals,
    )

    v, _ = _skin(skin)
    vt, tt = _skin(truth_skin)
    d, c = TriangleSurface(vt, tt).distance(v)
    n = vertex_normals(vt, tt)[cKDTree(vt).query(c)[1]]
    sign = np.sign(np.einsum("ij,ij->i", v - c, n))
    inner = boundary_distance(vt, tt, c) > COVERAGE_RIM_MM
    return float(np.mean((d * sign)[inner]))


def subject_row(pipeline: Path, truth: Path) -> dict:
    """Offsets per position and the modulus figures of one subject's two runs."""
    fp = json.loads((pipeline / "params.json").read_text())["fit"]
    ft = json.loads((truth / "params.json").read_text())["fit"]
    key = next(iter(fp["optimum"]))
    offsets = {f.name[: -len("_measured_skin.vtp")]: signed_offset(f, truth / f.name)
               for f in sorted(pipeline.glob("*_measured_skin.vtp"))}
    mean = float(np.mean(list(offsets.values())))
    sens = 100.0 * fp.get("skin_offset_sensitivity", {}).get(key, float("nan")) \
        / fp["optimum"][key]
    return {"parameter": key, "offset_mm": offsets, "mean_offset_mm": mean,
            "sensitivity_pct_per_mm": sens, "predicted_pct": mean * sens,
            "pipeline_vs_truth_labels_pct": {
                "optimum": 100.0 * (fp["optimum"][key] / ft["optimum"][key] - 1.0),
                "reported": 100.0 * (fp["best"]["params"][key] / ft["best"]["params"][key]
                                     - 1.0)}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pipeline", type=Path, required=True,
                    help="bench/validate.py work folder with the pipeline arm's runs")
    ap.add_argument("--truth-labels", type=Path, required=True,
                    help="bench/validate.py work folder with the truth_labels arm's runs")
    ap.add_argument("--subjects", required=True, help="comma-separated, e.g. small-001")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "results" / "skin_bias.json")
    args = ap.parse_args(argv)
    rows = {}
    print(f"{'subject':10s} {'offset mm per position':40s} {'%/mm':>7s} {'pred %':>7s} "
          f"{'pipe/truth %':>12s}")
    for name in args.subjects.split(","):
        p = args.pipeline / "runs" / name / "pipeline"
        t = args.truth_labels / "runs" / name / "truth_labels"
        if not (p / "params.json").is_file() or not (t / "params.json").is_file():
            print(f"skin_bias: {name}: no finished run under {p} and {t}", file=sys.stderr)
            return 2
        r = rows[name] = subject_row(p, t)
        offs = " ".join(f"{o:+.2f}" for o in r["offset_mm"].values())
        print(f"{name:10s} {offs:40s} {r['sensitivity_pct_per_mm']:+7.1f} "
              f"{r['predicted_pct']:+7.1f} {r['pipeline_vs_truth_labels_pct']['optimum']:+12.1f}",
              flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.json.with_suffix(".tmp")
    tmp.write_text(json.dumps(rows, indent=1), encoding="utf-8")
    os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
