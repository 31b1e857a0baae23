"""Phantoms: determinism, truth consistency, label volumes and rendering statistics."""

import json

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from breastmodel.phantom import Anatomy, make_phantom, patient_gravity, truth_folder
from breastmodel.phantom.anatomy import (
    FAT,
    GLAND,
    MARKER,
    MUSCLE,
    SKIN,
    THORAX,
    TISSUE_NAMES,
    Superellipsoid,
    reference_volumes,
)
from breastmodel.phantom.motion import RigidMotion, random_motion
from breastmodel.phantom.rendering import bias_field, render
from breastmodel.phantom.voxelize import Grid, voxelize
from imaging.subject import read_subject

FAST = dict(small=True, voxel_size=3.0, positions=("supine", "prone"), progress=False)


@pytest.fixture(scope="module")
def small_phantom(tmp_path_factory):
    out = tmp_path_factory.mktemp("ph") / "subj"
    make_phantom(out, seed=3, small=True, voxel_size=1.5, progress=False)
    return out


def _array(path):
    return sitk.GetArrayFromImage(sitk.ReadImage(str(path)))


def test_same_seed_gives_identical_bytes(tmp_path):
    a = make_phantom(tmp_path / "a", seed=7, **FAST)
    b = make_phantom(tmp_path / "b", seed=7, **FAST)
    c = make_phantom(tmp_path / "c", seed=8, **FAST)
    for name in ("supine.nii.gz", "prone.nii.gz", "subject.toml", "fiducials.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    for name in ("supine_tissue.nii.gz", "supine_labels.nii.gz", "supine_motion.tfm"):
        assert (truth_folder(a) / name).read_bytes() == (truth_folder(b) / name).read_bytes()
    assert (a / "supine.nii.gz").read_bytes() != (c / "supine.nii.gz").read_bytes()
    # A position's motion depends on its name and the seed only, not on the other positions.
    d = make_phantom(tmp_path / "d", seed=7, **{**FAST, "positions": ("supine",)})
    assert (a / "supine.nii.gz").read_bytes() == (d / "supine.nii.gz").read_bytes()


def test_phantom_folder_is_valid_and_matches_truth(small_phantom):
    s = read_subject(small_phantom)
    truth = json.loads((truth_folder(small_phantom) / "truth.json").read_text())
    assert s.reference == "supine" and set(s.positions) == {"prone", "supine", "supine_tilted"}
    assert s.positions["supine_tilted"].tilt_deg == 45.0
    an = Anatomy.small()
    for name, pos in s.positions.items():
        t = truth["positions"][name]
        m = np.array(t["motion"]["matrix_patient_to_image"])
        np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)
        assert t["motion"]["rotation_angle_deg"] <= 5.0
        assert np.linalg.norm(t["motion"]["translation_mm"]) <= 10.0
        # gravity in subject.toml = motion rotation of the patient-frame gravity
        g_patient, _ = patient_gravity(name)
        np.testing.assert_allclose(pos.gravity, m[:3, :3] @ g_patient, atol=1e-9)
        # fiducials.csv = truth markers = motion of the anatomy's markers (3 decimals in CSV)
        tfm = sitk.ReadTransform(str(truth_folder(small_phantom) / f"{name}_motion.tfm"))
        for label, p in an.markers().items():
            q = np.array(tfm.TransformPoint(tuple(p)))
            np.testing.assert_allclose(q, m[:3, :3] @ p + m[:3, 3], atol=1e-9)
            np.testing.assert_allclose(s.fiducials[name][label], q, atol=1e-3)
        # the truth labels at the moved anatomical points hold the right tissue
        tissue = sitk.ReadImage(str(truth_folder(small_phantom) / f"{name}_tissue.nii.gz"))
        image = _array(pos.volume_path)
        for label, expected in (
            ("gland_center_left", GLAND),
            ("gland_center_right", GLAND),
        ):
            idx = tissue.TransformPhysicalPointToIndex(tuple(s.landmarks[name][label]))
            assert tissue[idx] == expected
        for label in s.fiducials[name]:
            idx = tissue.TransformPhysicalPointToIndex(tuple(s.fiducials[name][label]))
            assert tissue[idx] == MARKER
            # markers are the brightest objects: above every fat voxel's median
            assert image[idx[::-1]] > np.median(image[_array(
                truth_folder(small_phantom) / f"{name}_tissue.nii.gz") == FAT])


