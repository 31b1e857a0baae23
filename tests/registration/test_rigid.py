"""Rigid registration on a phantom with known motions (15 deg / 30 mm bounds)."""

import json
import shutil

import numpy as np
import pytest
import SimpleITK as sitk

from breastmodel.phantom import make_phantom
from imaging.fiducials import find_fiducials
from imaging.io import read_volume
from imaging.preprocess import preprocess
from imaging.subject import read_subject
from registration.qa import rotation_error_deg, target_registration_error
from registration.rigid import (
    chest_wall_mask,
    landmark_transform,
    refine_rigid,
    register_rigid,
)
from registration.transforms import matrix_to_transform, read_transform, transform_points


@pytest.fixture(scope="module")
def phantom(mri_phantom):
    return mri_phantom


def _truth(truth_dir, ref, pos):
    m = json.loads((truth_dir / "truth.json").read_text())["positions"]
    a = {k: np.asarray(m[k]["motion"]["matrix_patient_to_image"]) for k in (ref, pos)}
    return matrix_to_transform(a[pos] @ np.linalg.inv(a[ref]))


def _chest_points(labels):
    idx = np.argwhere(sitk.GetArrayViewFromImage(labels) == 2)[::53][:, ::-1]
    return np.asarray([labels.TransformContinuousIndexToPhysicalPoint(tuple(map(float, i)))
                       for i in idx])


def test_fiducial_initialised_registration_meets_targets(phantom):
    subject_dir, truth_dir = phantom
    subject = read_subject(subject_dir)
    fixed = preprocess(subject.load("supine"), denoise_iterations=0)
    moving = preprocess(subject.load("prone"), denoise_iterations=0)
    labels = read_volume(truth_dir / "supine_labels.nii.gz")
    res = register_rigid(fixed, moving, fixed_points=find_fiducials(fixed),
                         moving_points=find_fiducials(moving), fixed_mask=chest_wall_mask(labels))
    truth = _truth(truth_dir, "supine", "prone")
    r_true = rotation_error_deg(truth, sitk.Euler3DTransform())
    assert r_true > 5.0  # the test means something: the positions differ by a real rotation
    tre = target_registration_error(res.transform, truth, _chest_points(labels))
    assert res.initialisation == "fiducials"
    assert tre.mean() <= 0.5  # the targets
    assert rotation_error_deg(res.transform, truth) <= 0.3
    assert max(res.fiducial_residuals.values()) <= 0.5


def test_landmark_initialiser_handles_missing_and_mislabelled_markers():
    rng = np.random.default_rng(2)
    fixed = {k: rng.normal(0, 60, 3) for k in ("a", "b", "c", "d")}
    true = sitk.Euler3DTransform((0.0, 0.0, 0.0), 0.2, -0.1, 0.25, (10.0, -20.0, 5.0))
    moving = {k: transform_points(true, v)[0] for k, v in fixed.items()}
    pts = rng.normal(0, 60, (20, 3))

    t, used, notes = landmark_transform(fixed, {k: moving[k] for k in "abc"})
    assert used == ("a", "b", "c") and not notes
    assert target_registration_error(t, true, pts).max() < 1e-6

    bad = dict(moving, d=moving["d"] + [25.0, 0.0, 0.0])  # one misdetected marker
    t, used, notes = landmark_transform(fixed, bad)
    assert used == ("a", "b", "c") and "['d'] dropped" in notes[0]
    assert target_registration_error(t, true, pts).max() < 1e-6

    swapped = dict(moving, a=moving["b"], b=moving["a"])  # two labels exchanged
    t, used, notes = landmark_transform(fixed, {k: swapped[k] for k in "abc"})
    assert t is None and "inconsistent" in notes[0]

    t, used, notes = landmark_transform(fixed, {"a": moving["a"]})
    assert t is None and "need 3" in notes[0]


def _blobs(n=48, seed=0):
    """Smooth asymmetric volume: six Gaussian blobs of different sizes, 2 mm voxels."""
    rng = np.random.default_rng(seed)
    z, y, x = np.mgrid[:n, :n, :n] * 2.0 - n
    a = np.zeros((n, n, n), np.float32)
    for _ in range(6):
        c = rng.uniform(-0.5 * n, 0.5 * n, 3)
        s = rng.uniform(4.0, 10.0)
        a += np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / (2 * s * s))
    img = sitk.GetImageFromArray(a)
    img.SetSpacing((2.0, 2.0, 2.0))
    img.SetOrigin((-float(n),) * 3)
    return img


