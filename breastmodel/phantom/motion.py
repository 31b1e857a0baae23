"""Rigid patient motion between scans and gravity direction per position.

A motion maps patient-frame points X to image-frame points x = R (X - c) + c + t, where c is
the rotation centre. The image grid is fixed to the scanner; the patient moves.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

__all__ = ["RigidMotion", "random_motion", "patient_gravity"]


@dataclass(frozen=True)
class RigidMotion:
    """x = R (X - c) + c + t (mm), patient frame -> image frame.

    Attributes
    ----------
    rotation : (3, 3) float
    translation : (3,) float, mm
    center : (3,) float, mm
    """

    rotation: np.ndarray
    translation: np.ndarray
    center: np.ndarray

    @classmethod
    def identity(cls, center=(0.0, 0.0, 0.0)) -> RigidMotion:
        return cls(np.eye(3), np.zeros(3), np.asarray(center, dtype=float))

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix mapping patient-frame points to image-frame points."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.center + self.translation - self.rotation @ self.center
        return m

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Patient-frame points (n, 3) mm -> image-frame points (n, 3) mm."""
        p = np.asarray(points, dtype=float)
        return (p - self.center) @ self.rotation.T + self.center + self.translation

    def inverse(self, points: np.ndarray) -> np.ndarray:
        """Image-frame points (n, 3) mm -> patient-frame points (n, 3) mm."""
        q = np.asarray(points, dtype=float)
        return (q - self.center - self.translation) @ self.rotation + self.center

    def apply_vector(self, v: np.ndarray) -> np.ndarray:
        """Rotate a direction (3,) from the patient frame into the image frame."""
        return self.rotation @ np.asarray(v, dtype=float)

    def axis_angle(self) -> tuple[np.ndarray, float]:
        """Unit rotation axis (3,) and angle in degrees."""
        r = self.rotation
        angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))
        w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
        norm = np.linalg.norm(w)
        axis = w / norm if norm > 1e-12 else np.array([0.0, 0.0, 1.0])
        return axis, float(np.degrees(angle))

    def to_sitk(self) -> sitk.Euler3DTransform:
        """ITK transform whose ``TransformPoint`` maps patient-frame to image-frame points."""
        tr = sitk.Euler3DTransform()
        tr.SetCenter(tuple(map(float, self.center)))
        tr.SetMatrix(tuple(map(float, self.rotation.ravel())))
        tr.SetTranslation(tuple(map(float, self.translation)))
        return tr

    def as_dict(self) -> dict:
        axis, angle = self.axis_angle()
        tr = self.to_sitk()
        return {
            "matrix_patient_to_image": self.matrix().tolist(),
            "rotation_center_mm": self.center.tolist(),
            "translation_mm": self.translation.tolist(),
            "rotation_axis": axis.tolist(),
            "rotation_angle_deg": angle,
            "euler_angles_deg_itk_zxy": [
                float(np.degrees(a)) for a in (tr.GetAngleX(), tr.GetAngleY(), tr.GetAngleZ())
            ],
        }


def _axis_angle_matrix(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * kx + (1 - np.cos(angle_rad)) * (kx @ kx)


def random_motion(
    rng: np.random.Generator,
    *,
    max_rotation_deg: float,
    max_translation_mm: float,
    center,
) -> RigidMotion:
    """Draw a rigid motion: uniform random axis, angle uniform in [0, max_rotation_deg],
    translation in a uniform random direction with length uniform in [0, max_translation_mm].
    """
    axis = rng.normal(size=3)
    angle = np.radians(rng.uniform(0.0, max_rotation_deg))
    direction = rng.normal(size=3)
    length = rng.uniform(0.0, max_translation_mm)
    t = direction / np.linalg.norm(direction) * length
    return RigidMotion(_axis_angle_matrix(axis, angle), t, np.asarray(center, dtype=float))


_TILT = re.compile(r"^supine_tilted(?:_(\d+(?:\.\d+)?))?$")


def patient_gravity(position: str, *, tilt_deg: float = 45.0) -> tuple[np.ndarray, float | None]:
    """Gravity direction (unit, patient frame) for a named position.

    ``supine``: +y (toward the back); ``prone``: -y; ``upright``: -z;
    ``supine_tilted`` (or ``supine_tilted_<deg>``): +y rotated about +z by the tilt angle
    (right-handed), i.e. (-sin t, cos t, 0): gravity gains a component toward the patient's
    right, so the patient lies turned onto the right side with the left side raised.

    Returns
    -------
    gravity : (3,) float
    tilt_deg : float or None
        The tilt for tilted positions.
    """
    if position == "supine":
        return np.array([0.0, 1.0, 0.0]), None
    if position == "prone":
        return np.array([0.0, -1.0, 0.0]), None
    if position == "upright":
        return np.array([0.0, 0.0, -1.0]), None
    m = _TILT.match(position)
    if m:
        t = float(m.group(1)) if m.group(1) else float(tilt_deg)
        r = np.radians(t)
        return np.array([-np.sin(r), np.cos(r), 0.0]), t
    raise ValueError(
        f"phantom: unknown position {position!r}; use prone, supine, upright, supine_tilted "
        "or supine_tilted_<degrees>"
    )
