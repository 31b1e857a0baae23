"""The directions a chest-wall mask leaves loose, and the blend that takes only those from
a second estimate (registration/directions.py)."""

import numpy as np
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from registration.directions import LOOSE_RATIO, blend_loose, loose_directions
from registration.transforms import transform_to_matrix


def _image(inside) -> tuple[sitk.Image, sitk.Image]:
    """A smoothed 0/1 image of ``inside(x, y, z)`` (mm, 1 mm voxels, centred grid) and a
    mask of the band within 4 mm of its edge."""
    z, y, x = np.mgrid[-30:31, -30:31, -30:31].astype(float)
    a = inside(x, y, z).astype(np.float32)
    img = sitk.GetImageFromArray(a)
    img.SetOrigin((-30.0, -30.0, -30.0))
    img = sitk.SmoothingRecursiveGaussian(img, 1.0)
    dist = sitk.SignedMaurerDistanceMap(sitk.GetImageFromArray(a.astype(np.uint8)),
                                        squaredDistance=False, useImageSpacing=True)
    band = sitk.GetImageFromArray((np.abs(sitk.GetArrayFromImage(dist)) <= 4.0)
                                  .astype(np.uint8))
    band.CopyInformation(img)
    return img, band


def test_a_cylinder_leaves_its_axis_loose_and_an_ellipsoid_nothing():
    img, mask = _image(lambda x, y, z: (x / 20) ** 2 + (y / 12) ** 2 <= 1)
    d = loose_directions(img, mask)
    assert d.loose.sum() == 1
    v = d.vectors[:, d.loose][:, 0]
    assert abs(v[5]) > 0.99  # translation along z, the cylinder's axis
    assert d.ratios[0] < 0.1 * LOOSE_RATIO
    img, mask = _image(lambda x, y, z: (x / 22) ** 2 + (y / 12) ** 2 + (z / 16) ** 2 <= 1)
    d = loose_directions(img, mask)
    assert not d.loose.any()
    assert d.describe() == []


def test_the_blend_takes_only_the_loose_directions():
    img, mask = _image(lambda x, y, z: (x / 20) ** 2 + (y / 12) ** 2 <= 1)
    d = loose_directions(img, mask)
    base = sitk.Euler3DTransform()
    base.SetTranslation((3.0, -1.0, 0.5))
    other = sitk.Euler3DTransform(base)
    other.SetRotation(0.01, 0.0, 0.0)
    other.SetTranslation((3.8, -1.0, 2.5))  # 0.8 mm across the axis, 2 mm along it
    out, moved = blend_loose(base, other, d)
    m = transform_to_matrix(out)
    rel = np.linalg.inv(transform_to_matrix(base)) @ m
    centre_shift = rel[:3, :3] @ d.centre + rel[:3, 3] - d.centre
    np.testing.assert_allclose(centre_shift[:2], 0.0, atol=0.05)  # across: the base's
    assert abs(centre_shift[2] - 2.0) < 0.2  # along the axis: the other's
    assert np.degrees(Rotation.from_matrix(rel[:3, :3]).magnitude()) < 0.05
    assert abs(moved - abs(centre_shift[2])) < 0.2
    same, zero = blend_loose(base, base, d)
    np.testing.assert_allclose(transform_to_matrix(same), transform_to_matrix(base),
                               atol=1e-9)
    assert zero < 1e-9
