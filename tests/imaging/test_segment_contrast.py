"""Segmentation of fat-suppressed scans (fat dark; muscle, gland and skin mid-grey to
bright), where the fat-bright method lost the muscle (Dice 0.00-0.01) on the validation
family's fat-suppressed subjects.

Volumes: the phantom renderer the family uses (``make_phantom(..., contrast=,
fat_suppressed=True)``, the same call ``family.make_subject`` makes with a spec's contrast)
on the small torso anatomy, and a numpy-built muscle slab meeting air (tests/mri_synth.py,
``"t1_fatsat"``). Bounds: the issue's targets for every scan of the suite (Dice >= 0.95
breast, >= 0.90 muscle); measured when written: T1 fat-suppressed phantom 0.988 / 0.986,
T2 0.981 / 0.975, slab 0.951 / 0.984.
"""

import numpy as np
import pytest
import SimpleITK as sitk
from mri_synth import Slab, render, render_family_supine, write_subject

from imaging.io import read_volume
from imaging.preprocess import preprocess
from imaging.qa import dice
from imaging.segment import SegmentationError, detect_contrast, segment_volume

BREAST_MIN, MUSCLE_MIN = 0.95, 0.90  # issue 14's targets on every subject of the suite


@pytest.fixture(scope="module")
def fat_suppressed_phantoms(tmp_path_factory):
    from breastmodel.phantom import make_phantom

    root = tmp_path_factory.mktemp("fatsat")
    out = {}
    for contrast in ("t1", "t2"):
        subject = root / contrast / "subject"
        make_phantom(subject, seed=3, small=True, positions=("supine",), progress=False,
                     max_rotation_deg=15.0, max_translation_mm=30.0, contrast=contrast,
                     fat_suppressed=True)
        out[contrast] = (read_volume(subject / "supine.nii.gz"),
                         read_volume(root / contrast / "subject_truth" / "supine_labels.nii.gz"))
    return out


@pytest.mark.parametrize("contrast", ["t1", "t2"])
def test_fat_suppressed_phantom_is_detected_and_segmented(fat_suppressed_phantoms, contrast):
    img, truth = fat_suppressed_phantoms[contrast]
    res = segment_volume(img, name=f"fatsat_{contrast}.nii.gz")
    assert res.contrast == "fat_suppressed"
    assert any(n.startswith("contrast detected: fat_suppressed") for n in res.notes)
    d = dice(res.labels, truth)
    assert d["breast"] >= BREAST_MIN, d
    assert d["muscle"] >= MUSCLE_MIN, d


def test_fat_suppressed_slab_meeting_air():
    img, truth = render(Slab(), seed=3, contrast="t1_fatsat")
    res = segment_volume(img, gland=True, name="slab_fatsat")
    assert res.contrast == "fat_suppressed"
    d = dice(res.labels, truth)
    assert d["breast"] >= BREAST_MIN, d
    assert d["muscle"] >= MUSCLE_MIN, d


@pytest.mark.parametrize("cut", [70, 80])
def test_field_of_view_cut_through_the_thorax(fat_suppressed_phantoms, cut):
    # The T1 phantom with its field of view ending inside the thorax (posterior rows from
    # ``cut`` on dropped), as a breast coil's box cuts it (the suite's small-soft-000). The
    # face is no edge of the tissue: erosions and openings that took the outside for
    # background thinned the thorax interior and the muscle's start there, and the layer
    # between went to the breast. Measured when written, on the cut face: breast Dice
    # 0.804 / 0.779 and 1.47 / 1.56 times the truth's breast voxels before, 0.940 / 0.950
    # and 1.11 / 1.10 after; the whole volume's breast / muscle Dice 0.986 / 0.969 and
    # 0.988 / 0.983 before, 0.993 / 0.981 and 0.992 / 0.987 after.
    img, truth = fat_suppressed_phantoms["t1"]
    img, truth = img[:, :cut, :], truth[:, :cut, :]
    res = segment_volume(img, name=f"fatsat_cut{cut}.nii.gz")
    face_own, face_truth = res.labels[:, -1:, :], truth[:, -1:, :]
    assert dice(face_own, face_truth)["breast"] >= 0.90
    breast = [np.isin(sitk.GetArrayViewFromImage(f), (1, 3)).sum() for f in (face_own, face_truth)]
    assert breast[0] <= 1.2 * breast[1]
    d = dice(res.labels, truth)
    assert d["breast"] >= BREAST_MIN, d
    assert d["muscle"] >= MUSCLE_MIN, d


