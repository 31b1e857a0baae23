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
    marker_mask_mm = 8.0       # balls around the reference markers join the mask
    shrink = [4, 2, 1]
    smooth_mm = [2.0, 1.0, 0.0]
    iterations = 50            # per level (at most)
    sampling = 0.1             # share of mask voxels at full resolution
    learning_rate_mm = 0.5     # first step per unit of shrink factor
    fine_levels = 2            # levels of the masked refinement (the finest)
    mask_margin_mm = 6.0       # chest-wall mask: band behind the muscle, mm
    marker_diameter_mm = 4.0
    fiducial_error_mm = 1.0    # smallest fiducial localisation error the checks assume
    require_fiducials = false  # stop (error) when a position's check fails ("flagged")
    seed = 20211               # metric sampling seed, >= 1 (0 would mean the wall clock)
    threads = 1                # metric threads (1: the same transform on every machine)

Each position's entry in ``registration.json`` has ``status``: ``"ok"`` (the refined
transform agrees with the fiducial-only solution at the markers and on the chest wall),
``"flagged"`` (it does not; the reasons are in ``warnings``) or ``"unchecked"`` (fewer than
three consistent fiducials found: a warning, not an error).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("breastmodel.register")

REGISTER_KEYS = {"max_residual_mm", "marker_mask_mm", "shrink", "smooth_mm", "iterations",
                 "sampling", "learning_rate_mm", "fine_levels", "mask_margin_mm",
                 "marker_diameter_mm", "seed", "threads", "fiducial_error_mm",
                 "require_fiducials"}


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
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


def read_config(path: Path | None) -> dict[str, Any]:
    from breastmodel.config import check_keys, load_toml

    if path is None:
        return {}
    cfg = dict(load_toml(path, stage="register").get("register", {}))
    check_keys(cfg, REGISTER_KEYS, where=f"register: {path} [register]")
    return cfg


def truth_transform(truth: Path, reference: str, position: str):
    """Phantom truth: reference -> position transform, ``M_pos M_ref^-1``."""
    from registration.transforms import matrix_to_transform

    path = Path(truth) / "truth.json"
    if not path.is_file():
        raise FileNotFoundError(f"register: truth file {path} does not exist")
    data = json.loads(path.read_text())["positions"]
    m = {k: np.asarray(data[k]["motion"]["matrix_patient_to_image"], float)
         for k in (reference, position)}
    return matrix_to_transform(m[position] @ np.linalg.inv(m[reference]))


def _labels_for(subject, name: str, seg_dir: Path | None, out: Path):
    """Label map of a position: from ``seg_dir`` or segmented now (and saved in out/seg)."""
    from imaging.io import read_volume

    if seg_dir is not None:
        p = Path(seg_dir) / f"{name}_labels.nii.gz"
        if p.is_file():
            return read_volume(p)
        log.warning("register: %s not found; segmenting %s now", p, name)
    from breastmodel.commands.segment import segment_position, update_summary

    seg_out = out / "segmentation"
    summary = segment_position(subject, name, seg_out)
    update_summary(seg_out, name, summary)
    return read_volume(seg_out / f"{name}_labels.nii.gz")


