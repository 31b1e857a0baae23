"""Is there a body, and in which contrast: the background's level and noise, fat bright
or fat suppressed (:func:`detect_contrast`), coherent blocks of background and tissue, and
the contrast-to-noise ratio, with the checks that refuse a volume without a body."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from imaging.segment_regions import STAGE, SegmentationError

#: Smallest accepted contrast-to-noise ratio between body (fat) and background.
MIN_CNR = 5.0
#: Fewest 4^3-voxel blocks of pure (>= 90 %) background, and of pure tissue, in a body MRI.
MIN_BLOCKS = 8

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


def _require_body(air: np.ndarray, name: str) -> None:
    """Stop unless the volume holds blocks of pure background and of pure tissue."""
    blocks = coherent_blocks(air)
    if min(blocks) < MIN_BLOCKS:
        raise SegmentationError(
            f"{STAGE}: {name}: no body found: {blocks[0]} block(s) of 4^3 voxels are "
            f"background and {blocks[1]} are tissue, at 90 % or more (at least {MIN_BLOCKS} "
            "of each expected; is this volume noise only?)")



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



def _require_cnr(cnr: float, name: str) -> None:
    """Stop unless the brightest tissue stands :data:`MIN_CNR` noise sigmas above the
    background."""
    if cnr < MIN_CNR:
        raise SegmentationError(
            f"{STAGE}: {name}: no body found: the contrast between the brightest tissue and "
            f"the background is {cnr:.1f} times the background noise (at least {MIN_CNR:g} "
            "expected; is this volume noise only, or all tissue?)")
