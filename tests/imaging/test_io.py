"""Volume reading/writing: round trips in every format and one clear error per bad file."""

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from imaging.io import VolumeError, read_volume, write_volume


def _image(shape_zyx=(4, 5, 6), dtype=np.int16) -> sitk.Image:
    arr = (np.arange(np.prod(shape_zyx)) % 251).reshape(shape_zyx).astype(dtype)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((0.7, 0.8, 1.5))
    img.SetOrigin((1.0, -2.0, 3.0))
    c, s = np.cos(0.3), np.sin(0.3)
    img.SetDirection((c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0))
    return img


def write_dicom_series(image: sitk.Image, folder: Path) -> Path:
    """Write a 3-D image as one DICOM file per axial slice (test helper, axial direction)."""
    folder.mkdir(parents=True, exist_ok=True)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    d = image.GetDirection()
    orientation = "\\".join(str(v) for v in (d[0], d[3], d[6], d[1], d[4], d[7]))
    for k in range(image.GetDepth()):
        sl = image[:, :, k]
        sl.SetMetaData("0020|000e", "1.2.826.0.1.3680043.2.1125.1.4242")
        sl.SetMetaData("0008|0060", "MR")
        pos = image.TransformIndexToPhysicalPoint((0, 0, k))
        sl.SetMetaData("0020|0032", "\\".join(str(v) for v in pos))
        sl.SetMetaData("0020|0037", orientation)
        sl.SetMetaData("0020|0013", str(k + 1))
        writer.SetFileName(str(folder / f"slice{k:03d}.dcm"))
        writer.Execute(sl)
    return folder


@pytest.mark.parametrize("name", ["v.nii.gz", "v.nii", "v.nrrd", "v.mha"])
def test_round_trip_keeps_voxels_and_geometry(tmp_path, name):
    img = _image()
    path = write_volume(img, tmp_path / name)
    back = read_volume(path)
    assert np.array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(img))
    # NIfTI stores geometry as float32: 1e-5 mm / 1e-6 is what survives.
    np.testing.assert_allclose(back.GetSpacing(), img.GetSpacing(), atol=1e-5)
    np.testing.assert_allclose(back.GetOrigin(), img.GetOrigin(), atol=1e-5)
    np.testing.assert_allclose(back.GetDirection(), img.GetDirection(), atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == [name]  # no temporary file left


def test_write_replaces_existing_file(tmp_path):
    path = tmp_path / "v.nii.gz"
    write_volume(_image(), path)
    arr = np.full((3, 3, 3), 7, dtype=np.int16)
    write_volume(sitk.GetImageFromArray(arr), path)
    assert np.array_equal(sitk.GetArrayFromImage(read_volume(path)), arr)


def test_dicom_series_folder(tmp_path):
    img = _image()
    img.SetDirection((1, 0, 0, 0, 1, 0, 0, 0, 1))
    folder = write_dicom_series(img, tmp_path / "dicom")
    back = read_volume(folder)
    assert back.GetSize() == img.GetSize()
    assert np.array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(img))
    np.testing.assert_allclose(back.GetSpacing(), img.GetSpacing(), atol=1e-4)
    np.testing.assert_allclose(back.GetOrigin(), img.GetOrigin(), atol=1e-4)


def _raw_mha(path: Path, *, dims="2 2 2", spacing="1 1 1", ndims=3, n=8) -> Path:
    header = (
        f"ObjectType = Image\nNDims = {ndims}\nDimSize = {dims}\nElementSpacing = {spacing}\n"
        "ElementType = MET_UCHAR\nElementDataFile = LOCAL\n"
    )
    path.write_bytes(header.encode() + bytes(n))
    return path


def _bad(tmp_path: Path, kind: str) -> Path:
    if kind == "2-D":
        path = tmp_path / "flat.nii.gz"
        sitk.WriteImage(sitk.GetImageFromArray(np.zeros((4, 5), np.float32)), str(path))
    elif kind == "4-D":
        path = tmp_path / "series.nii.gz"
        sitk.WriteImage(sitk.JoinSeries([_image(), _image()]), str(path))
    elif kind == "NaN":
        arr = np.zeros((3, 4, 5), np.float32)
        arr[1, 2, 3] = np.nan
        path = tmp_path / "nan.nrrd"
        sitk.WriteImage(sitk.GetImageFromArray(arr), str(path))
    elif kind == "spacing":
        path = _raw_mha(tmp_path / "zero.mha", spacing="1 0 1")
    elif kind == "vector":
        path = tmp_path / "rgb.mha"
        arr = np.zeros((3, 4, 5, 3), np.float32)
        sitk.WriteImage(sitk.GetImageFromArray(arr, isVector=True), str(path))
    elif kind == "missing":
        path = tmp_path / "nothing.nii.gz"
    elif kind == "garbage":
        path = tmp_path / "junk.nii.gz"
        path.write_bytes(b"not an image")
    elif kind == "empty-folder":
        path = tmp_path / "no_dicom"
        path.mkdir()
    return path


@pytest.mark.parametrize(
    "kind, phrase",
    [
        ("2-D", "expected a 3-D image, got 2-D"),
        ("4-D", "expected a 3-D image, got 4-D"),
        ("NaN", "1 voxel(s) are NaN or infinite"),
        ("spacing", "spacing must be > 0"),
        ("vector", "expected a scalar image, got 3 components"),
        ("missing", "does not exist"),
        ("garbage", "cannot be read"),
        ("empty-folder", "no DICOM series"),
    ],
)
def test_bad_volume_gets_one_clear_error(tmp_path, kind, phrase):
    path = _bad(tmp_path, kind)
    with pytest.raises(VolumeError) as info:
        read_volume(path)
    message = str(info.value)
    assert str(path) in message
    assert phrase in message
    assert "\n" not in message  # one line
