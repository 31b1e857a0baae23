"""Segmentation of one MRI volume into the label convention 0 background, 1 breast tissue,
2 muscle / chest wall, 3 glandular tissue (optional).

Method
------
1. Preprocess (N4, optional isotropic resampling, edge-preserving denoising, twice as long
   on a noisy scan, background -> 0, fat mode -> 1), so tissue levels are fractions of fat.
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
(fat dark, muscle/gland/skin mid-grey to bright) :mod:`imaging.segment_fat_suppressed` finds the
same regions from the geometry instead (the muscle is the thick layer brighter than both its
neighbours; the thorax interior is the dark region it keeps away from the air). The contrast
is given (``contrast=``) or detected from the profile under the body surface
(:func:`detect_contrast`); when the detected one fails, the other is tried, and if both fail
the error names the file and both reasons.

This module holds :func:`segment_volume` (preprocessing, the choice of contrast, the label
map) and re-exports the names of its parts: :mod:`imaging.segment_contrast` (background
noise, contrast detection, body checks), :mod:`imaging.segment_regions` (seeds, the error,
shared region steps), :mod:`imaging.levelset` (active contours),
:mod:`imaging.segment_fat_bright` and :mod:`imaging.segment_fat_suppressed` (the regions of
each contrast) and :mod:`imaging.segment_confidence`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from imaging.labels import BREAST, GLAND, MUSCLE
from imaging.levelset import MAX_COARSE_MM, levelset_refine
from imaging.segment_confidence import (
    BREAST_ML_RANGE,
    _dice,
    breast_behind_wall_mm,
    breast_volumes_by_side,
    segmentation_confidence,
)
from imaging.segment_contrast import (
    CONTRASTS,
    MIN_BLOCKS,
    MIN_CNR,
    _posterior_axis,
    air_noise,
    coherent_blocks,
    contrast_to_noise,
    detect_contrast,
    prepare_volume,
)
from imaging.segment_fat_bright import _fat_bright_regions
from imaging.segment_fat_suppressed import _fat_suppressed_regions
from imaging.segment_regions import (
    STAGE,
    Seed,
    SegmentationError,
    _components,
    _interior_median,
)
from imaging.segment_wall import glands_off_muscle, skin_rim_off

#: Gland and fat levels closer than this fraction of the fat level are one class (no gland).
GLAND_MIN_CONTRAST = 0.2

__all__ = [
    "BREAST_ML_RANGE", "CONTRASTS", "MAX_COARSE_MM", "MIN_BLOCKS", "MIN_CNR", "STAGE",
    "Seed", "SegmentationError", "SegmentationResult", "air_noise", "breast_volumes_by_side",
    "coherent_blocks", "contrast_to_noise", "detect_contrast", "levelset_refine",
    "segment_volume", "segmentation_confidence",
]


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


def segment_volume(
    img: sitk.Image, *, seeds: Sequence[Seed] = (), gland: bool = False, n4: bool = True,
    n4_shrink: int = 4, isotropic_mm: float | None = None, denoise_iterations: int | str = "auto",
    denoise_method: str = "gradient", skin_level: float = 0.7, levelset_iterations: int = 30,
    levelset_shrink: int = 1, curvature: float = 0.5, marker_diameter_mm: float = 4.0,
    min_region_mm3: float = 500.0, muscle_min_mm: float = 3.0, name: str = "volume",
    contrast: str = "auto", crop: bool = True, n4_cache: str | Path | None = None,
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
        Preprocessing (:func:`imaging.segment_contrast.prepare_volume`: ``"auto"``
        denoising doubles on a noisy scan, and says so).
    skin_level : float
        Skin intensity as a fraction of fat; the air boundary sits at half of it.
    levelset_iterations : int
        Active-contour iterations per region (0: thresholds and morphology only).
    levelset_shrink : int
        Active contours on a grid this many times coarser (:func:`levelset_refine`).
    curvature : float
        Curvature weight of the level sets.
    marker_diameter_mm : float
        Skin-marker diameter (markers are removed from the body).
    min_region_mm3 : float
        Dark regions and pieces of breast smaller than this are noise (in tissue, thorax).
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
        Folder of bias corrections shared with later stages (:func:`imaging.preprocess.n4_correct`).

    Returns
    -------
    SegmentationResult
    """
    if contrast != "auto" and contrast not in CONTRASTS:
        raise SegmentationError(f"{STAGE}: {name}: contrast must be 'auto' or one of "
                                f"{CONTRASTS}, got {contrast!r}")
    notes: list[str] = []
    pre, work, box, noise = prepare_volume(
        img, notes, crop=crop, n4=n4, n4_shrink=n4_shrink, n4_cache=n4_cache,
        isotropic_mm=isotropic_mm, denoise_iterations=denoise_iterations,
        denoise_method=denoise_method, name=name)
    a = sitk.GetArrayFromImage(pre)
    sp = np.asarray(pre.GetSpacing(), float)[::-1]  # (z, y, x)
    vox_mm3 = float(np.prod(sp))
    order = _contrast_order(a, sp, contrast, notes, direction=pre.GetDirection())
    opts = dict(seeds=seeds, levelset_iterations=levelset_iterations, curvature=curvature,
                marker_diameter_mm=marker_diameter_mm, min_region_mm3=min_region_mm3,
                muscle_min_mm=muscle_min_mm, name=name, levelset_shrink=levelset_shrink)
    kind, r, notes = _regions(pre, a, sp, order, notes, skin_level=skin_level, opts=opts)
    posterior = _posterior_axis(pre.GetDirection())
    _glands_off(r, a, sp, kind, notes, seeds=seeds, min_region_mm3=min_region_mm3,
                posterior=posterior)
    labels = _label_map(a, pre, r, kind, notes, seeds=seeds, gland=gland, vox_mm3=vox_mm3,
                        min_region_mm3=min_region_mm3)
    out = _on_input_grid(labels, pre, work, img, box, isotropic_mm)
    conf = _confidence(r, labels, sp, posterior, noise)
    notes += conf["warnings"]
    return SegmentationResult(out, pre, {k: float(v) for k, v in r["lv"].items()},
                              _midline_x(pre, r["thorax"], r["muscle"]),
                              np.asarray(r["markers_mm"]), tuple(notes), conf, kind)


