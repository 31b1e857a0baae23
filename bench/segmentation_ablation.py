"""Which voxels of the reference's segmentation move the fitted modulus: the suite's fit rerun
with the reference position's label map swapped piece by piece between the truth and the
pipeline's own segmentation (every other position keeps its truth labels, so the measured
skins are the same in every row).

    python bench/validate.py --seeds 4,9 --arms pipeline,truth_labels --work W  # first
    python bench/segmentation_ablation.py --work W --subjects small-004,small-009

Rows per subject (the reference's label map the mesh is built from):

- ``truth``: the truth labels;
- ``pipeline``: the pipeline's own segmentation;
- ``truth + spill``: the truth with the voxels the pipeline calls muscle where the truth has
  breast tissue (the *spill*) set to muscle;
- ``truth + skin spill`` / ``truth + fat spill``: the spill's voxels whose phantom tissue is
  skin / the others (fat, gland);
- ``pipeline - spill``: the pipeline's segmentation with the spill given back to the breast;
- ``truth + outline``: the truth with the pipeline's body outline (every voxel that is air in
  one of the two and tissue in the other takes the pipeline's label), and split:
  ``truth + muscle outline`` (those where either says muscle: the muscle's back and front
  where it meets air) and ``truth + breast outline`` (the others: the skin over the breast);
- ``truth + cut faces``: the truth with the pipeline's labels on the label map's six
  field-of-view faces (the one-voxel layers a scan cut the body at, where an active contour
  meets the image's edge);
- ``truth + muscle to breast``: the truth with the voxels the truth calls muscle and the
  pipeline breast tissue given to the breast (the spill's reverse).

``--rows`` runs a subset (the ``truth`` row is always run: the others are read against it).

Prints the fitted modulus of each row (and its change from the ``truth`` row), the spill's
size and the mean offset of the pipeline's breast-muscle interface from the truth's (face
centres, mm, positive into the breast). Writes ``--json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)

import numpy as np  # noqa: E402

SKIN_CODE = 4  # the phantom's fine tissue code of skin (breastmodel.phantom.anatomy.SKIN)


def _read(path: Path):
    import SimpleITK as sitk

    img = sitk.ReadImage(str(path))
    return img, sitk.GetArrayFromImage(img)


def _interface_faces(labels: np.ndarray) -> np.ndarray:
    """Centres of the faces between muscle and breast tissue voxels, (N, 3) in index units."""
    pts = []
    for ax in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[ax], hi[ax] = slice(0, -1), slice(1, None)
        a, b = labels[tuple(lo)], labels[tuple(hi)]
        idx = np.argwhere(((a == 2) & np.isin(b, (1, 3))) | ((b == 2) & np.isin(a, (1, 3))))
        idx = idx.astype(float)
        idx[:, ax] += 0.5
        pts.append(idx)
    return np.vstack(pts)


def _interface_offset_mm(truth: np.ndarray, own: np.ndarray, spacing_zyx) -> float:
    """Mean signed distance of the pipeline's breast-muscle faces from the truth muscle's
    boundary (mm; positive: outside the truth muscle, into the breast), less that of the
    truth's own faces (the distance map's bias on the voxel grid)."""
    from scipy import ndimage

    sp = np.asarray(spacing_zyx, float)
    muscle = truth == 2
    half = 0.5 * sp.min()  # voxel centres half a voxel from the boundary
    sdf = np.where(muscle, half - ndimage.distance_transform_edt(muscle, sampling=sp),
                   ndimage.distance_transform_edt(~muscle, sampling=sp) - half)
    mean = [float(ndimage.map_coordinates(sdf, f.T, order=1).mean()) if len(f) else 0.0
            for f in (_interface_faces(own), _interface_faces(truth))]
    return mean[0] - mean[1]


def variants(truth: np.ndarray, own: np.ndarray, tissue: np.ndarray) -> dict[str, np.ndarray]:
    """The reference label maps of the rows (see the module's docstring)."""
    spill = np.isin(truth, (1, 3)) & (own == 2)
    skin = spill & (tissue == SKIN_CODE)
    out = {"truth": truth, "pipeline": own}
    for name, part in [("truth + spill", spill), ("truth + skin spill", skin),
                       ("truth + fat spill", spill & ~skin)]:
        a = truth.copy()
        a[part] = 2
        out[name] = a
    a = own.copy()
    a[spill] = 1
    out["pipeline - spill"] = a
    outline = (truth == 0) != (own == 0)
    by_muscle = outline & ((truth == 2) | (own == 2))
    faces = np.zeros(truth.shape, bool)
    for ax in range(3):
        ends = [slice(None)] * 3
        ends[ax] = [0, -1]
        faces[tuple(ends)] = True
    for name, part in [("truth + outline", outline), ("truth + muscle outline", by_muscle),
                       ("truth + breast outline", outline & ~by_muscle),
                       ("truth + cut faces", faces & (truth != own)),
                       ("truth + muscle to breast", (truth == 2) & np.isin(own, (1, 3)))]:
        a = truth.copy()
        a[part] = own[part]
        out[name] = a
    return out


def ablate(work: Path, name: str, out: Path, rows: list[str] | None = None) -> dict:
    """The rows of one subject of a validation work folder (its pipeline arm run first);
    ``rows``: a subset of :func:`variants`' names (None: all)."""
    import SimpleITK as sitk

    from breastmodel.pipeline.run import run_subject
    from breastmodel.validation import suite_config
    from breastmodel.validation.figures import truth_breast_E
    from imaging.subject import read_subject

    subject_dir, truth_dir = work / "subjects" / name, work / "subjects" / f"{name}_truth"
    subject = read_subject(subject_dir)
    ref, positions = subject.reference, list(subject.positions)
    own_path = work / "runs" / name / "pipeline" / f"{ref}_labels_in_reference.nii.gz"
    if not own_path.is_file():
        raise SystemExit(f"segmentation_ablation: {own_path} is missing: run "
                         f"bench/validate.py --arms pipeline on {name} first")
    img, truth = _read(truth_dir / f"{ref}_labels.nii.gz")
    _, own = _read(own_path)
    _, tissue = _read(truth_dir / f"{ref}_tissue.nii.gz")
    spill = np.isin(truth, (1, 3)) & (own == 2)
    res = {"subject": name, "reference": ref,
           "spill_voxels": int(spill.sum()),
           "skin_spill_voxels": int((spill & (tissue == SKIN_CODE)).sum()),
           "interface_offset_mm": _interface_offset_mm(truth, own, img.GetSpacing()[::-1]),
           "truth_E": truth_breast_E(truth_dir).get("left"),
           "rows": {}}
    maps = variants(truth, own, tissue)
    unknown = sorted(set(rows or ()) - set(maps))
    if unknown:
        raise SystemExit(f"segmentation_ablation: unknown rows {unknown}; known {list(maps)}")
    res["changed_voxels"] = {row: int((m != truth).sum()) for row, m in maps.items()}
    for row, labels in maps.items():
        if rows and row != "truth" and row not in rows:
            continue
        d = out / name / row.replace(" ", "_").replace("+", "plus").replace("-", "minus")
        (d / "labels").mkdir(parents=True, exist_ok=True)
        for pos in positions:
            if pos != ref:
                src = truth_dir / f"{pos}_labels.nii.gz"
                (d / "labels" / src.name).write_bytes(src.read_bytes())
        new = sitk.GetImageFromArray(labels.astype(np.uint8))
        new.CopyInformation(img)
        sitk.WriteImage(new, str(d / "labels" / f"{ref}_labels.nii.gz"))
        cfg = suite_config("truth_labels", d / "labels", positions, ref)
        run_subject(subject_dir, cfg, d / "run", progress=False)
        params = json.loads((d / "run" / "params.json").read_text())
        res["rows"][row] = params["parameters"]["materials.breast_left.E"]
        logging.info("%s %s: E %.3f kPa", name, row, res["rows"][row])
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="a bench/validate.py work folder")
    ap.add_argument("--subjects", required=True, help="comma-separated, e.g. small-004")
    ap.add_argument("--out", type=Path, default=None, help="default WORK/ablation")
    ap.add_argument("--rows", default=None,
                    help="comma-separated row names (default: all), e.g. 'pipeline,truth + spill'")
    ap.add_argument("--json", type=Path,
                    default=ROOT / "bench" / "results" / "segmentation_ablation.json")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    os.environ.setdefault("OMP_NUM_THREADS", "2")
    out = args.out or args.work / "ablation"
    rows = args.rows.split(",") if args.rows else None
    results = [ablate(args.work, n, out, rows) for n in args.subjects.split(",")]
    print("| reference label map | " + " | ".join(r["subject"] for r in results) + " |")
    print("|---|" + "---|" * len(results))
    print("| spill voxels (skin) | " + " | ".join(
        f"{r['spill_voxels']} ({r['skin_spill_voxels']})" for r in results) + " |")
    print("| interface offset mm | " + " | ".join(
        f"{r['interface_offset_mm']:+.2f}" for r in results) + " |")
    print("| truth E kPa | " + " | ".join(f"{r['truth_E']}" for r in results) + " |")
    for row in results[0]["rows"]:
        cells = [f"{r['rows'][row]:.3f} ({100 * (r['rows'][row] / r['rows']['truth'] - 1):+.1f} %"
                 f", {r['changed_voxels'][row]} voxels)" for r in results]
        print(f"| fit with {row} | " + " | ".join(cells) + " |")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    from breastmodel.config import write_json

    write_json(args.json, {"command": " ".join(sys.argv), "results": results})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