def test_segmentation_labels_follow_the_convention(small_phantom):
    tdir = truth_folder(small_phantom)
    fine = _array(tdir / "supine_tissue.nii.gz")
    seg = _array(tdir / "supine_labels.nii.gz")
    assert set(np.unique(seg)) == {0, 1, 2, 3}
    # Surface voxels vote separately for the two label sets; the bulk must agree exactly.
    for f, expected in {MUSCLE: 2, GLAND: 3, THORAX: 0, MARKER: 0, 0: 0}.items():
        assert np.mean(seg[fine == f] == expected) > 0.97, TISSUE_NAMES[f]
    assert np.mean(seg[(fine == FAT) | (fine == SKIN)] == 1) > 0.97  # all anterior here


def test_tissue_behind_the_torso_axis_is_background():
    """Fat and skin are breast tissue (1) in front of the torso axis (patient y < 0), else 0."""
    an = Anatomy.small()
    grid = Grid.from_box((-85.0, -100.0, -20.0), (85.0, 30.0, 20.0), 2.0)
    tv = voxelize(an, grid)
    y = grid.origin[1] + grid.spacing * np.arange(grid.size[1])[None, :, None]
    soft = (tv.fine == FAT) | (tv.fine == SKIN)
    front, back = soft & (y < -grid.spacing), soft & (y > grid.spacing)
    assert front.sum() > 1000 and back.sum() > 100
    assert np.all(tv.seg[front] == 1)
    assert np.all(tv.seg[back] == 0)


def test_label_volumes_match_reference_volumes_at_half_mm():
    """Voxel-counted tissue volumes at 0.5 mm are within 1 % of the grid-free volumes.

    Crop around the left breast of the small anatomy (keeps the test at ~4 M voxels). The
    reference is exact along y and converges as step^2 in x, z (0.25 mm gives < 0.02 %).
    """
    an = Anatomy.small()
    lo, hi = (0.0, -100.0, -40.0), (80.0, -10.0, 30.0)
    ref = reference_volumes(an, box_min=lo, box_max=hi, step=0.25)
    tv = voxelize(an, Grid.from_box(lo, hi, 0.5))
    counts = np.bincount(tv.fine.ravel(), minlength=len(TISSUE_NAMES)) * 0.5**3
    for code, name in enumerate(TISSUE_NAMES):
        if name == "marker":
            continue  # 1.5 markers, 50 mm^3: checked against closed forms below
        assert counts[code] == pytest.approx(ref[name], rel=0.01), name
    assert ref["skin"] > 1e4 and ref["gland"] > 1e4  # the crop holds real amounts of each
    # the crop holds the left IMF marker and half the lower sternal marker; only 16 lines
    # cross a 4 mm marker at step 0.25, so the reference is good to ~1 % there
    sphere = 4 / 3 * np.pi * an.marker_radius**3
    assert ref["marker"] == pytest.approx(1.5 * sphere, rel=0.015)
    # 268 voxels per marker: +-3 % covers the surface-voxel vote noise
    assert counts[MARKER] == pytest.approx(1.5 * sphere, rel=0.03)


