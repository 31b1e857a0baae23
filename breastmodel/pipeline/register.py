"""The register stage: rigid transforms of every position of a subject into the reference
frame, written with the resampled volumes, gravity in the reference frame and
``registration.json`` (the files and the ``[register]`` config are described in
:mod:`breastmodel.commands.register`, the command that calls :func:`register_subject`)."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from imaging.subject import Subject

log = logging.getLogger("breastmodel.register")

REGISTER_KEYS = {"max_residual_mm", "marker_mask_mm", "shrink", "smooth_mm", "iterations",
                 "sampling", "learning_rate_mm", "fine_levels", "mask_margin_mm",
                 "marker_diameter_mm", "seed", "threads", "fiducial_error_mm",
                 "require_fiducials", "fiducial_fallback", "base_margin_mm", "repeats",
                 "spread_warn_mm"}
#: Depth of the breast tissue in front of the chest wall that sets the directions the wall
#: leaves loose (a torso's body axis) where no fiducial does, mm (``[register]
#: base_margin_mm``; 0: none, those directions stay the wall's)
BASE_MARGIN_MM = 6.0
#: ``[register]`` keys passed to :func:`registration.rigid.register_rigid` as they are.
_RIGID_KEYS = ("max_residual_mm", "marker_mask_mm", "iterations", "sampling",
               "learning_rate_mm", "fine_levels", "seed", "threads", "fiducial_error_mm",
               "fiducial_fallback", "repeats", "spread_warn_mm")


def read_config(path: Path | Mapping[str, Any] | None) -> dict[str, Any]:
    """The ``[register]`` table of a TOML file (empty without one), or the table itself
    when given as a mapping, its keys checked."""
    from breastmodel.config import check_keys, load_toml

    if path is None:
        return {}
    where = "register: [register]"
    if isinstance(path, Mapping):
        cfg = dict(path)
    else:
        cfg = dict(load_toml(path, stage="register").get("register", {}))
        where = f"register: {path} [register]"
    check_keys(cfg, REGISTER_KEYS, where=where)
    for key in ("require_fiducials", "fiducial_fallback"):
        if key in cfg and not isinstance(cfg[key], bool):
            raise ValueError(f"{where} {key} must be true or false, got {cfg[key]!r}")
    t = cfg.get("threads", 0)
    if isinstance(t, bool) or not isinstance(t, int) or t < 0:
        raise ValueError(f"{where} threads must be a whole number >= 0 (0: "
                         f"BREASTMODEL_THREADS, else the cores), got {t!r}")
    return cfg


def with_threads(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The ``[register]`` table with ``threads`` resolved: the setting (0 or absent: the
    environment's ``BREASTMODEL_THREADS``, else the cores, as the solver's,
    :func:`mechanics.threads.resolve_threads`). The correlation's sums depend on it (two
    counts end about 1e-9 mm apart), so the stage's cache key holds the count used."""
    from mechanics.threads import resolve_threads

    return {**cfg, "threads": resolve_threads(cfg.get("threads") or None)}


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
    from breastmodel.pipeline.segment import segment_position, update_summary

    seg_out = out / "segmentation"
    summary = segment_position(subject, name, seg_out)
    update_summary(seg_out, name, summary)
    return read_volume(seg_out / f"{name}_labels.nii.gz")


def register_subject(subject_dir: Path | Subject, out: Path, *, truth: Path | None = None,
                     seg_dir: Path | None = None, config: Path | Mapping | None = None) -> dict:
    """Register every position of a subject onto its reference; write the outputs.

    Parameters
    ----------
    subject_dir : Path or imaging.subject.Subject
        Subject folder (``subject.toml`` and volumes), or the subject already read.
    out : Path
        Output folder (made if missing); each file is written atomically, as it is done.
    truth : Path, optional
        Phantom truth folder (``truth.json``): adds TRE and rotation error per position.
    seg_dir : Path, optional
        Folder of ``<position>_labels.nii.gz``; positions without one are segmented here.
    config : Path or mapping, optional
        TOML with a ``[register]`` table, or that table.

    Returns
    -------
    dict
        The report also written to ``registration.json``.

    Raises
    ------
    breastmodel.errors.StageError
        With ``require_fiducials = true``: the subject has no fiducials, or a position's
        registration is "flagged" (failed a check, kept by ``fiducial_fallback = false``).
    """
    from breastmodel.config import write_json, write_provenance
    from breastmodel.errors import StageError
    from imaging.fiducials import find_fiducials
    from imaging.io import write_volume
    from imaging.subject import Subject, read_subject

    cfg = with_threads(read_config(config))
    require = cfg.get("require_fiducials", False)
    subject = subject_dir if isinstance(subject_dir, Subject) else read_subject(subject_dir)
    if require and not subject.fiducials:
        raise StageError("register", "require_fiducials = true but the subject has no "
                         "fiducials.csv", subject.root)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_provenance(out, {"register": cfg, "subject": str(subject.root),
                           "truth": str(truth) if truth else None,
                           "seg_dir": str(seg_dir) if seg_dir else None}, command="register")
    ref = subject.reference
    diameter = float(cfg.get("marker_diameter_mm", 4.0))
    images: dict = {}
    ref_raw, ref_img = _prepared(subject, ref, images)
    ref_labels = _labels_for(subject, ref, seg_dir, out)
    mask, base = _masks(ref_labels, cfg)
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
    tre_points = None if truth is None else _truth_points(truth, ref)
    for name in subject.positions:
        if name == ref:
            continue
        entry, res = _register_position(
            subject, name, images, out, ref_raw=ref_raw, ref_img=ref_img, ref_fid=ref_fid,
            mask=mask, base=base, seg_dir=seg_dir, cfg=cfg, truth=truth, tre_points=tre_points)
        gravity[name] = list(entry["gravity_reference"])
        report["positions"][name] = entry
        write_json(out / "registration.json", report)
        if require and res.status == "flagged":
            _stop(name, res, out / "registration.json")
    report["gravity_reference"] = gravity
    write_json(out / "gravity.json", gravity)
    write_json(out / "registration.json", report)
    return report