def _confidence(r: dict, labels: np.ndarray, sp: np.ndarray, posterior, noise) -> dict:
    """:func:`segmentation_confidence` of the regions ``r`` and their label map."""
    breast_ml = np.count_nonzero((labels == BREAST) | (labels == GLAND)) * np.prod(sp) / 1e3
    return segmentation_confidence(
        cnr=r["cnr"], body=(r["body_start"], r["body"]), muscle=(r["muscle_start"], r["muscle"]),
        breast_ml=float(breast_ml), noise=noise,
        breast_behind_wall_mm=breast_behind_wall_mm(labels, sp, posterior))


def _label_map(a, pre, r, kind, notes, *, seeds, gland, vox_mm3, min_region_mm3) -> np.ndarray:
    """(nz, ny, nx) uint8 labels from the regions ``r``: breast is the body less the thorax
    interior, the muscle and the markers, save specks (a note says how much); gland when
    asked for (its level and threshold go into ``r["lv"]``), and always where a gland seed
    lies."""
    labels = np.zeros(a.shape, np.uint8)
    labels[r["body"] & ~r["thorax"] & ~r["muscle"] & ~r["marker_mask"]] = BREAST
    labels[r["muscle"]] = MUSCLE
    specks_ml = _breast_specks_off(labels, min_region_mm3 / vox_mm3) * vox_mm3 / 1e3
    if specks_ml > 0:
        notes.append(f"{specks_ml:.2g} ml of breast in pieces under {min_region_mm3:g} mm^3 "
                     "given to their surroundings (noise)")
    if gland:
        _label_gland(labels, a, r["lv"], r["air"], kind, vox_mm3=vox_mm3,
                     min_region_mm3=min_region_mm3)
    _gland_seeds(labels, a, pre, seeds, r["t_bright"])
    return labels


