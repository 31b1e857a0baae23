"""Applying and storing rigid transforms.

Convention (SimpleITK resampling): a transform ``T`` of position P maps a point of the
reference frame to the corresponding point of P's image frame, ``x_P = T(x_ref)``. Resampling
P with ``T`` therefore puts P on the reference grid.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from decimal import Decimal
from pathlib import Path

import numpy as np
import SimpleITK as sitk

STAGE = "registration"
#: Suffixes of ITK's text transform files (:func:`transform_text`).
TEXT_SUFFIXES = (".tfm", ".txt")


def _umask() -> int:
    """The process's file-creation mask (read by setting it and putting it back)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()


def read_transform(path: str | Path) -> sitk.Transform:
    """Read an ITK transform file, failing with one clear message."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{STAGE}: transform file {path} does not exist")
    try:
        return sitk.ReadTransform(str(path))
    except RuntimeError as exc:
        raise ValueError(f"{STAGE}: {path} is not a readable ITK transform: "
                         f"{str(exc).strip().splitlines()[-1]}") from None


def write_transform(tfm: sitk.Transform, path: str | Path) -> None:
    """Write an ITK transform file atomically: a uniquely named temporary file in the target
    folder, flushed to disk, then renamed over ``path`` (removed on failure). A ``.tfm`` or
    ``.txt`` file holds :func:`transform_text`; other suffixes are written by SimpleITK in
    the format the suffix names."""
    path = Path(path)
    if path.suffix in TEXT_SUFFIXES:
        text = transform_text(tfm).encode()

        def write(tmp: str) -> None:
            with open(tmp, "wb") as f:
                f.write(text)
                f.flush()
                os.fsync(f.fileno())
    else:
        def write(tmp: str) -> None:
            sitk.WriteTransform(tfm, tmp)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}",
                               dir=path.parent)
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give what open() would
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def transform_text(tfm: sitk.Transform) -> str:
    """The ITK text transform file (``.tfm``) of ``tfm``: the bytes ``sitk.WriteTransform``
    writes, as a string, so that a caller can write it with its own writer.

    One ``#Transform k`` block per transform, each with its ITK class, precision and
    dimensions and, except for a composite's header, its parameters and fixed parameters
    as the shortest decimals that read back to the same doubles (:func:`_itk_number`). A
    composite transform comes first, followed by its transforms in order; ITK refuses one
    nested in another, and so does this function (``ValueError``).
    """
    tfm = tfm.Downcast()
    parts = [tfm]
    if isinstance(tfm, sitk.CompositeTransform):
        parts += [tfm.GetNthTransform(i) for i in range(tfm.GetNumberOfTransforms())]
        if any(isinstance(t, sitk.CompositeTransform) for t in parts[1:]):
            raise ValueError(f"{STAGE}: a composite transform nested in another cannot be "
                             "written to a transform file (ITK's limit)")
    lines = ["#Insight Transform File V1.0"]
    for k, t in enumerate(parts):
        d = t.GetDimension()
        lines += [f"#Transform {k}", f"Transform: {_itk_class(t)}_double_{d}_{d}"]
        if isinstance(t, sitk.CompositeTransform):  # its header only
            continue
        lines += ["Parameters: " + " ".join(map(_itk_number, t.GetParameters())),
                  "FixedParameters: " + " ".join(map(_itk_number, t.GetFixedParameters()))]
    return "\n".join(lines) + "\n"


def _itk_class(tfm: sitk.Transform) -> str:
    """The ITK class of the transform SimpleITK wraps, as its own printout names it."""
    return str(tfm).splitlines()[1].split()[0]


def _itk_number(x: float) -> str:
    """A double as ITK writes it (double-conversion's ECMAScript form, JavaScript's
    ``Number.toString``): the shortest digits that read back to ``x``, fixed-point for
    decimal exponents from -6 to 20, ``1.5e+21`` / ``1e-7`` style beyond; ``0`` for both
    zeros, ``NaN``, ``Infinity``."""
    x = float(x)
    if math.isnan(x):
        return "NaN"
    if math.isinf(x):
        return "Infinity" if x > 0 else "-Infinity"
    if x == 0.0:
        return "0"
    _, digits, exp = Decimal(repr(abs(x))).normalize().as_tuple()
    d = "".join(map(str, digits))
    k, n = len(d), len(d) + exp  # x = 0.d * 10**n
    if k <= n <= 21:
        s = d + "0" * (n - k)
    elif 0 < n <= 21:
        s = d[:n] + "." + d[n:]
    elif -6 < n <= 0:
        s = "0." + "0" * -n + d
    else:
        s = d[0] + ("." + d[1:] if k > 1 else "") + f"e{n - 1:+d}"
    return ("-" if x < 0 else "") + s


def rigid_matrix(tfm: sitk.Transform) -> tuple[np.ndarray, np.ndarray]:
    """(R (3,3), t (3,)) with ``T(x) = R x + t`` for any affine-like SimpleITK transform."""
    x0 = np.zeros(3)
    t = np.asarray(tfm.TransformPoint(tuple(x0)))
    r = np.stack([np.asarray(tfm.TransformPoint(tuple(e))) - t for e in np.eye(3)], axis=1)
    return r, t


def transform_points(tfm: sitk.Transform, points: np.ndarray) -> np.ndarray:
    """Map (N,3) points (mm) through ``tfm``; returns a new (N,3) array."""
    pts = np.asarray(points, float).reshape(-1, 3)
    return np.asarray([tfm.TransformPoint(tuple(p)) for p in pts]).reshape(-1, 3)


def gravity_in_reference(tfm: sitk.Transform, gravity: np.ndarray) -> np.ndarray:
    """A position's gravity direction (unit vector in its image frame) in the reference frame.

    ``tfm`` maps reference -> position, so directions go back through the inverse rotation.
    """
    r, _ = rigid_matrix(tfm)
    g = np.linalg.solve(r, np.asarray(gravity, float))
    return g / np.linalg.norm(g)


def matrix_to_transform(m: np.ndarray) -> sitk.AffineTransform:
    """4x4 homogeneous matrix (mm) -> SimpleITK affine transform."""
    m = np.asarray(m, float)
    a = sitk.AffineTransform(3)
    a.SetMatrix(m[:3, :3].ravel().tolist())
    a.SetTranslation(m[:3, 3].tolist())
    return a


def transform_to_matrix(tfm: sitk.Transform) -> np.ndarray:
    """SimpleITK transform (affine-like) -> 4x4 homogeneous matrix."""
    r, t = rigid_matrix(tfm)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


def resample_to_reference(
    moving: sitk.Image, reference: sitk.Image, tfm: sitk.Transform, *, labels: bool = False
) -> sitk.Image:
    """Resample a position's volume (or label map) onto the reference grid.

    Linear interpolation for intensities, nearest neighbour for label maps; outside -> 0.
    """
    interp = sitk.sitkNearestNeighbor if labels else sitk.sitkLinear
    return sitk.Resample(moving, reference, tfm, interp, 0.0, moving.GetPixelID())
