"""Segmentation QA numbers on label maps with known overlaps."""

import numpy as np
import pytest
import SimpleITK as sitk

from imaging.qa import dice, qa_figure, save_figure, tissue_volumes_ml


def _labels(shift=0, spacing=(0.5, 1.0, 2.0)):
    a = np.zeros((20, 30, 40), np.uint8)
    a[5:15, 5 + shift:25 + shift, 5:35] = 1
    a[8:12, 10 + shift:20 + shift, 10:30] = 3
    a[5:15, 25 + shift:28 + shift, 5:35] = 2
    img = sitk.GetImageFromArray(a)
    img.SetSpacing(spacing)
    return img


def test_dice_counts_overlaps():
    a, b = _labels(), _labels(shift=1)
    d = dice(a, b)
    # breast (1 and 3 together): 10 x 20 x 30 boxes shifted by one row -> 2*19/40
    assert d["breast"] == pytest.approx(2 * 19 / 40)
    # muscle: 3-row slabs shifted by one row -> 2*2/6
    assert d["muscle"] == pytest.approx(2 * 2 / 6)
    assert d["gland"] == pytest.approx(2 * 9 / 20)
    assert dice(a, a) == {"breast": 1.0, "muscle": 1.0, "gland": 1.0}


def test_dice_needs_the_same_grid():
    with pytest.raises(ValueError, match="different grids"):
        dice(_labels(), _labels(spacing=(1.0, 1.0, 1.0)))


def test_volumes_use_the_voxel_size():
    v = tissue_volumes_ml(_labels())
    vox_ml = 0.5 * 1.0 * 2.0 / 1000.0
    assert v["muscle"] == pytest.approx(10 * 3 * 30 * vox_ml)
    assert v["gland"] == pytest.approx(4 * 10 * 20 * vox_ml)
    assert v["breast"] == pytest.approx((10 * 20 * 30 - 4 * 10 * 20) * vox_ml)


def test_qa_figure_has_three_views_with_contours(tmp_path):
    lab = _labels()
    img = sitk.Cast(lab, sitk.sitkFloat32)
    fig = qa_figure(img, lab, seeds=[[5.0, 12.0, 20.0]], title="t")
    assert [ax.get_title() for ax in fig.axes] == ["axial", "coronal", "sagittal"]
    assert all(len(ax.collections) >= 2 for ax in fig.axes)  # breast and muscle contours
    save_figure(fig, tmp_path / "qa.png")
    assert [p.name for p in tmp_path.iterdir()] == ["qa.png"]
