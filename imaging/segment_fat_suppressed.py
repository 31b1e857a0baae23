"""Regions of a fat-suppressed volume (fat dark; muscle, gland and skin mid-grey to bright):
air, thorax interior, body and muscle, found from the geometry."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from imaging.levelset import levelset_refine
from imaging.segment_contrast import (
    _require_body,
    _require_cnr,
    air_noise,
    contrast_to_noise,
    tissue_floor,
)
from imaging.segment_regions import (
    STAGE,
    SegmentationError,
    _apply_seeds,
    _ball,
    _components,
    _interior_median,
    _markers,
    _muscle_start,
    dilated,
)


def _fat_suppressed_regions(pre: sitk.Image, a: np.ndarray, sp: np.ndarray, notes: list, *,
                            seeds, levelset_iterations, curvature, marker_diameter_mm,
                            min_region_mm3, muscle_min_mm, name, levelset_shrink=1) -> dict:
    """Air, thorax interior, body and muscle of a fat-suppressed volume.

    Fat is dark (but above the background noise); muscle, gland and skin are mid-grey to
    bright; the thorax interior is dark or between. What holds on every such scan is the
    geometry: the muscle is a thick layer brighter than both its neighbours (fat outside,
    thorax interior inside), and the dark regions it encloses do not come near the air,
    whereas fat lies under the skin. So:

    1. air: the dark regions reaching the field of view's edge, below the midpoint of the
       background and the darkest tissue (the 10th percentile of what rises above
       :func:`~imaging.segment_contrast.tissue_floor`), refined by a threshold level set;
       then the body's outer voxels darker than half their brightest body neighbour
       (partial volume of the skin, or of a muscle meeting air) go to the air;
    2. the body's interior is split at each of the two thresholds of a three-class Otsu of
       its histogram; dark regions that stay more than 4 mm (plus three voxels) from the
       air are the thorax interior; the first threshold that leaves one is the muscle's
       lower edge (on T2-like scans muscle is the middle class, on T1-like ones the thorax
       interior is);
    3. the muscle starts from the thick (``muscle_min_mm``) bright parts touching the
       thorax interior (else the largest thick bright part: a muscle meeting air) and its
       threshold level set settles at the midpoint of the muscle and its dark neighbours
       (each side its own: fat, thorax interior), kept within ``muscle_min_mm`` of its
       start (gland and skin are as bright).
    """
    air, peak, low, t_air = _edge_air(a, sp, min_region_mm3=min_region_mm3, name=name)
    lv = {"air": _interior_median(a, air, peak)}
    body = ~air
    _require_body(air, name)
    thorax, t_mid, thresholds = _deep_dark_thorax(a, sp, body, min_region_mm3=min_region_mm3,
                                                  name=name)
    muscle, thorax = _muscle_start_bright(pre, a, sp, body, thorax, t_mid, notes, seeds=seeds,
                                          muscle_min_mm=muscle_min_mm, name=name)
    t_fat, t_thorax = _muscle_levels(a, body, thorax, muscle, lv, low=low, t_mid=t_mid)
    lv.update(t_air=t_air, t_dark=t_fat, t_muscle_thorax=t_thorax, t_mid=t_mid,
              otsu_low=thresholds[0], otsu_high=thresholds[1])
    body_start = body.copy()
    ls = dict(iterations=levelset_iterations, curvature=curvature, shrink=levelset_shrink)
    air, body, markers_mm, marker_mask = _refine_air(
        pre, a, sp, air, lv["air"], t_air=t_air, marker_diameter_mm=marker_diameter_mm, ls=ls,
        name=name)
    thorax = ndimage.binary_fill_holes(thorax) & body
    muscle_start = muscle.copy()
    reach = dilated(muscle, _ball(muscle_min_mm, sp))
    feature = _toward_thorax(pre, thorax, t_fat=t_fat, t_thorax=t_thorax)
    muscle = levelset_refine(feature, muscle, lower=t_fat, upper=np.inf, **ls)
    muscle &= body & reach & ~marker_mask
    # a voxel between the muscle and the thorax interior is one of the two, never breast
    thorax |= _between(muscle, thorax, marker_mask) & body
    if not muscle.any():
        raise SegmentationError(f"{STAGE}: {name}: no muscle / chest wall left after its "
                                "active contour (fat-suppressed contrast)")
    muscle, air = _muscle_air_edge(a, muscle, air, marker_mask, lv)
    body &= ~air
    thorax &= ~muscle
    cnr = contrast_to_noise(a, air, {"air": lv["air"], "fat": max(lv["muscle"], 1.0)})
    _require_cnr(cnr, name)
    return {"lv": lv, "air": air, "thorax": thorax, "body": body, "body_start": body_start,
            "muscle": muscle, "muscle_start": muscle_start, "marker_mask": marker_mask,
            "markers_mm": markers_mm, "cnr": cnr, "t_bright": t_mid}


def _edge_air(a, sp, *, min_region_mm3, name):
    """Step 1's start: the dark regions reaching the field of view's edge, below the midpoint
    of the background and the darkest tissue (the 10th percentile of what rises above
    :func:`~imaging.segment_contrast.tissue_floor`: five noise sigmas, and enough that the
    partial-volume surface of a high-SNR scan stays out). Returns (air, background level,
    darkest tissue level, that midpoint)."""
    vox_mm3 = float(np.prod(sp))
    peak, sigma = air_noise(a)
    rough = a > tissue_floor(peak, sigma)
    vals = a[::2, ::2, ::2][rough[::2, ::2, ::2]]
    if vals.size < 100:
        raise SegmentationError(f"{STAGE}: {name}: no body found above the background noise "
                                "(fat-suppressed contrast)")
    low = float(np.percentile(vals, 10))
    # Below the darkest tissue (fat, under the skin): the air cannot leak into the body.
    t_air = 0.5 * (peak + low)
    dark = a < t_air
    lab, n = _components(dark)
    edge = np.zeros(n + 1, bool)
    for face in (lab[0], lab[-1], lab[:, 0], lab[:, -1], lab[:, :, 0], lab[:, :, -1]):
        edge[np.unique(face)] = True
    edge[0] = False
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    keep = edge & (sizes * vox_mm3 >= min_region_mm3)
    air = keep[lab]
    if not air.any():
        raise SegmentationError(
            f"{STAGE}: {name}: no background (air) reaches the edge of the field of view "
            "(fat-suppressed contrast; is this a body MRI with air around it?)")
    return air, peak, low, t_air


#: Erosions of the dark regions where one leaves none deep (:func:`_deep_dark_thorax`): on
#: the phantom family's T2 fat-suppressed torso small-053 (2 mm slices, its wall 3-4 voxels
#: thick) the thorax interior met the fat outside the wall after one, on the scan's
#: posterior face, where the wall crosses it at a slant.
ERODE_AGAIN = 2
#: The higher threshold's deep regions are taken over the lower's where they hold more than
#: this many times their volume: a thorax interior between fat and muscle (T1) that noise
#: riddles below the lower threshold leaves fragments there (the family's small-045 prone,
#: SNR 13: 19 ml against 364 ml, the fragments' threshold put most of the thorax interior
#: into the muscle). On the family's other 107 fat-suppressed scans the two differ by at
#: most 1.22 times where both hold deep regions after one erosion (19 scans, all T1).
RIDDLED = 2.0


def _deep_dark_thorax(a, sp, body, *, min_region_mm3, name):
    """Step 2: the thorax interior, dark regions of the body's interior that stay more than
    4 mm (plus three voxels) from the air, below the first of the two three-class Otsu
    thresholds that leaves one (unless the second's are :data:`RIDDLED` times larger).
    Returns (thorax, that threshold, both thresholds)."""
    from skimage.filters import threshold_multiotsu

    # distance of every voxel to the air, on every second voxel (mm)
    sub_body = body[::2, ::2, ::2]
    depth = ndimage.distance_transform_edt(sub_body, sampling=2.0 * sp)
    inner = sub_body & (depth > 2.0 * float(sp.max()) + 1.0)
    ivals = a[::2, ::2, ::2][inner]
    if ivals.size < 100:
        raise SegmentationError(f"{STAGE}: {name}: the body is too thin to segment "
                                "(fat-suppressed contrast)")
    thresholds = [float(t) for t in threshold_multiotsu(ivals, classes=3)]
    # one erosion cuts the one-voxel bridges that noise and partial volume open through the
    # muscle; the dark regions grow back as far once classified. Where none is deep after
    # one, two: ERODE_AGAIN. Past the field of view the tissue goes on: with the outside as
    # background the face's thorax was eroded away, and where the scan cuts the chest
    # (small-soft-000's coil box) a 2-3 voxel layer between muscle and thorax went to the
    # breast (381 voxels on its posterior face)
    min_voxels = min_region_mm3 / float(np.prod(sp))
    for erode in (1, ERODE_AGAIN):
        found = [_deep_dark(body & (a < t), depth, erode=erode, min_voxels=min_voxels,
                            near_mm=4.0 + 3.0 * float(sp.max())) for t in thresholds]
        n = [np.count_nonzero(d) for d in found]
        if max(n) == 0:
            continue
        k = 0 if n[0] > 0 and RIDDLED * n[0] >= n[1] else 1
        thorax = ndimage.binary_dilation(found[k], iterations=erode) & body & (a < thresholds[k])
        return thorax, thresholds[k], thresholds
    return np.zeros(body.shape, bool), thresholds[0], thresholds


def _deep_dark(dark, depth, *, erode, min_voxels, near_mm) -> np.ndarray:
    """The parts of ``dark`` eroded ``erode`` times that hold ``min_voxels`` and stay more
    than ``near_mm`` from the air (``depth``: the body's distance map on every second
    voxel; ``near_mm``: skin and partial volume, plus the erosion and that grid's steps)."""
    dlab, dn = _components(ndimage.binary_erosion(dark, iterations=erode, border_value=1))
    if dn == 0:
        return np.zeros(dark.shape, bool)
    dsizes = np.bincount(dlab.ravel(), minlength=dn + 1)
    closest = np.asarray(ndimage.minimum(depth, dlab[::2, ::2, ::2], np.arange(1, dn + 1)),
                         float)
    deep = np.zeros(dn + 1, bool)
    deep[1:] = (closest > near_mm) & (dsizes[1:] >= min_voxels)
    return deep[dlab]


def _muscle_start_bright(pre, a, sp, body, thorax, t_mid, notes, *, seeds, muscle_min_mm,
                         name):
    """Step 3's start: the thick bright parts touching the thorax interior (else the largest
    thick bright part), after the user's seeds. Returns (muscle, thorax)."""
    bright = body & ~thorax & (a >= t_mid)
    muscle, largest = _muscle_start(bright, thorax, sp, muscle_min_mm, outside=~body)
    if largest:
        notes.append("no thorax interior found; muscle = largest thick bright region "
                     "(meeting air where one does; fat-suppressed contrast)")
    mlab = _components(bright)[0]
    muscle, thorax = _apply_seeds(seeds, pre, mlab, thorax, muscle, notes, name,
                                  lambda m: body & ~thorax & ~m & (a < t_mid))
    if not muscle.any():
        raise SegmentationError(f"{STAGE}: {name}: no muscle / chest wall found "
                                "(fat-suppressed contrast: no thick layer brighter than fat)")
    return muscle, thorax


def _muscle_levels(a, body, thorax, muscle, lv, *, low, t_mid) -> tuple[float, float]:
    """Levels of muscle, fat and thorax interior (into ``lv``) and the muscle's two edges:
    the midpoints of the muscle and the fat, and of the muscle and the thorax interior."""
    lv["muscle"] = _interior_median(a, muscle, 1.0)
    fat = body & ~thorax & (a < t_mid) & ~ndimage.binary_dilation(muscle, iterations=2)
    lv["fat"] = _interior_median(a, fat, low) if fat.any() else low
    lv["thorax"] = _interior_median(a, thorax, lv["fat"]) if thorax.any() else lv["fat"]
    return 0.5 * (lv["muscle"] + lv["fat"]), 0.5 * (lv["muscle"] + lv["thorax"])


def _toward_thorax(pre, thorax, *, t_fat, t_thorax):
    """The feature for the muscle's level set at ``t_fat`` that settles it at ``t_thorax``
    on the thorax interior's side: ``pre`` shifted by their difference within two voxels of
    the thorax interior. One threshold for both sides (their mean) took a layer of partial
    volume that was more thorax than muscle: on small-000's supine scan 3 ml a voxel deep
    along the whole chest wall, and a fitted modulus 20 % stiffer for it. Thresholding the
    muscle's outer voxels after the level set instead lets the noise through (small-002's
    muscle Dice 0.919 -> 0.904): the level set's smoothing is what decides them well."""
    shift = float(t_thorax - t_fat)
    if shift == 0.0 or not thorax.any():
        return pre
    near = ndimage.binary_dilation(thorax, iterations=2).astype(np.float32)
    img = sitk.GetImageFromArray(near * np.float32(-shift))
    img.CopyInformation(pre)
    return sitk.Cast(pre, sitk.sitkFloat32) + img


def _refine_air(pre, a, sp, air, air_level, *, t_air, marker_diameter_mm, ls, name):
    """Step 1's end: the air's threshold level set, the body's outer partial-volume voxels
    to the air, the body the largest region left, skin markers out of it. Returns (air,
    body, marker centres (K, 3) mm, marker mask)."""
    air = levelset_refine(pre, air, lower=-np.inf, upper=t_air, **ls)
    air |= _surface_partial_volume(a, ~air, air_level)
    blab, bn = _components(~air)
    if bn == 0:
        raise SegmentationError(f"{STAGE}: {name}: empty body mask after removing air")
    bsizes = np.bincount(blab.ravel())
    bsizes[0] = 0
    body = blab == int(bsizes.argmax())
    markers_mm, marker_mask = _markers(pre, a, body, sp, marker_diameter_mm)
    body &= ~marker_mask
    return air, body, markers_mm, marker_mask


def _between(muscle, other, marker_mask):
    """The voxels that touch both the muscle and ``other`` (air, thorax interior) and are
    neither the muscle nor a marker: the partial volume between the two."""
    return (ndimage.binary_dilation(muscle) & ndimage.binary_dilation(other)
            & ~muscle & ~marker_mask)


def _muscle_air_edge(a, muscle, air, marker_mask, lv):
    """Where the muscle meets air (a slab's back, its front between the breasts), the
    voxels between the two (touching both) are muscle above the midpoint of the muscle's
    and the air's levels, else air. A half-muscle, half-air voxel is as dark as fat when fat
    is suppressed, so the muscle's contour (at the muscle-fat midpoint) leaves it to the
    breast, and the air's (below the fat) to the body. Returns (muscle, air)."""
    edge = _between(muscle, air, marker_mask)
    if not edge.any():
        return muscle, air
    solid = edge & (a >= 0.5 * (lv["muscle"] + lv["air"]))
    return muscle | solid, (air & ~solid) | (edge & ~solid)


def _surface_partial_volume(a: np.ndarray, body: np.ndarray, air_level: float) -> np.ndarray:
    """The body's outer voxels (face-adjacent to the rest) that are darker than the midpoint
    of the air level and their brightest body neighbour (of 26): partial-volume voxels that
    are more air than tissue, whatever the tissue at the surface (bright skin, mid-grey
    muscle)."""
    outer = body & ~ndimage.binary_erosion(body, border_value=1)
    idx = np.nonzero(outer)
    if idx[0].size == 0:
        return outer
    local = np.full(idx[0].size, -np.inf, np.float32)
    shape = np.asarray(a.shape)
    for dz in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dz == dy == dx == 0:
                    continue
                j = [np.clip(i + d, 0, n - 1) for i, d, n in zip(idx, (dz, dy, dx), shape)]
                v = np.where(body[tuple(j)], a[tuple(j)], -np.inf)
                np.maximum(local, v, out=local)
    drop = a[idx] < 0.5 * (air_level + local)
    out = np.zeros(a.shape, bool)
    out[tuple(i[drop] for i in idx)] = True
    return out

