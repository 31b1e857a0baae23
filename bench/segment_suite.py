"""The segmentation on every scan of the validation suite: contrast detected against the
truth's, Dice per tissue against the truth's label maps, and wall time (one thread).

The scans are the ones ``bench/validate.py`` made (FEBio-deformed anatomies, the suite's
fields of view, voxel shapes and contrasts); this script reads them from its work folder::

    .venv/bin/python bench/validate.py --work /data/validation        # makes the subjects
    .venv/bin/python bench/segment_suite.py --work /data/validation   # this table

Prints a table and writes bench/results/segment_suite.json. Targets (issue 14): Dice >= 0.95
breast, >= 0.90 muscle, >= 0.80 gland where labelled, on every scan; and a scan that misses
them is flagged by the segmentation's own confidence (never silently wrong).

Beyond the suite's subjects, ``--family`` renders the phantom family's specs of the given
seeds (all three positions, with their rigid motions only: no FE truth is needed to score a
segmentation; small-005's FEBio-deformed scans score within 0.01 of its rigid ones),
optionally only one field of view or contrast, under ``--work``/family::

    .venv/bin/python bench/segment_suite.py --family 0-59 --fov slab --contrast fat_bright \
        --work /tmp/family --json bench/results/segment_family_slab_fat_bright.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TARGETS = {"breast": 0.95, "muscle": 0.90, "gland": 0.80}


def segment_subject(subject: Path) -> list[dict]:
    """One row per position of ``subject`` (a folder with ``<position>.nii.gz`` and the
    truth folder ``<subject>_truth`` with ``spec.json`` and ``<position>_labels.nii.gz``)."""
    from imaging.io import read_volume
    from imaging.qa import dice
    from imaging.segment import segment_volume
    from imaging.segment_contrast import contrast_disagreement

    truth = subject.parent / f"{subject.name}_truth"
    spec = json.loads((truth / "spec.json").read_text(encoding="utf-8"))
    want = "fat_suppressed" if spec["fat_suppressed"] else "fat_bright"
    rows = []
    for scan in sorted(subject.glob("*.nii.gz")):
        pos = scan.name[: -len(".nii.gz")]
        t0 = time.perf_counter()
        res = segment_volume(read_volume(scan), gland=True, name=str(scan))
        wall = time.perf_counter() - t0
        d = dice(res.labels, read_volume(truth / f"{pos}_labels.nii.gz"))
        rows.append({"subject": subject.name, "position": pos, "fov": spec["fov"],
                     "contrast": f"{spec['contrast']}{'-fs' if spec['fat_suppressed'] else ''}",
                     "truth_contrast": want, "detected": res.contrast,
                     "dice": {k: round(float(v), 4) for k, v in d.items()},
                     "wall_s": round(wall, 2), "confident": res.confidence["confident"],
                     "agreement": {k: round(float(v), 4)
                                   for k, v in res.confidence["agreement"].items()},
                     "notes": list(res.notes)})
    said = contrast_disagreement({r["position"]: r["detected"] for r in rows})
    for r in rows if said else ():  # as the pipeline marks them (read_confidences)
        r["confident"] = False
        r["notes"].append(said)
    return rows


def _seeds(text: str) -> list[int]:
    """"0-59" or "5,12,18" (or both, joined by commas)."""
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi) + 1)) if hi else [int(lo)]
    return out


def render_family(seeds, work: Path, *, fov: str | None = None,
                  contrast: str | None = None) -> list[Path]:
    """Subject folders of the family's small specs of ``seeds`` (only ``fov`` and
    ``contrast``, "fat_bright" or "fat_suppressed", where given), rendered with rigid
    motion only under ``work``/family, each with its truth's ``spec.json`` (made once)."""
    from breastmodel.phantom.family import draw_spec, make_rigid_subject

    subjects = []
    for seed in seeds:
        spec = draw_spec(seed, size="small")
        kind = "fat_suppressed" if spec.fat_suppressed else "fat_bright"
        if (fov and spec.fov != fov) or (contrast and kind != contrast):
            continue
        subject = work / "family" / f"small-{seed:03d}"
        if not (subject.parent / f"{subject.name}_truth" / "spec.json").is_file():
            make_rigid_subject(spec, subject)
        subjects.append(subject)
    return subjects


def _met(row: dict, tissue: str, bound: float) -> bool:
    """The tissue's Dice meets its bound, or the tissue is not labelled (no figure)."""
    return not row["dice"].get(tissue, float("nan")) < bound


def meets(row: dict) -> bool:
    return all(_met(row, k, v) for k, v in TARGETS.items())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=ROOT / "bench" / "validation_work",
                    help="bench/validate.py's work folder (its subjects/ are read)")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "results" / "segment_suite.json")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--family", type=_seeds, default=None,
                    help="render the family's specs of these seeds (0-59, or 5,12) instead")
    ap.add_argument("--fov", choices=("torso", "coil", "slab"), default=None)
    ap.add_argument("--contrast", choices=("fat_bright", "fat_suppressed"), default=None)
    args = ap.parse_args(argv)
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(args.threads)
    if args.family is not None:
        subjects = render_family(args.family, args.work, fov=args.fov, contrast=args.contrast)
    else:
        subjects = sorted(p for p in (args.work / "subjects").glob("*")
                          if p.is_dir() and not p.name.endswith("_truth")
                          and (p.parent / f"{p.name}_truth" / "spec.json").exists())
    if not subjects:
        print(f"bench/segment_suite.py: no subjects under {args.work / 'subjects'}: run "
              "bench/validate.py --work with this folder first", file=sys.stderr)
        return 2
    rows = []
    print(f"{'subject':10s} {'position':18s} {'fov':6s} {'contrast':7s} {'detected':15s} "
          f"{'breast':>6s} {'muscle':>6s} {'gland':>6s} {'s':>5s}  target, confidence")
    for subject in subjects:
        for r in segment_subject(subject):
            rows.append(r)
            d = r["dice"]
            ok = "detected" if r["detected"] == r["truth_contrast"] else "MISREAD"
            print(f"{r['subject']:10s} {r['position']:18s} {r['fov']:6s} {r['contrast']:7s} "
                  f"{r['detected']:15s} {d['breast']:6.3f} {d['muscle']:6.3f} "
                  f"{d.get('gland', float('nan')):6.3f} {r['wall_s']:5.1f}  "
                  f"{'met' if meets(r) else 'missed'} ({ok}), "
                  f"{'confident' if r['confident'] else 'flagged'}", flush=True)
    summary = {"scans": len(rows),
               "contrast_right": sum(r["detected"] == r["truth_contrast"] for r in rows),
               "targets_met": sum(meets(r) for r in rows),
               "missed_and_flagged": sum(not meets(r) and not r["confident"] for r in rows),
               "missed_silently": sum(not meets(r) and r["confident"] for r in rows),
               "met_but_flagged": sum(meets(r) and not r["confident"] for r in rows),
               **{f"{k}_met": sum(_met(r, k, v) for r in rows) for k, v in TARGETS.items()}}
    print(json.dumps(summary))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.json.with_suffix(".tmp")
    tmp.write_text(json.dumps({"targets": TARGETS, "threads": args.threads,
                               "family": args.family, "fov": args.fov,
                               "contrast": args.contrast, "summary": summary, "rows": rows},
                              indent=1), encoding="utf-8")
    os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
