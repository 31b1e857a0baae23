"""Bad label maps: a clear error, or a repair with a warning that says what was repaired."""

import numpy as np
import pytest
import SimpleITK as sitk

from meshing import MeshingWarning
from meshing.analytic import ellipsoid_labels, touching_boxes_labels
from meshing.labels import Grid, collect_repairs, tissue_masks
from meshing.volume import midline_x


def _with(img, arr):
    out = sitk.GetImageFromArray(arr)
    out.CopyInformation(img)
    return out


def test_empty_label_map_is_a_clear_error():
    img = touching_boxes_labels()
    empty = _with(img, np.zeros_like(sitk.GetArrayFromImage(img)))
    with pytest.raises(ValueError, match="no breast tissue"):
        tissue_masks(empty)


def test_missing_muscle_is_a_clear_error():
    with pytest.raises(ValueError, match="no muscle"):
        tissue_masks(ellipsoid_labels((10.0, 10.0, 10.0)))


def test_unexpected_values_are_named():
    img = touching_boxes_labels()
    arr = sitk.GetArrayFromImage(img)
    arr[0, 0, 0] = 7
    with pytest.raises(ValueError, match="unexpected label values 7"):
        tissue_masks(_with(img, arr))


def test_non_integer_and_2d_images_are_rejected():
    with pytest.raises(ValueError, match="non-integer"):
        tissue_masks(sitk.GetImageFromArray(np.full((4, 4, 4), 0.5, np.float32)))
    with pytest.raises(ValueError, match="3D"):
        tissue_masks(sitk.GetImageFromArray(np.ones((4, 4), np.uint8)))


def test_holes_and_islands_are_repaired_with_a_warning():
    img = touching_boxes_labels()
    arr = sitk.GetArrayFromImage(img)
    z, y, x = np.argwhere(arr == 1).mean(0).astype(int)
    arr[z - 2 : z + 3, y - 2 : y + 3, x - 2 : x + 3] = 0  # 125-voxel cavity in the breast
    arr[1, 1, 1] = 1  # one-voxel island
    with pytest.warns(MeshingWarning) as rec:
        masks = tissue_masks(_with(img, arr))
    text = " ".join(str(w.message) for w in rec)
    assert "filled 1 enclosed hole" in text and "125 voxels" in text
    assert "removed 1 small disconnected" in text
    assert masks.breast[z, y, x] and not masks.breast[1, 1, 1]
    assert masks.breast.sum() == (sitk.GetArrayFromImage(img) == 1).sum()


def test_touching_breasts_are_split_on_the_thinnest_plane_with_a_warning():
    spacing = 1.0
    n = (80, 30, 30)  # x, y, z
    x = np.arange(n[0]) * spacing
    zz, yy, xx = np.meshgrid(np.arange(n[2]), np.arange(n[1]), x, indexing="ij")
    arr = np.zeros((n[2], n[1], n[0]), np.uint8)
    for cx in (20.0, 58.0):  # two balls of radius 12 joined by a 4-voxel bridge at x = 35
        arr[(xx - cx) ** 2 + (yy - 15) ** 2 + (zz - 15) ** 2 <= 144] = 1
    arr[13:17, 13:17, 30:48] = 1
    img = sitk.GetImageFromArray(arr)
    with pytest.warns(MeshingWarning, match="touch"):
        xm = midline_x(arr.astype(bool), Grid.of(img))
    # thinnest slices are the bridge, x in [33, 45]: its middle
    assert 33.0 <= xm <= 45.0
    # separated balls: the middle of the gap, no warning
    arr[:, :, 30:48] = 0
    xm2 = midline_x(arr.astype(bool), Grid.of(img))
    assert xm2 == pytest.approx(0.5 * (32 + 46), abs=1.0)


def test_a_thin_sheet_apart_from_the_breast_is_dropped_a_thick_piece_kept():
    """The partial-volume rim where muscle meets air looks like fat on a fat-suppressed scan:
    a sheet of "breast" two voxels thick behind the muscle (10 % of the breast's volume, so
    not an island) is removed with a warning; a block five voxels thick apart from the
    breast is tissue and stays."""
    img = touching_boxes_labels()  # breast y 6-25, muscle y 26-45, 1 mm voxels
    arr = sitk.GetArrayFromImage(img)
    arr[6:56, 46:48, 6:66] = 1  # 6000 voxels, 2 thick, on the muscle's back
    arr[20:40, 0:5, 20:40] = 1  # 2000 voxels, 5 thick, on the field of view's edge
    with collect_repairs() as repairs:
        masks = tissue_masks(_with(img, arr))
    text = " ".join(repairs)
    assert "removed 1 thin sheet(s) of breast tissue (6000 voxels, at most 1.0 mm deep)" in text
    assert not masks.breast[:, 46:48].any()
    assert masks.breast[20:40, 0:5, 20:40].all()
    assert masks.breast.sum() == 60000 + 2000


def test_collect_repairs_keeps_repairs_and_passes_other_warnings_on():
    import warnings

    from meshing.labels import repaired

    with pytest.warns(RuntimeWarning, match="not a repair"):
        with collect_repairs() as got:
            repaired("meshing: filled 1 hole")
            warnings.warn("not a repair", RuntimeWarning, stacklevel=1)
    assert got == ["meshing: filled 1 hole"]


def test_a_pieces_depth_from_its_crop_equals_the_whole_volumes_below_the_limit():
    """_drop_sheets measures each piece's depth on its bounding box grown by the limit; below
    the limit that is the whole volume's distance transform exactly (beyond the volume is
    outside, as a pad of 0)."""
    from scipy import ndimage as ndi

    from meshing.labels import _depth_mm

    rng = np.random.default_rng(0)
    mask = ndi.binary_opening(rng.random((30, 40, 50)) > 0.45, iterations=1)
    spacing = (1.0, 1.5, 2.0)  # x, y, z
    lab, n = ndi.label(mask)
    edt = ndi.distance_transform_edt(np.pad(mask, 1), sampling=spacing[::-1])[1:-1, 1:-1, 1:-1]
    limit = 4.0
    checked = 0
    for k, box in enumerate(ndi.find_objects(lab)):
        whole = float(edt[lab == k + 1].max())
        got = _depth_mm(mask, lab, k + 1, box, spacing, limit)
        if whole < limit:
            assert got == pytest.approx(whole, abs=1e-12)
            checked += 1
        else:
            assert got >= limit
    assert checked >= 5
