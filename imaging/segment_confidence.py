"""What a segmentation says of itself: the agreement of each region's two methods, a
plausible breast volume (:func:`segmentation_confidence`), and the breast volume by side."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from imaging.labels import BREAST, GLAND, MUSCLE
from imaging.segment_contrast import NOISY_SIGMA

#: Plausible breast-tissue volume of one scan, ml (both sides; a small phantom has ~20 ml).
BREAST_ML_RANGE = (5.0, 6000.0)
#: Agreement (Dice) of each region's two estimates below which the segmentation says it is
#: of low confidence. The body's boundary (air against skin) is the sharpest edge of a scan:
#: on the validation suite's 33 scans (bench/segment_suite.py) its two estimates agreed to
#: 0.968-0.996 on the scans that met the Dice targets (so one is flagged needlessly) and to
#: 0.917-0.968 on the 15 that missed them, save one whose muscle agreed to 0.23.
MIN_AGREEMENT = {"body": 0.97, "muscle": 0.9}


def _dice(x: np.ndarray, y: np.ndarray) -> float:
    n = int(np.count_nonzero(x)) + int(np.count_nonzero(y))
    return 1.0 if n == 0 else 2.0 * int(np.count_nonzero(x & y)) / n


def segmentation_confidence(
    *,
    cnr: float,
    body: tuple[np.ndarray, np.ndarray],
    muscle: tuple[np.ndarray, np.ndarray],
    breast_ml: float,
    min_agreement: float | dict | None = None,
    noise: float | None = None,
    breast_behind_wall_mm: float | None = None,
) -> dict:
    """How far to trust a segmentation, from what it knows itself.

    Parameters
    ----------
    cnr : float
        Contrast-to-noise ratio of tissue against background (:func:`contrast_to_noise`).
    body, muscle : (start, final) pairs of bool arrays
        Each region's threshold initialisation and its active-contour result: two
        segmentations of one region from two methods; their Dice is the agreement.
    breast_ml : float
        Breast tissue volume (labels 1 and 3), ml.
    min_agreement : float or dict region -> float, optional
        Dice below which a region's agreement is a warning (default :data:`MIN_AGREEMENT`).
    noise : float, optional
        The background's noise sigma (fraction of the fat level) after the usual denoising;
        above :data:`imaging.segment_contrast.NOISY_SIGMA` a warning: the suite's one such
        scan (small-002, 2 mm voxels, SNR 13) missed the breast's Dice target (0.93-0.94)
        with both regions' estimates agreeing.
    breast_behind_wall_mm : float, optional
        How far the breast tissue's median lies behind the muscle's along the posterior
        axis, mm (:func:`breast_behind_wall_mm`); at 0 or more a warning: the breasts lie in
        front of the chest wall in every body (the validation suite's 36 truth label maps:
        7.5-30 mm in front), and a contrast read wrong segments them behind it while both
        regions' estimates agree (small-000 at SNR 300 read fat bright: 9 mm behind,
        agreement 0.995 / 0.969).

    Returns
    -------
    dict
        ``cnr``, ``agreement`` (Dice per region), ``breast_ml``, ``breast_ml_plausible``
        (within ``BREAST_ML_RANGE``), ``breast_behind_wall_mm``, ``breast_in_front`` (it is
        below 0 or unknown), ``warnings`` and ``confident`` (no warning).
    """
    agree = {"body": _dice(*body), "muscle": _dice(*muscle)}
    floor = dict(MIN_AGREEMENT) if min_agreement is None else (
        dict(min_agreement) if isinstance(min_agreement, dict)
        else dict.fromkeys(agree, float(min_agreement)))
    lo, hi = BREAST_ML_RANGE
    plausible = lo <= breast_ml <= hi
    warnings = [f"low confidence: the {k}'s active contour and its threshold start agree "
                f"only to Dice {v:.3f} (< {floor[k]:g})"
                for k, v in agree.items() if v < floor[k]]
    if noise is not None and noise > NOISY_SIGMA:
        warnings.append(f"low confidence: noisy scan (background sigma {noise:.3g} of the fat "
                        f"level > {NOISY_SIGMA}): boundaries uncertain by about a voxel")
    if not plausible:
        warnings.append(f"low confidence: {breast_ml:.1f} ml of breast tissue is outside the "
                        f"plausible {lo:g}-{hi:g} ml")
    behind = breast_behind_wall_mm
    in_front = behind is None or behind < 0
    if not in_front:
        warnings.append(f"low confidence: the breast tissue lies {behind:.1f} mm behind the "
                        "chest wall (median depths along the posterior axis; breasts lie in "
                        "front of it): was the contrast read right? ([segment] contrast = "
                        "\"fat_bright\" or \"fat_suppressed\" sets it)")
    return {"cnr": float(cnr), "agreement": agree, "breast_ml": float(breast_ml),
            "noise": float(noise) if noise is not None and np.isfinite(noise) else None,
            "breast_ml_plausible": bool(plausible),
            "breast_behind_wall_mm": None if behind is None else float(behind),
            "breast_in_front": bool(in_front),
            "warnings": warnings, "confident": not warnings}


def breast_behind_wall_mm(labels: np.ndarray, spacing_zyx, posterior: tuple[int, bool]
                          ) -> float | None:
    """How far the median of the breast tissue (labels 1 and 3) lies behind the median of
    the muscle (2) along the posterior array axis ``posterior`` = (axis, runs anterior), mm;
    negative in front, None without either."""
    axis, flip = posterior
    depth = []
    for m in ((labels == BREAST) | (labels == GLAND), labels == MUSCLE):
        per_slice = np.count_nonzero(np.moveaxis(m, axis, 0).reshape(m.shape[axis], -1), axis=1)
        if per_slice.sum() == 0:
            return None
        med = float(np.searchsorted(np.cumsum(per_slice), 0.5 * per_slice.sum()))
        depth.append(-med if flip else med)
    return (depth[0] - depth[1]) * float(np.asarray(spacing_zyx, float)[axis])


def breast_volumes_by_side(labels: sitk.Image, midline_x_mm: float) -> dict[str, float]:
    """Breast tissue (labels 1 and 3) volume left and right of the sagittal midline, ml."""
    a = sitk.GetArrayViewFromImage(labels)
    idx = np.argwhere((a == BREAST) | (a == GLAND))
    if len(idx) == 0:
        return {"breast_left": 0.0, "breast_right": 0.0}
    d = np.asarray(labels.GetDirection()).reshape(3, 3)
    x = labels.GetOrigin()[0] + (idx[:, ::-1] * np.asarray(labels.GetSpacing())) @ d[0]
    vox = float(np.prod(labels.GetSpacing())) / 1000.0
    return {"breast_left": float(np.count_nonzero(x > midline_x_mm) * vox),
            "breast_right": float(np.count_nonzero(x <= midline_x_mm) * vox)}