def _breast_specks_off(labels: np.ndarray, min_voxels: float) -> int:
    """Pieces of breast smaller than ``min_voxels`` apart from the largest take the label
    most of their neighbours have (in place): voxels of a noisy thorax interior above its
    threshold (on the suite's 2 mm, SNR 13 coil scan small-002, 142 pieces of 1-11 voxels,
    620 voxels in all, all thorax or muscle in the truth). Returns the voxels relabelled."""
    lab, n = _components(labels == BREAST)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    sizes[0] = 0
    moved = 0
    for k, box in enumerate(ndimage.find_objects(lab), start=1):
        if box is None or sizes[k] >= min_voxels or k == int(sizes.argmax()):
            continue
        box = tuple(slice(max(b.start - 1, 0), b.stop + 1) for b in box)
        piece = lab[box] == k
        around = labels[box][ndimage.binary_dilation(piece) & ~piece]
        counts = np.bincount(around[around != BREAST], minlength=4)
        labels[box][piece] = int(counts.argmax())
        moved += int(sizes[k])
    return moved


def _contrast_order(a: np.ndarray, sp: np.ndarray, contrast: str, notes: list, *,
                    direction=None) -> list[str]:
    """The contrasts to try, in order: the declared one, or the detected one then the other
    (a note says what was detected and why)."""
    if contrast != "auto":
        return [contrast]
    kind, why = detect_contrast(a, sp, direction=direction)
    notes.append(f"contrast detected: {kind} (" + ", ".join(
        f"{k} {v:.3g}" if isinstance(v, float) else f"{k}: {v}" for k, v in why.items())
        + ")")
    return [kind, next(k for k in CONTRASTS if k != kind)]


def _regions(pre, a, sp, order, notes, *, skin_level, opts) -> tuple[str, dict, list]:
    """Air, thorax, body and muscle by the first contrast in ``order`` that works; a second
    guess must also hold up on its own (its muscle's active contour agrees with its start).
    Returns (contrast, regions, notes); raises naming every contrast's reason."""
    name = opts["name"]
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
        return kind, r, tried + [f"segmented as {kind} after: {f}" for f in failed]
    if len(failed) == 1:
        raise SegmentationError(failed[0][failed[0].index(": ") + 2:])
    raise SegmentationError(f"{STAGE}: {name}: cannot segment with either contrast: "
                            + "; ".join(failed))


def _glands_off(r: dict, a: np.ndarray, sp: np.ndarray, kind: str, notes: list, *,
                seeds, min_region_mm3: float, posterior: tuple[int, bool]) -> None:
    """Glands the muscle's region took in go back to the breast
    (:func:`imaging.segment_wall.glands_off_muscle`), in place; with fat suppressed their
    level is the gland's. Then the breast's skin at its rim
    (:func:`imaging.segment_wall.skin_rim_off`). A user's muscle seed has the last word:
    then nothing is taken."""
    if any(s.label == MUSCLE for s in seeds):
        return
    muscle, blobs = glands_off_muscle(r["muscle"], r["body"], r["thorax"], sp,
                                      min_mm3=min_region_mm3, posterior=posterior)
    if blobs.any():
        _blobs_off(r, a, sp, kind, notes, muscle, blobs)
    skin_rim_off(r, sp, notes, posterior=posterior)


def _blobs_off(r, a, sp, kind, notes, muscle, blobs) -> None:
    """Record the glands taken off the muscle in the regions ``r`` and the notes."""
    r["muscle"], r["muscle_start"] = muscle, r["muscle_start"] & ~blobs
    if kind == "fat_suppressed":
        r["lv"]["gland"] = float(np.median(a[blobs]))
    notes.append(f"{float(np.count_nonzero(blobs) * np.prod(sp)) / 1000.0:.1f} ml on the "
                 "chest wall's front taken off the muscle as gland (blobs thicker than the "
                 "wall, among breast tissue)")


