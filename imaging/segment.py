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
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from imaging.fiducials import body_without_markers, detect_markers
from imaging.preprocess import check_volume, preprocess

STAGE = "segment"
log = logging.getLogger(__name__)

BACKGROUND, BREAST, MUSCLE, GLAND = 0, 1, 2, 3


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
        What the user should know (seeds applied, fallbacks).
    """

    labels: sitk.Image
    preprocessed: sitk.Image
    levels: dict = field(default_factory=dict)
    midline_x_mm: float = 0.0
    markers_mm: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    notes: tuple = ()


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


def levelset_refine(
    feature: sitk.Image,
    mask: np.ndarray,
    *,
    lower: float,
    upper: float,
    iterations: int,
    curvature: float = 0.5,
    margin_vox: int = 4,
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
    init = sitk.Cast(sub_mask, sitk.sitkFloat32) - 0.5
    ls = sitk.ThresholdSegmentationLevelSetImageFilter()
    ls.SetLowerThreshold(float(lower))
    ls.SetUpperThreshold(float(upper))
    ls.SetMaximumRMSError(0.01)
    ls.SetNumberOfIterations(int(iterations))
    ls.SetCurvatureScaling(float(curvature))
    ls.SetPropagationScaling(1.0)
    ls.ReverseExpansionDirectionOn()
    out = ls.Execute(init, sub_feat)
    res = mask.copy()
    res[sl] = sitk.GetArrayViewFromImage(out) > 0
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
    curvature: float = 0.5,
    marker_diameter_mm: float = 4.0,
    min_region_mm3: float = 500.0,
    name: str = "volume",
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
    curvature : float
        Curvature weight of the level sets.
    marker_diameter_mm : float
        Skin-marker diameter (markers are removed from the body).
    min_region_mm3 : float
        Dark regions smaller than this are noise inside tissue, not air or thorax.
    name : str
        Name for messages (the file path).

    Returns
    -------
    SegmentationResult
    """
    check_volume(img, name=name, stage=STAGE)
    pre = preprocess(img, n4=n4, n4_shrink=n4_shrink, isotropic_mm=isotropic_mm,
                     denoise_iterations=denoise_iterations, denoise_method=denoise_method,
                     name=name)
    a = sitk.GetArrayFromImage(pre)
    sp = np.asarray(pre.GetSpacing(), float)[::-1]  # (z, y, x)
    vox_mm3 = float(np.prod(sp))
    notes: list[str] = []

    # Initial levels (fractions of fat); refined below from the regions they produce.
    lv = {"air": 0.0, "thorax": 0.1, "muscle": 0.25, "fat": 1.0, "skin": skin_level}
    t_dark = 0.5 * (lv["thorax"] + lv["muscle"])
    t_bright = 0.5 * (lv["muscle"] + lv["fat"])
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
        for k in big:
            if objs[k - 1] is None:
                continue
            sl = tuple(slice(max(s.start - 3, 0), s.stop + 3) for s in objs[k - 1])
            comp = sub_lab[sl] == k
            shell = ndimage.binary_dilation(comp, iterations=3) & ~ndimage.binary_dilation(comp)
            ring = float(np.mean(sub_a[sl][shell])) if shell.any() else 1.0
            target = air if ring > 0.5 * (lv["muscle"] + lv["skin"]) else thorax
            target |= lab == k
        if not air.any():
            raise ValueError(f"{STAGE}: {name}: no air found around the body (is this a "
                             "body MRI with background?)")
        lv["air"] = _interior_median(a, air, lv["air"])
        if thorax.any():
            lv["thorax"] = _interior_median(a, thorax, lv["thorax"])
        bright = (a > t_bright) & ~air
        lv["fat"] = _interior_median(a, bright, lv["fat"])
        mid = ~air & ~thorax & ~bright
        if thorax.any():
            mlab, mn = _components(mid)
            touch = _touching(mlab, mn, thorax)
            muscle0 = touch[mlab]
            lv["muscle"] = _interior_median(a, muscle0, lv["muscle"])
        t_dark = 0.5 * (lv["thorax"] + lv["muscle"])
        t_bright = 0.5 * (lv["muscle"] + lv["fat"])
    # Noise voxels above the threshold inside the thorax interior are not tissue.
    thorax = ndimage.binary_fill_holes(thorax)
    t_air = 0.5 * (lv["air"] + skin_level * lv["fat"])
    lv.update(t_dark=t_dark, t_bright=t_bright, t_air=t_air)

    body = ~air
    if not body.any():
        raise ValueError(f"{STAGE}: {name}: empty body mask")

    # Skin markers: bright blobs outside the (opened) body; remove a ball around each.
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

    # Active contour on the air: settles the skin surface at the air/skin midpoint.
    air = levelset_refine(pre, air, lower=-np.inf, upper=t_air,
                          iterations=levelset_iterations, curvature=curvature)
    air |= marker_mask
    # Keep the air that touches the original air (the level set may open small pockets).
    body = ~air
    blab, bn = _components(body)
    if bn == 0:
        raise ValueError(f"{STAGE}: {name}: empty body mask after removing air and markers")
    bsizes = np.bincount(blab.ravel())
    bsizes[0] = 0
    body = blab == int(bsizes.argmax())
    thorax &= body

    # Chest-wall band: mid-intensity layer touching the thorax interior.
    mid = body & ~thorax & (a <= t_bright)
    mlab, mn = _components(mid)
    if thorax.any():
        muscle = _touching(mlab, mn, thorax)[mlab]
    else:
        notes.append("no thorax interior found; muscle = largest mid-intensity region")
        msizes = np.bincount(mlab.ravel())
        msizes[0] = 0
        muscle = mlab == int(msizes.argmax()) if mn else np.zeros(a.shape, bool)

    # Seeds: reassign the connected region (of its intensity class) that holds each seed.
    for s in seeds:
        if s.label not in (BACKGROUND, BREAST, MUSCLE, GLAND):
            raise ValueError(f"{STAGE}: seed label must be 0, 1, 2 or 3, got {s.label}")
        c = np.round(pre.TransformPhysicalPointToContinuousIndex(tuple(map(float, s.point))))
        k = tuple(int(v) for v in c[::-1])
        if any(i < 0 or i >= n for i, n in zip(k, a.shape)):
            raise ValueError(f"{STAGE}: seed {s.point} mm lies outside {name}")
        if mlab[k] > 0:
            region = mlab == mlab[k]
        elif thorax[k]:
            region = thorax.copy()
        else:
            region = ndimage.label(body & ~thorax & ~muscle & (a > t_bright))[0]
            region = region == region[k] if region[k] > 0 else np.zeros(a.shape, bool)
        if not region.any():
            notes.append(f"seed {s.point} (label {s.label}) is in air: ignored")
            continue
        muscle &= ~region
        thorax &= ~region
        if s.label == MUSCLE:
            muscle |= region
        elif s.label == BACKGROUND:
            thorax |= region  # treated as non-tissue inside the body
        notes.append(f"seed {s.point} -> label {s.label} ({int(region.sum())} voxels)")

    if not muscle.any():
        raise ValueError(f"{STAGE}: {name}: no muscle / chest wall found")
    # Active contour on the muscle: boundaries settle at the thorax and fat midpoints.
    muscle = levelset_refine(pre, muscle, lower=t_dark, upper=t_bright,
                             iterations=levelset_iterations, curvature=curvature)
    muscle &= body & ~marker_mask
    thorax &= ~muscle

    labels = np.zeros(a.shape, np.uint8)
    labels[body & ~thorax & ~muscle & ~marker_mask] = BREAST
    labels[muscle] = MUSCLE
    if gland:
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
        out = sitk.Resample(out, img, sitk.Transform(), sitk.sitkNearestNeighbor, 0,
                            sitk.sitkUInt8)
    return SegmentationResult(out, pre, {k: float(v) for k, v in lv.items()}, midline,
                              np.asarray(markers_mm), tuple(notes))


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
