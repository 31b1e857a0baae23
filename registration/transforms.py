"""Applying and storing rigid transforms.

Convention (SimpleITK resampling): a transform ``T`` of position P maps a point of the
reference frame to the corresponding point of P's image frame, ``x_P = T(x_ref)``. Resampling
P with ``T`` therefore puts P on the reference grid.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import SimpleITK as sitk

STAGE = "registration"


def read_transform(path: str | Path) -> sitk.Transform:
    """Read an ITK transform file, failing with one clear message."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{STAGE}: transform file {path} does not exist")
    try:
        return sitk.ReadTransform(str(path))
    except RuntimeError as exc:
        raise ValueError(f"{STAGE}: {path} is not a readable ITK transform: "
                         f"{str(exc).strip().splitlines()[-1]}") from None


def write_transform(tfm: sitk.Transform, path: str | Path) -> None:
    """Write an ITK transform file atomically (temporary name, then rename)."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    sitk.WriteTransform(tfm, str(tmp))
    os.replace(tmp, path)


def rigid_matrix(tfm: sitk.Transform) -> tuple[np.ndarray, np.ndarray]:
    """(R (3,3), t (3,)) with ``T(x) = R x + t`` for any affine-like SimpleITK transform."""
    x0 = np.zeros(3)
    t = np.asarray(tfm.TransformPoint(tuple(x0)))
    r = np.stack([np.asarray(tfm.TransformPoint(tuple(e))) - t for e in np.eye(3)], axis=1)
    return r, t


def transform_points(tfm: sitk.Transform, points: np.ndarray) -> np.ndarray:
    """Map (N,3) points (mm) through ``tfm``; returns a new (N,3) array."""
    pts = np.asarray(points, float).reshape(-1, 3)
    return np.asarray([tfm.TransformPoint(tuple(p)) for p in pts]).reshape(-1, 3)


def gravity_in_reference(tfm: sitk.Transform, gravity: np.ndarray) -> np.ndarray:
    """A position's gravity direction (unit vector in its image frame) in the reference frame.

    ``tfm`` maps reference -> position, so directions go back through the inverse rotation.
    """
    r, _ = rigid_matrix(tfm)
    g = np.linalg.solve(r, np.asarray(gravity, float))
    return g / np.linalg.norm(g)


def matrix_to_transform(m: np.ndarray) -> sitk.AffineTransform:
    """4x4 homogeneous matrix (mm) -> SimpleITK affine transform."""
    m = np.asarray(m, float)
    a = sitk.AffineTransform(3)
    a.SetMatrix(m[:3, :3].ravel().tolist())
    a.SetTranslation(m[:3, 3].tolist())
    return a


def transform_to_matrix(tfm: sitk.Transform) -> np.ndarray:
    """SimpleITK transform (affine-like) -> 4x4 homogeneous matrix."""
    r, t = rigid_matrix(tfm)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


def resample_to_reference(
    moving: sitk.Image, reference: sitk.Image, tfm: sitk.Transform, *, labels: bool = False
) -> sitk.Image:
    """Resample a position's volume (or label map) onto the reference grid.

    Linear interpolation for intensities, nearest neighbour for label maps; outside -> 0.
    """
    interp = sitk.sitkNearestNeighbor if labels else sitk.sitkLinear
    return sitk.Resample(moving, reference, tfm, interp, 0.0, moving.GetPixelID())
