"""Segmentation of one MRI volume into the label convention 0 background, 1 breast tissue,
2 muscle / chest wall, 3 glandular tissue (optional).

Method
------
1. Preprocess (N4, optional isotropic resampling, edge-preserving denoising, background -> 0,
   fat mode -> 1), so tissue levels are fractions of fat.
2. Automatic initialisation: dark regions (air and thorax interior) are split by what
   surrounds them (air meets skin/fat, the thorax interior meets muscle); the body is
   everything that is not air; skin markers (detected blobs) are removed; the chest-wall band
   is the mid-intensity layer touching the thorax interior; the left/right split is the
   sagittal midline of the thorax.
3. Class levels are re-estimated from the interiors of these regions and each boundary is
   placed at the midpoint of the two tissues it separates (partial-volume threshold).
4. Active contours: threshold level sets (SimpleITK ``ThresholdSegmentationLevelSet``,
   curvature-regularised) evolve the air and muscle regions from this initialisation to
   those midpoints.
5. User seeds ``(label, point_mm)`` override the automatic choice for the region that holds
   the point (e.g. a muscle seed turns a mid-intensity region into muscle).

Steps 2-4 assume fat is the brightest large tissue (T1/T2-weighted). On fat-suppressed scans
(fat dark, muscle/gland/skin mid-grey to bright) :func:`_fat_suppressed_regions` finds the
same regions from the geometry instead (the muscle is the thick layer brighter than both its
neighbours; the thorax interior is the dark region it keeps away from the air). The contrast
is given (``contrast=``) or detected from the profile under the body surface
(:func:`detect_contrast`); when the detected one fails, the other is tried, and if both fail
the error names the file and both reasons.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from imaging.fiducials import body_without_markers, detect_markers
from imaging.labels import BACKGROUND, BREAST, GLAND, MUSCLE
from imaging.preprocess import (
    background_of,
    body_box,
    check_volume,
    n4_correct,
    preprocess,
)

STAGE = "segment"
log = logging.getLogger(__name__)

#: Coarsest voxel (mm) a level set may run on when ``levelset_shrink`` > 1.
MAX_COARSE_MM = 2.0
#: Smallest accepted contrast-to-noise ratio between body (fat) and background.
MIN_CNR = 5.0
#: Fewest 4^3-voxel blocks of pure (>= 90 %) background, and of pure tissue, in a body MRI.
MIN_BLOCKS = 8
#: Plausible breast-tissue volume of one scan, ml (both sides; a small phantom has ~20 ml).
BREAST_ML_RANGE = (5.0, 6000.0)


#: Contrasts :func:`segment_volume` knows: fat the brightest large tissue (T1/T2-weighted), or
#: fat suppressed (fat dark, gland/muscle/skin mid-grey to bright).
CONTRASTS = ("fat_bright", "fat_suppressed")


def air_noise(a: np.ndarray) -> tuple[float, float]:
    """Level and noise sigma of the background of a normalised volume: the histogram peak
    nearest 0 and its half width at half maximum on the bright side / 1.1774 (a Gaussian's;
    the dark side is missing from a magnitude image's Rayleigh background), on every second
    voxel."""
    v = a[::2, ::2, ::2].ravel()
    v = v[(v > -0.5) & (v < 0.5)]
    if v.size < 100:
        return 0.0, 0.05
    hist, edges = np.histogram(v, bins=400)
    hist = np.convolve(hist, np.ones(3) / 3, mode="same")
    k = int(hist.argmax())
    peak = float(0.5 * (edges[k] + edges[k + 1]))
    right = np.flatnonzero(hist[k:] < 0.5 * hist[k])
    width = (right[0] if right.size else 1) * float(edges[1] - edges[0])
    return peak, max(width / 1.1774, 1e-4)


def detect_contrast(a: np.ndarray, spacing_zyx: np.ndarray) -> tuple[str, dict]:
    """Fat-bright or fat-suppressed, from the intensity profile under the body surface.

    The body's outer layer (0-2 grid steps of a 2x-strided copy, i.e. skin and its partial
    volume) is compared with the layer 3-8 mm deep (subcutaneous tissue, fat where there is
    any). With fat bright, the tissue under the skin is brighter than the skin's layer (fat
    is the brightest large tissue); with fat suppressed, the skin's layer is brighter than the
    dark fat beneath it. The body is what rises 5 noise sigmas above the background.

    Returns
    -------
    (str, dict)
        One of :data:`CONTRASTS` and the numbers that decided it.
    """
    peak, sigma = air_noise(a)
    sub = a[::2, ::2, ::2]
    sp2 = 2.0 * np.asarray(spacing_zyx, float)
    rough = sub > peak + 5.0 * sigma
    lab, n = ndimage.label(rough)
    if n == 0:
        return "fat_bright", {"reason": "no body above the noise"}
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    body = ndimage.binary_fill_holes(lab == int(sizes.argmax()))
    depth = ndimage.distance_transform_edt(body, sampling=sp2)
    step = float(sp2.max())
    outer = sub[(depth > 0) & (depth <= step)]
    inner = sub[(depth > step) & (depth <= 3.0 * step)]
    o, i = float(np.median(outer)), float(np.median(inner))
    kind = "fat_suppressed" if i < o else "fat_bright"
    return kind, {"outer_layer": o, "under_layer": i, "air": peak, "air_sigma": sigma}


class SegmentationError(ValueError):
    """The volume cannot be segmented; the message names the file and the problem."""


@dataclass(frozen=True)
class Seed:
    """A user seed: the region holding ``point`` (LPS mm) gets ``label`` (0/1/2/3)."""

    label: int
    point: tuple[float, float, float]


@dataclass(frozen=True)
class SegmentationResult:
    """Outcome of :func:`segment_volume`.

    Attributes
    ----------
    labels : SimpleITK.Image
        uint8 label map on the input grid.
    preprocessed : SimpleITK.Image
        The normalised volume the segmentation used (float32, maybe resampled).
    levels : dict
        Estimated tissue levels (fractions of fat): air, thorax, muscle, fat, and the
        thresholds used at each boundary.
    midline_x_mm : float
        x of the sagittal midline (thorax centre), mm; left breast at larger x.
    markers_mm : (K, 3) ndarray
        Skin-marker centres removed from the body.
    notes : tuple of str
        What the user should know (seeds applied, fallbacks, low confidence).
    confidence : dict
        The segmentation's own confidence (see :func:`segmentation_confidence`).
    contrast : str
        The contrast segmented (one of :data:`CONTRASTS`).
    """

    labels: sitk.Image
    preprocessed: sitk.Image
    levels: dict = field(default_factory=dict)
    midline_x_mm: float = 0.0
    markers_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    notes: tuple = ()
    confidence: dict = field(default_factory=dict)
    contrast: str = "fat_bright"


def _ball(radius_mm: float, spacing_zyx: np.ndarray) -> np.ndarray:
    rad = np.maximum(1, np.floor(radius_mm / spacing_zyx)).astype(int)
    zz, yy, xx = np.ogrid[-rad[0]:rad[0] + 1, -rad[1]:rad[1] + 1, -rad[2]:rad[2] + 1]
    s = spacing_zyx
    return (zz * s[0]) ** 2 + (yy * s[1]) ** 2 + (xx * s[2]) ** 2 <= radius_mm ** 2 + 1e-9


def _interior_median(a: np.ndarray, mask: np.ndarray, default: float) -> float:
    """Median of ``a`` over the interior of ``mask`` (two voxels in), on every second voxel
    in each direction: a level estimate needs thousands of samples, not millions."""
    sub, m = a[::2, ::2, ::2], mask[::2, ::2, ::2]
    inner = ndimage.binary_erosion(m)
    vals = sub[inner] if np.count_nonzero(inner) > 50 else a[mask]
    return float(np.median(vals)) if vals.size else default


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
                  min_mm: float) -> tuple[np.ndarray, bool]:
    """The chest wall's start: the thick parts (opening by a ball of ``min_mm / 2``) of the
    mid-intensity layer that touch the thorax interior, else the largest thick part.
    Returns the mask and whether it is the largest-part fallback."""
    thick = ndimage.binary_opening(mid, structure=_ball(min_mm / 2, spacing_zyx))
    tlab, tn = _components(thick)
    if thorax.any():
        muscle = _touching(tlab, tn, thorax)[tlab]
        if muscle.any():
            return muscle, False
    if tn == 0:
        return np.zeros(mid.shape, bool), True
    tsizes = np.bincount(tlab.ravel())
    tsizes[0] = 0
    return tlab == int(tsizes.argmax()), True


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


def levelset_refine(
    feature: sitk.Image,
    mask: np.ndarray,
    *,
    lower: float,
    upper: float,
    iterations: int,
    curvature: float = 0.5,
    margin_vox: int = 4,
    shrink: int = 1,
) -> np.ndarray:
    """Evolve ``mask`` with a threshold level set: it grows where ``lower <= feature <=
    upper`` and shrinks elsewhere, with curvature regularisation, so the boundary settles at
    the thresholds. Runs on the bounding box of the mask (plus a margin) only.

    Parameters
    ----------
    feature : SimpleITK.Image
        Float32 normalised volume.
    mask : (nz, ny, nx) bool
        Initial region.
    lower, upper : float
        Intensity window of the region.
    iterations : int
        Maximum level-set iterations (0: return ``mask`` unchanged).
    curvature : float
        Weight of the curvature (smoothing) term relative to the propagation term.
    margin_vox : int
        Voxels added around the bounding box.
    shrink : int
        Run the level set on a grid ``shrink`` times coarser (averaged voxels), then settle
        the boundary voxels of the result (one voxel either side) at full resolution by the
        thresholds: the level set's cost grows with its surface's voxels, so 2 costs about a
        quarter. Only where the coarse voxels stay within :data:`MAX_COARSE_MM` (thin
        layers, skin and muscle, need that resolution).

    Returns
    -------
    (nz, ny, nx) bool
    """
    if iterations <= 0 or not mask.any():
        return mask.copy()
    # bounding box from the axis projections (np.argwhere of a body-sized mask is ~1 GB)
    ext = [np.flatnonzero(mask.any(axis=tuple(j for j in range(3) if j != i)))
           for i in range(3)]
    lo = np.maximum([e[0] - margin_vox for e in ext], 0)
    hi = np.minimum([e[-1] + margin_vox + 1 for e in ext], mask.shape)
    sl = tuple(slice(a, b) for a, b in zip(lo, hi))
    sub_mask = sitk.GetImageFromArray(mask[sl].astype(np.uint8))
    sub_feat = sitk.RegionOfInterest(
        feature, [int(b - a) for a, b in zip(lo[::-1], hi[::-1])], [int(a) for a in lo[::-1]]
    )
    sub_mask.CopyInformation(sub_feat)
    # Zero level half-way between the mask's boundary voxels and their outside neighbours.
    # The sparse-field level set builds its narrow band from the zero crossing alone, so a
    # +-0.5 binary image starts it exactly where a signed distance map + 0.5 would, at a
    # fraction of the cost.
    if (shrink > 1 and min(sub_feat.GetSize()) >= 8 * shrink
            and shrink * max(feature.GetSpacing()) <= MAX_COARSE_MM):
        return _levelset_shrunk(sub_feat, sub_mask, mask, sl, lower=lower, upper=upper,
                                iterations=iterations, curvature=curvature, shrink=shrink)
    init = sitk.Cast(sub_mask, sitk.sitkFloat32) - 0.5
    out = _threshold_levelset(lower, upper, iterations, curvature).Execute(init, sub_feat)
    res = mask.copy()
    res[sl] = sitk.GetArrayViewFromImage(out) > 0
    return res


def _require_body(air: np.ndarray, name: str) -> None:
    """Stop unless the volume holds blocks of pure background and of pure tissue."""
    blocks = coherent_blocks(air)
    if min(blocks) < MIN_BLOCKS:
        raise SegmentationError(
            f"{STAGE}: {name}: no body found: {blocks[0]} block(s) of 4^3 voxels are "
            f"background and {blocks[1]} are tissue, at 90 % or more (at least {MIN_BLOCKS} "
            "of each expected; is this volume noise only?)")


def _threshold_levelset(lower, upper, iterations, curvature):
    """ITK's threshold level set, grown where the feature lies in [lower, upper]."""
    ls = sitk.ThresholdSegmentationLevelSetImageFilter()
    ls.SetLowerThreshold(float(lower))
    ls.SetUpperThreshold(float(upper))
    ls.SetMaximumRMSError(0.01)
    ls.SetNumberOfIterations(int(iterations))
    ls.SetCurvatureScaling(float(curvature))
    ls.SetPropagationScaling(1.0)
    ls.ReverseExpansionDirectionOn()
    return ls


