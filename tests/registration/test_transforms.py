"""Transform helpers: conventions, gravity, file round trip and clear errors."""

import numpy as np
import pytest
import SimpleITK as sitk

from registration.qa import fiducial_residuals, rotation_error_deg, target_registration_error
from registration.transforms import (
    gravity_in_reference,
    matrix_to_transform,
    read_transform,
    resample_to_reference,
    rigid_matrix,
    transform_points,
    transform_to_matrix,
    write_transform,
)


def _euler(deg=(10.0, -5.0, 20.0), t=(3.0, -4.0, 5.0)):
    return sitk.Euler3DTransform((1.0, 2.0, 3.0), *np.radians(deg), t)


def test_matrix_round_trip_and_points():
    e = _euler()
    m = transform_to_matrix(e)
    a = matrix_to_transform(m)
    pts = np.random.default_rng(0).normal(0, 50, (10, 3))
    assert np.allclose(transform_points(a, pts), transform_points(e, pts))
    r, t = rigid_matrix(e)
    assert np.allclose(r @ r.T, np.eye(3))
    assert np.allclose(pts @ r.T + t, transform_points(e, pts))


def test_gravity_goes_back_through_the_rotation():
    e = _euler()
    r, _ = rigid_matrix(e)
    g_ref = np.array([0.0, 1.0, 0.0])
    g_pos = r @ g_ref  # the same physical direction seen in the position's frame
    assert np.allclose(gravity_in_reference(e, g_pos), g_ref)


def test_transform_file_round_trip_and_missing_file(tmp_path):
    e = _euler()
    write_transform(e, tmp_path / "p.tfm")
    back = read_transform(tmp_path / "p.tfm")
    pts = np.array([[10.0, 20.0, 30.0]])
    assert np.allclose(transform_points(back, pts), transform_points(e, pts))
    assert [p.name for p in tmp_path.iterdir()] == ["p.tfm"]
    with pytest.raises(FileNotFoundError, match="registration: transform file .* does not"):
        read_transform(tmp_path / "missing.tfm")
    (tmp_path / "bad.tfm").write_text("not a transform\n")
    with pytest.raises(ValueError, match="not a readable ITK transform"):
        read_transform(tmp_path / "bad.tfm")


def test_errors_and_residuals():
    e = _euler()
    f = _euler(t=(3.5, -4.0, 5.0))
    pts = np.zeros((3, 3))
    assert np.allclose(target_registration_error(e, f, pts), 0.5)
    assert rotation_error_deg(e, f) < 1e-4  # arccos near 1 loses half the digits
    g = _euler(deg=(10.0, -5.0, 20.3))
    assert rotation_error_deg(e, g) == pytest.approx(0.3, abs=0.05)
    fixed = {"a": np.zeros(3), "b": np.ones(3)}
    moving = {k: transform_points(e, v)[0] + [0, 0, 1.0] for k, v in fixed.items()}
    assert fiducial_residuals(e, fixed, moving) == pytest.approx({"a": 1.0, "b": 1.0})


def test_resampling_labels_uses_nearest_neighbour():
    a = np.zeros((20, 20, 20), np.uint8)
    a[5:15, 5:15, 5:15] = 2
    img = sitk.GetImageFromArray(a)
    shift = sitk.TranslationTransform(3, (2.0, 0.0, 0.0))
    out = sitk.GetArrayFromImage(resample_to_reference(img, img, shift, labels=True))
    assert set(np.unique(out)) == {0, 2}
    assert np.array_equal(out[:, :, 3:13], a[:, :, 5:15])
