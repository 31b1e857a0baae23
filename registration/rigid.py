"""Rigid registration of one position onto the reference: fiducial (landmark) initialisation,
or a moments/multi-start initialisation when the fiducials are missing or inconsistent,
refined by maximising normalised correlation (multi-resolution) inside a chest-wall mask.

The returned transform maps reference points to the moving position's image frame
(SimpleITK's resampling convention: fixed = reference, moving = the position).
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from registration.qa import fiducial_residuals
from registration.transforms import STAGE, rigid_matrix

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RigidResult:
    """Outcome of :func:`register_rigid`.

    Attributes
    ----------
    transform : SimpleITK.Euler3DTransform
        Reference frame -> moving image frame, mm.
    initialisation : str
        ``"fiducials"`` or ``"moments"``.
    fiducial_residuals : dict label -> float
        ``|T(fixed) - moving|`` in mm after refinement, for the shared labels.
    used_labels : tuple of str
        Fiducial labels that drove the initialisation.
    metric : float
        Final correlation metric (negative: -1 is perfect).
    warnings : tuple of str
        Human-readable notes (fallbacks, dropped markers).
    """

    transform: sitk.Transform
    initialisation: str
    fiducial_residuals: dict = field(default_factory=dict)
    used_labels: tuple = ()
    metric: float = float("nan")
    warnings: tuple = ()


def _to_euler(tfm: sitk.Transform, center: np.ndarray) -> sitk.Euler3DTransform:
    r, t = rigid_matrix(tfm)
    u, _, vt = np.linalg.svd(r)  # nearest rotation (guards against round-off)
    r = u @ vt
    e = sitk.Euler3DTransform()
    e.SetCenter(tuple(float(c) for c in center))
    e.SetMatrix(r.ravel().tolist(), 1e-6)
    # T(x) = R(x - c) + c + t_e  must equal  R x + t
    e.SetTranslation(tuple(t - center + r @ center))
    return e


def landmark_transform(
    fixed_points: Mapping[str, np.ndarray],
    moving_points: Mapping[str, np.ndarray],
    *,
    max_residual_mm: float = 3.0,
) -> tuple[sitk.Euler3DTransform | None, tuple[str, ...], list[str]]:
    """Least-squares rigid fit of labelled points, fixed -> moving.

    Uses every shared label; if a residual exceeds ``max_residual_mm`` (a mislabelled or
    misdetected marker), tries dropping markers one at a time and keeps the best consistent
    subset of at least three.

    Returns
    -------
    transform or None, labels used, warnings
    """
    notes: list[str] = []
    shared = sorted(set(fixed_points) & set(moving_points))
    if len(shared) < 3:
        notes.append(f"only {len(shared)} fiducial label(s) shared with the reference "
                     f"(need 3): {shared}")
        return None, (), notes
    best = None
    for k in range(len(shared), 2, -1):
        for subset in itertools.combinations(shared, k):
            fx = np.asarray([fixed_points[s] for s in subset], float)
            mv = np.asarray([moving_points[s] for s in subset], float)
            init = sitk.LandmarkBasedTransformInitializer(
                sitk.VersorRigid3DTransform(), fx.ravel().tolist(), mv.ravel().tolist()
            )
            res = fiducial_residuals(init, dict(zip(subset, fx)), dict(zip(subset, mv)))
            worst = max(res.values())
            if worst <= max_residual_mm and (best is None or worst < best[0]):
                best = (worst, subset, init, fx.mean(axis=0))
        if best is not None:
            break
    if best is None:
        notes.append(f"fiducials are inconsistent with a rigid motion (residual > "
                     f"{max_residual_mm} mm for every subset of >= 3 of {shared})")
        return None, (), notes
    _, subset, init, centre = best
    if len(subset) < len(shared):
        notes.append(f"fiducial(s) {sorted(set(shared) - set(subset))} dropped: inconsistent "
                     "with the others (mislabelled or misdetected)")
    return _to_euler(init, centre), tuple(subset), notes


def _mask_centroid(img: sitk.Image, mask: sitk.Image | None) -> np.ndarray:
    m = sitk.OtsuThreshold(img, 0, 1) if mask is None else sitk.Cast(mask > 0, sitk.sitkUInt8)
    stats = sitk.LabelShapeStatisticsImageFilter()
    stats.Execute(m)
    if not stats.HasLabel(1):
        raise ValueError(f"{STAGE}: empty mask, cannot initialise the registration")
    return np.asarray(stats.GetCentroid(1))


def moments_transform(
    fixed: sitk.Image,
    moving: sitk.Image,
    *,
    fixed_mask: sitk.Image | None = None,
    angles_deg: tuple[float, ...] = (-15.0, 0.0, 15.0),
    shrink: int = 4,
) -> sitk.Euler3DTransform:
    """Initialise without fiducials: match body centroids, then try rotations about the
    centroid (every combination of ``angles_deg`` about x, y, z) and keep the best
    correlation on a shrunken copy.
    """
    cf = _mask_centroid(fixed, None)
    cm = _mask_centroid(moving, None)
    small_f = sitk.Shrink(sitk.SmoothingRecursiveGaussian(fixed, 2.0), [shrink] * 3)
    small_m = sitk.Shrink(sitk.SmoothingRecursiveGaussian(moving, 2.0), [shrink] * 3)
    reg = sitk.ImageRegistrationMethod()
    reg.SetMetricAsCorrelation()
    reg.SetInterpolator(sitk.sitkLinear)
    if fixed_mask is not None:
        reg.SetMetricFixedMask(sitk.Resample(fixed_mask, small_f, sitk.Transform(),
                                             sitk.sitkNearestNeighbor))
    best = None
    for ax, ay, az in itertools.product(angles_deg, repeat=3):
        e = sitk.Euler3DTransform(tuple(cf), *np.radians([ax, ay, az]), tuple(cm - cf))
        reg.SetInitialTransform(e, inPlace=False)
        try:
            val = reg.MetricEvaluate(small_f, small_m)
        except RuntimeError:  # too few overlapping samples
            continue
        if best is None or val < best[0]:
            best = (val, e)
    if best is None:
        raise RuntimeError(f"{STAGE}: moments initialisation found no overlap between volumes")
    return best[1]


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
    seed: int = 0,
    crop: bool = True,
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
        Seed of the random sampling.
    crop : bool
        Crop both images around the mask first.

    Returns
    -------
    transform, final metric value
    """
    if len(shrink) != len(smooth_mm) or not shrink:
        raise ValueError(f"{STAGE}: shrink {shrink} and smooth_mm {smooth_mm} need one entry "
                         "per level")
    fixed = sitk.Cast(fixed, sitk.sitkFloat32)
    moving = sitk.Cast(moving, sitk.sitkFloat32)
    if fixed_mask is not None and crop:
        # Only the mask is sampled: crop both images around it (the smoothing and shrinking
        # of every level then cost a fraction of the full volumes).
        lo, hi = _bounding_box_mm(fixed_mask)
        margin = 4.0 * max(shrink) * max(fixed.GetSpacing()) + 3.0 * max(smooth_mm)
        fixed = _crop(fixed, lo - margin, hi + margin)
        box = np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi)
                        for c in (lo, hi)])
        moved = np.array([initial.TransformPoint(tuple(map(float, p))) for p in box])
        moving = _crop(moving, moved.min(axis=0) - margin - 20.0,
                       moved.max(axis=0) + margin + 20.0)
    tfm = sitk.Euler3DTransform(initial)
    metric = float("nan")
    for s, sigma in zip(shrink, smooth_mm):
        f = _pyramid_level(fixed, s, sigma)
        m = _pyramid_level(moving, s, sigma)
        reg = sitk.ImageRegistrationMethod()
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
        out = reg.Execute(f, m)
        metric, params = track["best"]
        if not np.isfinite(metric):  # converged before its first step: nothing visited
            if isinstance(out, sitk.CompositeTransform) and out.GetNumberOfTransforms():
                out = out.GetBackTransform()
            metric, params = reg.GetMetricValue(), sitk.Euler3DTransform(out).GetParameters()
        tfm = sitk.Euler3DTransform(tfm)
        tfm.SetParameters(params)
    return tfm, float(metric)


