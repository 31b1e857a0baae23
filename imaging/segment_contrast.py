"""Is there a body, and in which contrast: the background's level and noise, fat bright
or fat suppressed (:func:`detect_contrast`), coherent blocks of background and tissue, and
the contrast-to-noise ratio, with the checks that refuse a volume without a body; and
whether the scans of one subject read alike (:func:`contrast_disagreement`)."""

from __future__ import annotations

import warnings
from collections.abc import Mapping

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from imaging.preprocess import (
    background_of,
    body_box,
    check_volume,
    denoise,
    n4_correct,
    normalise,
    preprocess,
)
from imaging.segment_regions import STAGE, SegmentationError

#: Smallest accepted contrast-to-noise ratio between body (fat) and background.
MIN_CNR = 5.0
#: Fewest 4^3-voxel blocks of pure (>= 90 %) background, and of pure tissue, in a body MRI.
MIN_BLOCKS = 8

#: Contrasts :func:`segment_volume` knows: fat the brightest large tissue (T1/T2-weighted), or
#: fat suppressed (fat dark, gland/muscle/skin mid-grey to bright).
CONTRASTS = ("fat_bright", "fat_suppressed")
#: The breasts' apex: body surface within this distance of the most anterior point, mm.
APEX_BAND_MM = 10.0
#: Subcutaneous fat over skin below this ratio reads as fat suppressed. On the validation
#: suite's 33 scans (bench/segment_suite.py): fat suppressed 0.82 at most, fat bright 1.07 at
#: least (the median profile's ratio, before the columns' own); with the columns' ratios on
#: the suite's specs rendered with rigid motion (``bench/contrast_family.py --family 0-11``,
#: 36 scans) 0.80 and 1.05, without noise or bias 0.80 and 1.10.
FAT_SUPPRESSED_RATIO = 0.95
#: Tissue rises at least this far above the air for a first look (:func:`tissue_floor`; the
#: normalised volume's fat level is 1), however low the noise: at high SNR the partial-volume
#: voxels over the skin rise 5 noise sigmas above the air, move the contrast profile's skin
#: window outwards (:func:`detect_contrast`) and pull the darkest tissue's level, which the
#: fat-suppressed air threshold is set from, towards the air. The validation suite's 11
#: small subjects rendered without noise or bias field (``bench/register_suite.py --family
#: '{"snr": 10000, "bias": 0}'``): the 9 scans of three of the eight fat-suppressed subjects
#: (small-000, -001, -002) read fat bright without it (small-000's prone scan at SNR 80
#: already), none with it (ratios: fat suppressed <= 0.83, fat bright >= 1.05). The suite's
#: 35 noisy scans read fat suppressed <= 0.86 and fat bright >= 1.03 with it (0.82 and 1.09
#: without; 0.93 and 1.03 with 0.15).
SURFACE_LEVEL = 0.1
#: Denoising iterations of ``denoise_iterations="auto"``, doubled on a scan whose background
#: noise after them is above NOISY_SIGMA (fraction of the fat level). On the validation
#: suite's 33 scans (bench/segment_suite.py) it was 0.009-0.019, save the 2 mm, SNR 13 coil
#: subject's three (0.045-0.072), whose thorax interior the air took in part at 3 iterations.
NOISY_SIGMA = 0.03
DENOISE_ITERATIONS = 3


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


def tissue_floor(peak: float, sigma: float) -> float:
    """The level above which a voxel is tissue for a first look: 5 noise sigmas above the
    background ``peak``, and at least :data:`SURFACE_LEVEL` above it."""
    return peak + max(5.0 * sigma, SURFACE_LEVEL)


