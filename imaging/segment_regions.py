"""Shared vocabulary and region steps of the segmentation (:mod:`imaging.segment`): the
error it raises, user seeds, mask helpers, the chest wall's start, skin markers and the
reassignment of the region holding each seed. Both contrast paths
(:mod:`imaging.segment_fat_bright`, :mod:`imaging.segment_fat_suppressed`) use them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from imaging.fiducials import body_without_markers, detect_markers
from imaging.labels import BACKGROUND, BREAST, GLAND, MUSCLE

STAGE = "segment"


class SegmentationError(ValueError):
    """The volume cannot be segmented; the message names the file and the problem."""


@dataclass(frozen=True)
class Seed:
    """A user seed: the region holding ``point`` (LPS mm) gets ``label`` (0/1/2/3)."""

    label: int
    point: tuple[float, float, float]




def _ball(radius_mm: float, spacing_zyx: np.ndarray) -> np.ndarray:
    rad = np.maximum(1, np.floor(radius_mm / spacing_zyx)).astype(int)
    zz, yy, xx = np.ogrid[-rad[0]:rad[0] + 1, -rad[1]:rad[1] + 1, -rad[2]:rad[2] + 1]
    s = spacing_zyx
    return (zz * s[0]) ** 2 + (yy * s[1]) ** 2 + (xx * s[2]) ** 2 <= radius_mm ** 2 + 1e-9


#: Least share of a mask's voxels its interior must hold to stand for it in a level
#: estimate. A layer a few voxels thick has no interior two voxels in; what interior its
#: mask has then belongs to thicker parts that came along: the 3-voxel muscle of the suite's
#: 2 mm coil subject (small-002) started with the glands it touches, its "interior" was
#: the glands alone, and the muscle's level came out at the glands' (1.63 against 0.5): its
#: active contour kept the glands and the muscle's Dice was 0.01-0.05.
INTERIOR_MIN_SHARE = 0.25


def _interior_median(a: np.ndarray, mask: np.ndarray, default: float) -> float:
    """Median of ``a`` over the interior of ``mask`` (two voxels in), on every second voxel
    in each direction: a level estimate needs thousands of samples, not millions. Where that
    interior holds less than :data:`INTERIOR_MIN_SHARE` of the mask (a thin layer), one
    voxel in at full resolution, else the whole mask."""
    for arr, m in ((a[::2, ::2, ::2], mask[::2, ::2, ::2]), (a, mask)):
        inner = ndimage.binary_erosion(m)
        n_inner = np.count_nonzero(inner)
        if n_inner > 50 and n_inner >= INTERIOR_MIN_SHARE * np.count_nonzero(m):
            return float(np.median(arr[inner]))
    vals = a[mask]
    return float(np.median(vals)) if vals.size else default


def bounding_box(mask: np.ndarray, margin) -> tuple[slice, ...] | None:
    """The bounding box of ``mask`` grown by ``margin`` voxels per axis, within the array
    (None: nothing in it). A distance map cropped to the box of its object grown by one
    voxel equals the whole one there: every voxel outside the object is the box's or
    farther than the box's face; at the array's faces the crop ends where the array does.
    (Two distance maps over the whole volume took 3.8 of bench/mri.py's 21 s.)"""
    found = ndimage.find_objects(np.asarray(mask, bool).view(np.uint8))
    if not found or found[0] is None:
        return None
    return tuple(slice(max(0, s.start - int(m)), min(n, s.stop + int(m)))
                 for s, m, n in zip(found[0], margin, mask.shape))


def dilated(mask: np.ndarray, structure: np.ndarray) -> np.ndarray:
    """``ndimage.binary_dilation(mask, structure)`` computed on the box of ``mask`` grown by
    the structure's reach: the same voxels, at the box's cost."""
    out = np.zeros(mask.shape, bool)
    box = bounding_box(mask, np.asarray(structure.shape) // 2 + 1)
    if box is not None:
        out[box] = ndimage.binary_dilation(mask[box], structure=structure)
    return out


def _components(mask: np.ndarray) -> tuple[np.ndarray, int]:
    return ndimage.label(mask)


def _touching(lab: np.ndarray, n: int, region: np.ndarray) -> np.ndarray:
    """Boolean (n+1,) flags: component k has a voxel face-adjacent to ``region``."""
    near = ndimage.binary_dilation(region)
    hit = np.zeros(n + 1, bool)
    hit[np.unique(lab[near & (lab > 0)])] = True
    hit[0] = False
    return hit


def _muscle_start(mid: np.ndarray, thorax: np.ndarray, spacing_zyx: np.ndarray,
                  min_mm: float, outside: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """The chest wall's start: the thick parts (opening by a ball of ``min_mm / 2``, and
    at least one voxel's size in every direction) of the mid-intensity layer that touch the
    thorax interior; else the largest thick part that touches ``outside`` (the air: a muscle
    meeting air; a gland as thick lies among fat), else the largest thick part. Returns the
    mask and whether it is a fallback."""
    # a layer one voxel thick along an axis is at the resolution (skin seen edge-on in thick
    # slices): the ball is at least a voxel's size in every direction
    r = max(min_mm / 2, float(np.max(spacing_zyx)))
    thick = _opening_beyond_edge(mid, _ball(r, spacing_zyx))
    tlab, tn = _components(thick)
    if thorax.any():
        muscle = _touching(tlab, tn, thorax)[tlab]
        if muscle.any():
            return muscle, False
    if tn == 0:
        return np.zeros(mid.shape, bool), True
    tsizes = np.bincount(tlab.ravel())
    tsizes[0] = 0
    if outside is not None and outside.any():
        meets = _touching(tlab, tn, outside)
        if meets.any():
            tsizes[~meets] = 0
    return tlab == int(tsizes.argmax()), True


def _opening_beyond_edge(mask: np.ndarray, structure: np.ndarray) -> np.ndarray:
    """Binary opening of ``mask`` as if it went on past the field of view unchanged (edge
    padding): where a scan cuts through the chest wall its face is no edge of the layer. An
    opening with the outside as background thinned the muscle's start on the cut face by
    the ball's radius, and its active contour did not win it back (the T1 fat-suppressed
    phantom cut through its thorax: 597 muscle voxels of the face called breast, 296 with
    the padding)."""
    pad = [(h, h) for h in (np.asarray(structure.shape) // 2)]
    opened = ndimage.binary_opening(np.pad(mask, pad, mode="edge"), structure=structure)
    return opened[tuple(slice(h, h + n) for (h, _), n in zip(pad, mask.shape))]


def _markers(pre: sitk.Image, a: np.ndarray, body: np.ndarray, sp: np.ndarray,
             marker_diameter_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Skin markers: bright blobs outside the (opened) body; returns their centres (K, 3) mm
    and a mask of a ball around each (outside the opened body)."""
    opened = body_without_markers(body, spacing=sp[::-1], diameter_mm=marker_diameter_mm)
    markers_mm = detect_markers(pre, diameter_mm=marker_diameter_mm, n_expected=None,
                                min_contrast=1.0, localise=False, foreground=body,
                                body=opened)
    marker_mask = np.zeros(a.shape, bool)
    if len(markers_mm):
        r = 0.5 * marker_diameter_mm + 1.5
        for p in markers_mm:
            c = np.asarray(pre.TransformPhysicalPointToContinuousIndex(tuple(p)))[::-1]
            lo = np.maximum(np.floor(c - r / sp).astype(int), 0)
            hi = np.minimum(np.ceil(c + r / sp).astype(int) + 1, a.shape)
            zz, yy, xx = np.ogrid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
            d2 = (((zz - c[0]) * sp[0]) ** 2 + ((yy - c[1]) * sp[1]) ** 2
                  + ((xx - c[2]) * sp[2]) ** 2)
            sl = tuple(slice(x, y) for x, y in zip(lo, hi))
            marker_mask[sl] |= (d2 <= r * r) & ~opened[sl]
    return markers_mm, marker_mask


def _apply_seeds(seeds, pre, mlab, thorax, muscle, notes, name, other):
    """Reassign the connected region holding each seed: a component of ``mlab`` (the muscle
    candidates), the thorax interior, or a component of ``other(muscle)`` (the remaining
    tissue class). Returns the new (muscle, thorax)."""
    a_shape = mlab.shape
    for s in seeds:
        if s.label not in (BACKGROUND, BREAST, MUSCLE, GLAND):
            raise SegmentationError(f"{STAGE}: seed label must be 0, 1, 2 or 3, got {s.label}")
        c = np.round(pre.TransformPhysicalPointToContinuousIndex(tuple(map(float, s.point))))
        k = tuple(int(v) for v in c[::-1])
        if any(i < 0 or i >= n for i, n in zip(k, a_shape)):
            raise SegmentationError(f"{STAGE}: seed {s.point} mm lies outside {name}")
        if mlab[k] > 0:
            region = mlab == mlab[k]
        elif thorax[k]:
            region = thorax.copy()
        else:
            region = ndimage.label(other(muscle))[0]
            region = region == region[k] if region[k] > 0 else np.zeros(a_shape, bool)
        if not region.any():
            notes.append(f"seed {s.point} (label {s.label}) is in air: ignored")
            continue
        muscle = muscle & ~region
        thorax = thorax & ~region
        if s.label == MUSCLE:
            muscle |= region
        elif s.label == BACKGROUND:
            thorax |= region  # treated as non-tissue inside the body
        notes.append(f"seed {s.point} -> label {s.label} ({int(region.sum())} voxels)")
    return muscle, thorax