def _label_gland(labels, a, lv, air, kind, *, vox_mm3, min_region_mm3) -> None:
    """Label glandular tissue (3) in place: breast voxels on the gland's side of the
    gland/fat midpoint (brighter than the dark fat when fat is suppressed, darker than fat
    otherwise), in pieces of at least a tenth of ``min_region_mm3``; records the gland's
    level and threshold in ``lv``.

    Both levels come from the breast's interior (two voxels from the air and the muscle:
    their partial volume lies between the classes), split in two by Otsu's threshold, when
    the two classes differ by :data:`GLAND_MIN_CONTRAST` of the fat level; otherwise from
    the gland's level found earlier (or a default) and the fat's. Next to the muscle its
    partial volume with fat passes for gland: with fat bright (dark muscle) no voxel touching
    the muscle is gland; with fat suppressed, only those nearer the gland's level than the
    threshold (a gland may lie on the wall)."""
    from skimage.filters import threshold_otsu

    breast = labels == BREAST
    muscle = labels == MUSCLE
    inner = breast & ~ndimage.binary_dilation(air | muscle, iterations=2)
    vals = a[::2, ::2, ::2][inner[::2, ::2, ::2]]
    fs = kind == "fat_suppressed"
    split = None
    if vals.size >= 200:
        t = float(threshold_otsu(vals))
        lo, hi = float(np.median(vals[vals <= t])), float(np.median(vals[vals > t]))
        if hi - lo >= GLAND_MIN_CONTRAST * abs(lv["fat"]):
            split = (hi, lo) if fs else (lo, hi)  # (gland, fat)
    if split is not None:
        lv["gland"] = split[0]
        t_gland = 0.5 * (split[0] + split[1])
    elif fs:  # gland brighter than the (dark) fat
        t_gland = 0.5 * (lv.setdefault("gland", lv["muscle"]) + lv["fat"])
    else:
        t_gland = 0.5 * (lv.setdefault("gland", 0.6) + lv["fat"])
    if fs:  # a gland may lie on the wall: next to it, only what is nearer the gland's level
        rim = ndimage.binary_dilation(muscle) & (a < 0.5 * (lv["gland"] + t_gland))
        cand = breast & (a > t_gland) & ~rim
    else:  # the rim of the dark muscle with fat is as dark as gland: not gland
        cand = breast & (a < t_gland) & ~ndimage.binary_dilation(muscle)
    glab, gn = _components(cand & ~ndimage.binary_dilation(air, iterations=2))
    if gn:
        gs = np.bincount(glab.ravel())
        gs[0] = 0
        keep = gs * vox_mm3 >= 0.1 * min_region_mm3
        g = keep[glab]
        lv["gland"] = _interior_median(a, g, lv["gland"])
        labels[g] = GLAND
    lv["t_gland"] = t_gland


def _gland_seeds(labels, a, pre, seeds, t_bright) -> None:
    """A gland seed's own voxel always carries its label: the breast region below
    ``t_bright`` holding it becomes gland (in place)."""
    for s in seeds:
        if s.label == GLAND:
            c = np.round(pre.TransformPhysicalPointToContinuousIndex(tuple(map(float, s.point))))
            k = tuple(int(v) for v in c[::-1])
            cand = ndimage.label((labels == BREAST) & (a <= t_bright))[0]
            if cand[k]:
                labels[cand == cand[k]] = GLAND


def _midline_x(pre: sitk.Image, thorax: np.ndarray, muscle: np.ndarray) -> float:
    """Sagittal midline: x (mm) of the centre of the thorax interior (or of the muscle)."""
    ref = thorax if thorax.any() else muscle
    ix = np.argwhere(ref).mean(axis=0)[::-1]
    return float(pre.TransformContinuousIndexToPhysicalPoint(tuple(ix))[0])


def _on_input_grid(labels, pre, work, img, box, isotropic_mm) -> sitk.Image:
    """The label array as a uint8 image on the input's grid: resampled back from the
    isotropic grid, pasted into the whole volume from the body's box."""
    out = sitk.GetImageFromArray(labels)
    out.CopyInformation(pre)
    if isotropic_mm is not None:
        out = sitk.Resample(out, work, sitk.Transform(), sitk.sitkNearestNeighbor, 0,
                            sitk.sitkUInt8)
    if box is not None:
        full = sitk.Image(img.GetSize(), sitk.sitkUInt8)
        full.CopyInformation(img)
        out = sitk.Paste(full, out, out.GetSize(), [0, 0, 0], box[0])
    return out
