"""Preprocessing on tiny synthetic volumes with known answers."""

import numpy as np
import pytest
import SimpleITK as sitk

from imaging.preprocess import (
    _N4_MEMORY,
    BACKGROUND_OVER_FAT,
    body_box,
    check_volume,
    denoise,
    n4_correct,
    normalise,
    preprocess,
    resample_isotropic,
)
from imaging.segment_contrast import magnitude_level


def _block(shape=(40, 48, 56), spacing=(2.0, 2.0, 2.0)):
    """Air with a bright box (100) holding a darker slab (30); returns (image, box mask)."""
    a = np.zeros(shape, np.float32)
    box = np.zeros(shape, bool)
    box[6:-6, 6:-6, 6:-6] = True
    a[box] = 100.0
    a[15:25, 6:-6, 6:-6] = 30.0
    img = sitk.GetImageFromArray(a)
    img.SetSpacing(spacing)
    img.SetOrigin((-10.0, 5.0, 3.0))
    return img, box


def test_check_volume_rejects_bad_inputs():
    with pytest.raises(ValueError, match="2-D"):
        check_volume(sitk.Image(8, 8, sitk.sitkFloat32), name="x.nii")
    with pytest.raises(ValueError, match="4-D"):
        check_volume(sitk.Image([8, 8, 8, 3], sitk.sitkFloat32), name="x.nii")
    with pytest.raises(ValueError, match="components"):
        check_volume(sitk.Image([8, 8, 8], sitk.sitkVectorFloat32, 2), name="x.nii")
    a = np.ones((8, 8, 8), np.float32)
    a[2, 3, 4] = np.nan
    with pytest.raises(ValueError, match="1 NaN"):
        check_volume(sitk.GetImageFromArray(a), name="x.nii")
    check_volume(sitk.GetImageFromArray(np.ones((8, 8, 8), np.float32)))  # passes


def test_n4_removes_a_smooth_bias_field():
    img, box = _block()
    a = sitk.GetArrayFromImage(img)
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in a.shape], indexing="ij")
    biased = sitk.GetImageFromArray((a * (1.0 + 0.3 * x + 0.15 * y * z)).astype(np.float32))
    biased.CopyInformation(img)
    out = sitk.GetArrayFromImage(n4_correct(biased, shrink=2))
    bright = box.copy()
    bright[13:27] = False  # the bright tissue only, away from the dark slab
    inner = bright & (np.abs(x) < 0.6)
    cv = lambda v: float(np.std(v) / np.mean(v))  # noqa: E731
    # The field varies +-30 % over the box (cv ~0.15); N4 must remove most of it.
    assert cv(sitk.GetArrayFromImage(biased)[inner]) > 0.1
    assert cv(out[inner]) < 0.35 * cv(sitk.GetArrayFromImage(biased)[inner])
    assert out.shape == a.shape


def test_normalise_maps_background_to_zero_and_bright_mode_to_one():
    img, box = _block()
    rng = np.random.default_rng(0)
    a = sitk.GetArrayFromImage(img) + 10.0 + rng.normal(0, 2.0, box.shape).astype(np.float32)
    a[20, 20, 20] = 400.0  # a marker-like outlier must not set the scale
    noisy = sitk.GetImageFromArray(a)
    out = sitk.GetArrayFromImage(normalise(noisy))
    assert abs(np.median(out[~box])) < 0.02
    assert abs(np.median(out[box & (out > 0.6)]) - 1.0) < 0.03


def test_magnitude_level_is_where_a_normalised_magnitude_image_shows_a_tissue():
    """Magnitude images (Gaussian noise of sigma 1/11 on both channels: SNR 11) of air (0)
    around a block of fat (1); muscle (0.25) and thorax (0.1) sampled alike. Normalised as
    the volume is, the muscle reads about 0.17, not 0.25: magnitude_level predicts each
    tissue's normalised mean from the background's level over the fat's, which normalise()
    records on the volume."""
    rng = np.random.default_rng(1)
    sigma = 1.0 / 11.0

    def magnitude(signal, size):
        return np.hypot(signal + rng.normal(0, sigma, size), rng.normal(0, sigma, size))

    box = np.zeros((40, 40, 40), bool)
    box[8:32, 8:32, 8:32] = True
    a = magnitude(0.0, box.shape).astype(np.float32)
    a[box] = magnitude(1.0, int(box.sum()))
    out = normalise(sitk.GetImageFromArray(a))
    beta = float(out.GetMetaData(BACKGROUND_OVER_FAT))
    b = sitk.GetArrayFromImage(out)  # b = (a - lo) / (hi - lo): normalise's lo and hi
    i, j = np.argmin(a), np.argmax(a)
    scale = (a.flat[j] - a.flat[i]) / (b.flat[j] - b.flat[i])
    lo = float(a.flat[i] - b.flat[i] * scale)
    hi = lo + float(scale)
    assert beta == pytest.approx(lo / hi, rel=1e-4)
    for f in (0.1, 0.25):
        shown = (magnitude(f, 50000).mean() - lo) / (hi - lo)
        assert magnitude_level(f, beta) == pytest.approx(shown, abs=0.01)
    assert magnitude_level(0.25, beta) < 0.19  # well below its share of the fat
    assert magnitude_level(0.25, 0.0) == 0.25
    assert magnitude_level(1.0, beta) == pytest.approx(1.0)


