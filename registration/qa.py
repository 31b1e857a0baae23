"""Registration quality: fiducial residuals, target registration error, rotation error."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import SimpleITK as sitk

from registration.transforms import rigid_matrix, transform_points


def fiducial_residuals(
    tfm: sitk.Transform,
    fixed: Mapping[str, np.ndarray],
    moving: Mapping[str, np.ndarray],
) -> dict[str, float]:
    """Distance (mm) between ``tfm(fixed[label])`` and ``moving[label]`` for shared labels."""
    out = {}
    for k in sorted(set(fixed) & set(moving)):
        p = transform_points(tfm, np.asarray(fixed[k]))[0]
        out[k] = float(np.linalg.norm(p - np.asarray(moving[k], float)))
    return out


def target_registration_error(
    tfm: sitk.Transform, truth: sitk.Transform, points: np.ndarray
) -> np.ndarray:
    """(N,) distances in mm between ``tfm(p)`` and ``truth(p)`` for (N,3) reference points."""
    return np.linalg.norm(transform_points(tfm, points) - transform_points(truth, points), axis=1)


def rotation_error_deg(tfm: sitk.Transform, truth: sitk.Transform) -> float:
    """Angle (degrees) of the rotation R_truth^T R between two rigid transforms."""
    r1, _ = rigid_matrix(tfm)
    r2, _ = rigid_matrix(truth)
    c = (np.trace(r2.T @ r1) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
