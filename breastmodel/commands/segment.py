"""``breastmodel segment``: label maps, QA pictures and tissue volumes for every position.

Writes, per position, ``OUT/<position>_labels.nii.gz`` (0 background, 1 breast, 2 muscle,
3 gland when ``gland = true``) on the input grid and ``OUT/<position>_qa.png`` (with
orientation letters), plus ``OUT/segmentation.json`` (volumes, levels, the segmentation's
own confidence: contrast-to-noise, agreement of the threshold start and the active contours,
volume plausibility; Dice with ``--truth``) and provenance. Each file
is written atomically and ``segmentation.json`` is merged per position, so a failure in one
position loses nothing already written.

Config (TOML, all optional)::

    [preprocess]
    n4 = true            # N4 bias-field correction
    n4_shrink = 4
    isotropic_mm = 1.0   # omit to keep the grid
    denoise_iterations = "auto"  # 3, or 6 on a noisy scan; or a number
    denoise_method = "gradient"   # or "curvature" (slower)

    [segment]
    gland = false
    skin_level = 0.7     # skin / fat intensity ratio
    levelset_iterations = 30
    curvature = 0.5
    marker_diameter_mm = 4.0
    contrast = "auto"    # or "fat_bright" (T1/T2-weighted), "fat_suppressed"
    positions = ["supine", "prone"]   # default: all
    stop_below_agreement = 0.5   # stop when a region's two estimates agree below this
                                 # (Dice), or the breast volume is implausible; 0: go on

A segmentation that does not hold up stops with an error naming the volume and the reason,
after its label map and QA picture are written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from breastmodel.pipeline.segment import (  # noqa: F401 - the library side, re-exported
    PREPROCESS_KEYS,
    SEGMENT_KEYS,
    read_config,
    read_seeds,
    segment_position,
    segment_subject,
    update_summary,
)


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "segment",
        help="segment breast tissue and muscle in every position of a subject",
        description=(
            "Bias-correct, denoise and segment each position's MRI volume with automatically "
            "initialised active contours. Writes OUT/<position>_labels.nii.gz (0 background, "
            "1 breast, 2 muscle/chest wall, 3 gland if enabled), OUT/<position>_qa.png and "
            "OUT/segmentation.json (tissue volumes; Dice per tissue with --truth)."
        ),
    )
    p.add_argument("subject", type=Path, help="subject folder (subject.toml + volumes)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--truth", type=Path, help="truth folder with <position>_labels.nii.gz")
    p.add_argument("--config", type=Path, help="TOML with [preprocess] and [segment] tables")
    p.add_argument("--position", action="append", dest="positions",
                   help="segment only this position (repeatable)")
    p.add_argument("--seeds", type=Path,
                   help="CSV 'position,label,x,y,z' of user seeds (mm, LPS)")
    p.add_argument("--gland", action="store_true", help="also label glandular tissue (3)")
    return p


def run(args: argparse.Namespace) -> int:
    seeds = read_seeds(args.seeds) if args.seeds else None
    res = segment_subject(args.subject, args.out, truth=args.truth, config=args.config,
                          positions=args.positions, seeds=seeds, gland=args.gland or None)
    for name, s in res.items():
        vol = ", ".join(f"{k} {v:.0f} ml" for k, v in s["volumes_ml"].items())
        dice = s.get("dice")
        extra = ("; Dice " + ", ".join(f"{k} {v:.3f}" for k, v in dice.items())) if dice else ""
        print(f"{name}: {vol}{extra}")
        for w in s.get("confidence", {}).get("warnings", []):
            print(f"  warning: {w}")
    print(f"labels and QA pictures in {args.out}")
    return 0