def register_rigid(
    fixed: sitk.Image,
    moving: sitk.Image,
    *,
    fixed_points: Mapping[str, np.ndarray] | None = None,
    moving_points: Mapping[str, np.ndarray] | None = None,
    fixed_mask: sitk.Image | None = None,
    max_residual_mm: float = 3.0,
    marker_mask_mm: float = 8.0,
    shrink: tuple[int, ...] = (4, 2, 1),
    smooth_mm: tuple[float, ...] = (2.0, 1.0, 0.0),
    iterations: int = 50,
    sampling: float = 0.1,
    learning_rate_mm: float = 0.5,
    fine_levels: int = 2,
    seed: int = 0,
) -> RigidResult:
    """Register ``moving`` onto ``fixed`` (the reference) rigidly.

    Parameters
    ----------
    fixed, moving : SimpleITK.Image
        Reference volume and the position's volume (preprocessed: bias-corrected,
        normalised).
    fixed_points, moving_points : mapping label -> (3,) mm, optional
        Fiducials of each volume in its own physical frame.
    fixed_mask : SimpleITK.Image, optional
        Chest-wall mask on the reference grid; only it drives the correlation.
    max_residual_mm : float
        Fiducial consistency threshold for the landmark initialisation.
    marker_mask_mm : float
        Radius of balls around the used reference fiducials added to the mask (0: none).
        The markers sit on stiff zones (sternum, inframammary folds) and pin the directions
        a smooth chest wall leaves loose (e.g. along the body axis).
    shrink, smooth_mm, iterations, sampling, learning_rate_mm, seed
        Multi-resolution schedule (shrink factors, Gaussian sigmas in mm), optimiser
        iterations per level, fraction of mask voxels sampled, first step (mm) and the
        sampling seed; see :func:`refine_rigid`.
    fine_levels : int
        How many of the finest levels the masked chest-wall refinement runs. Its start is
        already close (the fiducials, or the moments start after a whole-body pass over the
        coarser levels), and a coarse level's blurred optimum would pull it away along the
        directions a smooth chest wall leaves loose. Measured on the 256^3 phantom with
        fiducials: TRE 0.03-0.17 mm over repeated runs with two levels, 0.3-0.5 mm with all
        three; on the small phantom's moments fallback 0.05-0.35 mm against 0.2-1.0 mm. The
        runs differ because the threads' partial sums of the metric arrive in varying
        order.

    Returns
    -------
    RigidResult
    """
    notes: list[str] = []
    init, used = None, ()
    if fixed_points and moving_points:
        init, used, more = landmark_transform(
            fixed_points, moving_points, max_residual_mm=max_residual_mm
        )
        notes += more
    else:
        notes.append("no fiducials")
    how = "fiducials"
    if init is None:
        how = "moments"
        notes.append("falling back to a moments/multi-start initialisation: check the result")
        for n in notes:
            log.warning("%s: %s", STAGE, n)
        init = moments_transform(fixed, moving, fixed_mask=fixed_mask)
        # Coarse whole-image pass first: a chest wall alone can be nearly symmetric (e.g.
        # along the body axis), so far from the answer the whole body guides better.
        init, _ = refine_rigid(fixed, moving, init, fixed_mask=None, shrink=shrink[:-1] or shrink,
                               smooth_mm=smooth_mm[:-1] or smooth_mm, iterations=iterations,
                               sampling=sampling, learning_rate_mm=learning_rate_mm,
                               seed=seed)
    else:
        for n in notes:
            log.warning("%s: %s", STAGE, n)
    if fixed_mask is not None and how == "fiducials" and marker_mask_mm > 0:
        fixed_mask = add_balls(fixed_mask, [fixed_points[k] for k in used], marker_mask_mm)
    # Either start is close by now (the fiducials, or the moments start after the
    # whole-body pass): the masked refinement runs the finest levels only.
    k = max(1, int(fine_levels))
    shrink, smooth_mm = tuple(shrink)[-k:], tuple(smooth_mm)[-k:]
    tfm, metric = refine_rigid(
        fixed, moving, init, fixed_mask=fixed_mask, shrink=shrink, smooth_mm=smooth_mm,
        iterations=iterations, sampling=sampling, learning_rate_mm=learning_rate_mm, seed=seed,
    )
    res = fiducial_residuals(tfm, fixed_points or {}, moving_points or {})
    return RigidResult(tfm, how, res, used, metric, tuple(notes))


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
    labels: sitk.Image, *, margin_mm: float = 6.0, breast_margin_mm: float = 2.0
) -> sitk.Image:
    """Mask (uint8) of the chest wall on a label map: muscle (label 2) dilated by
    ``margin_mm``, minus breast tissue (1, 3) farther than ``breast_margin_mm`` from the
    muscle, because the breasts deform between positions and must not drive a rigid fit.
    """
    lab = sitk.Cast(labels, sitk.sitkUInt8)
    muscle = lab == 2
    if sitk.GetArrayViewFromImage(muscle).max() == 0:
        raise ValueError(f"{STAGE}: the reference label map has no muscle (label 2) for the "
                         "chest-wall mask")
    dist = sitk.SignedMaurerDistanceMap(muscle, insideIsPositive=False, squaredDistance=False,
                                        useImageSpacing=True)
    near = dist <= margin_mm
    breast = (lab == 1) | (lab == 3)
    far_breast = breast & (dist > breast_margin_mm)
    return sitk.Cast(near & (far_breast == 0), sitk.sitkUInt8)