def _masks(ref_labels, cfg: dict):
    """The chest-wall mask that drives the registration, and the one with the breasts'
    base that sets the directions the wall leaves loose where no marker does (None with
    ``base_margin_mm = 0``)."""
    from registration.masks import chest_wall_masks

    base_mm = float(cfg.get("base_margin_mm", BASE_MARGIN_MM))
    masks = chest_wall_masks(ref_labels, margin_mm=float(cfg.get("mask_margin_mm", 6.0)),
                             breast_margins_mm=(0.0, base_mm) if base_mm > 0 else (0.0,))
    return masks[0], (masks[1] if base_mm > 0 else None)


def _stop(name: str, res, report_path: Path) -> None:
    """Raise: with ``require_fiducials`` a position's registration must pass its checks."""
    from breastmodel.errors import StageError

    why = "; ".join(res.warnings) or res.status
    raise StageError("register", f"position {name!r}: the registration is "
                     f"{res.status} ({why}); with require_fiducials = true it must "
                     "agree with the fiducials (check the overlays in the report; "
                     "[register] require_fiducials = false accepts the kept transform)",
                     report_path)



def _rigid_options(cfg: dict) -> dict[str, Any]:
    """Keyword options of :func:`registration.rigid.register_rigid` from ``[register]``."""
    opts = {k: cfg[k] for k in _RIGID_KEYS if k in cfg}
    if "shrink" in cfg:
        opts["shrink"] = tuple(int(v) for v in cfg["shrink"])
    if "smooth_mm" in cfg:
        opts["smooth_mm"] = tuple(float(v) for v in cfg["smooth_mm"])
    return opts


def _prepared(subject, name: str, images: dict):
    """(raw volume, registration copy) of a position, read and preprocessed once (no
    denoising) and kept in ``images``."""
    from imaging.preprocess import preprocess

    if name not in images:
        raw = subject.load(name)
        images[name] = (raw, preprocess(raw, denoise_iterations=0, name=name))
    return images[name]


def _truth_points(truth: Path, reference: str) -> np.ndarray:
    """(N, 3) mm: every 97th muscle voxel of the truth's reference label map, where the TRE
    is measured."""
    import SimpleITK as sitk

    from imaging.io import read_volume

    tl = read_volume(Path(truth) / f"{reference}_labels.nii.gz")
    idx = np.argwhere(sitk.GetArrayViewFromImage(tl) == 2)[::97][:, ::-1]
    return np.asarray([tl.TransformContinuousIndexToPhysicalPoint(
        tuple(float(v) for v in i)) for i in idx])


def _register_position(subject, name, images, out, *, ref_raw, ref_img, ref_fid, mask, base,
                       seg_dir, cfg, truth, tre_points):
    """Register one position onto the reference and write its transform and its volume
    and labels resampled onto the reference grid. Returns (its report entry, the
    :class:`registration.rigid.RigidResult`)."""
    from breastmodel.config import write_atomic
    from imaging.fiducials import find_fiducials
    from imaging.io import write_volume
    from registration.rigid import register_rigid
    from registration.transforms import (
        gravity_in_reference,
        resample_to_reference,
        transform_text,
    )

    log.info("register: %s -> %s", name, subject.reference)
    raw, img = _prepared(subject, name, images)
    listed = subject.fiducials or {}
    fid = find_fiducials(img, listed=listed.get(name),
                         diameter_mm=float(cfg.get("marker_diameter_mm", 4.0)))
    res = register_rigid(ref_img, img, fixed_points=ref_fid, moving_points=fid,
                         fixed_mask=mask, base_mask=base, **_rigid_options(cfg))
    write_atomic(out / f"{name}.tfm", transform_text(res.transform))
    write_volume(resample_to_reference(raw, ref_raw, res.transform),
                 out / f"{name}_in_reference.nii.gz")
    labels = _labels_for(subject, name, seg_dir, out)
    write_volume(resample_to_reference(labels, ref_raw, res.transform, labels=True),
                 out / f"{name}_labels_in_reference.nii.gz")
    g = gravity_in_reference(res.transform, subject.positions[name].gravity)
    entry = _entry(name, res, fid, g)
    if truth is not None:
        _add_truth_errors(entry, res.transform, truth, subject.reference, name, tre_points)
    return entry, res


def _entry(name: str, res, fid: dict, g: np.ndarray) -> dict[str, Any]:
    """A position's ``registration.json`` entry."""
    from registration.transforms import transform_to_matrix

    return {
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
        "refined_matrix": transform_to_matrix(res.refined_transform).tolist(),
        "seed_spread_mm": res.spread,
        "gravity_reference": g.tolist(),
        "warnings": list(res.warnings),
    }


def _add_truth_errors(entry: dict, tfm, truth: Path, reference: str, name: str,
                      tre_points: np.ndarray) -> None:
    """TRE on the truth's chest wall and rotation error against the phantom's motion."""
    from registration.qa import rotation_error_deg, target_registration_error

    t = truth_transform(truth, reference, name)
    tre = target_registration_error(tfm, t, tre_points)
    entry["tre_mm"] = {"mean": float(tre.mean()), "max": float(tre.max()),
                       "n_points": len(tre), "where": "truth chest wall (label 2)"}
    entry["rotation_error_deg"] = rotation_error_deg(tfm, t)
