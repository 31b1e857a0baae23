"""Masks that drive a rigid registration: what is rigid on a label map
(:func:`chest_wall_mask`, :func:`chest_wall_masks`) and balls around the fiducials
(:func:`add_balls`)."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from registration.transforms import STAGE


def add_balls(mask: sitk.Image, centres, radius_mm: float) -> sitk.Image:
    """Copy of ``mask`` (uint8) with balls of ``radius_mm`` around (K,3) mm ``centres``."""
    out = sitk.GetArrayFromImage(sitk.Cast(mask > 0, sitk.sitkUInt8))
    sp = np.asarray(mask.GetSpacing(), float)[::-1]
    for p in centres:
        c = np.asarray(mask.TransformPhysicalPointToContinuousIndex(
            tuple(float(v) for v in p)))[::-1]
        lo = np.maximum(np.floor(c - radius_mm / sp).astype(int), 0)
        hi = np.minimum(np.ceil(c + radius_mm / sp).astype(int) + 1, out.shape)
        if np.any(hi <= lo):
            continue
        zz, yy, xx = np.ogrid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        d2 = (((zz - c[0]) * sp[0]) ** 2 + ((yy - c[1]) * sp[1]) ** 2
              + ((xx - c[2]) * sp[2]) ** 2)
        out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] |= (d2 <= radius_mm ** 2).astype(np.uint8)
    img = sitk.GetImageFromArray(out)
    img.CopyInformation(mask)
    return img


def chest_wall_mask(
    labels: sitk.Image, *, margin_mm: float = 6.0, breast_margin_mm: float = 0.0
) -> sitk.Image:
    """Mask (uint8) of what is rigid on a label map: the chest wall, breasts masked out
    (:func:`chest_wall_masks` with one ``breast_margin_mm``)."""
    return chest_wall_masks(labels, margin_mm=margin_mm, breast_margins_mm=(breast_margin_mm,))[0]


def chest_wall_masks(
    labels: sitk.Image, *, margin_mm: float = 6.0, breast_margins_mm: tuple[float, ...] = (0.0,)
) -> list[sitk.Image]:
    """Masks (uint8) of what is rigid on a label map, one per breast margin, from one
    distance map: the chest wall, breasts masked out.

    The muscle (label 2), the band within ``margin_mm`` of it on the side away from the
    breasts (thorax interior, or the air behind a muscle slab), and only the breast tissue
    (1, 3) within a breast margin in front of it. The breasts deform between positions
    and the space in front of the muscle (air between the breasts, subcutaneous fat) is where
    they swing, so neither may drive a rigid fit.

    Parameters
    ----------
    labels : SimpleITK.Image
        Reference label map (0 background, 1 breast, 2 muscle, 3 gland).
    margin_mm : float
        Width of the band behind the muscle, mm.
    breast_margins_mm : tuple of float
        Depths of the breast tissue layer in front of the muscle kept, mm, one per mask.

    Returns
    -------
    list of SimpleITK.Image
        uint8 0/1 on the label map's grid, in the order of ``breast_margins_mm``.
    """
    lab = sitk.Cast(labels, sitk.sitkUInt8)
    full = sitk.GetArrayViewFromImage(lab)
    found = ndimage.find_objects((full == 2).view(np.uint8))
    if not found or found[0] is None:
        raise ValueError(f"{STAGE}: the reference label map has no muscle (label 2) for the "
                         "chest-wall mask")
    spz = np.asarray(lab.GetSpacing(), float)[::-1]
    # Nothing farther from the muscle than the margins is in a mask: work on the muscle's
    # box grown by them (and a voxel, so that its distance map equals the whole one there).
    grow = np.ceil(max(margin_mm, *breast_margins_mm, 0.0) / spz).astype(int) + 2
    box = tuple(slice(max(0, s.start - int(g)), min(n, s.stop + int(g)))
                for s, g, n in zip(found[0], grow, full.shape))
    a = np.ascontiguousarray(full[box])
    sub = sitk.GetImageFromArray((a == 2).astype(np.uint8))
    sub.SetSpacing(lab.GetSpacing())
    d = sitk.GetArrayFromImage(sitk.SignedMaurerDistanceMap(
        sub, insideIsPositive=False, squaredDistance=False, useImageSpacing=True))
    breast = (a == 1) | (a == 3)
    band = (d <= margin_mm) & (a != 2)
    # Band components that reach the breasts hold the space in front of the muscle (a
    # closed chest wall separates it from the thorax interior). Where the band wraps round
    # the edge of a muscle slab, the side is the one the distance gradient faces: toward the
    # breasts (front) or away from them.
    comp, n = ndimage.label(band)
    touches = np.zeros(n + 1, bool)
    touches[np.unique(comp[breast & band])] = True
    touches[0] = False
    front = touches[comp]
    if front.any():
        every2 = full[::2, ::2, ::2]  # centroids of the whole map, as before the crop
        cm = np.argwhere(every2 == 2).mean(axis=0)
        cb = np.argwhere((every2 == 1) | (every2 == 3)).mean(axis=0)
        toward = (cb - cm) * spz  # (z, y, x) mm, muscle -> breasts
        toward /= max(np.linalg.norm(toward), 1e-9)
        facing = np.zeros(d.shape, np.float32)
        for i in range(3):
            facing += toward[i] * np.gradient(d, spz[i], axis=i).astype(np.float32)
        front &= facing > -0.5  # not clearly facing away from the breasts
    rigid = (a == 2) | (band & ~front)
    out = []
    for depth in breast_margins_mm:
        m = np.zeros(full.shape, np.uint8)
        m[box] = rigid | (breast & (d <= depth))
        out.append(sitk.GetImageFromArray(m))
        out[-1].CopyInformation(lab)
    return out