def detect_contrast(a: np.ndarray, spacing_zyx: np.ndarray, *,
                    direction: tuple | None = None) -> tuple[str, dict]:
    """Fat-bright or fat-suppressed, from the intensity profile under the skin of the breasts.

    The breasts are the body's most anterior part in every position, and under their skin
    lies fat in every subject. Along the posterior direction (LPS +y, found from the image's
    ``direction``) from the body's surface, over the columns whose surface lies within
    :data:`APEX_BAND_MM` of the most anterior body point, each column's profile is read: the
    skin's peak (the brightest value in the first 3 mm, at least two voxels) and the median
    of the next 4 mm (the subcutaneous fat; a gland close under the skin reaches into it, so
    not its minimum), and their ratio; the scan's ratio is the columns' median. With fat
    bright the profile rises from the skin to the fat (ratio >= 1: fat is the brightest large
    tissue); with fat suppressed the bright skin is followed by the dark fat (ratio well
    below 1). The columns' median ratio, not the ratio of the columns' median profile: where
    the glands reach under the skin in some columns, the median profile mixed the columns'
    skins and glands at each depth, and the family's 180 scans (``bench/contrast_family.py``)
    read 13 contrasts wrong against 8. The apex keeps out the
    surfaces where muscle meets air (a slab's back, the field of view's cuts), which read the
    same in both contrasts and misled a comparison over the whole surface. The body is what
    rises 5 noise sigmas above the background.

    Returns
    -------
    (str, dict)
        One of :data:`CONTRASTS` and the numbers that decided it (``skin``, ``fat``: the
        columns' medians; ``ratio``: the median of the columns' ratios; the ``columns`` read).
    """
    peak, sigma = air_noise(a)
    sp = np.asarray(spacing_zyx, float)
    rough = a > tissue_floor(peak, sigma)
    lab, n = ndimage.label(rough)
    if n == 0:
        return "fat_bright", {"reason": "no body above the noise"}
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    body = ndimage.binary_fill_holes(lab == int(sizes.argmax()))
    axis, flip = _posterior_axis(direction)
    body, b = np.moveaxis(body, axis, 0), np.moveaxis(a, axis, 0)
    if flip:
        body, b = body[::-1], b[::-1]
    step = float(sp[axis])
    has = body.any(axis=0)
    first = np.argmax(body, axis=0)
    cols = has & ((first - first[has].min()) * step <= APEX_BAND_MM)
    n_skin = max(2, int(np.ceil(3.0 / step)))
    n_fat = max(2, int(np.ceil(4.0 / step)))
    k = np.arange(n_skin + n_fat)
    j, i = np.nonzero(cols)
    depth = first[j, i][:, None] + k[None, :]
    ok = depth < b.shape[0]
    prof = np.where(ok, b[np.minimum(depth, b.shape[0] - 1), j[:, None], i[:, None]], np.nan)
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # columns cut by the volume's end
        skins, fats = np.nanmax(prof[:, :n_skin], axis=1), np.nanmedian(prof[:, n_skin:], axis=1)
        ratios = np.where(skins > 0, fats / skins, np.nan)
    skin, fat = float(np.nanmedian(skins)), float(np.nanmedian(fats))
    ratio = float(np.nanmedian(ratios)) if np.isfinite(ratios).any() else 1.0
    kind = "fat_suppressed" if ratio < FAT_SUPPRESSED_RATIO else "fat_bright"
    return kind, {"skin": skin, "fat": fat, "ratio": ratio, "columns": int(j.size),
                  "air": peak, "air_sigma": sigma}


def _posterior_axis(direction) -> tuple[int, bool]:
    """The array axis (z, y, x order) closest to the posterior direction (LPS +y) and whether
    it runs anterior (i.e. its index grows towards the front)."""
    d = np.eye(3) if direction is None else np.asarray(direction, float).reshape(3, 3)
    i = int(np.argmax(np.abs(d[1])))  # the index axis (x, y, z order) most along y
    return 2 - i, bool(d[1, i] < 0)


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


