"""Is a validation truth converged? One suite subject's FEBio truth on meshes of several
sizes (and, optionally, FEBio's quadratic tets on one of them), each against the finest.

    python bench/truth_refinement.py --seed 0 --sizes 5,3.5,2.5 --tet10 5 --arm

Per truth: the displacement of the finest truth's skin nodes (its stress-free mesh) against
this truth's, interpolated there (mean / p95 / max over the nodes inside both meshes, per
position); the rendered label maps against the finest's (breast Dice, mean and largest
surface distance, mm); with ``--arm`` also the validation's truth-labels arm run on it
(fitted breast modulus, MHD per position, over all the skin and over the skin both show).
Prints a table and writes ``--json`` (default ``bench/results/truth_refinement.json``).
FEBio runs single-threaded; a 2.5 mm truth of a small subject takes about 20 minutes.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)


def make(seed: int, size_mm: float, element: str, work: Path) -> Path:
    """The subject's folder (its truth beside it) with this truth mesh size and element."""
    from breastmodel.phantom import truth_solvers
    from breastmodel.validation.suite import family_maker

    truth_solvers.FEBIO_ELEMENT = element
    try:
        mk = family_maker(size="small", cache=work / "truth_cache", truth_mesh_size_mm=size_mm)
        folder, _, _ = mk(f"small-{seed}", work / f"h{size_mm:g}_{element}" / "subject")
    finally:
        truth_solvers.FEBIO_ELEMENT = "ut4"
    return folder


def displacement_gap(fine: Path, other: Path, position: str) -> dict:
    """The other truth's displacement at the finest truth's skin nodes against the finest's."""
    from breastmodel.phantom.warp import PullBack

    F = np.load(fine / "stress_free_mesh.npz")
    C = np.load(other / "stress_free_mesh.npz")
    X = F["nodes"][F["node_sets/skin"]]
    uf = np.load(fine / f"{position}_displacement.npy")[F["node_sets/skin"]]
    uc = np.load(other / f"{position}_displacement.npy")
    y, inside = PullBack(C["nodes"] + uc, C["nodes"], C["tets"])(X)
    d = np.linalg.norm((y - X) - uf, axis=1)[inside]
    return {"nodes": int(inside.sum()), "of": len(X), "mean_mm": float(d.mean()),
            "p95_mm": float(np.percentile(d, 95)), "max_mm": float(d.max()),
            "max_displacement_mm": float(np.linalg.norm(uf, axis=1).max())}


def label_gap(fine: Path, other: Path, position: str) -> dict:
    """Breast Dice and surface distances of the rendered label maps (same grid)."""
    import SimpleITK as sitk
    from scipy import ndimage as ndi

    ims = [sitk.ReadImage(str(d / f"{position}_labels.nii.gz")) for d in (fine, other)]
    sp = np.array(ims[0].GetSpacing())[::-1]
    a, b = (np.isin(sitk.GetArrayFromImage(i), (1, 3)) for i in ims)  # breast and gland
    surf = [m & ~ndi.binary_erosion(m) for m in (a, b)]
    da, db = (ndi.distance_transform_edt(~s, sampling=sp) for s in surf)
    d = np.concatenate([da[surf[1]], db[surf[0]]])
    return {"dice_breast": float(2 * (a & b).sum() / (a.sum() + b.sum())),
            "mean_mm": float(d.mean()), "max_mm": float(d.max())}


def arm(folder: Path) -> dict:
    from breastmodel.validation.suite import run_arm

    r = run_arm(folder, Path(f"{folder}_truth"), folder.parent / "truth_labels", "truth_labels")
    return {k: r.get(k) for k in ("error", "fitted", "truth_E", "mhd_mm", "mhd_overlap_mm")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sizes", default="5,3.5,2.5", help="truth mesh sizes, mm (UT4 tets)")
    ap.add_argument("--tet10", default="", help="sizes also solved with quadratic tets")
    ap.add_argument("--arm", action="store_true", help="run the truth-labels arm on each")
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "truth_refinement_work")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "results" /
                    "truth_refinement.json")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    runs = [(float(h), "ut4") for h in args.sizes.split(",")]
    runs += [(float(h), "tet10") for h in args.tet10.split(",") if h]
    runs.sort(key=lambda r: (r[0], r[1] != "ut4"))
    rows, fine = [], None
    for h, el in runs:
        t0 = time.perf_counter()
        folder = make(args.seed, h, el, args.work)
        truth = Path(f"{folder}_truth")
        fine = fine or truth
        positions = json.loads((truth / "spec.json").read_text())["positions"]
        row = {"size_mm": h, "element": el, "make_s": round(time.perf_counter() - t0, 1),
               "n_tets": int(len(np.load(truth / "stress_free_mesh.npz")["tets"])),
               "displacement": {p: displacement_gap(fine, truth, p) for p in positions},
               "labels": {p: label_gap(fine, truth, p) for p in positions}}
        if args.arm:
            row["arm"] = arm(folder)
        rows.append(row)
        print(_line(row), flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"seed": args.seed, "finest": runs[0], "rows": rows},
                                    indent=1))
    print(f"wrote {args.json}")
    return 0


def _line(row: dict) -> str:
    d = " ".join(f"{p[:6]} {v['mean_mm']:.2f}/{v['p95_mm']:.2f}/{v['max_mm']:.2f}"
                 for p, v in row["displacement"].items())
    lab = " ".join(f"{v['dice_breast']:.4f}/{v['mean_mm']:.2f}" for v in row["labels"].values())
    out = (f"{row['size_mm']:4g} mm {row['element']:5s} {row['n_tets']:6d} tets "
           f"{row['make_s']:7.1f} s | skin u gap mean/p95/max mm: {d} | labels dice/mean: {lab}")
    a = row.get("arm")
    if a and not a.get("error"):
        out += (f" | E {a['fitted']['breast_E']:.3f} MHD "
                + " ".join(f"{v:.2f}" for v in a["mhd_mm"].values()) + " shared "
                + " ".join(f"{v:.2f}" for v in a["mhd_overlap_mm"].values()))
    return out


if __name__ == "__main__":
    sys.exit(main())
