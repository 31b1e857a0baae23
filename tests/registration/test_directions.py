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


def test_a_loose_turn_is_not_taken_from_a_second_estimate():
    """A round cylinder leaves its axis loose twice, along it and about it. Markers dragged
    round the body by the skin turn the second estimate about the axis: only the shift along
    it is taken (``Directions.translations``)."""
    img, mask = _image(lambda x, y, z: x ** 2 + y ** 2 <= 18.0 ** 2)
    d = loose_directions(img, mask)
    assert d.loose.sum() == 2 and d.rotations()[d.loose].sum() == 1
    t = d.translations()
    assert t.loose.sum() == 1 and not t.rotations()[t.loose].any()
    assert abs(t.vectors[5, t.loose][0]) > 0.99  # the shift along z
    assert any(w.startswith("rotation (") for w in d.describe())
    base = sitk.Euler3DTransform()
    other = sitk.Euler3DTransform()
    other.SetRotation(0.0, 0.0, np.radians(2.0))  # turned about the axis
    other.SetTranslation((0.0, 0.0, 1.5))
    out, moved = blend_loose(base, other, t)
    rel = transform_to_matrix(out)
    assert np.degrees(Rotation.from_matrix(rel[:3, :3]).magnitude()) < 0.05
    np.testing.assert_allclose(rel[:3, 3], [0.0, 0.0, 1.5], atol=0.05)
    turned, _ = blend_loose(base, other, d)  # every loose direction: the turn comes along
    assert np.degrees(Rotation.from_matrix(transform_to_matrix(turned)[:3, :3])
                      .magnitude()) > 1.9


