"""Intensity refinement of a rigid transform: normalised correlation maximised coarse to
fine (:func:`refine_rigid`), sampling only inside a mask, with a fixed sampling seed."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from registration.transforms import STAGE

#: Seed of the metric's random sampling. Never 0: SimpleITK reads 0 as "seed from the wall
#: clock" (``sitk.sitkWallClock``), which makes every run differ.
DEFAULT_SEED = 20211


def _check_seed(seed) -> None:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not (
            1 <= seed < 2**31):
        raise ValueError(f"{STAGE}: the sampling seed must be an integer in [1, 2^31), got "
                         f"{seed!r} (0 would seed from the wall clock: every run would differ)")


def _crop(img: sitk.Image, lo_mm: np.ndarray, hi_mm: np.ndarray) -> sitk.Image:
    """Sub-image covering the physical box [lo_mm, hi_mm] (clipped to the image)."""
    corners = np.array([[a[0], b[1], c[2]] for a in (lo_mm, hi_mm) for b in (lo_mm, hi_mm)
                        for c in (lo_mm, hi_mm)])
    idx = np.array([img.TransformPhysicalPointToContinuousIndex(tuple(map(float, p)))
                    for p in corners])
    size = np.asarray(img.GetSize())
    lo = np.clip(np.floor(idx.min(axis=0)).astype(int), 0, size - 1)
    hi = np.clip(np.ceil(idx.max(axis=0)).astype(int) + 1, lo + 1, size)
    return sitk.RegionOfInterest(img, [int(v) for v in hi - lo], [int(v) for v in lo])


def _bounding_box_mm(img: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """Physical box (mm) of the voxels of a binary image."""
    stats = sitk.LabelShapeStatisticsImageFilter()
    stats.Execute(sitk.Cast(img > 0, sitk.sitkUInt8))
    if not stats.HasLabel(1):
        raise ValueError(f"{STAGE}: the registration mask is empty")
    b = stats.GetBoundingBox(1)
    lo_i, hi_i = np.asarray(b[:3]), np.asarray(b[:3]) + np.asarray(b[3:]) - 1
    pts = np.array([img.TransformIndexToPhysicalPoint(tuple(int(v) for v in (x, y, z)))
                    for x in (lo_i[0], hi_i[0]) for y in (lo_i[1], hi_i[1])
                    for z in (lo_i[2], hi_i[2])])
    return pts.min(axis=0), pts.max(axis=0)


def _pyramid_level(img: sitk.Image, shrink: int, sigma_mm: float) -> sitk.Image:
    """Smoothed (recursive Gaussian, cost independent of sigma) and bin-shrunk copy."""
    out = sitk.SmoothingRecursiveGaussian(img, float(sigma_mm)) if sigma_mm > 0 else img
    return sitk.BinShrink(out, [int(shrink)] * 3) if shrink > 1 else out


def refine_rigid(
    fixed: sitk.Image,
    moving: sitk.Image,
    initial: sitk.Euler3DTransform,
    *,
    fixed_mask: sitk.Image | None = None,
    shrink: tuple[int, ...] = (4, 2, 1),
    smooth_mm: tuple[float, ...] = (2.0, 1.0, 0.0),
    iterations: int = 50,
    sampling: float = 0.1,
    learning_rate_mm: float = 0.5,
    seed: int = DEFAULT_SEED,
    crop: bool = True,
    threads: int | None = None,
) -> tuple[sitk.Euler3DTransform, float]:
    """Maximise normalised correlation (SimpleITK ``Correlation`` metric) over a rigid
    transform, coarse to fine, sampling only inside ``fixed_mask``.

    Each level is its own single-level registration on images this function smooths and
    shrinks itself: SimpleITK's built-in pyramid smooths the full-size images at every level
    and rebuilds the moving-image gradient at full size each time, which cost about 4x the
    optimisation itself on a 256^3 volume.

    Parameters
    ----------
    fixed, moving : SimpleITK.Image
        Reference and moving volumes.
    initial : SimpleITK.Euler3DTransform
        Starting transform (reference -> moving frame).
    fixed_mask : SimpleITK.Image, optional
        Where the metric samples the reference.
    shrink, smooth_mm : tuple
        Per level: shrink factor and Gaussian sigma in mm (0: no smoothing).
    iterations : int
        Maximum optimiser iterations per level.
    sampling : float
        Fraction of (masked) voxels sampled at full resolution; a level shrunk by ``s``
        samples ``min(1, sampling * s**2)`` of its voxels.
    learning_rate_mm : float
        First optimiser step (physical shift, mm) per unit of shrink factor: a level
        shrunk by ``s`` starts with steps of ``s * learning_rate_mm`` (its voxels are
        ``s`` times larger and it starts farther from the answer).
    seed : int
        Seed of the random sampling, >= 1 (0 would mean "from the wall clock").
    crop : bool
        Crop both images around the mask first.
    threads : int, optional
        Threads of the metric (default: SimpleITK's global count, the machine's cores
        unless set). The metric's per-thread partial sums are added in an order that
        depends on how the work is split, so one thread count gives one transform bit for
        bit on every machine, and two counts differ by about 1e-9 mm.

    Returns
    -------
    transform, final metric value
    """
    return refine_rigid_seeds(fixed, moving, initial, (seed,), fixed_mask=fixed_mask,
                              shrink=shrink, smooth_mm=smooth_mm, iterations=iterations,
                              sampling=sampling, learning_rate_mm=learning_rate_mm,
                              crop=crop, threads=threads)[0]


def refine_rigid_seeds(fixed, moving, initial, seeds, *, fixed_mask=None, shrink=(4, 2, 1),
                       smooth_mm=(2.0, 1.0, 0.0), iterations=50, sampling=0.1,
                       learning_rate_mm=0.5, crop=True, threads=None) -> list:
    """:func:`refine_rigid` from one ``initial`` once per sampling seed of ``seeds``, the
    cropped and smoothed levels made once for all: [(transform, metric)] in their order."""
    for seed in seeds:
        _check_seed(seed)
    if len(shrink) != len(smooth_mm) or not shrink:
        raise ValueError(f"{STAGE}: shrink {shrink} and smooth_mm {smooth_mm} need one entry "
                         "per level")
    fixed = sitk.Cast(fixed, sitk.sitkFloat32)
    moving = sitk.Cast(moving, sitk.sitkFloat32)
    if fixed_mask is not None and crop:
        fixed, moving = _crop_to_mask(fixed, moving, fixed_mask, initial, shrink=shrink,
                                      smooth_mm=smooth_mm)
    levels = [(s, _pyramid_level(fixed, s, sigma), _pyramid_level(moving, s, sigma))
              for s, sigma in zip(shrink, smooth_mm)]
    out = []
    for seed in seeds:
        tfm, metric = sitk.Euler3DTransform(initial), float("nan")
        for s, f, m in levels:
            tfm, metric = _refine_level(
                f, m, tfm, fixed_mask=fixed_mask, shrink=s, iterations=iterations,
                sampling=sampling, learning_rate_mm=learning_rate_mm, seed=seed,
                threads=threads)
        out.append((tfm, float(metric)))
    return out


def _crop_to_mask(fixed, moving, fixed_mask, initial, *, shrink, smooth_mm):
    """Both images cropped around the mask (the reference's box, and where ``initial``
    puts it in the moving image, 20 mm wider), with a margin for the coarsest level's
    voxels and the widest smoothing: only the mask is sampled, and the smoothing and
    shrinking of every level then cost a fraction of the full volumes."""
    lo, hi = _bounding_box_mm(fixed_mask)
    margin = 4.0 * max(shrink) * max(fixed.GetSpacing()) + 3.0 * max(smooth_mm)
    fixed = _crop(fixed, lo - margin, hi + margin)
    box = np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi)
                    for c in (lo, hi)])
    moved = np.array([initial.TransformPoint(tuple(map(float, p))) for p in box])
    moving = _crop(moving, moved.min(axis=0) - margin - 20.0,
                   moved.max(axis=0) + margin + 20.0)
    return fixed, moving


def _refine_level(f, m, tfm, *, fixed_mask, shrink, iterations, sampling, learning_rate_mm,
                  seed, threads) -> tuple[sitk.Euler3DTransform, float]:
    """One level of :func:`refine_rigid` on its smoothed, shrunk images ``f`` and ``m``:
    the best position the optimiser visited, and its metric."""
    s = shrink
    threads = int(threads or sitk.ProcessObject.GetGlobalDefaultNumberOfThreads())
    reg = sitk.ImageRegistrationMethod()
    reg.SetNumberOfThreads(threads)
    reg.SetMetricAsCorrelation()
    if fixed_mask is not None:
        reg.SetMetricFixedMask(sitk.Resample(fixed_mask, f, sitk.Transform(),
                                             sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8))
    reg.SetMetricSamplingStrategy(reg.RANDOM)
    # Fewer samples at the coarse levels would be too few; the fine level needs a share.
    reg.SetMetricSamplingPercentage(min(1.0, float(sampling) * s ** 2), int(seed))
    reg.SetInterpolator(sitk.sitkLinear)
    # Gradients by central differences at the samples only: the default gradient filter
    # computes a vector image of the whole (cropped) moving volume at every level.
    reg.MetricUseMovingImageGradientFilterOff()
    reg.MetricUseFixedImageGradientFilterOff()
    reg.SetOptimizerAsRegularStepGradientDescent(
        learningRate=float(learning_rate_mm) * s, minStep=1e-3,
        numberOfIterations=int(iterations), relaxationFactor=0.6,
        gradientMagnitudeTolerance=1e-6,
    )
    reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetInitialTransform(sitk.Euler3DTransform(tfm), inPlace=False)
    # Keep the best position visited: near the optimum the fixed-step optimiser can
    # wander along the directions a smooth chest wall leaves loose while the metric
    # worsens. An iteration event reports the metric of the position before its step.
    track = {"pos": tfm.GetParameters(), "best": (np.inf, tfm.GetParameters())}

    def visit(reg=reg, track=track):
        if reg.GetMetricValue() < track["best"][0]:
            track["best"] = (reg.GetMetricValue(), track["pos"])
        track["pos"] = reg.GetOptimizerPosition()

    reg.AddCommand(sitk.sitkIterationEvent, visit)
    # The metric splits its sums over SimpleITK's global thread count, whatever the
    # method's own is set to (measured: 2 global threads with the method's set to 1 ran on
    # 2 cores and ended 1e-9 mm from 1 global thread): that count is set for the call.
    was = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)
    try:
        out = reg.Execute(f, m)
    finally:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(was)
    metric, params = track["best"]
    if not np.isfinite(metric):  # converged before its first step: nothing visited
        if isinstance(out, sitk.CompositeTransform) and out.GetNumberOfTransforms():
            out = out.GetBackTransform()
        metric, params = reg.GetMetricValue(), sitk.Euler3DTransform(out).GetParameters()
    tfm = sitk.Euler3DTransform(tfm)
    tfm.SetParameters(params)
    return tfm, metric
