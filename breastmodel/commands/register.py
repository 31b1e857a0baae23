"""``breastmodel register``: rigid transforms of every position into the reference frame.

Writes, per non-reference position P:

- ``OUT/P.tfm``: ITK transform mapping reference points to P's image frame (SimpleITK's
  resampling convention: ``sitk.Resample(P_image, reference_image, T)`` aligns P);
- ``OUT/P_in_reference.nii.gz`` and ``OUT/P_labels_in_reference.nii.gz``: P resampled onto
  the reference grid;

and for the subject: ``OUT/reference.nii.gz``, ``OUT/reference_labels.nii.gz``,
``OUT/gravity.json`` (every position's gravity direction in the reference frame) and
``OUT/registration.json`` (initialisation, fiducial residuals, warnings; TRE and rotation
error with ``--truth``). Every file is written atomically, position by position.

Config (TOML, all optional)::

    [register]
    max_residual_mm = 3.0      # fiducial consistency threshold
    marker_mask_mm = 8.0       # balls around the markers set what the chest wall leaves loose
    shrink = [4, 2, 1]
    smooth_mm = [2.0, 1.0, 0.0]
    iterations = 50            # per level (at most)
    sampling = 0.1             # share of mask voxels at full resolution
    learning_rate_mm = 0.5     # first step per unit of shrink factor
    fine_levels = 2            # levels of the masked refinement (the finest)
    mask_margin_mm = 6.0       # chest-wall mask: band behind the muscle, mm
    base_margin_mm = 6.0       # breasts' base that sets loose directions without markers (0: off)
    marker_diameter_mm = 4.0
    fiducial_error_mm = 1.0    # smallest fiducial localisation error the checks assume
    fiducial_fallback = true   # a refined transform that failed by sliding: use the fiducials'
    require_fiducials = false  # stop (error) when a position's check fails ("flagged")
    seed = 20211               # metric sampling seed, >= 1 (0 would mean the wall clock)
    repeats = 3                # refinements with seeds seed, seed + 1, ...; their mean is used
    spread_warn_mm = 0.25      # warn where that mean's standard error (their scatter) is larger
    threads = 0                # metric threads (0: BREASTMODEL_THREADS, else the cores); one
                               # count gives one transform bit for bit on every machine

Each position's entry in ``registration.json`` has ``status``: ``"ok"`` (the refined
transform agrees with the fiducial-only solution at the markers and on the chest wall),
``"fiducials"`` (it does not, having moved every marker alike, so the fiducial-only transform
is used; the reasons and that transform's expected error on the chest wall are in
``warnings``), ``"flagged"`` (it does not, and it was kept: the disagreement sits at one
marker, which the skin may have pulled along, or on the chest wall it is within what the
markers' localisation error alone gives 9 times in 10, or ``fiducial_fallback = false``) or
``"unchecked"`` (fewer than three consistent fiducials found: a warning, not an error).
``matrix`` is the transform used, ``refined_matrix`` the correlation's (the mean of its
``repeats``) and ``fiducial_only_matrix`` the markers'; ``seed_spread_mm`` says how far the
repeats scattered on the chest wall (``rms``, ``max``) and the mean's ``standard_error``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from breastmodel.pipeline.register import (  # noqa: F401  (importable from here too)
    REGISTER_KEYS,
    read_config,
    register_subject,
    truth_transform,
)


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """The ``register`` subcommand's arguments."""
    p = sub.add_parser(
        "register",
        help="rigidly register every position onto the reference position",
        description=(
            "Detect the skin fiducials, initialise a rigid transform from them (or from "
            "image moments, with a warning, when they are missing or inconsistent) and refine "
            "it by maximising image correlation inside a chest-wall mask. Writes "
            "OUT/<position>.tfm (reference -> position, SimpleITK resampling convention), "
            "resampled volumes and labels, gravity in the reference frame and "
            "registration.json (fiducial residuals; TRE with --truth)."
        ),
    )
    p.add_argument("subject", type=Path, help="subject folder (subject.toml + volumes)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--truth", type=Path, help="phantom truth folder (truth.json) for TRE")
    p.add_argument("--seg-dir", type=Path,
                   help="output of 'breastmodel segment' (default: segment here)")
    p.add_argument("--config", type=Path, help="TOML with a [register] table")
    return p


def run(args: argparse.Namespace) -> int:
    """Register the subject (:func:`breastmodel.pipeline.register.register_subject`) and
    print each position's status, residuals and warnings."""
    rep = register_subject(args.subject, args.out, truth=args.truth, seg_dir=args.seg_dir,
                           config=args.config)
    for name, e in rep["positions"].items():
        res = e["fiducial_residuals_mm"]
        fr = f"fiducial residual max {max(res.values()):.2f} mm" if res else "no fiducials"
        tre = f", TRE mean {e['tre_mm']['mean']:.2f} mm" if "tre_mm" in e else ""
        rot = (f", rotation error {e['rotation_error_deg']:.3f} deg"
               if "rotation_error_deg" in e else "")
        print(f"{name}: {e['status']}, initialised from {e['initialisation']}, "
              f"{fr}{tre}{rot}")
        for w in e["warnings"]:
            print(f"  warning: {w}")
    print(f"transforms in {args.out}")
    return 0