def test_reference_volumes_against_closed_forms():
    an = Anatomy.small()
    # A slab above the breasts and markers holds only the nested torso ellipses.
    lo, hi = (-80.0, -60.0, 36.0), (80.0, 60.0, 44.0)
    ref = reference_volumes(an, box_min=lo, box_max=hi, step=0.25)
    area = [an.torso_layer(d).volume_per_mm for d in (0.0, 2.0, 7.0, 15.0)]
    length = hi[2] - lo[2]
    assert ref["skin"] == pytest.approx((area[0] - area[1]) * length, rel=2e-4)
    assert ref["fat"] == pytest.approx((area[1] - area[2]) * length, rel=2e-4)
    assert ref["muscle"] == pytest.approx((area[2] - area[3]) * length, rel=2e-4)
    assert ref["thorax"] == pytest.approx(area[3] * length, rel=2e-4)
    # superellipsoid volume formula vs its chords (exponent 2.4)
    shape = Superellipsoid((0.0, 0.0, 0.0), (20.0, 15.0, 10.0), 2.4)
    h = 0.05
    x, z = np.meshgrid(np.arange(-20 + h / 2, 20, h), np.arange(-10 + h / 2, 10, h))
    lo_y, hi_y = shape.chord_y(x.ravel(), z.ravel())
    assert np.nansum(hi_y - lo_y) * h * h == pytest.approx(shape.volume, rel=1e-3)


@pytest.mark.parametrize("snr", [10.0, 40.0])
def test_rendered_snr_matches_request(snr):
    """SNR = mean fat signal / noise sigma, measured on the noisy image alone.

    sigma from the Rayleigh-distributed air far from the body (mean = sigma sqrt(pi/2)),
    fat signal from eroded pure-fat voxels (Rician bias < 1/(2 SNR^2) = 0.5 % at SNR 10).
    """
    an = Anatomy.small()
    tv = voxelize(an, Grid.from_box(an.fov_min, an.fov_max, 2.0))
    r = render(tv, np.random.default_rng(0), snr=snr, bias=0.3)
    air = ndimage.binary_erosion(tv.fine == 0, iterations=3)
    fat = ndimage.binary_erosion(tv.fine == FAT, iterations=1)
    assert air.sum() > 5000 and fat.sum() > 2000
    sigma = r.image[air].mean() / np.sqrt(np.pi / 2)
    measured = r.image[fat].mean() / sigma
    assert measured == pytest.approx(snr, rel=0.10)
    assert r.noise_sigma == pytest.approx(r.mean_fat / snr, rel=1e-6)


def test_bias_field_is_smooth_and_bounded():
    field = bias_field((40, 30, 50), np.random.default_rng(1), amplitude=0.3)
    assert field.min() == pytest.approx(0.7, abs=1e-5)  # centred quadratic, peak scaled
    assert field.max() == pytest.approx(1.3, abs=1e-5)
    # Markov's inequality: a quadratic bounded by 1 on [-1, 1] has |slope| <= 4, so one step
    # of 2/49 changes the field by at most 0.3 * 4 * 2/49.
    assert np.abs(np.diff(field, axis=2)).max() <= 0.3 * 4 * 2 / 49
    assert np.all(bias_field((4, 5, 6), np.random.default_rng(1), amplitude=0.0) == 1.0)


def test_rigid_motion_round_trip_and_gravity():
    m = random_motion(
        np.random.default_rng(5), max_rotation_deg=5, max_translation_mm=10, center=(1, 2, 3)
    )
    p = np.random.default_rng(6).normal(size=(20, 3)) * 50
    np.testing.assert_allclose(m.inverse(m.apply(p)), p, atol=1e-10)
    hom = np.c_[p, np.ones(len(p))] @ m.matrix().T
    np.testing.assert_allclose(hom[:, :3], m.apply(p), atol=1e-10)
    np.testing.assert_allclose(m.to_sitk().TransformPoint(tuple(p[0])), m.apply(p[:1])[0])
    assert 0 < m.axis_angle()[1] <= 5
    assert RigidMotion.identity().axis_angle()[1] == 0.0
    np.testing.assert_allclose(patient_gravity("supine")[0], [0, 1, 0])
    np.testing.assert_allclose(patient_gravity("prone")[0], [0, -1, 0])
    g, tilt = patient_gravity("supine_tilted_30")
    assert tilt == 30.0
    np.testing.assert_allclose(g, [-0.5, np.sqrt(3) / 2, 0], atol=1e-12)
    with pytest.raises(ValueError, match="unknown position 'sideways'"):
        patient_gravity("sideways")


