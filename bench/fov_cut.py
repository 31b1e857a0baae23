"""How far the fitted model's predicted skin lies from FEBio's, near the reference scan's
field-of-view cut and away from it: is a position's miss the cut's?

For each validation run (``WORK/runs/<subject>/<arm>`` of ``bench/validate.py``) and its
subject's truth (``WORK/subjects/<subject>_truth``): the distance of every predicted skin
node (the run's cached predictions) to FEBio's skin in that position (its stress-free mesh
moved by its displacement, in the reference image's frame by the phantom's true motion, so
no registration or measured skin is involved), within ``--near-mm`` of the model's faces on
the reference label map's cut planes and elsewhere; and where the reference's field of view
cut each breast (:func:`meshing.field_of_view.breast_cut`). Prints a table and writes
``--json`` (default ``bench/results/fov_cut.json``).

    python bench/fov_cut.py W/runs/small-soft-000/truth_labels W/runs/small-000/truth_labels
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)


def _one(path: str, pattern: str) -> Path:
    found = sorted(glob.glob(str(Path(path) / pattern)))
    if not found:
        raise SystemExit(f"fov_cut: nothing matches {pattern} under {path}")
    return Path(found[0])


def measure(run: Path, truth: Path, near_mm: float) -> dict:
    """The distances of one run's predictions to FEBio's skin, near the cuts and elsewhere."""
    import SimpleITK as sitk
    from scipy.spatial import cKDTree

    from mechanics.mesh import Mesh
    from meshing import _occupancy
    from meshing.field_of_view import breast_cut
    from meshing.labels import Grid
    from meshing.sets import tet_faces
    from meshing.surface import fov_faces
    from registration.transforms import read_transform, transform_points

    mesh = Mesh.load_npz(_one(run, "cache/problem/*/mesh.npz"))
    ref = json.loads(_one(run, "cache/problem/*/problem.json").read_text())["reference"]
    grid = Grid.of(sitk.ReadImage(str(_one(run, "cache/register/*/reference_labels.nii.gz"))))
    truth_mesh = Mesh.load_npz(truth / "stress_free_mesh.npz")
    faces, _, _, _ = tet_faces(truth_mesh.tets)
    skin_faces = faces[np.all(np.isin(faces, truth_mesh.node_sets["skin"]), axis=1)]
    motion = read_transform(truth / f"{ref}_motion.tfm")
    skin = mesh.node_sets["skin"]
    bf, _, _, _ = tet_faces(mesh.tets)
    cut_nodes = np.unique(bf[fov_faces(mesh.nodes, bf, grid)])
    near = (cKDTree(mesh.nodes[cut_nodes]).query(mesh.nodes[skin])[0] < near_mm
            if len(cut_nodes) else np.zeros(len(skin), bool))
    out = {"run": str(run), "reference": ref, "cut": breast_cut(mesh, grid), "positions": {}}
    for stage in sorted(glob.glob(str(run / "cache/predict/*/stage.json"))):
        pos = json.loads(Path(stage).read_text())["config"]["position"]
        pred = np.load(Path(stage).with_name("predicted.npz"))["x"][skin]
        u = np.load(truth / f"{pos}_displacement.npy")
        moved = transform_points(motion, truth_mesh.nodes + u)
        d = _occupancy.distance(moved, skin_faces, pred)
        out["positions"][pos] = {
            part: {"n": int(m.sum()), "mean_mm": round(float(d[m].mean()), 3),
                   "p95_mm": round(float(np.percentile(d[m], 95)), 3),
                   "max_mm": round(float(d[m].max()), 3)}
            for part, m in (("near_cut", near), ("elsewhere", ~near), ("all", near | ~near))
            if m.any()}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="WORK/runs/<subject>/<arm> folders")
    ap.add_argument("--near-mm", type=float, default=15.0)
    ap.add_argument("--json", type=Path, default=ROOT / "bench/results/fov_cut.json")
    args = ap.parse_args(argv)
    from breastmodel.config import write_json

    rows = []
    for run in map(Path, args.runs):
        subject = run.parent.name
        truth = run.parents[2] / "subjects" / f"{subject}_truth"
        rows.append({"subject": subject, "arm": run.name, **measure(run, truth, args.near_mm)})
    print(f"{'subject':16} {'arm':13} {'position':18} {'cut L/R %':11} "
          f"{'near cut mean/p95/max mm':26} {'elsewhere mean/p95/max mm'}")
    for r in rows:
        cut = "/".join(f"{100 * r['cut'][s]['share']:.0f}" for s in ("left", "right")
                       if s in r["cut"])
        for pos, p in r["positions"].items():
            none = {"mean_mm": np.nan, "p95_mm": np.nan, "max_mm": np.nan}
            a, b = p.get("near_cut", none), p.get("elsewhere", none)
            print(f"{r['subject']:16} {r['arm']:13} {pos:18} {cut:11} "
                  f"{a['mean_mm']:.2f}/{a['p95_mm']:.2f}/{a['max_mm']:.2f}{'':12} "
                  f"{b['mean_mm']:.2f}/{b['p95_mm']:.2f}/{b['max_mm']:.2f}")
    write_json(args.json, {"near_mm": args.near_mm, "rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
