"""Analytic label maps with known geometry, for tests, benchmarks and examples.

All return SimpleITK label images (0 background, 1 breast, 2 muscle) in physical LPS mm.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk


def _image(labels_zyx: np.ndarray, spacing: float, origin) -> sitk.Image:
    img = sitk.GetImageFromArray(labels_zyx.astype(np.uint8))
    img.SetSpacing((spacing,) * 3)
    img.SetOrigin(tuple(float(o) for o in origin))
    return img


def _centres(shape_xyz, spacing, origin):
    nx, ny, nz = shape_xyz
    z, y, x = np.meshgrid(
        origin[2] + spacing * np.arange(nz),
        origin[1] + spacing * np.arange(ny),
        origin[0] + spacing * np.arange(nx),
        indexing="ij",
    )
    return x, y, z


def ellipsoid_labels(radii=(40.0, 40.0, 40.0), *, spacing=1.0, label=1, margin=5.0):
    """An ellipsoid of semi-axes ``radii`` (mm) centred at the origin."""
    r = np.asarray(radii, float)
    n = np.ceil(2 * (r + margin) / spacing).astype(int)
    origin = -(n - 1) * spacing / 2.0
    x, y, z = _centres(n, spacing, origin)
    inside = (x / r[0]) ** 2 + (y / r[1]) ** 2 + (z / r[2]) ** 2 <= 1.0
    return _image(np.where(inside, label, 0), spacing, origin)


def touching_boxes_labels(*, size=(60.0, 40.0, 50.0), split_y=20.0, spacing=1.0, margin=6.0):
    """A box (mm) split at y = ``split_y`` (from its anterior face) into breast (front, label
    1) and muscle (back, label 2): two boxes sharing one face."""
    s = np.asarray(size, float)
    n = np.ceil((s + 2 * margin) / spacing).astype(int)
    origin = -(n - 1) * spacing / 2.0
    x, y, z = _centres(n, spacing, origin)
    inside = (np.abs(x) <= s[0] / 2) & (np.abs(y) <= s[1] / 2) & (np.abs(z) <= s[2] / 2)
    lab = np.where(inside, 2, 0)
    lab[inside & (y < -s[1] / 2 + split_y)] = 1
    return _image(lab, spacing, origin)


def torso_labels(*, spacing=2.0, fov=(320.0, 180.0, 200.0), breast_radius=55.0,
                 muscle_mm=12.0, fat_mm=8.0, gap_mm=30.0):
    """A simple torso: an anterior muscle half-ring around an elliptic thorax, a thin layer
    of fat over it and two hemispherical breasts, cut by the field of view in z.

    Returns
    -------
    sitk.Image
        Labels 0 (air, thorax), 1 breast/fat, 2 muscle; FOV ``fov`` (x, y, z) mm.
    """
    f = np.asarray(fov, float)
    n = np.round(f / spacing).astype(int)
    origin = np.array([-f[0] / 2, -f[1] + 40.0, -f[2] / 2]) + spacing / 2
    x, y, z = _centres(n, spacing, origin)
    a, b = 130.0, 100.0  # thorax outer semi-axes (x, y), centred at (0, 0)

    def ellipse(d):
        return (x / (a - d)) ** 2 + (y / (b - d)) ** 2 <= 1.0

    outer = ellipse(-fat_mm)
    muscle = ellipse(0.0) & ~ellipse(muscle_mm)
    lab = np.zeros(x.shape, np.uint8)
    lab[outer & ~ellipse(0.0)] = 1
    lab[muscle] = 2
    cx = gap_mm / 2 + breast_radius
    for sx in (-1, 1):
        xb, zb = sx * cx, -10.0
        yb = -(b + fat_mm) * np.sqrt(max(1 - (xb / (a + fat_mm)) ** 2, 0.0)) + 10.0
        sphere = (x - xb) ** 2 + (y - yb) ** 2 + (z - zb) ** 2 <= breast_radius**2
        lab[sphere & ~ellipse(0.0) & (y < yb + 20)] = 1
    lab[y >= 0] = np.where(lab[y >= 0] == 2, 2, 0)
    return _image(lab, spacing, origin)