def test_refinement_keeps_a_perfect_start():
    """Registering a volume to itself from the identity: every other position has a worse
    correlation, so the best-visited rule must return the identity exactly (a fixed-step
    optimiser alone would take at least one step away from it)."""
    img = _blobs()
    pts = np.random.default_rng(1).uniform(-30, 30, (20, 3))
    ident = sitk.Euler3DTransform()
    res, metric = refine_rigid(img, img, ident, shrink=(2, 1), smooth_mm=(2.0, 0.0),
                               sampling=0.2)
    assert target_registration_error(res, ident, pts).max() < 1e-9
    assert metric == pytest.approx(-1.0, abs=1e-6)


def test_missing_markers_warn_and_fall_back(caplog):
    """No fiducials: a warning, the moments/multi-start initialisation, and still aligned."""
    img = _blobs()
    true = sitk.Euler3DTransform((0.0, 0.0, 0.0), 0.05, -0.03, 0.08, (4.0, -3.0, 2.0))
    # moving(x) = img(true^-1 x), so the registration must find true
    moving = sitk.Resample(img, img, true.GetInverse(), sitk.sitkLinear, 0.0)
    with caplog.at_level("WARNING"):
        res = register_rigid(img, moving)
    assert res.initialisation == "moments"
    assert any("moments" in r.getMessage() for r in caplog.records)
    pts = np.random.default_rng(1).uniform(-30, 30, (20, 3))
    assert target_registration_error(res.transform, true, pts).mean() <= 0.5