def _levelset_shrunk(sub_feat, sub_mask, mask, sl, *, lower, upper, iterations, curvature,
                     shrink):
    """:func:`levelset_refine` on a ``shrink`` times coarser grid, its boundary settled at
    full resolution by the thresholds."""
    f = sitk.BinShrink(sub_feat, [int(shrink)] * 3)
    m = sitk.BinShrink(sitk.Cast(sub_mask, sitk.sitkFloat32), [int(shrink)] * 3)
    out = _threshold_levelset(lower, upper, iterations, curvature).Execute(m - 0.5, f)
    # back to the full grid: the coarse level set's zero crossing, linearly interpolated
    up = sitk.Resample(out, sub_feat, sitk.Transform(), sitk.sitkLinear, -1.0,
                       sitk.sitkFloat32)
    region = sitk.GetArrayViewFromImage(up) > 0
    band = ndimage.binary_dilation(region) & ~ndimage.binary_erosion(region)
    a = sitk.GetArrayViewFromImage(sub_feat)
    region = region & ~band | band & (a >= lower) & (a <= upper)
    res = mask.copy()
    res[sl] = region
    return res


def segment_volume(
    img: sitk.Image,
    *,
    seeds: Sequence[Seed] = (),
    gland: bool = False,
    n4: bool = True,
    n4_shrink: int = 4,
    isotropic_mm: float | None = None,
    denoise_iterations: int = 3,
    denoise_method: str = "gradient",
    skin_level: float = 0.7,
    levelset_iterations: int = 30,
    levelset_shrink: int = 1,
    curvature: float = 0.5,
    marker_diameter_mm: float = 4.0,
    min_region_mm3: float = 500.0,
    muscle_min_mm: float = 3.0,
    name: str = "volume",
    contrast: str = "auto",
    crop: bool = True,
    n4_cache: str | Path | None = None,
) -> SegmentationResult:
    """Segment breast tissue, muscle (and optionally gland) in one MRI volume.

    Parameters
    ----------
    img : SimpleITK.Image
        Raw scalar 3-D volume (fat bright, muscle and thorax interior dark).
    seeds : sequence of Seed
        User corrections: the region holding each point gets the seed's label.
    gland : bool
        Also label glandular tissue (3) inside the breast.
    n4, n4_shrink, isotropic_mm, denoise_iterations, denoise_method
        Preprocessing options (see :func:`imaging.preprocess.preprocess`).
    skin_level : float
        Skin intensity as a fraction of fat; the air boundary sits at half of it.
    levelset_iterations : int
        Active-contour iterations per region (0: thresholds and morphology only).
    levelset_shrink : int
        The active contours run on a grid this many times coarser, their boundaries then
        settled at full resolution (:func:`levelset_refine`); 1: full resolution.
    curvature : float
        Curvature weight of the level sets.
    marker_diameter_mm : float
        Skin-marker diameter (markers are removed from the body).
    min_region_mm3 : float
        Dark regions smaller than this are noise inside tissue, not air or thorax.
    muscle_min_mm : float
        Mid-intensity layers thinner than this (skin, partial volume) cannot start the
        muscle; the muscle's active contour still reaches them.
    name : str
        Name for messages (the file path).
    contrast : {"auto", "fat_bright", "fat_suppressed"}
        Fat bright (T1/T2-weighted) or fat suppressed; ``"auto"`` detects it
        (:func:`detect_contrast`) and says so in the notes.
    crop : bool
        Work on the body's box (:func:`imaging.preprocess.body_box`); the label map is
        pasted back on the input grid. ``preprocessed`` is then the cropped volume.
    n4_cache : path, optional
        Folder of bias corrections shared with later stages (see
        :func:`imaging.preprocess.n4_correct`).

    Returns
    -------
    SegmentationResult
    """
    if contrast != "auto" and contrast not in CONTRASTS:
        raise SegmentationError(f"{STAGE}: {name}: contrast must be 'auto' or one of "
                                f"{CONTRASTS}, got {contrast!r}")
    notes: list[str] = []
    try:
        check_volume(img, name=name, stage=STAGE)
        box = body_box(img) if crop else None
        work, background = img, None
        if box is not None:  # everything below scales with the voxels it sees
            # N4 on the whole volume: the same correction serves the registration (cached)
            corrected = n4_correct(img, shrink=n4_shrink, cache=n4_cache) if n4 else img
            background = background_of(corrected)  # the whole volume's, as uncropped
            work = sitk.RegionOfInterest(corrected, box[1], box[0])
            n4 = False
            notes.append(f"cropped to the body's box: index {box[0]}, size {box[1]} voxels")
        pre = preprocess(work, n4=n4, n4_shrink=n4_shrink, n4_cache=n4_cache,
                         background=background,
                         isotropic_mm=isotropic_mm,
                         denoise_iterations=denoise_iterations, denoise_method=denoise_method,
                         name=name)
    except SegmentationError:
        raise
    except ValueError as exc:
        raise SegmentationError(str(exc)) from None
    a = sitk.GetArrayFromImage(pre)
    sp = np.asarray(pre.GetSpacing(), float)[::-1]  # (z, y, x)
    vox_mm3 = float(np.prod(sp))

    if contrast == "auto":
        kind, why = detect_contrast(a, sp)
        notes.append(f"contrast detected: {kind} (" + ", ".join(
            f"{k} {v:.3g}" if isinstance(v, float) else f"{k}: {v}" for k, v in why.items())
            + ")")
        order = [kind, next(k for k in CONTRASTS if k != kind)]
    else:
        order = [contrast]
    opts = dict(seeds=seeds, levelset_iterations=levelset_iterations, curvature=curvature,
                marker_diameter_mm=marker_diameter_mm, min_region_mm3=min_region_mm3,
                muscle_min_mm=muscle_min_mm, name=name, levelset_shrink=levelset_shrink)
    failed: list[str] = []
    for kind in order:
        tried = list(notes)
        try:
            if kind == "fat_suppressed":
                r = _fat_suppressed_regions(pre, a, sp, tried, **opts)
            else:
                r = _fat_bright_regions(pre, a, sp, tried, skin_level=skin_level, **opts)
        except SegmentationError as exc:
            failed.append(f"as {kind}: {exc}")
            continue
        agree = _dice(r["muscle_start"], r["muscle"])
        if failed and agree < 0.9:  # a second guess must hold up on its own
            failed.append(f"as {kind}: {STAGE}: {name}: the muscle's active contour and its "
                          f"start agree only to Dice {agree:.2f} (< 0.9)")
            continue
        notes = tried + [f"segmented as {kind} after: {f}" for f in failed]
        break
    else:
        if len(failed) == 1:
            raise SegmentationError(failed[0][failed[0].index(": ") + 2:])
        raise SegmentationError(f"{STAGE}: {name}: cannot segment with either contrast: "
                                + "; ".join(failed))
    lv, air, thorax, body, muscle = r["lv"], r["air"], r["thorax"], r["body"], r["muscle"]
    marker_mask, markers_mm, t_bright = r["marker_mask"], r["markers_mm"], r["t_bright"]

    labels = np.zeros(a.shape, np.uint8)
    labels[body & ~thorax & ~muscle & ~marker_mask] = BREAST
    labels[muscle] = MUSCLE
    if gland:
        if kind == "fat_suppressed":  # gland brighter than the (dark) fat
            t_gland = 0.5 * (lv.setdefault("gland", lv["muscle"]) + lv["fat"])
            cand = (labels == BREAST) & (a > t_gland)
        else:
            t_gland = 0.5 * (lv.setdefault("gland", 0.6) + lv["fat"])
            cand = (labels == BREAST) & (a < t_gland)
        glab, gn = _components(cand & ~ndimage.binary_dilation(air, iterations=2))
        if gn:
            gs = np.bincount(glab.ravel())
            gs[0] = 0
            keep = gs * vox_mm3 >= 0.1 * min_region_mm3
            g = keep[glab]
            lv["gland"] = _interior_median(a, g, lv["gland"])
            labels[g] = GLAND
        lv["t_gland"] = t_gland
    for s in seeds:  # a seed's own voxel always carries its label
        if s.label == GLAND:
            c = np.round(pre.TransformPhysicalPointToContinuousIndex(tuple(map(float, s.point))))
            k = tuple(int(v) for v in c[::-1])
            cand = ndimage.label((labels == BREAST) & (a <= t_bright))[0]
            if cand[k]:
                labels[cand == cand[k]] = GLAND

    # Sagittal midline: x centre of the thorax interior (or of the muscle).
    ref = thorax if thorax.any() else muscle
    ix = np.argwhere(ref).mean(axis=0)[::-1]
    midline = float(pre.TransformContinuousIndexToPhysicalPoint(tuple(ix))[0])

    out = sitk.GetImageFromArray(labels)
    out.CopyInformation(pre)
    if isotropic_mm is not None:
        out = sitk.Resample(out, work, sitk.Transform(), sitk.sitkNearestNeighbor, 0,
                            sitk.sitkUInt8)
    if box is not None:
        full = sitk.Image(img.GetSize(), sitk.sitkUInt8)
        full.CopyInformation(img)
        out = sitk.Paste(full, out, out.GetSize(), [0, 0, 0], box[0])
    conf = segmentation_confidence(
        cnr=r["cnr"], body=(r["body_start"], body), muscle=(r["muscle_start"], muscle),
        breast_ml=float(np.count_nonzero((labels == BREAST) | (labels == GLAND)))
        * vox_mm3 / 1000.0)
    notes += conf["warnings"]
    return SegmentationResult(out, pre, {k: float(v) for k, v in lv.items()}, midline,
                              np.asarray(markers_mm), tuple(notes), conf, kind)


