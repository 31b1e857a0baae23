"""Which rigid directions a chest-wall mask leaves loose, and a transform that takes those
directions from a second estimate (:func:`loose_directions`, :func:`blend_loose`).

A rigid fit on the chest wall alone is sharp across the wall but can slide along it: a
torso's wall is close to a cylinder, so a shift along the body axis changes the correlation
little. The information matrix of the reference image over the mask (Gauss-Newton, the
image gradient against the six rigid motions) says how sharp each direction is; its small
eigenvalues are the loose directions. Rotations are measured as the displacement they give at
the mask's radius of gyration, so all six directions are in mm and comparable.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from registration.initialise import _to_euler
from registration.refine import _bounding_box_mm, _crop
from registration.transforms import matrix_to_transform, transform_to_matrix

#: A direction is loose when a 1 mm motion along it changes the masked image by less than
#: this fraction of what 1 mm along the sharpest direction does (eigenvalue ratio of the
#: information matrix). Measured on the validation suite's 11 reference masks: a torso's or
#: coil's translation along the body axis 0.003-0.006, the next direction 0.013-0.026, a
#: slab's weakest 0.032-0.050.
LOOSE_RATIO = 0.01


@dataclass(frozen=True)
class Directions:
    """The six rigid directions of a mask: ``vectors`` (6, 6) columns (rotation about
    ``centre`` scaled by ``radius_mm``, then translation, mm), their ``ratios`` to the
    sharpest (ascending) and which are ``loose``."""

    centre: np.ndarray
    radius_mm: float
    vectors: np.ndarray
    ratios: np.ndarray
    loose: np.ndarray

    def rotations(self) -> np.ndarray:
        """Which of the six directions are rotations (most of their length in the rotation
        part), the others translations."""
        return np.linalg.norm(self.vectors[:3], axis=0) > 0.5

    def translations(self) -> Directions:
        """A copy whose loose directions are only the translations."""
        return replace(self, loose=self.loose & ~self.rotations())

    def turns(self) -> Directions:
        """A copy whose loose directions are only the rotations."""
        return replace(self, loose=self.loose & self.rotations())

    def describe(self) -> list[str]:
        """One phrase per loose direction, e.g. ``"translation (0.00, 0.02, 1.00)"``."""
        out = []
        rotations = self.rotations()
        for k in np.flatnonzero(self.loose):
            v = self.vectors[:, k]
            kind = "rotation" if rotations[k] else "translation"
            axis = v[:3] if rotations[k] else v[3:]
            axis = axis / max(np.linalg.norm(axis), 1e-12)
            out.append(f"{kind} ({axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}), "
                       f"sharpness {self.ratios[k]:.4f}")
        return out


def loose_directions(fixed: sitk.Image, mask: sitk.Image, *, ratio: float = LOOSE_RATIO,
                     sigma_mm: float = 1.0, every: int = 3) -> Directions:
    """The information matrix of ``fixed`` over ``mask`` (every ``every``-th voxel, gradient
    of a Gaussian of ``sigma_mm``) and its eigen-directions; those below ``ratio`` of the
    largest eigenvalue are loose."""
    # Only the mask's box (and the smoothing's reach) is read: the gradient of a whole
    # adult volume cost 6.7 s for 43 M voxels.
    lo, hi = _bounding_box_mm(mask)
    margin = 4.0 * float(sigma_mm) + 2.0 * max(fixed.GetSpacing())
    fixed = _crop(sitk.Cast(fixed, sitk.sitkFloat32), lo - margin, hi + margin)
    grad = sitk.GetArrayFromImage(sitk.GradientRecursiveGaussian(fixed, float(sigma_mm)))
    on = sitk.Resample(mask, fixed, sitk.Transform(), sitk.sitkNearestNeighbor, 0,
                       sitk.sitkUInt8)
    idx = np.argwhere(sitk.GetArrayViewFromImage(on) > 0)[::max(1, int(every))]
    if len(idx) < 6:
        raise ValueError("register: the chest-wall mask holds fewer than 6 voxels")
    sp = np.asarray(fixed.GetSpacing(), float)
    d = np.asarray(fixed.GetDirection(), float).reshape(3, 3)
    x = np.asarray(fixed.GetOrigin(), float) + (idx[:, ::-1] * sp) @ d.T
    g = grad[tuple(idx.T)].astype(float)  # physical-frame gradient (x, y, z)
    c = x.mean(axis=0)
    r = float(np.sqrt(((x - c) ** 2).sum(axis=1).mean()))
    jac = np.hstack([np.cross(x - c, g) / r, g])
    val, vec = np.linalg.eigh(jac.T @ jac)
    rel = val / max(float(val[-1]), 1e-300)
    return Directions(c, r, vec, rel, rel < ratio)


def blend_loose(base: sitk.Euler3DTransform, other: sitk.Transform, dirs: Directions
                ) -> tuple[sitk.Euler3DTransform, float]:
    """``base`` moved along the loose directions of ``dirs`` to where ``other`` lies (its
    other directions kept), and how far that moved the mask's points at its radius (mm).

    Both transforms map reference points to the moving frame; the difference
    ``base^-1 o other`` is a small motion of the reference, split into the eigen-directions.
    """
    mb, mo = transform_to_matrix(base), transform_to_matrix(other)
    rel = np.linalg.inv(mb) @ mo
    c, r = dirs.centre, dirs.radius_mm
    rotvec = Rotation.from_matrix(rel[:3, :3]).as_rotvec()
    shift = rel[:3, :3] @ c + rel[:3, 3] - c  # displacement of the centre
    delta = np.concatenate([rotvec * r, shift])
    v = dirs.vectors[:, dirs.loose]
    step = v @ (v.T @ delta)
    rot = Rotation.from_rotvec(step[:3] / r).as_matrix()
    small = np.eye(4)
    small[:3, :3] = rot
    small[:3, 3] = c + step[3:] - rot @ c
    return (_to_euler(matrix_to_transform(mb @ small), np.asarray(base.GetCenter(), float)),
            float(np.linalg.norm(step)))
