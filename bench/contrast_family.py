"""The contrast reader (:func:`imaging.segment_contrast.detect_contrast`) on the phantom
family's scans: each scan's skin / subcutaneous ratio against the contrast it was rendered
in, and the subjects whose scans read different contrasts
(:func:`imaging.segment_contrast.contrast_disagreement`), without segmenting (about 2
minutes for seeds 0-59 on one core, rendering included)::

    .venv/bin/python bench/contrast_family.py --family 0-59 --work /tmp/family \
        --json bench/results/contrast_family.json

Prints one row per misread scan and a summary; writes every scan's row to ``--json``.
The scans are rendered as ``bench/segment_suite.py --family`` renders them (same folders,
so the two share a ``--work``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from segment_suite import ROOT, _seeds, render_family  # noqa: E402


def read_scan(scan: Path) -> tuple[str, dict]:
    """The contrast read on ``scan`` preprocessed as :func:`imaging.segment.segment_volume`
    preprocesses it by default, and the numbers that decided it."""
    import inspect

    import numpy as np
    import SimpleITK as sitk

    from imaging.io import read_volume
    from imaging.segment import segment_volume
    from imaging.segment_contrast import detect_contrast, prepare_volume

    keys = ("crop", "n4", "n4_shrink", "n4_cache", "isotropic_mm", "denoise_iterations",
            "denoise_method")
    default = inspect.signature(segment_volume).parameters
    pre = prepare_volume(read_volume(scan), [], name=str(scan),
                         **{k: default[k].default for k in keys})[0]
    return detect_contrast(sitk.GetArrayFromImage(pre),
                           np.asarray(pre.GetSpacing(), float)[::-1],
                           direction=pre.GetDirection())


def main(argv=None) -> int:
    from imaging.segment_contrast import contrast_disagreement

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--family", type=_seeds, default=_seeds("0-59"))
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "validation_work")
    ap.add_argument("--json", type=Path,
                    default=ROOT / "bench" / "results" / "contrast_family.json")
    args = ap.parse_args(argv)
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    rows, subjects = [], []
    for subject in render_family(args.family, args.work):
        spec = json.loads((subject.parent / f"{subject.name}_truth" / "spec.json").read_text())
        want = "fat_suppressed" if spec["fat_suppressed"] else "fat_bright"
        read = {}
        for scan in sorted(subject.glob("*.nii.gz")):
            pos = scan.name[: -len(".nii.gz")]
            read[pos], why = read_scan(scan)
            rows.append({"subject": subject.name, "position": pos, "truth": want,
                         "read": read[pos], "ratio": round(why.get("ratio", float("nan")), 3),
                         "contrast": spec["contrast"], "voxel_mm": spec["voxel_size"],
                         "fov": spec["fov"]})
            if read[pos] != want:
                print(f"{subject.name} {pos:18s} {spec['contrast']:3s} {want:15s} read "
                      f"{read[pos]:15s} ratio {rows[-1]['ratio']:.3f}", flush=True)
        said = contrast_disagreement(read)
        subjects.append({"subject": subject.name, "disagree": bool(said),
                         "misread": sum(c != want for c in read.values())})
    summary = {"scans": len(rows), "misread": sum(r["read"] != r["truth"] for r in rows),
               "subjects": len(subjects),
               "subjects_disagreeing": sum(s["disagree"] for s in subjects),
               "misread_in_disagreeing": sum(s["misread"] for s in subjects if s["disagree"]),
               "misread_in_agreeing": sum(s["misread"] for s in subjects if not s["disagree"])}
    print(json.dumps(summary))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.json.with_suffix(".tmp")
    tmp.write_text(json.dumps({"family": args.family, "summary": summary, "subjects": subjects,
                               "rows": rows}, indent=1), encoding="utf-8")
    os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
