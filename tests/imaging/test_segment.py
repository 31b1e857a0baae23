"""Segmentation against phantom truth: Dice, seeds, bad input, and the command's outputs."""

import json
import os

import numpy as np
import pytest
import SimpleITK as sitk

from breastmodel.phantom import make_phantom
from imaging.io import read_volume
from imaging.qa import dice
from imaging.segment import Seed, segment_volume


@pytest.fixture(scope="module")
def phantom(mri_phantom):
    return mri_phantom


@pytest.fixture(scope="module")
def segmented(phantom, tmp_path_factory):
    """Run the command once on one position (it is the slow part of these tests)."""
    from breastmodel.cli import main

    subject, truth = phantom
    out = tmp_path_factory.mktemp("seg")
    assert main(["segment", str(subject), "--out", str(out), "--truth", str(truth),
                 "--position", "prone", "--gland"]) == 0
    return out


def test_dice_on_small_phantom(phantom, segmented):
    subject, truth = phantom
    lab = read_volume(segmented / "prone_labels.nii.gz")
    img = read_volume(subject / "prone.nii.gz")
    d = dice(lab, read_volume(truth / "prone_labels.nii.gz"))
    # The targets; on the half-size phantom (5 mm fat layer, 8 mm muscle) a boundary
    # error costs about twice the Dice it costs at full size, so meeting them here is harder.
    assert d["breast"] >= 0.97
    assert d["muscle"] >= 0.95
    assert d["gland"] >= 0.8  # optional label; the gland/fat contrast is the lowest
    assert lab.GetSize() == img.GetSize()
    assert np.allclose(lab.GetOrigin(), img.GetOrigin())
    rep = json.loads((segmented / "segmentation.json").read_text())["positions"]["prone"]
    assert rep["dice"] == pytest.approx(d)
    a = sitk.GetArrayViewFromImage(lab)
    assert rep["volumes_ml"]["muscle"] == pytest.approx((a == 2).sum() / 1000.0)
    assert rep["markers_removed"] >= 4
    assert abs(rep["midline_x_mm"]) < 45.0  # moved by up to 30 mm (+15 deg rotation)


def test_seed_turns_a_region_into_muscle(phantom, segmented):
    subject, _ = phantom
    img = read_volume(subject / "prone.nii.gz")
    lab = sitk.GetArrayFromImage(read_volume(segmented / "prone_labels.nii.gz"))
    gland = np.argwhere(lab == 3)
    assert len(gland)
    k = gland[len(gland) // 2]
    # a slab of 30 slices around the seed keeps the test fast; it still holds air and body
    z0 = max(0, int(k[0]) - 15)
    sub = img[:, :, z0:z0 + 30]
    p = img.TransformIndexToPhysicalPoint(tuple(int(v) for v in k[::-1]))
    before = segment_volume(sub, levelset_iterations=0)
    after = segment_volume(sub, seeds=[Seed(2, p)], levelset_iterations=0)
    kk = tuple(int(v) for v in sub.TransformPhysicalPointToIndex(p))[::-1]
    assert sitk.GetArrayViewFromImage(before.labels)[kk] == 1
    assert sitk.GetArrayViewFromImage(after.labels)[kk] == 2
    assert any("label 2" in n for n in after.notes)


def test_bad_inputs_fail_clearly():
    with pytest.raises(ValueError, match="segment: v.nii is 2-D"):
        segment_volume(sitk.Image(16, 16, sitk.sitkFloat32), name="v.nii")
    nan = np.ones((16, 16, 16), np.float32)
    nan[3, 3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        segment_volume(sitk.GetImageFromArray(nan), name="v.nii")
    empty = sitk.GetImageFromArray(np.zeros((16, 16, 16), np.float32))
    with pytest.raises(ValueError, match="segment|preprocess"):
        segment_volume(empty, name="v.nii")


def test_command_keeps_outputs_on_failure(phantom, segmented):
    from breastmodel.cli import main

    subject, _ = phantom
    out = segmented
    assert (out / "prone_qa.png").stat().st_size > 10_000
    assert (out / "config.toml").is_file() and (out / "provenance.json").is_file()
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    # unknown position: one clear error, nothing already written is touched
    assert main(["segment", str(subject), "--out", str(out), "--position", "nope"]) == 1
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert {k: after[k] for k in before if k not in ("config.toml", "provenance.json")} == {
        k: v for k, v in before.items() if k not in ("config.toml", "provenance.json")}
    assert not [p for p in os.listdir(out) if ".tmp" in p]


@pytest.mark.slow
def test_dice_targets_on_full_size_phantom(tmp_path):
    """The issue's targets at full size: 1 mm voxels, SNR 20, 30 % bias field."""
    subject = make_phantom(tmp_path / "full", seed=1, positions=("supine",),
                           max_rotation_deg=15.0, max_translation_mm=30.0, progress=False)
    res = segment_volume(read_volume(subject / "supine.nii.gz"))
    d = dice(res.labels, read_volume(tmp_path / "full_truth" / "supine_labels.nii.gz"))
    assert d["breast"] >= 0.97
    assert d["muscle"] >= 0.95


def test_t1_like_contrast(tmp_path, monkeypatch):
    """Another contrast: T1-like levels (muscle 0.35, gland 0.45, skin 0.6 of fat, dark
    lungs). The thresholds come from the measured levels, so the targets still hold."""
    import breastmodel.phantom.rendering as rendering

    for tissue, level in (("MUSCLE", 0.35), ("GLAND", 0.45), ("SKIN", 0.6), ("THORAX", 0.05)):
        monkeypatch.setitem(rendering.T2_INTENSITY, getattr(rendering, tissue), level)
    subject = make_phantom(tmp_path / "t1", seed=3, small=True, positions=("supine",),
                           max_rotation_deg=15.0, max_translation_mm=30.0, progress=False)
    res = segment_volume(read_volume(subject / "supine.nii.gz"))
    d = dice(res.labels, read_volume(tmp_path / "t1_truth" / "supine_labels.nii.gz"))
    assert d["breast"] >= 0.97
    assert d["muscle"] >= 0.95
    assert res.levels["muscle"] == pytest.approx(0.35, abs=0.05)  # measured, not assumed