def prepare_volume(img, notes, *, crop, n4, n4_shrink, n4_cache, name, **options):
    """Check and preprocess ``img`` (step 1), on the body's box when ``crop``: N4 then runs
    on the whole volume (the same correction serves the registration, cached) and the
    normalisation uses the whole volume's background. ``denoise_iterations="auto"``:
    :data:`DENOISE_ITERATIONS`, and where the background's noise after them is still above
    :data:`NOISY_SIGMA` the denoising starts again with twice as many (more smooths the thin
    muscle of a coarse scan away: on small-002, muscle Dice 0.91-0.94 at 6, 0.84-0.88 at
    12). Returns (preprocessed, the volume it was made from, the box or None, the
    background's noise after :data:`DENOISE_ITERATIONS` or the given iterations: NaN where
    too little background is seen); notes say when the volume was cropped and when it was
    denoised more."""
    its = options.pop("denoise_iterations")
    if its != "auto" and (not isinstance(its, int) or isinstance(its, bool) or its < 0):
        raise SegmentationError(f"{STAGE}: {name}: denoise_iterations must be 'auto' or a "
                                f"whole number >= 0, got {its!r}")
    try:
        check_volume(img, name=name, stage=STAGE)
        box = body_box(img) if crop else None
        work, background = img, None
        if box is not None:  # everything below scales with the voxels it sees
            corrected = n4_correct(img, shrink=n4_shrink, cache=n4_cache) if n4 else img
            background = background_of(corrected)  # the whole volume's, as uncropped
            work = sitk.RegionOfInterest(corrected, box[1], box[0])
            n4 = False
            notes.append(f"cropped to the body's box: index {box[0]}, size {box[1]} voxels")
        auto = its == "auto"
        if n4 and auto:  # the denoising may run twice: correct the bias once
            work, n4 = n4_correct(sitk.Cast(img, sitk.sitkFloat32), shrink=n4_shrink,
                                  cache=n4_cache), False
        raw = preprocess(work, n4=n4, n4_shrink=n4_shrink, n4_cache=n4_cache, name=name,
                         normalise_intensity=False,
                         denoise_iterations=DENOISE_ITERATIONS if auto else its, **options)
        pre = normalise(raw, background=background, name=name)
        a = sitk.GetArrayViewFromImage(pre)
        seen = np.count_nonzero(np.abs(a[::2, ::2, ::2]) < 0.5) >= 100  # else air_noise guesses
        sigma = air_noise(a)[1] if seen else float("nan")
        if auto and sigma > NOISY_SIGMA:
            # The diffusion goes on from where it stopped: its conductance is rescaled at
            # every iteration, so N more after N equal 2N from the start, bit for bit.
            more = denoise(raw, iterations=DENOISE_ITERATIONS,
                           method=options.get("denoise_method", "gradient"))
            pre = normalise(more, background=background, name=name)
            notes.append(f"noisy scan (background sigma {sigma:.3g} of the fat level after "
                         f"{DENOISE_ITERATIONS} denoising iterations > {NOISY_SIGMA}): "
                         f"denoised with {2 * DENOISE_ITERATIONS}")
    except SegmentationError:
        raise
    except ValueError as exc:
        raise SegmentationError(str(exc)) from None
    return pre, work, box, sigma


def magnitude_level(fraction: float, background_over_fat: float) -> float:
    """Normalised level of a tissue whose signal is ``fraction`` of the fat's, in a magnitude
    image whose background sat at ``background_over_fat`` of the fat level before
    :func:`normalise`. A magnitude image's background is Rician noise of zero signal (mean
    sigma sqrt(pi / 2)), and a tissue's mean is the Rician mean of its signal: the
    normalisation, which takes the background to 0, takes a dark tissue lower than its share
    of the fat (at SNR 11, a muscle of 0.25 of the fat to 0.17: Gudbjartsson & Patz, Magn
    Reson Med 1995, on the Rician bias of magnitude images)."""
    from scipy.special import i0e, i1e

    b = float(background_over_fat)
    if b <= 0.0:
        return float(fraction)
    sigma = b * np.sqrt(2.0 / np.pi)

    def rician_mean(signal: float) -> float:
        nu = signal**2 / (2.0 * sigma**2)
        return float(sigma * np.sqrt(np.pi / 2.0)
                     * ((1.0 + nu) * i0e(nu / 2.0) + nu * i1e(nu / 2.0)))

    return (rician_mean(fraction) - b) / (rician_mean(1.0) - b)


def contrast_disagreement(contrasts: Mapping[str, str]) -> str:
    """"" where the scans of one subject (``{position: contrast}``, each as
    :func:`detect_contrast` read it) read the same contrast, else one sentence that says
    which read which. One subject's scans come from one protocol as a rule, so scans that
    read differently hold a misread: on the phantom family's 180 scans (60 subjects, one
    contrast each; ``bench/contrast_family.py --family 0-59``) the 3 subjects whose scans
    read differently hold 5 of the 8 misreads (2 of them segmented confidently, small-040
    prone and tilted); the other 3 are one subject read wrong in every position (small-044),
    which this cannot see."""
    kinds = sorted(set(contrasts.values()))
    if len(kinds) < 2:
        return ""
    said = "; ".join(f"{k}: {', '.join(p for p, c in contrasts.items() if c == k)}"
                     for k in kinds)
    return (f"the subject's scans read different contrasts ({said}): one is misread unless "
            "they were acquired so; if they were acquired alike, declare [segment] contrast")