def _cli(argv):
    """Parse and run one command module the way ``breastmodel`` does (without its wrapper)."""
    import argparse

    from breastmodel.commands import info, phantom

    parser = argparse.ArgumentParser(prog="breastmodel")
    sub = parser.add_subparsers(dest="command")
    for module in (phantom, info):
        module.add_parser(sub).set_defaults(_run=module.run)
    args = parser.parse_args(argv)
    return args._run(args)


def test_cli_phantom_and_info(tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["phantom", str(out), "--small", "--voxel-size", "3", "--positions", "supine,prone",
            "--seed", "2", "--snr", "15"]
    assert _cli(args) == 0
    assert _cli(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "subject   phantom-0002" in text and text.rstrip().endswith("valid")
    assert "57x30x33 voxels" in text  # 170 x 90 x 100 mm at 3 mm, rounded
    truth = json.loads((truth_folder(out) / "truth.json").read_text())
    assert truth["snr"] == 15.0 and set(truth["positions"]) == {"supine", "prone"}
    (out / "prone.nii.gz").unlink()
    assert _cli(["info", str(out)]) == 1
    assert "prone.nii.gz does not exist" in capsys.readouterr().err
    with pytest.raises(ValueError, match="unknown position 'sideways'"):
        _cli(["phantom", str(tmp_path / "x"), "--positions", "sideways"])


def test_deformation_hook_moves_the_anatomy(tmp_path):
    """A displacement field is one added step: a uniform 3 mm superior shift moves the labels
    by exactly 2 slices of 1.5 mm, and the truth landmarks by 3 mm."""
    an = Anatomy.small()
    grid = Grid.from_box(an.fov_min, an.fov_max, 1.5)

    def shift(points):
        return np.tile([0.0, 0.0, 3.0], (len(points), 1))

    plain = voxelize(an, grid).fine
    moved = voxelize(an, grid, displacement=shift).fine
    np.testing.assert_array_equal(moved[2:], plain[:-2])
    assert not np.array_equal(moved, plain)

    out = make_phantom(
        tmp_path / "def", seed=0, small=True, voxel_size=3.0, positions=("supine",),
        max_rotation_deg=0.0, max_translation_mm=0.0, progress=False,
        deformation=lambda position: shift,
    )
    s = read_subject(out)
    for label, p in an.landmarks().items():
        np.testing.assert_allclose(s.landmarks["supine"][label], p + [0, 0, 3], atol=1e-3)


def test_bounding_box_classification_equals_brute_force():
    """The per-breast bounding boxes are a speed-up only: same codes as testing every shape."""
    an = Anatomy()
    rng = np.random.default_rng(0)
    lo, hi = np.array(an.fov_min), np.array(an.fov_max)
    marks = np.array(list(an.markers().values()))
    p = np.vstack([
        lo + (hi - lo) * rng.random((200_000, 3)),
        (marks[:, None, :] + 2.0 * rng.normal(size=(4, 5000, 3))).reshape(-1, 3),
    ])
    inside = {k: v.contains(*p.T) for k, v in an.primitives().items()}
    outer = inside["torso_outer"] | inside["breast_left_outer"] | inside["breast_right_outer"]
    outer |= inside["nipple_left"] | inside["nipple_right"]
    inner = inside["torso_inner"] | inside["breast_left_inner"] | inside["breast_right_inner"]
    expected = np.full(len(p), FAT, np.uint8)
    expected[inside["gland_left"] | inside["gland_right"]] = GLAND
    expected[inside["muscle_outer"]] = MUSCLE
    expected[inside["muscle_inner"]] = THORAX
    expected[~inner] = SKIN
    expected[~outer] = 0
    for k, v in inside.items():
        if k.startswith("marker_"):
            expected[v] = MARKER
    got = an.classify(p)
    np.testing.assert_array_equal(got, expected)
    assert np.count_nonzero(got == MARKER) > 1000  # the marker samples do hit markers


@pytest.mark.slow
def test_full_size_default_phantom(tmp_path):
    """The default 1 mm phantom (3 x 11.5 M voxels) is valid and has the requested SNR."""
    out = make_phantom(tmp_path / "full", seed=0, progress=False)
    s = read_subject(out)
    img = s.load("supine")
    assert img.GetSize() == (320, 180, 200)
    arr = sitk.GetArrayFromImage(img).astype(float)
    fine = _array(truth_folder(out) / "supine_tissue.nii.gz")
    air = ndimage.binary_erosion(fine == 0, iterations=3)
    fat = ndimage.binary_erosion(fine == FAT, iterations=1)
    sigma = arr[air].mean() / np.sqrt(np.pi / 2)
    assert arr[fat].mean() / sigma == pytest.approx(20.0, rel=0.10)


def test_markers_follow_a_deformation_the_fixed_point_cannot_invert():
    """x = X + u(x) with |grad u| > 1 (u = -1.5 (x - c): the plain fixed point diverges) is
    solved by the Newton fallback; the result satisfies the equation and is the exact root."""
    from breastmodel.phantom.placement import deformed_point

    c = np.array([10.0, -20.0, 5.0])

    def u(p):
        return -1.5 * (np.asarray(p, float) - c)

    X = np.array([3.0, 4.0, -7.0])
    x = deformed_point(X, u)
    assert np.max(np.abs(x - X - u(x))) < 1e-8
    assert np.allclose(x[0], (X + 1.5 * c) / 2.5, atol=1e-8)


def test_markers_where_the_deformation_jumps_by_less_than_the_root_tolerance():
    """u continuous only up to a 0.006 mm jump at the root (the closest-point extrapolation
    outside a simulated mesh): no exact root exists (|x - X - u(x)| >= 0.003 mm); the marker
    lands within ROOT_TOL_MM of one. A fold (a jump of millimetres) is an error."""
    from breastmodel.phantom.placement import ROOT_TOL_MM, deformed_point

    def jumping(jump):
        def u(p):  # x - X - u(x) jumps from -jump/2 to +jump/2 in x0 at the root x0 = 1
            p = np.asarray(p, float)
            shift = np.where(p[:, :1] >= 1.0, -jump / 2, jump / 2)
            return 0.2 * p + shift * np.array([1.0, 0.0, 0.0])
        return u

    X = np.array([0.8, 4.0, -7.0])  # the smooth root is x = X / 0.8
    u = jumping(0.006)
    x = deformed_point(X, u)
    assert np.max(np.abs(x - X - u(x))) < ROOT_TOL_MM
    assert np.allclose(x[0], X / 0.8, atol=0.01)
    with pytest.raises(RuntimeError, match="not invertible"):
        deformed_point(X, jumping(6.0))


def test_a_marker_where_the_deformation_jumps_lands_where_the_image_shows_it():
    """u jumps by 0.3 mm at the root (the closest-point extrapolation switching surfaces in a
    concave corner): no root within ROOT_TOL_MM exists, and the marker is placed at the centre
    of the rendered ball, the points x whose material point x - u(x) lies in the marker's
    ball, here computed again on a finer grid; a jump above half the radius is an error."""
    from breastmodel.phantom.placement import ROOT_TOL_MM, deformed_point

    def u(p, jump=0.3):  # X(x) = 0.8 x -+ jump/2 in x0 on either side of x0 = 1
        p = np.asarray(p, float)
        shift = np.where(p[:, :1] >= 1.0, -jump / 2, jump / 2)
        return 0.2 * p + shift * np.array([1.0, 0.0, 0.0])

    X, r = np.array([0.8, 4.0, -7.0]), 2.0
    x = deformed_point(X, u, radius=r)
    assert np.max(np.abs(x - X - u(x))) > ROOT_TOL_MM  # no root: the fallback placed it
    t = np.arange(-4.0, 4.0, 0.04)
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3) + X / 0.8
    inside = np.sum((g - u(g) - X) ** 2, axis=1) <= r**2
    assert 0 < inside.sum() and np.allclose(x[0], g[inside].mean(axis=0), atol=0.02)
    assert np.linalg.norm(x[0] - X / 0.8) < 0.3  # within the jump of the smooth root
    with pytest.raises(RuntimeError, match="not invertible"):
        deformed_point(X, lambda p: u(p, jump=1.2), radius=r)
