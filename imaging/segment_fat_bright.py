"""Regions of a fat-bright (T1/T2-weighted) volume: air, thorax interior, body and muscle
(steps 2-5 of :mod:`imaging.segment`'s method)."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from imaging.levelset import levelset_refine
from imaging.preprocess import BACKGROUND_OVER_FAT
from imaging.segment_contrast import (
    _require_body,
    _require_cnr,
    contrast_to_noise,
    magnitude_level,
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


def _fat_bright_regions(pre: sitk.Image, a: np.ndarray, sp: np.ndarray, notes: list, *,
                        seeds, skin_level, levelset_iterations, curvature,
                        marker_diameter_mm, min_region_mm3, muscle_min_mm, name,
                        levelset_shrink=1) -> dict:
    """Air, thorax interior, body and muscle of a fat-bright (T1/T2-weighted) volume
    (steps 2-5 of the module's method)."""
    floor = (float(pre.GetMetaData(BACKGROUND_OVER_FAT))
             if pre.HasMetaDataKey(BACKGROUND_OVER_FAT) else 0.0)
    lv, air, thorax, muscle0, by_edge = _levels_and_dark_regions(
        a, sp, skin_level=skin_level, min_region_mm3=min_region_mm3,
        muscle_min_mm=muscle_min_mm, name=name, background_over_fat=floor)
    if by_edge:
        notes.append("background taken from the field-of-view boundary (no dark region is "
                     "surrounded by skin: muscle meets air?)")
    # Noise voxels above the threshold inside the thorax interior are not tissue.
    thorax = ndimage.binary_fill_holes(thorax)
    t_dark, t_bright = _thresholds(lv)
    t_air = 0.5 * (lv["air"] + skin_level * lv["fat"])
    lv.update(t_dark=t_dark, t_bright=t_bright, t_air=t_air)

    body = ~air
    if not body.any():
        raise SegmentationError(f"{STAGE}: {name}: empty body mask")
    _require_body(air, name)
    cnr = contrast_to_noise(a, air, lv)
    _require_cnr(cnr, name)
    body_start = body.copy()

    markers_mm, marker_mask = _markers(pre, a, body, sp, marker_diameter_mm)
    ls = dict(iterations=levelset_iterations, curvature=curvature, shrink=levelset_shrink)
    air, body = _refine_air(pre, a, sp, air, muscle0, marker_mask, t_air=t_air, t_dark=t_dark,
                            muscle_min_mm=muscle_min_mm, ls=ls, name=name)
    thorax &= body
    muscle, muscle_start, thorax = _refine_muscle(
        pre, a, sp, body, thorax, marker_mask, notes, seeds=seeds, t_dark=t_dark,
        t_bright=t_bright, t_air=t_air, muscle_min_mm=muscle_min_mm, ls=ls, name=name)
    return {"lv": lv, "air": air, "thorax": thorax, "body": body, "body_start": body_start,
            "muscle": muscle, "muscle_start": muscle_start, "marker_mask": marker_mask,
            "markers_mm": markers_mm, "cnr": cnr, "t_bright": t_bright}


def _thresholds(lv: dict) -> tuple[float, float]:
    """(t_dark, t_bright): the thorax/muscle and muscle/fat midpoints."""
    return 0.5 * (lv["thorax"] + lv["muscle"]), 0.5 * (lv["muscle"] + lv["fat"])


#: Passes of the levels and the dark regions they give. The initial levels are the nominal
#: T2 shares of the fat; on a T1 torso (thorax 0.15, muscle 0.35) the first pass's dark
#: threshold then lies low, and a second pass from its regions had not settled (family seed
#: 19 prone: gland Dice 0.72 after two passes, 0.93 after three).
LEVEL_PASSES = 3


def _levels_and_dark_regions(a, sp, *, skin_level, min_region_mm3, muscle_min_mm, name,
                             background_over_fat=0.0):
    """Tissue levels (fractions of fat) and the dark regions they give, estimated
    :data:`LEVEL_PASSES` times: from initial levels (the thorax's and muscle's nominal shares
    of the fat, where the normalised magnitude image shows them:
    :func:`imaging.segment_contrast.magnitude_level` of the background's level before
    normalisation), then each time from the levels the regions before gave.

    Returns
    -------
    lv : dict
        Levels of air, thorax, muscle, fat and skin.
    air, thorax : (nz, ny, nx) bool
    muscle0 : (nz, ny, nx) bool
        The chest wall's start (:func:`imaging.segment_regions._muscle_start`).
    by_edge : bool
        The background was taken from the field-of-view boundary.
    """
    vox_mm3 = float(np.prod(sp))
    # Initial levels (fractions of fat); refined below from the regions they produce. On a
    # noisy scan the normalisation takes dark tissue below its share of the fat: a T2 slab's
    # wall at SNR 11 (family seed 18) read 0.15, half of it under the nominal levels' dark
    # threshold (0.175), and went to the air (muscle Dice 0.001; 0.93-0.94 from these levels).
    lv = {"air": 0.0, "thorax": magnitude_level(0.1, background_over_fat),
          "muscle": magnitude_level(0.25, background_over_fat), "fat": 1.0, "skin": skin_level}
    t_dark, t_bright = _thresholds(lv)
    by_edge = False
    for _ in range(LEVEL_PASSES):
        air, thorax, edge = _split_dark(a, t_dark, lv, vox_mm3=vox_mm3,
                                        min_region_mm3=min_region_mm3, name=name)
        by_edge |= edge
        lv["air"] = _interior_median(a, air, lv["air"])
        if thorax.any():
            lv["thorax"] = _interior_median(a, thorax, lv["thorax"])
        bright = (a > t_bright) & ~air
        lv["fat"] = _interior_median(a, bright, lv["fat"])
        mid = ~air & ~thorax & ~bright
        muscle0 = _muscle_start(mid, thorax, sp, muscle_min_mm, outside=air)[0]
        if muscle0.any() and thorax.any():
            lv["muscle"] = _interior_median(a, muscle0, lv["muscle"])
        elif muscle0.any():  # a wall meeting air is thin: its interior is the glands on it
            lv["muscle"] = _darker_mode(a[muscle0])
        if not thorax.any():  # muscle meets air: the dark side of the muscle is air
            lv["thorax"] = lv["air"]
        t_dark, t_bright = _thresholds(lv)
    return lv, air, thorax, muscle0, by_edge


#: Otsu's effectiveness (between-class over total variance) above which intensities are two
#: modes: a single Gaussian gives 2 / pi = 0.64 at its best split.
BIMODAL_EFFECTIVENESS = 0.75


def _darker_mode(values: np.ndarray) -> float:
    """The muscle's level from the start of a wall that meets air: the median of the darker
    Otsu class where the values are two modes (on a T2-weighted scan the glands lying on the
    wall are more than twice as bright as the muscle and join its start), else the median.
    The plain median of such a start took the glands' level (small-005's tilted scan: a start
    of 8150 muscle and 7501 gland voxels read 0.41 of fat against the muscle's 0.18; the next
    threshold made half the wall dark and the glands became the muscle)."""
    from skimage.filters import threshold_otsu

    v = np.asarray(values, float)
    if np.ptp(v) == 0:  # one value (the caller's start is never empty)
        return float(np.median(v))
    t = float(threshold_otsu(v))
    low, high = v[v <= t], v[v > t]
    if low.size == 0 or high.size == 0:
        return float(np.median(v))
    between = low.size * high.size / v.size**2 * (low.mean() - high.mean()) ** 2
    if between / v.var() > BIMODAL_EFFECTIVENESS:
        return float(np.median(low))
    return float(np.median(v))


def _split_dark(a, t_dark, lv, *, vox_mm3, min_region_mm3, name):
    """Dark regions (below ``t_dark``, at least ``min_region_mm3``) split into air and thorax
    interior by what surrounds them: air meets skin/fat, the thorax interior meets muscle.
    Without any air (muscle meeting air), the region reaching the field of view's boundary
    with the brightest surroundings is the air. Returns (air, thorax, by_edge)."""
    dark = a < t_dark
    lab, n = _components(dark)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    big = np.flatnonzero(sizes * vox_mm3 >= min_region_mm3)
    big = big[big > 0]
    air = np.zeros(a.shape, bool)
    thorax = np.zeros(a.shape, bool)
    # Air meets skin/fat, the thorax interior meets muscle: judge by the median of the shell
    # one voxel out (past the partial volume). A shell farther out (it was 4-6 voxels, on
    # every second voxel) passes a 6 mm muscle into the fat behind it and calls the thorax
    # air (small-007's torso scans: the muscle's dark level was then the air's).
    objs = ndimage.find_objects(lab)
    edge_hit = np.zeros(n + 1, bool)
    for face in (lab[0], lab[-1], lab[:, 0], lab[:, -1], lab[:, :, 0], lab[:, :, -1]):
        edge_hit[np.unique(face)] = True
    rings: dict[int, float] = {}
    for k in big:
        if objs[k - 1] is None:
            continue
        sl = tuple(slice(max(s.start - 2, 0), s.stop + 2) for s in objs[k - 1])
        comp = lab[sl] == k
        shell = ndimage.binary_dilation(comp, iterations=2) & ~ndimage.binary_dilation(comp)
        ring = float(np.median(a[sl][shell])) if shell.any() else 1.0
        target = air if ring > 0.5 * (lv["muscle"] + lv["skin"]) else thorax
        target |= lab == k
        rings[k] = ring
    if air.any():
        return air, thorax, False
    # Muscle meeting air (no thorax shell): every dark region touches some muscle.
    # The background is then the region reaching the field-of-view boundary whose
    # surroundings are brightest (skin and fat around it).
    edge = [k for k in rings if edge_hit[k]]
    if not edge:
        raise SegmentationError(
            f"{STAGE}: {name}: no background (air) reaches the edge of the field of "
            "view (is this a body MRI with air around it?)")
    k = max(edge, key=lambda j: (rings[j], sizes[j]))
    air |= lab == k
    thorax &= lab != k
    return air, thorax, True


def _refine_air(pre, a, sp, air, muscle0, marker_mask, *, t_air, t_dark, muscle_min_mm, ls,
                name):
    """Active contour on the air: settles the skin surface at the air/skin midpoint and,
    where the muscle meets air, the muscle surface at the air/muscle midpoint (the feature
    is scaled there so that one threshold serves both). The markers join the air; the body
    is the largest region left. Returns (air, body)."""
    feature = pre
    if muscle0.any() and t_dark < t_air:
        near = dilated(muscle0, _ball(muscle_min_mm, sp))
        scale = np.where(near, np.float32(t_air / max(t_dark, 1e-3)), np.float32(1.0))
        feature = sitk.GetImageFromArray(a * scale)
        feature.CopyInformation(pre)
    air = levelset_refine(feature, air, lower=-np.inf, upper=t_air, **ls)
    air |= marker_mask
    # Keep the air that touches the original air (the level set may open small pockets).
    body = ~air
    blab, bn = _components(body)
    if bn == 0:
        raise SegmentationError(f"{STAGE}: {name}: empty body mask after removing air and markers")
    bsizes = np.bincount(blab.ravel())
    bsizes[0] = 0
    return air, blab == int(bsizes.argmax())


def _refine_muscle(pre, a, sp, body, thorax, marker_mask, notes, *, seeds, t_dark, t_bright,
                   t_air, muscle_min_mm, ls, name):
    """The chest wall: its start (the thick mid-intensity layer touching the thorax
    interior, after the user's seeds), then its active contour between the thorax and fat
    midpoints, plus the partial-volume rim where it meets air. Returns (muscle, its start,
    thorax)."""
    # Chest-wall band: mid-intensity layer touching the thorax interior.
    # Thin mid-intensity shells (skin, partial volume at the skin) are cut off first: where
    # the muscle meets air, the skin of the breasts meets the muscle at their base.
    mid = body & ~thorax & (a <= t_bright)
    mlab, mn = _components(mid)
    muscle, largest = _muscle_start(mid, thorax, sp, muscle_min_mm, outside=~body)
    if largest:
        notes.append("no thorax interior found; muscle = largest thick mid-intensity region "
                     "(meeting air where one does)")

    # Seeds: reassign the connected region (of its intensity class) that holds each seed.
    muscle, thorax = _apply_seeds(
        seeds, pre, mlab, thorax, muscle, notes, name,
        lambda m: body & ~thorax & ~m & (a > t_bright))

    if not muscle.any():
        raise SegmentationError(f"{STAGE}: {name}: no muscle / chest wall found")
    muscle_start = muscle.copy()
    # Active contour on the muscle: boundaries settle at the thorax and fat midpoints.
    muscle = levelset_refine(pre, muscle, lower=t_dark, upper=t_bright, **ls)
    muscle &= body & ~marker_mask
    if not muscle.any():
        raise SegmentationError(f"{STAGE}: {name}: no muscle / chest wall left after its "
                                "active contour")
    # Partial-volume voxels where the muscle meets air are darker than any skin: muscle.
    rim = body & ~thorax & ~muscle & ~marker_mask & (a < t_air)
    muscle |= rim & ndimage.binary_dilation(muscle)
    thorax &= ~muscle
    return muscle, muscle_start, thorax
