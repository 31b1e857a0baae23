"""Reading and writing 3-D volumes (NIfTI, NRRD, MHA, DICOM series folders), with validation.

Every volume that enters the toolkit goes through :func:`read_volume`, which checks what the
later stages assume (a scalar 3-D image, finite voxels, positive and plausible spacing) and
fails with one message naming the file and the problem.

For NIfTI files it reads the header and the voxel bytes itself before ITK does
(:func:`check_nifti`): ITK's NIfTI reader fills a truncated file with zeros, reads NaN voxels
as 0 and a zero pixdim as 1 mm without a word. Paths that are not valid UTF-8 are refused
before ITK sees them (ITK aborts the process on them).
"""

from __future__ import annotations

import gzip
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from imaging.atomic import write_atomic_with

__all__ = ["VolumeError", "read_volume", "write_volume", "check_volume", "check_nifti",
           "check_path", "MAX_SPACING_MM", "MAX_VOXELS"]

#: Largest accepted voxel spacing, mm: a breast MRI with coarser voxels is a header error.
MAX_SPACING_MM = 20.0
#: Smallest accepted voxel spacing, mm.
MIN_SPACING_MM = 1e-3
#: Largest accepted number of voxels (2^30: 4 GiB of float32).
MAX_VOXELS = 2**30


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
        If the path is not valid UTF-8, does not exist, cannot be read, is truncated, or the
        image is not 3-D, not scalar, has a non-finite voxel or a spacing outside
        [``MIN_SPACING_MM``, ``MAX_SPACING_MM``].
    """
    path = Path(path)
    check_path(path)
    if not path.exists():
        raise VolumeError(f"volume {path}: file or folder does not exist")
    if path.is_file() and path.name.lower().endswith((".nii", ".nii.gz")):
        check_nifti(path)
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
    _check_spacing(reader.GetSpacing(), str(path))
    _check_size(reader.GetSize(), str(path))
    return reader.Execute()


def _check_spacing(spacing, name: str) -> None:
    sp = np.asarray(spacing, dtype=float)
    text = "(" + ", ".join(f"{v:.6g}" for v in sp) + ")"
    if not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise VolumeError(f"volume {name}: voxel spacing must be > 0 mm, got {text}")
    if np.any(sp < MIN_SPACING_MM) or np.any(sp > MAX_SPACING_MM):
        raise VolumeError(
            f"volume {name}: voxel spacing {text} mm is outside "
            f"[{MIN_SPACING_MM:g}, {MAX_SPACING_MM:g}] mm (a header error?)"
        )


def _check_size(size, name: str) -> None:
    n = int(np.prod([int(v) for v in size], dtype=object))
    if n > MAX_VOXELS:
        raise VolumeError(f"volume {name}: {n} voxels (size {tuple(size)}) is more than "
                          f"{MAX_VOXELS} (a header error?)")


def check_path(path: str | Path) -> None:
    """Refuse a path that is not valid UTF-8 (ITK aborts the process on one).

    Raises
    ------
    VolumeError
    """
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        raise VolumeError(f"volume {os.fspath(path)!a}: the path is not valid UTF-8; rename "
                          "the file or folder") from None


#: NIfTI datatype code -> numpy dtype (the scalar types a volume may hold).
_NIFTI_TYPES = {2: "u1", 4: "i2", 8: "i4", 16: "f4", 64: "f8", 256: "i1", 512: "u2",
                768: "u4", 1024: "i8", 1280: "u8"}


def _open_nifti(path: Path):
    return gzip.open(path, "rb") if path.name.lower().endswith(".gz") else path.open("rb")


def check_nifti(path: str | Path, *, chunk_bytes: int = 1 << 24) -> None:
    """Check a NIfTI-1/2 file against its own header, reading every byte once.

    Checks the header (size field, magic, 3-D dimensions, a scalar datatype, finite
    positive pixdim within [``MIN_SPACING_MM``, ``MAX_SPACING_MM``], finite scaling), that
    the (decompressed) file holds the bytes the header announces, and that float voxels are
    finite.

    Parameters
    ----------
    path
        A ``.nii`` or ``.nii.gz`` file.
    chunk_bytes
        Bytes read at a time.

    Raises
    ------
    VolumeError
        Naming the file and the problem.
    """
    path = Path(path)
    try:
        with _open_nifti(path) as f:
            head = f.read(540)
            hdr = _nifti_header(head, str(path))
            off, need = hdr["vox_offset"], hdr["nbytes"]
            dtype = np.dtype(hdr["dtype"]).newbyteorder(hdr["endian"])
            pos = len(head)
            while pos < off:  # header extensions
                got = f.read(min(off - pos, chunk_bytes))
                if not got:
                    break
                pos += len(got)
            data = head[off:off + need] if pos >= off else b""
            have, bad, carry = 0, 0, b""
            while data:
                have += len(data)
                if dtype.kind == "f":
                    buf = carry + data
                    usable = len(buf) - len(buf) % dtype.itemsize
                    v = np.frombuffer(buf[:usable], dtype=dtype)
                    bad += int(np.count_nonzero(~np.isfinite(v)))
                    carry = buf[usable:]
                if have >= need:
                    break
                data = f.read(min(chunk_bytes, need - have))
    except (OSError, EOFError, zlib.error) as exc:
        raise VolumeError(f"volume {path}: cannot be read: corrupt or truncated file "
                          f"({exc})") from None
    if have < need:
        raise VolumeError(
            f"volume {path}: truncated: the header announces {need} bytes of voxels "
            f"({'x'.join(str(d) for d in hdr['dims'])} x {dtype.itemsize} bytes), the file "
            f"holds {have}"
        )
    if bad:
        raise VolumeError(f"volume {path}: {bad} voxel(s) are NaN or infinite")


def _nifti_header(head: bytes, name: str) -> dict:
    """The fields of a NIfTI-1 or NIfTI-2 header that the checks need."""
    if len(head) < 348:
        raise VolumeError(f"volume {name}: truncated: {len(head)} bytes, shorter than a NIfTI "
                          "header (348)")
    for endian in ("<", ">"):
        (size,) = struct.unpack(endian + "i", head[:4])
        if size in (348, 540):
            break
    else:
        raise VolumeError(f"volume {name}: not a NIfTI file (header size field {size})")
    if size == 348:
        magic = head[344:348]
        dim = struct.unpack(endian + "8h", head[40:56])
        datatype, bitpix = struct.unpack(endian + "2h", head[70:74])
        pixdim = struct.unpack(endian + "8f", head[76:108])
        (vox_offset,) = struct.unpack(endian + "f", head[108:112])
        slope, inter = struct.unpack(endian + "2f", head[112:120])
        ok_magic = magic == b"n+1\0"
    else:
        if len(head) < 540:
            raise VolumeError(f"volume {name}: truncated NIfTI-2 header")
        magic = head[4:12]
        datatype, bitpix = struct.unpack(endian + "2h", head[12:16])
        dim = struct.unpack(endian + "8q", head[16:80])
        pixdim = struct.unpack(endian + "8d", head[104:168])
        (vox_offset,) = struct.unpack(endian + "q", head[168:176])
        slope, inter = struct.unpack(endian + "2d", head[176:192])
        ok_magic = magic[:3] == b"n+2"
    if not ok_magic:
        raise VolumeError(f"volume {name}: bad NIfTI magic {magic!r} (not a single-file "
                          "NIfTI)")
    nd = int(dim[0])
    if not 1 <= nd <= 7:
        raise VolumeError(f"volume {name}: NIfTI header dim[0] = {nd} is not 1..7")
    dims = [int(d) for d in dim[1:nd + 1]]
    if any(d < 1 for d in dims):
        raise VolumeError(f"volume {name}: NIfTI header has a dimension < 1: {dims}")
    extra = [d for d in dims[3:] if d != 1]
    if nd < 3 or extra:
        raise VolumeError(f"volume {name}: expected a 3-D image, got {nd}-D (size "
                          f"{'x'.join(map(str, dims))})")
    if datatype not in _NIFTI_TYPES:
        raise VolumeError(f"volume {name}: NIfTI datatype {datatype} is not a scalar type "
                          "(RGB, complex or unknown)")
    _check_spacing(pixdim[1:4], name)
    _check_size(dims, name)
    if not (np.isfinite(slope) and np.isfinite(inter)):
        raise VolumeError(f"volume {name}: NIfTI scaling (scl_slope {slope}, scl_inter "
                          f"{inter}) is not finite")
    vox_offset = int(vox_offset)
    if vox_offset < size + 4:
        raise VolumeError(f"volume {name}: NIfTI vox_offset {vox_offset} lies inside the "
                          "header")
    dt = _NIFTI_TYPES[datatype]
    return {"dims": dims, "dtype": dt, "endian": endian, "vox_offset": vox_offset,
            "nbytes": int(np.prod(dims, dtype=object)) * np.dtype(dt).itemsize}


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
    if min(image.GetSize()) < 2:
        size = "x".join(str(s) for s in image.GetSize())
        raise VolumeError(f"volume {name}: size {size}: every axis needs at least 2 voxels "
                          "(a single slice is not a volume)")
    _check_spacing(image.GetSpacing(), name)
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
    # the writer picks the format from the extension: the temporary file keeps it
    suffix = "".join(path.suffixes[-2:]) if path.name.endswith(".gz") else path.suffix
    return write_atomic_with(path, lambda tmp: sitk.WriteImage(image, str(tmp), compress),
                             suffix=suffix)
