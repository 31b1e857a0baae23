"""Slice views put the patient's directions where the axis labels say, whatever the file's
direction matrix; the browser's sliders scroll every orientation."""

import numpy as np
import pytest
import SimpleITK as sitk

from imaging.views import ORIENTATIONS, oriented_slice, slice_browser, slice_count

BLOB = np.array([5.0, -24.0, 42.0])  # patient left, anterior, superior (LPS mm)


def _volume(flip: bool) -> sitk.Image:
    """A 20 x 30 x 40 volume (spacing 1, 2, 3 mm) with one bright voxel at BLOB; with
    ``flip`` the same physical image stored with x and y reversed (an RAS-ordered file)."""
    size, sp = np.array([20, 30, 40]), np.array([1.0, 2.0, 3.0])
    origin = np.array([-10.0, -40.0, -60.0])
    d = np.diag([-1.0, -1.0, 1.0]) if flip else np.eye(3)
    if flip:
        origin = origin + (size - 1) * sp * np.array([1, 1, 0])
    img = sitk.Image([int(v) for v in size], sitk.sitkFloat32)
    img.SetSpacing(sp.tolist())
    img.SetOrigin(origin.tolist())
    img.SetDirection(d.ravel().tolist())
    img[img.TransformPhysicalPointToIndex(BLOB.tolist())] = 100.0
    return img


@pytest.mark.parametrize("flip", [False, True])
def test_views_put_directions_where_the_labels_say(flip):
    img = _volume(flip)
    # in-plane axes (x = 0, y = 1, z = 2) and the blob's slice along the fixed axis
    planes = {"axial": (0, 1), "coronal": (0, 2), "sagittal": (1, 2)}
    for view, (h, v) in planes.items():
        fixed = 3 - h - v
        n = slice_count(img, view)
        origin_fixed = min(img.TransformIndexToPhysicalPoint([0, 0, 0])[fixed],
                           img.TransformIndexToPhysicalPoint(
                               [s - 1 for s in img.GetSize()])[fixed])
        index = int(round((BLOB[fixed] - origin_fixed) / img.GetSpacing()[fixed]))
        assert 0 <= index < n
        plane, (left, right, bottom, top) = oriented_slice(img, view, index)
        r, c = np.unravel_index(np.argmax(plane), plane.shape)
        x = left + (c + 0.5) / plane.shape[1] * (right - left)
        y = bottom + (r + 0.5) / plane.shape[0] * (top - bottom)
        assert (x, y) == pytest.approx((BLOB[h], BLOB[v])), view
        _, (sl, sr), (sb, st) = ORIENTATIONS[view]
        # screen right is the label on the right: larger x is L, larger y is P
        assert (right > left) == (sr in "LP")
        # screen top: S (larger z) for coronal and sagittal, A (smaller y) for axial
        assert (top > bottom) == (st in "SLP")


def test_browser_scrolls_each_orientation():
    img = _volume(False)
    box = slice_browser(img)
    assert set(box.sliders) == {"axial", "coronal", "sagittal"}
    assert [box.sliders[v].max for v in ("axial", "coronal", "sagittal")] == [39, 29, 19]
    before = [ax.get_title() for ax in box.figure.axes]
    box.sliders["axial"].value = 3
    after = [ax.get_title() for ax in box.figure.axes]
    assert after[0] == "axial z = -51.0 mm" and after[0] != before[0]
    assert after[1:] == before[1:]