def register_subject(
    subject_dir: Path,
    out: Path,
    *,
    truth: Path | None = None,
    seg_dir: Path | None = None,
    config: Path | None = None,
) -> dict[str, Any]:
    """Register every position of a subject onto its reference; write the outputs."""
    import SimpleITK as sitk

    from breastmodel.config import write_json, write_provenance
    from breastmodel.errors import StageError
    from imaging.fiducials import find_fiducials
    from imaging.io import write_volume
    from imaging.preprocess import preprocess
    from imaging.subject import read_subject
    from registration.qa import rotation_error_deg, target_registration_error
    from registration.rigid import chest_wall_mask, register_rigid
    from registration.transforms import (
        gravity_in_reference,
        resample_to_reference,
        transform_to_matrix,
        write_transform,
    )

    cfg = read_config(config)
    require = cfg.get("require_fiducials", False)
    if not isinstance(require, bool):
        raise ValueError(f"register: {config} [register] require_fiducials must be true or "
                         f"false, got {require!r}")
    subject = read_subject(subject_dir)
    if require and not subject.fiducials:
        raise StageError("register", "require_fiducials = true but the subject has no "
                         "fiducials.csv", subject.root)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_provenance(out, {"register": cfg, "subject": str(subject_dir),
                           "truth": str(truth) if truth else None,
                           "seg_dir": str(seg_dir) if seg_dir else None}, command="register")
    ref = subject.reference
    diameter = float(cfg.get("marker_diameter_mm", 4.0))
    images = {}

    def prepared(name):
        if name not in images:
            raw = subject.load(name)
            images[name] = (raw, preprocess(raw, denoise_iterations=0, name=name))
        return images[name]

    ref_raw, ref_img = prepared(ref)
    ref_labels = _labels_for(subject, ref, seg_dir, out)
    mask = chest_wall_mask(ref_labels, margin_mm=float(cfg.get("mask_margin_mm", 6.0)))
    write_volume(ref_raw, out / "reference.nii.gz")
    write_volume(ref_labels, out / "reference_labels.nii.gz")

    listed = subject.fiducials or {}
    ref_fid = find_fiducials(ref_img, listed=listed.get(ref), diameter_mm=diameter)
    report: dict[str, Any] = {
        "reference": ref,
        "convention": "T maps reference-frame points (mm) to the position's image frame",
        "fiducials_reference_mm": {k: v.tolist() for k, v in ref_fid.items()},
        "positions": {},
    }
    gravity = {ref: np.asarray(subject.positions[ref].gravity, float).tolist()}
    tre_points = None
    if truth is not None:
        from imaging.io import read_volume

        tl = read_volume(Path(truth) / f"{ref}_labels.nii.gz")
        idx = np.argwhere(sitk.GetArrayViewFromImage(tl) == 2)[::97][:, ::-1]
        tre_points = np.asarray([tl.TransformContinuousIndexToPhysicalPoint(
            tuple(float(v) for v in i)) for i in idx])

    for name in subject.positions:
        if name == ref:
            continue
        log.info("register: %s -> %s", name, ref)
        raw, img = prepared(name)
        fid = find_fiducials(img, listed=listed.get(name), diameter_mm=diameter)
        opts = {k: cfg[k] for k in ("max_residual_mm", "marker_mask_mm", "iterations",
                                    "sampling", "learning_rate_mm", "fine_levels", "seed",
                                    "threads", "fiducial_error_mm")
                if k in cfg}
        if "shrink" in cfg:
            opts["shrink"] = tuple(int(v) for v in cfg["shrink"])
        if "smooth_mm" in cfg:
            opts["smooth_mm"] = tuple(float(v) for v in cfg["smooth_mm"])
        res = register_rigid(ref_img, img, fixed_points=ref_fid, moving_points=fid,
                             fixed_mask=mask, **opts)
        write_transform(res.transform, out / f"{name}.tfm")
        write_volume(resample_to_reference(raw, ref_raw, res.transform),
                     out / f"{name}_in_reference.nii.gz")
        labels = _labels_for(subject, name, seg_dir, out)
        write_volume(resample_to_reference(labels, ref_raw, res.transform, labels=True),
                     out / f"{name}_labels_in_reference.nii.gz")
        g = gravity_in_reference(res.transform, subject.positions[name].gravity)
        gravity[name] = g.tolist()
        entry: dict[str, Any] = {
            "transform": f"{name}.tfm",
            "matrix": transform_to_matrix(res.transform).tolist(),
            "initialisation": res.initialisation,
            "fiducials_used": list(res.used_labels),
            "fiducial_residuals_mm": res.fiducial_residuals,
            "fiducials_mm": {k: v.tolist() for k, v in fid.items()},
            "correlation": res.metric,
            "status": res.status,
            "checks": res.checks,
            "fiducial_only_matrix": (None if res.fiducial_transform is None else
                                     transform_to_matrix(res.fiducial_transform).tolist()),
            "gravity_reference": g.tolist(),
            "warnings": list(res.warnings),
        }
        if truth is not None:
            t = truth_transform(truth, ref, name)
            tre = target_registration_error(res.transform, t, tre_points)
            entry["tre_mm"] = {"mean": float(tre.mean()), "max": float(tre.max()),
                               "n_points": len(tre), "where": "truth chest wall (label 2)"}
            entry["rotation_error_deg"] = rotation_error_deg(res.transform, t)
        report["positions"][name] = entry
        write_json(out / "registration.json", report)
        if require and res.status == "flagged":
            why = "; ".join(res.warnings) or res.status
            raise StageError("register", f"position {name!r}: the registration is "
                             f"{res.status} ({why}); with require_fiducials = true it must "
                             "agree with the fiducials", out / "registration.json")
    report["gravity_reference"] = gravity
    write_json(out / "gravity.json", gravity)
    write_json(out / "registration.json", report)
    return report


def run(args: argparse.Namespace) -> int:
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