def _torso(shift_mm, markers, drag_mm) -> sitk.Image:
    """A torso-like volume (1 mm voxels): an elliptic body along z, an inner 'thorax' darker
    than it, and bright marker balls on the body's surface at ``markers``; all shifted by
    ``shift_mm``, the skin (the body's outline) and the markers by ``drag_mm`` more."""
    z, y, x = np.mgrid[0:50, -45:46, -60:61].astype(float)
    sx, sy, sz = shift_mm
    xb, yb = x - sx, y - sy
    xs, ys = xb - drag_mm[0], yb - drag_mm[1]
    a = np.where((xs / 50) ** 2 + (ys / 35) ** 2 <= 1, 1.0, 0.0)
    a[(xb / 36) ** 2 + ((yb - 4) / 22) ** 2 <= 1] = 0.85
    for m in markers:
        c = np.asarray(m, float) + drag_mm + np.asarray(shift_mm)
        a[(x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 <= 2.0 ** 2] = 2.0
    img = sitk.GetImageFromArray(a.astype(np.float32))
    img.SetOrigin((-60.0, -45.0, 0.0))
    return sitk.SmoothingRecursiveGaussian(img, 0.7)


def test_markers_dragged_by_the_skin_set_only_what_the_wall_leaves_loose():
    """The chest wall (the thorax's boundary, a cylinder along z) sets x and y; the markers,
    dragged 1 mm sideways with the skin, may only set z, which the wall leaves loose."""
    from registration.rigid import register_rigid

    markers = [(-30.0, -28.0, 12.0), (30.0, -28.0, 14.0), (0.0, -35.0, 22.0),
               (-8.0, -35.0, 36.0)]
    truth = np.array([1.5, -1.0, 2.5])
    fixed = _torso((0.0, 0.0, 0.0), markers, np.zeros(3))
    moving = _torso(truth, markers, np.array([1.0, 0.0, 0.0]))
    z, y, x = np.mgrid[0:50, -45:46, -60:61].astype(float)
    ring = np.abs(np.sqrt((x / 36) ** 2 + ((y - 4) / 22) ** 2) - 1.0) <= 0.15
    ring[:6], ring[-6:] = False, False  # away from the image's ends along z
    mask = sitk.GetImageFromArray(ring.astype(np.uint8))
    mask.CopyInformation(fixed)
    pts = {f"m{i}": np.asarray(p, float) for i, p in enumerate(markers)}
    # the marker list is off in z by 0.6 mm on average (the balls' image is not)
    moved = {k: p + truth + [1.0, 0.0, dz] for (k, p), dz in zip(pts.items(), (0.9, 0.9, 0.3, 0.3))}
    res = register_rigid(fixed, moving, fixed_points=pts, moving_points=moved,
                         fixed_mask=mask, fiducial_error_mm=1.5)
    shift = np.asarray(res.transform.TransformPoint((0.0, 0.0, 25.0))) - [0.0, 0.0, 25.0]
    fid = np.asarray(res.fiducial_transform.TransformPoint((0.0, 0.0, 25.0))) - [0, 0, 25.0]
    assert abs(fid[0] - truth[0]) > 0.9  # the markers alone carry the drag
    np.testing.assert_allclose(shift, truth, atol=0.3)
    wall = register_rigid(fixed, moving, fixed_points=pts, moving_points=moved,
                          fixed_mask=mask, fiducial_error_mm=1.5, marker_mask_mm=0)
    loose = np.asarray(wall.transform.TransformPoint((0.0, 0.0, 25.0))) - [0.0, 0.0, 25.0]
    assert abs(loose[2] - truth[2]) > 0.4  # the wall alone keeps the start's z
    assert any("loose" in w for w in res.warnings)


def test_without_markers_a_loose_direction_is_named():
    """No marker to set the cylinder's axis: the registration says it is not determined
    along it instead of passing in silence."""
    from registration.rigid import register_rigid

    markers = [(-30.0, -28.0, 12.0)]
    fixed = _torso((0.0, 0.0, 0.0), markers, np.zeros(3))
    moving = _torso((1.0, 0.0, 2.0), markers, np.zeros(3))
    z, y, x = np.mgrid[0:50, -45:46, -60:61].astype(float)
    ring = np.abs(np.sqrt((x / 36) ** 2 + ((y - 4) / 22) ** 2) - 1.0) <= 0.15
    ring[:6], ring[-6:] = False, False
    mask = sitk.GetImageFromArray(ring.astype(np.uint8))
    mask.CopyInformation(fixed)
    start = sitk.Euler3DTransform()
    start.SetTranslation((1.0, 0.0, 2.0))
    res = register_rigid(fixed, moving, fixed_mask=mask, initial=start)
    assert res.status == "unchecked"
    assert any("not determined along it" in w and "translation (" in w for w in res.warnings)


def test_without_markers_the_breasts_base_sets_the_loose_direction():
    """No marker: the tissue in front of the wall (here a blob bounded along z, as a
    breast's base is) sets the cylinder's axis, which the wall leaves at the start's."""
    from registration.rigid import register_rigid

    def torso(shift):
        z, y, x = np.mgrid[0:50, -45:46, -60:61].astype(float)
        xb, yb, zb = x - shift[0], y - shift[1], z - shift[2]
        a = np.where((xb / 50) ** 2 + (yb / 35) ** 2 <= 1, 1.0, 0.0)
        a[(xb / 36) ** 2 + ((yb - 4) / 22) ** 2 <= 1] = 0.85
        a[(xb / 12) ** 2 + ((yb + 29) / 4) ** 2 + ((zb - 25) / 9) ** 2 <= 1] = 0.5
        img = sitk.GetImageFromArray(a.astype(np.float32))
        img.SetOrigin((-60.0, -45.0, 0.0))
        return sitk.SmoothingRecursiveGaussian(img, 0.7)

    truth = np.array([1.0, 0.0, 2.5])
    fixed, moving = torso(np.zeros(3)), torso(truth)
    z, y, x = np.mgrid[0:50, -45:46, -60:61].astype(float)
    ring = np.abs(np.sqrt((x / 36) ** 2 + ((y - 4) / 22) ** 2) - 1.0) <= 0.15
    ring[:6], ring[-6:] = False, False
    base = ring | ((np.abs(x) <= 16) & (y >= -35) & (y <= -19) & (z >= 10) & (z <= 40))
    masks = []
    for m in (ring, base):
        masks.append(sitk.GetImageFromArray(m.astype(np.uint8)))
        masks[-1].CopyInformation(fixed)
    start = sitk.Euler3DTransform()
    start.SetTranslation((1.0, 0.0, 0.5))  # 2 mm short along the axis
    centre = (0.0, 0.0, 25.0)
    wall = register_rigid(fixed, moving, fixed_mask=masks[0], initial=start)
    res = register_rigid(fixed, moving, fixed_mask=masks[0], initial=start,
                         base_mask=masks[1])
    along = [np.asarray(r.transform.TransformPoint(centre))[2] - centre[2]
             for r in (wall, res)]
    assert abs(along[0] - truth[2]) > 1.5  # the wall alone keeps the start's z
    assert abs(along[1] - truth[2]) < 0.3
    shift = np.asarray(res.transform.TransformPoint(centre)) - centre
    np.testing.assert_allclose(shift[:2], truth[:2], atol=0.3)
    assert any("set by the breasts' base" in w for w in res.warnings)