def _wall_and_breast(breast_shift_mm, n=48):
    """(volume, y): six blobs behind y = 0 (a rigid wall) and a big bright one in front (a
    breast) moved by ``breast_shift_mm`` (x, y, z), 2 mm voxels; y the voxels' y, mm."""
    rng = np.random.default_rng(0)
    z, y, x = np.mgrid[:n, :n, :n] * 2.0 - n
    a = np.zeros((n, n, n), np.float32)
    for _ in range(6):
        c = rng.uniform(-0.5 * n, 0.5 * n, 3)
        c[1] = rng.uniform(0.0, 0.5 * n)
        s = rng.uniform(4.0, 8.0)
        a += np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / (2 * s * s))
    c = np.array([0.0, -25.0, 0.0]) + breast_shift_mm
    a += 3.0 * np.exp(-((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) / 200.0)
    img = sitk.GetImageFromArray(a)
    img.SetSpacing((2.0, 2.0, 2.0))
    img.SetOrigin((-float(n),) * 3)
    return img, y


@pytest.mark.parametrize("fall, kept, tre_mm", [
    ((10.0, -20.0, 15.0), "the scanner's frame", 0.5),
    ((0.0, -12.0, 10.0), "moments and the whole body", 1.2)])
def test_without_fiducials_another_start_is_kept_only_where_it_fits_the_wall_clearly_better(
        fall, kept, tre_mm):
    """No fiducials, a breast that fell forward and up besides the body's small rigid motion.
    Fallen 20 mm forward, 15 up and 10 sideways it draws the moments start refined over the
    whole body 5.8 mm off the wall (correlation -0.952); the scanner's frame fits the wall
    (0.12 mm, -0.999), better by more than the margin, and is kept. Fallen 12 mm and 10 mm
    the first start comes to 0.96 mm (-0.997) and the others (-0.999) are not clearly
    better: the first is kept, as the suite's scans need (their starts' correlations lay
    within 0.003, at poses along the wall's weak directions)."""
    fixed, y = _wall_and_breast(np.zeros(3))
    true = sitk.Euler3DTransform((0.0, 0.0, 0.0), 0.03, -0.02, 0.04, (3.0, -2.0, 2.0))
    fallen, _ = _wall_and_breast(np.array(fall))
    moving = sitk.Resample(fallen, fixed, true.GetInverse(), sitk.sitkLinear, 0.0)
    wall = sitk.GetImageFromArray((y > -2.0).astype(np.uint8))
    wall.CopyInformation(fixed)
    res = register_rigid(fixed, moving, fixed_mask=wall)
    pts = np.argwhere(sitk.GetArrayViewFromImage(wall)[::6, ::6, ::6])[:, ::-1] * 12.0 - 48.0
    assert res.initialisation == "moments"
    assert target_registration_error(res.transform, true, pts).mean() <= tre_mm
    assert any(f"the chest-wall fit from {kept} was kept" in w for w in res.warnings)


def test_chest_wall_mask_needs_muscle():
    labels = sitk.Image(8, 8, 8, sitk.sitkUInt8)
    with pytest.raises(ValueError, match="no muscle"):
        chest_wall_mask(labels)


@pytest.mark.slow
def test_command_falls_back_when_markers_are_mislabelled(phantom, tmp_path):
    """Prone's CSV labels exchanged: a warning, the moments fallback, and still aligned."""
    from breastmodel.cli import main

    subject_dir, truth_dir = phantom
    subj = tmp_path / "subject"
    shutil.copytree(subject_dir, subj)
    rows = (subj / "fiducials.csv").read_text().splitlines()
    fixed_rows = []
    for r in rows:
        if r.startswith("prone,sternum_upper"):
            r = r.replace("sternum_upper", "imf_left")
        elif r.startswith("prone,imf_left"):
            r = r.replace("imf_left", "sternum_upper")
        fixed_rows.append(r)
    (subj / "fiducials.csv").write_text("\n".join(fixed_rows) + "\n")
    seg = tmp_path / "seg"  # truth labels stand in for a segmentation (keeps the test fast)
    seg.mkdir()
    for p in ("supine", "prone"):
        shutil.copy(truth_dir / f"{p}_labels.nii.gz", seg / f"{p}_labels.nii.gz")
    out = tmp_path / "reg"
    assert main(["register", str(subj), "--out", str(out), "--truth", str(truth_dir),
                 "--seg-dir", str(seg)]) == 0
    rep = json.loads((out / "registration.json").read_text())
    e = rep["positions"]["prone"]
    assert e["initialisation"] == "moments"
    assert any("moments" in w for w in e["warnings"])
    assert e["tre_mm"]["mean"] <= 1.0  # looser: no fiducials to start from
    tfm = read_transform(out / "prone.tfm")
    assert np.allclose(np.asarray(e["matrix"])[:3, 3], tfm.TransformPoint((0.0, 0.0, 0.0)))
    for name in ("prone_in_reference.nii.gz", "prone_labels_in_reference.nii.gz",
                 "reference_labels.nii.gz", "gravity.json"):
        assert (out / name).is_file()
    g = json.loads((out / "gravity.json").read_text())
    # prone and supine gravity are opposite in the patient; in one frame they must be too
    assert np.dot(g["prone"], g["supine"]) < -0.99
    # a missing transform file: one clear error
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_transform(out / "supine.tfm")


@pytest.mark.slow
def test_full_size_registration_meets_targets(tmp_path):
    """Full-size phantom, motions up to 15 deg / 30 mm, segmentation-derived chest wall."""
    from imaging.segment import segment_volume

    subject_dir = make_phantom(tmp_path / "full", seed=1,
                               positions=("supine", "supine_tilted"),
                               max_rotation_deg=15.0, max_translation_mm=30.0, progress=False)
    truth_dir = tmp_path / "full_truth"
    subject = read_subject(subject_dir)
    fixed = preprocess(subject.load("supine"), denoise_iterations=0)
    moving = preprocess(subject.load("supine_tilted"), denoise_iterations=0)
    labels = segment_volume(subject.load("supine")).labels
    res = register_rigid(fixed, moving, fixed_points=find_fiducials(fixed),
                         moving_points=find_fiducials(moving), fixed_mask=chest_wall_mask(labels))
    truth = _truth(truth_dir, "supine", "supine_tilted")
    tre = target_registration_error(res.transform, truth,
                                    _chest_points(read_volume(truth_dir / "supine_labels.nii.gz")))
    assert tre.mean() <= 0.5
    assert rotation_error_deg(res.transform, truth) <= 0.3


def test_the_chest_wall_levels_keep_voxels_of_at_most_3_mm():
    """A level shrunk to voxels coarser than 3 mm is left out (on the suite's 2 mm coil
    subject the 4 mm level moved a start at the truth 3 mm away); the finest level always
    runs."""
    from registration.rigid import MAX_VOXEL_MM, _fine

    def image(spacing):
        img = sitk.Image(8, 8, 8, sitk.sitkFloat32)
        img.SetSpacing(spacing)
        return img

    assert MAX_VOXEL_MM == 3.0
    both, fine = {"shrink": (2, 1), "smooth_mm": (1.0, 0.0)}, {"shrink": (1,), "smooth_mm": (0.0,)}
    for spacing, want in (((1.0, 1.0, 1.0), both), ((1.5, 1.5, 1.5), both),
                          ((1.0, 1.0, 2.0), both), ((2.0, 2.0, 2.0), fine),
                          ((4.0, 4.0, 4.0), fine)):
        assert _fine(image(spacing), (2, 1), (1.0, 0.0)) == want