@pytest.mark.parametrize("contrast", ["t2", "t1"])
def test_fat_bright_slab_is_detected_as_fat_bright(contrast):
    img, _ = render(Slab(), seed=3, contrast=contrast)
    pre = preprocess(img)
    kind, why = detect_contrast(sitk.GetArrayFromImage(pre),
                                np.asarray(pre.GetSpacing())[::-1])
    assert kind == "fat_bright", why


def test_declared_contrast_is_used_and_checked():
    img, _ = render(Slab(), seed=3, contrast="t1_fatsat")
    res = segment_volume(img, contrast="fat_suppressed", levelset_iterations=0, name="s")
    assert res.contrast == "fat_suppressed"
    assert not any(n.startswith("contrast detected") for n in res.notes)
    with pytest.raises(SegmentationError, match="contrast must be"):
        segment_volume(img, contrast="t3", name="s")


def test_no_muscle_with_either_contrast_names_file_and_both_reasons():
    # a uniform ellipsoid of one tissue in air: a body, but no muscle layer in any contrast
    n = 60
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32)
    inside = ((x - 30) / 24) ** 2 + ((y - 30) / 20) ** 2 + ((z - 30) / 22) ** 2 <= 1
    a = np.where(inside, 400.0, 0.0).astype(np.float32)
    a += np.abs(np.random.default_rng(0).normal(0, 10, a.shape)).astype(np.float32)
    img = sitk.GetImageFromArray(a)
    with pytest.raises(SegmentationError) as err:
        segment_volume(img, name="blob.nii.gz")
    msg = str(err.value)
    assert "blob.nii.gz" in msg and "segment" in msg
    assert "muscle" in msg and "either contrast" in msg


@pytest.mark.parametrize("seed, fov, snr, bias", [
    (0, "coil", None, None), (0, "coil", 300.0, 0.0), (1, "slab", 100.0, None)])
def test_validation_family_fat_suppressed_subject(tmp_path, seed, fov, snr, bias):
    # The suite's subjects of seeds 0 and 1 (small): a breast coil's box and a muscle slab
    # meeting air, T1 fat-suppressed, 1.5 mm voxels, SNR 28 and 21. Measured when written:
    # seed 0, Dice 0.967 / 0.957 (supine).
    # At high SNR (seed 0 at 300 without a bias field, seed 1 at 100) the partial-volume
    # voxels over the skin rose above the noise floor: seed 0's contrast read fat bright
    # (ratio 4.2) and its muscle was lost (Dice 0.006); seed 1's darkest-tissue level fell
    # from the fat's 0.34 to 0.03, and the muscle took the breasts (Dice 0.43 / 0.85).
    spec, img, truth = render_family_supine(seed, tmp_path, snr=snr, bias=bias)
    assert spec.fat_suppressed and spec.fov == fov
    res = segment_volume(img, name=f"seed{seed}/supine.nii.gz")
    assert res.contrast == "fat_suppressed"
    d = dice(res.labels, truth)
    assert d["breast"] >= BREAST_MIN, d
    assert d["muscle"] >= MUSCLE_MIN, d
    assert res.confidence["breast_behind_wall_mm"] < 0


def test_a_contrast_read_wrong_is_flagged(tmp_path, monkeypatch):
    # Seed 0 at SNR 300 with the contrast's first look at 5 noise sigmas alone (before its
    # tissue floor): read fat bright, a segmentation that agrees with itself (0.995 / 0.969)
    # and puts the breast tissue 9 mm behind the chest wall; the confidence now says so,
    # and the segment stage stops on it.
    import imaging.segment_contrast as contrast
    from breastmodel.errors import StageError
    from breastmodel.pipeline.segment import segment_subject

    _, img, _ = render_family_supine(0, tmp_path, snr=300.0, bias=0.0)
    monkeypatch.setattr(contrast, "SURFACE_LEVEL", 0.0)
    res = segment_volume(img, name="seed0/supine.nii.gz")
    assert res.contrast == "fat_bright"
    assert res.confidence["breast_behind_wall_mm"] >= 0
    assert not res.confidence["confident"]
    assert any("behind the chest wall" in w for w in res.confidence["warnings"])
    subject = write_subject(tmp_path / "folder", {"supine": (img, (0.0, 1.0, 0.0))})
    with pytest.raises(StageError) as err:
        segment_subject(subject, tmp_path / "seg")
    assert "behind the chest wall" in str(err.value) and "contrast" in str(err.value)