def test_resample_isotropic_keeps_geometry():
    img, _ = _block(spacing=(1.0, 1.0, 2.0))
    out = resample_isotropic(img)
    assert out.GetSpacing() == (1.0, 1.0, 1.0)
    assert out.GetSize() == (img.GetSize()[0], img.GetSize()[1], 2 * img.GetSize()[2])
    assert np.allclose(out.GetOrigin(), img.GetOrigin())
    p = (0.0, 30.0, 40.0)  # inside the box: same value on both grids
    assert out.GetPixel(out.TransformPhysicalPointToIndex(p)) == pytest.approx(
        img.GetPixel(img.TransformPhysicalPointToIndex(p)), abs=1e-3)


@pytest.mark.parametrize("method", ["gradient", "curvature"])
def test_denoise_lowers_noise_and_keeps_the_edge(method):
    img, box = _block()
    rng = np.random.default_rng(1)
    a = sitk.GetArrayFromImage(img)
    noisy = sitk.GetImageFromArray(a + rng.normal(0, 5.0, a.shape).astype(np.float32))
    noisy.CopyInformation(img)
    out = sitk.GetArrayFromImage(denoise(noisy, iterations=5, method=method))
    flat = np.zeros_like(box)
    flat[10:14, 12:-12, 12:-12] = True
    assert np.std(out[flat]) < 0.6 * 5.0
    # the 30 -> 100 edge stays where it was: the half-way crossing within half a voxel
    prof = out[:, 24, 28]
    k = int(np.argmax(prof[24:30] > 65.0)) + 24
    assert k == 25


def test_preprocess_leaves_input_untouched_and_validates():
    img, _ = _block()
    before = sitk.GetArrayFromImage(img).copy()
    out = preprocess(img, n4=False, denoise_iterations=1)
    assert np.array_equal(sitk.GetArrayFromImage(img), before)
    assert out.GetSize() == img.GetSize()
    with pytest.raises(ValueError, match="denoising method"):
        denoise(img, method="median")
    with pytest.raises(ValueError, match="preprocess: bad.nii is 2-D"):
        preprocess(sitk.Image(8, 8, sitk.sitkFloat32), name="bad.nii")


def test_n4_cache_returns_the_same_correction_across_processes(tmp_path):
    img, _ = _block()
    ramp = np.linspace(0.7, 1.3, 56, dtype=np.float32)[None, None, :]
    biased = sitk.GetImageFromArray(sitk.GetArrayFromImage(img) * ramp + 1.0)
    biased.CopyInformation(img)
    first = n4_correct(biased, iterations=(10,), cache=tmp_path)
    files = list(tmp_path.glob("n4_*.nrrd"))
    assert len(files) == 1  # one file per input and options
    _N4_MEMORY.clear()  # as a new process would: only the folder remains
    again = n4_correct(biased, iterations=(10,), cache=tmp_path)
    assert np.array_equal(sitk.GetArrayViewFromImage(first), sitk.GetArrayViewFromImage(again))
    # other options are another entry
    n4_correct(biased, iterations=(5,), cache=tmp_path)
    assert len(list(tmp_path.glob("n4_*.nrrd"))) == 2
    # the segmentation corrects the volume as read (integers), the registration's
    # preprocessing a float32 copy: one entry serves both
    as_read = sitk.Cast(sitk.Round(biased), sitk.sitkInt16)
    n4_correct(as_read, iterations=(10,), cache=tmp_path)
    n4_correct(sitk.Cast(as_read, sitk.sitkFloat32), iterations=(10,), cache=tmp_path)
    assert len(list(tmp_path.glob("n4_*.nrrd"))) == 3


def test_body_box_keeps_mid_grey_tissue_below_the_otsu_threshold():
    # bright block (fat, 100) beside a dim slab (muscle meeting air, 25): Otsu's foreground
    # is the bright block only; the box must hold the slab too
    a = np.zeros((60, 60, 60), np.float32)
    a[20:40, 20:40, 8:30] = 100.0
    a[20:40, 20:40, 30:50] = 25.0
    a += np.abs(np.random.default_rng(1).normal(0, 3, a.shape)).astype(np.float32)
    img = sitk.GetImageFromArray(a)
    index, size = body_box(img, margin_mm=2.0)
    assert index[0] <= 8 - 2 and index[0] + size[0] >= 50 + 2
    assert index[1] <= 18 and index[1] + size[1] >= 42


@pytest.mark.parametrize("method", ["gradient", "curvature"])
def test_denoising_goes_on_from_where_it_stopped_bit_for_bit(method):
    """The segmentation's second denoising of a noisy scan goes on from the first's result
    (:func:`imaging.segment_contrast.prepare_volume`): ITK's anisotropic diffusion rescales
    its conductance at every iteration, so n more after n equal 2n from the start."""
    img, _ = _block()
    a = sitk.GetArrayFromImage(img)
    noisy = sitk.GetImageFromArray(
        a + np.random.default_rng(2).normal(0, 8.0, a.shape).astype(np.float32))
    noisy.CopyInformation(img)
    once = sitk.GetArrayFromImage(denoise(noisy, iterations=6, method=method))
    twice = sitk.GetArrayFromImage(denoise(denoise(noisy, iterations=3, method=method),
                                           iterations=3, method=method))
    assert np.array_equal(once, twice)
