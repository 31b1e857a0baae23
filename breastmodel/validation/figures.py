"""Figures of one arm of one subject, read from the pipeline's outputs and the truth."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np


def read_json(path: Path) -> dict | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def _stage_dir(out: Path, stage: Mapping[str, Any]) -> Path:
    return out / "cache" / stage["name"] / stage["key"]


def dice_per_position(stages, out: Path, truth_dir: Path) -> dict[str, dict[str, float]]:
    from imaging.io import read_volume
    from imaging.qa import dice

    res = {}
    for st in stages:
        if st["name"] != "segment" or st["status"] == "failed":
            continue
        pos = st["label"].split(" ", 1)[1]
        mine = _stage_dir(out, st) / f"{pos}_labels.nii.gz"
        truth = truth_dir / f"{pos}_labels.nii.gz"
        if mine.is_file() and truth.is_file():
            res[pos] = {k: round(v, 4) for k, v in dice(read_volume(mine),
                                                        read_volume(truth)).items()}
    return res


def chest_wall_points(truth_dir: Path, reference: str, *, every: int = 97) -> np.ndarray:
    """(n, 3) physical points (mm) of the truth chest wall (label 2) in the reference image."""
    import SimpleITK as sitk

    from imaging.io import read_volume

    tl = read_volume(truth_dir / f"{reference}_labels.nii.gz")
    idx = np.argwhere(sitk.GetArrayViewFromImage(tl) == 2)[::every][:, ::-1]
    return np.asarray([tl.TransformContinuousIndexToPhysicalPoint(tuple(map(float, i)))
                       for i in idx]).reshape(-1, 3)


def registration_figures(stages, out: Path, truth_dir: Path, reference: str) -> dict[str, dict]:
    from registration.transforms import read_transform, rigid_matrix, transform_points

    reg = next((s for s in stages if s["name"] == "register" and s["status"] != "failed"),
               None)
    if reg is None:
        return {}
    d = _stage_dir(out, reg)
    report = read_json(d / "registration.json") or {}
    pts = chest_wall_points(truth_dir, reference)
    m_ref = read_transform(truth_dir / f"{reference}_motion.tfm")
    res = {}
    for pos, entry in (report.get("positions") or {}).items():
        est = read_transform(d / f"{pos}.tfm")
        m_pos = read_transform(truth_dir / f"{pos}_motion.tfm")
        truth_pts = transform_points(m_pos, transform_points(m_ref.GetInverse(), pts))
        tre = np.linalg.norm(transform_points(est, pts) - truth_pts, axis=1)
        r_est, _ = rigid_matrix(est)
        r_true = rigid_matrix(m_pos)[0] @ rigid_matrix(m_ref)[0].T
        c = (np.trace(r_true.T @ r_est) - 1.0) / 2.0
        fid = entry.get("fiducial_residuals_mm") or {}
        res[pos] = {"tre_mean_mm": round(float(tre.mean()), 4),
                    "tre_max_mm": round(float(tre.max()), 4),
                    "rotation_error_deg": round(float(np.degrees(np.arccos(np.clip(c, -1, 1)))),
                                                4),
                    "fiducial_residual_max_mm": (round(max(fid.values()), 3) if fid else None),
                    "warnings": list(entry.get("warnings") or [])}
    return res


def truth_breast_E(truth_dir: Path) -> dict[str, float]:
    tm = read_json(truth_dir / "truth_model.json") or {}
    mats = tm.get("materials") or {}
    out = {}
    for code, side in (("1", "left"), ("3", "right")):
        if code in mats and "E" in mats[code]:
            out[side] = float(mats[code]["E"])
    from mechanics.effects import EFFECTS, effect_name

    for key, table in (tm.get("effects") or {}).items():  # effects that set a side's modulus
        cls = EFFECTS.get(effect_name(key))
        values = cls.material_values(dict(table or {})) if cls is not None else {}
        for side in ("left", "right"):
            if f"breast_{side}.E" in values:
                out[side] = float(values[f"breast_{side}.E"])
    return out


def arm_figures(arm: str, result: Mapping[str, Any], calibrate, held_out) -> dict[str, float]:
    """Flat figures of one arm (None where a stage did not get that far)."""
    f: dict[str, Any] = {"completed": 1.0 if result.get("error") is None else 0.0}
    dice = result.get("dice") or {}
    if dice:
        f["dice_breast_min"] = min(v.get("breast", np.nan) for v in dice.values())
        f["dice_muscle_min"] = min(v.get("muscle", np.nan) for v in dice.values())
    reg = result.get("registration") or {}
    if reg:
        f["tre_max_mm"] = max(v["tre_max_mm"] for v in reg.values())
        f["rotation_error_max_deg"] = max(v["rotation_error_deg"] for v in reg.values())
    fit = result.get("fitted") or {}
    truth = result.get("truth_E") or {}
    if fit.get("breast_E") is not None and truth:
        t = np.mean(list(truth.values()))
        f["breast_E_rel_error"] = abs(fit["breast_E"] - t) / t
    for key, tail in (("mhd_mm", ""), ("mhd_overlap_mm", "_overlap")):
        mhd = {p: v for p, v in (result.get(key) or {}).items() if v is not None}
        cal = [mhd[p] for p in calibrate if p in mhd]
        held = [mhd[p] for p in held_out if p in mhd]
        if cal:
            f[f"mhd_calibrated{tail}_max_mm"] = max(cal)
        if held:
            f[f"mhd_held_out{tail}_max_mm"] = max(held)
    return {k: (None if v is None or not np.isfinite(v) else round(float(v), 4))
            for k, v in f.items()}
