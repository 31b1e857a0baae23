"""Starts of a rigid registration: a least-squares fit of labelled fiducials
(:func:`landmark_transform`, dropping inconsistent markers), or, without them, matched body
centroids and the best of a set of rotations (:func:`moments_transform`)."""

from __future__ import annotations

import itertools
from collections.abc import Mapping

import numpy as np
import SimpleITK as sitk

from registration.qa import fiducial_residuals
from registration.transforms import STAGE, rigid_matrix


def _to_euler(tfm: sitk.Transform, center: np.ndarray) -> sitk.Euler3DTransform:
    r, t = rigid_matrix(tfm)
    u, _, vt = np.linalg.svd(r)  # nearest rotation (guards against round-off)
    r = u @ vt
    e = sitk.Euler3DTransform()
    e.SetCenter(tuple(float(c) for c in center))
    e.SetMatrix(r.ravel().tolist(), 1e-6)
    # T(x) = R(x - c) + c + t_e  must equal  R x + t
    e.SetTranslation(tuple(t - center + r @ center))
    return e


def landmark_transform(
    fixed_points: Mapping[str, np.ndarray],
    moving_points: Mapping[str, np.ndarray],
    *,
    max_residual_mm: float = 3.0,
) -> tuple[sitk.Euler3DTransform | None, tuple[str, ...], list[str]]:
    """Least-squares rigid fit of labelled points, fixed -> moving.

    Uses every shared label; if a residual exceeds ``max_residual_mm`` (a mislabelled or
    misdetected marker), tries dropping markers one at a time and keeps the best consistent
    subset of at least three.

    Returns
    -------
    transform or None, labels used, warnings
    """
    notes: list[str] = []
    shared = sorted(set(fixed_points) & set(moving_points))
    if len(shared) < 3:
        notes.append(f"only {len(shared)} fiducial label(s) shared with the reference "
                     f"(need 3): {shared}")
        return None, (), notes
    best = None
    for k in range(len(shared), 2, -1):
        for subset in itertools.combinations(shared, k):
            fx = np.asarray([fixed_points[s] for s in subset], float)
            mv = np.asarray([moving_points[s] for s in subset], float)
            init = sitk.LandmarkBasedTransformInitializer(
                sitk.VersorRigid3DTransform(), fx.ravel().tolist(), mv.ravel().tolist()
            )
            res = fiducial_residuals(init, dict(zip(subset, fx)), dict(zip(subset, mv)))
            worst = max(res.values())
            if worst <= max_residual_mm and (best is None or worst < best[0]):
                best = (worst, subset, init, fx.mean(axis=0))
        if best is not None:
            break
    if best is None:
        notes.append(f"fiducials are inconsistent with a rigid motion (residual > "
                     f"{max_residual_mm} mm for every subset of >= 3 of {shared})")
        return None, (), notes
    _, subset, init, centre = best
    if len(subset) < len(shared):
        notes.append(f"fiducial(s) {sorted(set(shared) - set(subset))} dropped: inconsistent "
                     "with the others (mislabelled or misdetected)")
    return _to_euler(init, centre), tuple(subset), notes


def _mask_centroid(img: sitk.Image, mask: sitk.Image | None) -> np.ndarray:
    m = sitk.OtsuThreshold(img, 0, 1) if mask is None else sitk.Cast(mask > 0, sitk.sitkUInt8)
    stats = sitk.LabelShapeStatisticsImageFilter()
    stats.Execute(m)
    if not stats.HasLabel(1):
        raise ValueError(f"{STAGE}: empty mask, cannot initialise the registration")
    return np.asarray(stats.GetCentroid(1))


def moments_transform(
    fixed: sitk.Image,
    moving: sitk.Image,
    *,
    fixed_mask: sitk.Image | None = None,
    angles_deg: tuple[float, ...] = (-15.0, 0.0, 15.0),
    shrink: int = 4,
) -> sitk.Euler3DTransform:
    """Initialise without fiducials: match body centroids, then try rotations about the
    centroid (every combination of ``angles_deg`` about x, y, z) and keep the best
    correlation on a shrunken copy.
    """
    cf = _mask_centroid(fixed, None)
    cm = _mask_centroid(moving, None)
    small_f = sitk.Shrink(sitk.SmoothingRecursiveGaussian(fixed, 2.0), [shrink] * 3)
    small_m = sitk.Shrink(sitk.SmoothingRecursiveGaussian(moving, 2.0), [shrink] * 3)
    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsCorrelation()
    reg.SetInterpolator(sitk.sitkLinear)
    if fixed_mask is not None:
        reg.SetMetricFixedMask(sitk.Resample(fixed_mask, small_f, sitk.Transform(),
                                             sitk.sitkNearestNeighbor))
    best = None
    for ax, ay, az in itertools.product(angles_deg, repeat=3):
        e = sitk.Euler3DTransform(tuple(cf), *np.radians([ax, ay, az]), tuple(cm - cf))
        reg.SetInitialTransform(e, inPlace=False)
        try:
            val = reg.MetricEvaluate(small_f, small_m)
        except RuntimeError:  # too few overlapping samples
            continue
        if best is None or val < best[0]:
            best = (val, e)
    if best is None:
        raise RuntimeError(f"{STAGE}: moments initialisation found no overlap between volumes")
    return best[1]

