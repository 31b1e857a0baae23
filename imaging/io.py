"""Reading and writing 3-D volumes (NIfTI, NRRD, MHA, DICOM series folders), with validation.

Every volume that enters the toolkit goes through :func:`read_volume`, which checks what the
later stages assume (a scalar 3-D image, finite voxels, positive spacing) and fails with one
message naming the file and the problem.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import SimpleITK as sitk

__all__ = ["VolumeError", "read_volume", "write_volume", "check_volume"]


class VolumeError(ValueError):
    """A volume file is unreadable or violates the toolkit's assumptions; names the file."""


def read_volume(path: str | Path) -> sitk.Image:
    """Read and validate one 3-D volume.

    Parameters
    ----------
    path
        A file in any format SimpleITK reads (``.nii``, ``.nii.gz``, ``.nrrd``, ``.mha``, ...)
        or a folder holding one DICOM series.

    Returns
    -------
    sitk.Image
        The scalar 3-D image with its spacing (mm), origin (mm) and direction (LPS).

    Raises
    ------
    VolumeError
        If the path does not exist, cannot be read, or the image is not 3-D, not scalar, has
        a non-finite voxel or a spacing that is not positive.
    """
    path = Path(path)
    if not path.exists():
        raise VolumeError(f"volume {path}: file or folder does not exist")
    try:
        image = _read_dicom_folder(path) if path.is_dir() else _read_file(path)
    except RuntimeError as exc:
        raise VolumeError(f"volume {path}: cannot be read ({_itk_reason(exc)})") from None
    check_volume(image, name=str(path))
    return image


def _read_file(path: Path) -> sitk.Image:
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    # The header first: ITK refuses to build an image with zero spacing, with a cryptic error.
    reader.ReadImageInformation()
    dim = reader.GetDimension()
    if dim != 3:
        size = "x".join(str(s) for s in reader.GetSize())
        raise VolumeError(f"volume {path}: expected a 3-D image, got {dim}-D (size {size})")
    spacing = reader.GetSpacing()
    if not all(np.isfinite(spacing)) or min(spacing) <= 0:
        raise VolumeError(f"volume {path}: voxel spacing must be > 0 mm, got {tuple(spacing)}")
    return reader.Execute()


def _itk_reason(exc: RuntimeError) -> str:
    """The informative line of an ITK/SimpleITK exception (not the source location)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    for ln in lines[1:] or lines:
        for prefix in ("sitk::ERROR:", "ITK ERROR:"):
            if ln.startswith(prefix):
                ln = ln[len(prefix):].strip()
        if ln and not ln.startswith("Exception thrown"):
            return ln.split("): ", 1)[-1] if ln.startswith("Image(") else ln
    return lines[0] if lines else "unknown reader error"


def _read_dicom_folder(path: Path) -> sitk.Image:
    series = sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(path))
    if not series:
        raise VolumeError(f"volume {path}: folder holds no DICOM series")
    if len(series) > 1:
        raise VolumeError(
            f"volume {path}: folder holds {len(series)} DICOM series; keep one per folder"
        )
    files = sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(path), series[0])
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(files)
    return reader.Execute()


def check_volume(image: sitk.Image, *, name: str = "image") -> None:
    """Validate an in-memory image: 3-D, scalar, positive spacing, finite voxels.

    Parameters
    ----------
    image
        The image to check (not modified).
    name
        What to call it in the error message (usually the file path).
    """
    dim = image.GetDimension()
    if dim != 3:
        size = "x".join(str(s) for s in image.GetSize())
        raise VolumeError(f"volume {name}: expected a 3-D image, got {dim}-D (size {size})")
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise VolumeError(
            f"volume {name}: expected a scalar image, got "
            f"{image.GetNumberOfComponentsPerPixel()} components per voxel"
        )
    if min(image.GetSize()) < 1:
        raise VolumeError(f"volume {name}: empty image (size {image.GetSize()})")
    spacing = np.asarray(image.GetSpacing(), dtype=float)
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise VolumeError(f"volume {name}: voxel spacing must be > 0 mm, got {tuple(spacing)}")
    if not np.all(np.isfinite(image.GetOrigin())) or not np.all(
        np.isfinite(image.GetDirection())
    ):
        raise VolumeError(f"volume {name}: origin or direction is not finite")
    array = sitk.GetArrayViewFromImage(image)
    if np.issubdtype(array.dtype, np.floating):
        bad = np.count_nonzero(~np.isfinite(array))
        if bad:
            raise VolumeError(f"volume {name}: {bad} voxel(s) are NaN or infinite")


def write_volume(image: sitk.Image, path: str | Path, *, compress: bool = True) -> Path:
    """Write a volume atomically (a reader never sees a half-written file).

    Parameters
    ----------
    image
        The image to write; its format follows the file extension (``.nii.gz``, ``.nrrd``,
        ``.mha``, ...).
    path
        Destination file. Its folder is created if missing.
    compress
        Ask the writer to compress (gzip for NIfTI ``.nii.gz``, NRRD and MHA).

    Returns
    -------
    Path
        The written path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Same folder (atomic rename) and same extension (the writer picks the format from it).
    tmp = path.with_name(f".tmp{os.getpid()}-{path.name}")
    try:
        sitk.WriteImage(image, str(tmp), compress)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