def _fat_bright_regions(pre: sitk.Image, a: np.ndarray, sp: np.ndarray, notes: list, *,
                        seeds, skin_level, levelset_iterations, curvature,
                        marker_diameter_mm, min_region_mm3, muscle_min_mm, name,
                        levelset_shrink=1) -> dict:
    """Air, thorax interior, body and muscle of a fat-bright (T1/T2-weighted) volume
    (steps 2-5 of the module's method)."""
    vox_mm3 = float(np.prod(sp))
    # Initial levels (fractions of fat); refined below from the regions they produce.
    lv = {"air": 0.0, "thorax": 0.1, "muscle": 0.25, "fat": 1.0, "skin": skin_level}
    t_dark = 0.5 * (lv["thorax"] + lv["muscle"])
    t_bright = 0.5 * (lv["muscle"] + lv["fat"])
    by_edge = False
    for _ in range(2):
        dark = a < t_dark
        lab, n = _components(dark)
        sizes = np.bincount(lab.ravel(), minlength=n + 1)
        big = np.flatnonzero(sizes * vox_mm3 >= min_region_mm3)
        big = big[big > 0]
        air = np.zeros(a.shape, bool)
        thorax = np.zeros(a.shape, bool)
        # Air meets skin/fat, the thorax interior meets muscle: judge by the mean of a shell.
        # (on every second voxel: the shell 2-6 voxels out is what matters, not its detail)
        sub_lab, sub_a = lab[::2, ::2, ::2], a[::2, ::2, ::2]
        objs = ndimage.find_objects(sub_lab)
        edge_hit = np.zeros(n + 1, bool)
        for face in (lab[0], lab[-1], lab[:, 0], lab[:, -1], lab[:, :, 0], lab[:, :, -1]):
            edge_hit[np.unique(face)] = True
        rings: dict[int, float] = {}
        for k in big:
            if objs[k - 1] is None:
                continue
            sl = tuple(slice(max(s.start - 3, 0), s.stop + 3) for s in objs[k - 1])
            comp = sub_lab[sl] == k
            shell = ndimage.binary_dilation(comp, iterations=3) & ~ndimage.binary_dilation(comp)
            ring = float(np.mean(sub_a[sl][shell])) if shell.any() else 1.0
            target = air if ring > 0.5 * (lv["muscle"] + lv["skin"]) else thorax
            target |= lab == k
            rings[k] = ring
        if not air.any():
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
            by_edge = True
        lv["air"] = _interior_median(a, air, lv["air"])
        if thorax.any():
            lv["thorax"] = _interior_median(a, thorax, lv["thorax"])
        bright = (a > t_bright) & ~air
        lv["fat"] = _interior_median(a, bright, lv["fat"])
        mid = ~air & ~thorax & ~bright
        muscle0 = _muscle_start(mid, thorax, sp, muscle_min_mm)[0]
        if muscle0.any():
            lv["muscle"] = _interior_median(a, muscle0, lv["muscle"])
        if not thorax.any():  # muscle meets air: the dark side of the muscle is air
            lv["thorax"] = lv["air"]
        t_dark = 0.5 * (lv["thorax"] + lv["muscle"])
        t_bright = 0.5 * (lv["muscle"] + lv["fat"])
    if by_edge:
        notes.append("background taken from the field-of-view boundary (no dark region is "
                     "surrounded by skin: muscle meets air?)")
    # Noise voxels above the threshold inside the thorax interior are not tissue.
    thorax = ndimage.binary_fill_holes(thorax)
    t_air = 0.5 * (lv["air"] + skin_level * lv["fat"])
    lv.update(t_dark=t_dark, t_bright=t_bright, t_air=t_air)

    body = ~air
    if not body.any():
        raise SegmentationError(f"{STAGE}: {name}: empty body mask")
    _require_body(air, name)
    cnr = contrast_to_noise(a, air, lv)
    if cnr < MIN_CNR:
        raise SegmentationError(
            f"{STAGE}: {name}: no body found: the contrast between the brightest tissue and "
            f"the background is {cnr:.1f} times the background noise (at least {MIN_CNR:g} "
            "expected; is this volume noise only, or all tissue?)")
    body_start = body.copy()

    markers_mm, marker_mask = _markers(pre, a, body, sp, marker_diameter_mm)

    # Active contour on the air: settles the skin surface at the air/skin midpoint and, where
    # the muscle meets air, the muscle surface at the air/muscle midpoint (the feature is
    # scaled there so that one threshold serves both).
    feature = pre
    if muscle0.any() and t_dark < t_air:
        near = ndimage.binary_dilation(muscle0, structure=_ball(muscle_min_mm, sp))
        scale = np.where(near, np.float32(t_air / max(t_dark, 1e-3)), np.float32(1.0))
        feature = sitk.GetImageFromArray(a * scale)
        feature.CopyInformation(pre)
    air = levelset_refine(feature, air, lower=-np.inf, upper=t_air,
                          iterations=levelset_iterations, curvature=curvature,
                          shrink=levelset_shrink)
    air |= marker_mask
    # Keep the air that touches the original air (the level set may open small pockets).
    body = ~air
    blab, bn = _components(body)
    if bn == 0:
        raise SegmentationError(f"{STAGE}: {name}: empty body mask after removing air and markers")
    bsizes = np.bincount(blab.ravel())
    bsizes[0] = 0
    body = blab == int(bsizes.argmax())
    thorax &= body

    # Chest-wall band: mid-intensity layer touching the thorax interior.
    # Thin mid-intensity shells (skin, partial volume at the skin) are cut off first: where
    # the muscle meets air, the skin of the breasts meets the muscle at their base.
    mid = body & ~thorax & (a <= t_bright)
    mlab, mn = _components(mid)
    muscle, largest = _muscle_start(mid, thorax, sp, muscle_min_mm)
    if largest:
        notes.append("no thorax interior found; muscle = largest thick mid-intensity region")

    # Seeds: reassign the connected region (of its intensity class) that holds each seed.
    muscle, thorax = _apply_seeds(
        seeds, pre, mlab, thorax, muscle, notes, name,
        lambda m: body & ~thorax & ~m & (a > t_bright))

    if not muscle.any():
        raise SegmentationError(f"{STAGE}: {name}: no muscle / chest wall found")
    muscle_start = muscle.copy()
    # Active contour on the muscle: boundaries settle at the thorax and fat midpoints.
    muscle = levelset_refine(pre, muscle, lower=t_dark, upper=t_bright,
                             iterations=levelset_iterations, curvature=curvature,
                          shrink=levelset_shrink)
    muscle &= body & ~marker_mask
    if not muscle.any():
        raise SegmentationError(f"{STAGE}: {name}: no muscle / chest wall left after its "
                                "active contour")
    # Partial-volume voxels where the muscle meets air are darker than any skin: muscle.
    rim = body & ~thorax & ~muscle & ~marker_mask & (a < t_air)
    muscle |= rim & ndimage.binary_dilation(muscle)
    thorax &= ~muscle
    return {"lv": lv, "air": air, "thorax": thorax, "body": body, "body_start": body_start,
            "muscle": muscle, "muscle_start": muscle_start, "marker_mask": marker_mask,
            "markers_mm": markers_mm, "cnr": cnr, "t_bright": t_bright}


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
       background and the darkest tissue (the 10th percentile of what rises five noise
       sigmas above the background), refined by a threshold level set; then the body's
       outer voxels darker than half their brightest body neighbour (partial volume of the
       skin, or of a muscle meeting air) go to the air;
    2. the body's interior is split at each of the two thresholds of a three-class Otsu of
       its histogram; dark regions that stay more than 4 mm (plus three voxels) from the
       air are the thorax interior; the first threshold that leaves one is the muscle's
       lower edge (on T2-like scans muscle is the middle class, on T1-like ones the thorax
       interior is);
    3. the muscle starts from the thick (``muscle_min_mm``) bright parts touching the
       thorax interior (else the largest thick bright part: a muscle meeting air) and its
       threshold level set settles at the midpoint of the muscle and its dark neighbours,
       kept within ``muscle_min_mm`` of its start (gland and skin are as bright).
    """
    from skimage.filters import threshold_multiotsu

    vox_mm3 = float(np.prod(sp))
    peak, sigma = air_noise(a)
    rough = a > peak + 5.0 * sigma
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
    lv = {"air": _interior_median(a, air, peak)}
    body = ~air
    _require_body(air, name)
    # distance of every voxel to the air, on every second voxel (mm)
    sub_body = body[::2, ::2, ::2]
    depth = ndimage.distance_transform_edt(sub_body, sampling=2.0 * sp)
    inner = sub_body & (depth > 2.0 * float(sp.max()) + 1.0)
    ivals = a[::2, ::2, ::2][inner]
    if ivals.size < 100:
        raise SegmentationError(f"{STAGE}: {name}: the body is too thin to segment "
                                "(fat-suppressed contrast)")
    thresholds = [float(t) for t in threshold_multiotsu(ivals, classes=3)]
    # skin and partial volume, plus the erosion and the distance grid's steps
    near_mm = 4.0 + 3.0 * float(sp.max())
    thorax = np.zeros(a.shape, bool)
    t_mid = thresholds[0]
    for t in thresholds:
        # one erosion cuts the one-voxel bridges that noise and partial volume open through
        # the muscle; the dark regions grow back by one voxel once classified
        dlab, dn = _components(ndimage.binary_erosion(body & (a < t)))
        if dn == 0:
            continue
        dsizes = np.bincount(dlab.ravel(), minlength=dn + 1)
        sub_lab = dlab[::2, ::2, ::2]
        idx = np.arange(1, dn + 1)
        closest = np.asarray(ndimage.minimum(depth, sub_lab, idx), float)
        deep = np.zeros(dn + 1, bool)
        deep[1:] = (closest > near_mm) & (dsizes[1:] * vox_mm3 >= min_region_mm3)
        if deep.any():
            thorax = ndimage.binary_dilation(deep[dlab]) & body & (a < t)
            t_mid = t
            break
    bright = body & ~thorax & (a >= t_mid)
    muscle, largest = _muscle_start(bright, thorax, sp, muscle_min_mm)
    if largest:
        notes.append("no thorax interior found; muscle = largest thick bright region "
                     "(fat-suppressed contrast)")
    mlab = _components(bright)[0]
    muscle, thorax = _apply_seeds(seeds, pre, mlab, thorax, muscle, notes, name,
                                  lambda m: body & ~thorax & ~m & (a < t_mid))
    if not muscle.any():
        raise SegmentationError(f"{STAGE}: {name}: no muscle / chest wall found "
                                "(fat-suppressed contrast: no thick layer brighter than fat)")
    lv["muscle"] = _interior_median(a, muscle, 1.0)
    fat = body & ~thorax & (a < t_mid) & ~ndimage.binary_dilation(muscle, iterations=2)
    lv["fat"] = _interior_median(a, fat, low) if fat.any() else low
    lv["thorax"] = _interior_median(a, thorax, lv["fat"]) if thorax.any() else lv["fat"]
    # the muscle's lower edge: midpoint of the muscle and its dark neighbours
    t_low = 0.5 * lv["muscle"] + 0.25 * (lv["fat"] + lv["thorax"])
    lv.update(t_air=t_air, t_dark=t_low, t_mid=t_mid, otsu_low=thresholds[0],
              otsu_high=thresholds[1])
    body_start = body.copy()
    air = levelset_refine(pre, air, lower=-np.inf, upper=t_air,
                          iterations=levelset_iterations, curvature=curvature,
                          shrink=levelset_shrink)
    air |= _surface_partial_volume(a, ~air, lv["air"])
    blab, bn = _components(~air)
    if bn == 0:
        raise SegmentationError(f"{STAGE}: {name}: empty body mask after removing air")
    bsizes = np.bincount(blab.ravel())
    bsizes[0] = 0
    body = blab == int(bsizes.argmax())
    markers_mm, marker_mask = _markers(pre, a, body, sp, marker_diameter_mm)
    body &= ~marker_mask
    thorax = ndimage.binary_fill_holes(thorax) & body
    muscle_start = muscle.copy()
    reach = ndimage.binary_dilation(muscle, structure=_ball(muscle_min_mm, sp))
    muscle = levelset_refine(pre, muscle, lower=t_low, upper=np.inf,
                             iterations=levelset_iterations, curvature=curvature,
                          shrink=levelset_shrink)
    muscle &= body & reach & ~marker_mask
    if not muscle.any():
        raise SegmentationError(f"{STAGE}: {name}: no muscle / chest wall left after its "
                                "active contour (fat-suppressed contrast)")
    thorax &= ~muscle
    cnr = contrast_to_noise(a, air, {"air": lv["air"], "fat": max(lv["muscle"], 1.0)})
    if cnr < MIN_CNR:
        raise SegmentationError(
            f"{STAGE}: {name}: no body found: the contrast between the brightest tissue and "
            f"the background is {cnr:.1f} times the background noise (at least {MIN_CNR:g} "
            "expected; is this volume noise only, or all tissue?)")
    return {"lv": lv, "air": air, "thorax": thorax, "body": body, "body_start": body_start,
            "muscle": muscle, "muscle_start": muscle_start, "marker_mask": marker_mask,
            "markers_mm": markers_mm, "cnr": cnr, "t_bright": t_mid}


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


def coherent_blocks(air: np.ndarray, *, block: int = 4, share: float = 0.9) -> tuple[int, int]:
    """Number of ``block``^3-voxel blocks that are background (``air``) for at least
    ``share`` of their voxels, and of those that are tissue for as much. A scan has whole
    regions of each; in pure noise the classes interleave voxel by voxel and neither has
    any."""
    n = [s // block * block for s in air.shape]
    if min(n) == 0:
        return 0, 0
    sub = air[: n[0], : n[1], : n[2]].reshape(n[0] // block, block, n[1] // block, block,
                                             n[2] // block, block)
    frac = sub.mean(axis=(1, 3, 5))
    return int(np.count_nonzero(frac >= share)), int(np.count_nonzero(frac <= 1 - share))


def contrast_to_noise(a: np.ndarray, air: np.ndarray, levels: dict) -> float:
    """(fat - air) level over the background noise (1.4826 x the median absolute deviation
    inside the air, two voxels in from its edge), on every second voxel."""
    sub = ndimage.binary_erosion(air[::2, ::2, ::2], iterations=2)
    v = a[::2, ::2, ::2][sub] if np.count_nonzero(sub) > 50 else a[air]
    if v.size == 0:
        return 0.0
    sigma = 1.4826 * float(np.median(np.abs(v - np.median(v))))
    gap = float(levels["fat"] - levels["air"])
    return float(min(gap / max(sigma, 1e-6 * max(abs(gap), 1e-12)), 1e6))


def _dice(x: np.ndarray, y: np.ndarray) -> float:
    n = int(np.count_nonzero(x)) + int(np.count_nonzero(y))
    return 1.0 if n == 0 else 2.0 * int(np.count_nonzero(x & y)) / n


def segmentation_confidence(
    *,
    cnr: float,
    body: tuple[np.ndarray, np.ndarray],
    muscle: tuple[np.ndarray, np.ndarray],
    breast_ml: float,
    min_agreement: float = 0.9,
) -> dict:
    """How far to trust a segmentation, from what it knows itself.

    Parameters
    ----------
    cnr : float
        Contrast-to-noise ratio of tissue against background (:func:`contrast_to_noise`).
    body, muscle : (start, final) pairs of bool arrays
        Each region's threshold initialisation and its active-contour result: two
        segmentations of one region from two methods; their Dice is the agreement.
    breast_ml : float
        Breast tissue volume (labels 1 and 3), ml.
    min_agreement : float
        Dice below which a region's agreement is a warning.

    Returns
    -------
    dict
        ``cnr``, ``agreement`` (Dice per region), ``breast_ml``, ``breast_ml_plausible``
        (within ``BREAST_ML_RANGE``), ``warnings`` and ``confident`` (no warning).
    """
    agree = {"body": _dice(*body), "muscle": _dice(*muscle)}
    lo, hi = BREAST_ML_RANGE
    plausible = lo <= breast_ml <= hi
    warnings = [f"low confidence: the {k}'s active contour and its threshold start agree "
                f"only to Dice {v:.3f} (< {min_agreement})"
                for k, v in agree.items() if v < min_agreement]
    if not plausible:
        warnings.append(f"low confidence: {breast_ml:.1f} ml of breast tissue is outside the "
                        f"plausible {lo:g}-{hi:g} ml")
    return {"cnr": float(cnr), "agreement": agree, "breast_ml": float(breast_ml),
            "breast_ml_plausible": bool(plausible), "warnings": warnings,
            "confident": not warnings}


def breast_volumes_by_side(labels: sitk.Image, midline_x_mm: float) -> dict[str, float]:
    """Breast tissue (labels 1 and 3) volume left and right of the sagittal midline, ml."""
    a = sitk.GetArrayViewFromImage(labels)
    idx = np.argwhere((a == BREAST) | (a == GLAND))
    if len(idx) == 0:
        return {"breast_left": 0.0, "breast_right": 0.0}
    d = np.asarray(labels.GetDirection()).reshape(3, 3)
    x = labels.GetOrigin()[0] + (idx[:, ::-1] * np.asarray(labels.GetSpacing())) @ d[0]
    vox = float(np.prod(labels.GetSpacing())) / 1000.0
    return {"breast_left": float(np.count_nonzero(x > midline_x_mm) * vox),
            "breast_right": float(np.count_nonzero(x <= midline_x_mm) * vox)}
