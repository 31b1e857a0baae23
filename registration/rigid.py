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
from scipy import ndimage

from registration.qa import fiducial_residuals
from registration.transforms import STAGE, rigid_matrix, transform_points

log = logging.getLogger(__name__)

#: Seed of the metric's random sampling. Never 0: SimpleITK reads 0 as "seed from the wall
#: clock" (``sitk.sitkWallClock``), which makes every run differ.
DEFAULT_SEED = 20211


@dataclass(frozen=True)
class RigidResult:
    """Outcome of :func:`register_rigid`.

    Attributes
    ----------
    transform : SimpleITK.Euler3DTransform
        Reference frame -> moving image frame, mm.
    initialisation : str
        ``"fiducials"``, ``"moments"`` or ``"given"`` (a start passed by the caller).
    fiducial_residuals : dict label -> float
        ``|T(fixed) - moving|`` in mm after refinement, for the shared labels.
    used_labels : tuple of str
        Fiducial labels that drove the initialisation.
    metric : float
        Final correlation metric (negative: -1 is perfect).
    warnings : tuple of str
        Human-readable notes (fallbacks, dropped markers, failed checks).
    status : str
        ``"ok"`` (checked against the fiducials and passed), ``"flagged"`` (a check failed)
        or ``"unchecked"`` (no consistent fiducials).
    checks : dict
        Outcome of :func:`check_registration` (empty when unchecked).
    fiducial_transform : SimpleITK.Euler3DTransform or None
        The fiducial-only solution.
    """

    transform: sitk.Transform
    initialisation: str
    fiducial_residuals: dict = field(default_factory=dict)
    used_labels: tuple = ()
    metric: float = float("nan")
    warnings: tuple = ()
    status: str = "unchecked"
    checks: dict = field(default_factory=dict)
    fiducial_transform: sitk.Transform | None = None


def _check_seed(seed) -> None:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not (
            1 <= seed < 2**31):
        raise ValueError(f"{STAGE}: the sampling seed must be an integer in [1, 2^31), got "
                         f"{seed!r} (0 would seed from the wall clock: every run would differ)")


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
    seed: int = DEFAULT_SEED,
    crop: bool = True,
    threads: int = 1,
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
    threads : int
        Threads of the metric. One (the default) makes the result independent of the
        machine: the metric's per-thread partial sums are added in an order that depends on
        how the work is split.

    Returns
    -------
    transform, final metric value
    """
    _check_seed(seed)
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
        reg.SetNumberOfThreads(int(threads))
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
    initial: sitk.Transform | None = None,
    max_residual_mm: float = 3.0,
    marker_mask_mm: float = 8.0,
    fiducial_error_mm: float = 1.0,
    shrink: tuple[int, ...] = (4, 2, 1),
    smooth_mm: tuple[float, ...] = (2.0, 1.0, 0.0),
    iterations: int = 50,
    sampling: float = 0.1,
    learning_rate_mm: float = 0.5,
    fine_levels: int = 2,
    seed: int = DEFAULT_SEED,
    threads: int = 1,
) -> RigidResult:
    """Register ``moving`` onto ``fixed`` (the reference) rigidly, then check the result
    against the fiducial-only solution.

    Parameters
    ----------
    fixed, moving : SimpleITK.Image
        Reference volume and the position's volume (preprocessed: bias-corrected,
        normalised).
    fixed_points, moving_points : mapping label -> (3,) mm, optional
        Fiducials of each volume in its own physical frame.
    fixed_mask : SimpleITK.Image, optional
        Chest-wall mask on the reference grid (breasts masked out, see
        :func:`chest_wall_mask`); only it drives the correlation.
    initial : SimpleITK.Transform, optional
        A start that replaces the fiducial initialisation (the fiducials still check the
        result).
    max_residual_mm : float
        Fiducial consistency threshold for the landmark initialisation.
    marker_mask_mm : float
        Radius of balls around the used reference fiducials added to the mask (0: none).
        The markers sit on stiff zones (sternum, inframammary folds) and pin the directions
        a smooth chest wall leaves loose (e.g. along the body axis).
    fiducial_error_mm : float
        Fiducial localisation error (FLE) assumed at least, mm, and at least half the
        diagonal of the coarser image's voxel; see :func:`check_registration`.
    shrink, smooth_mm, iterations, sampling, learning_rate_mm, seed, threads
        Multi-resolution schedule (shrink factors, Gaussian sigmas in mm), optimiser
        iterations per level, fraction of mask voxels sampled, first step (mm), the sampling
        seed and the metric's threads; see :func:`refine_rigid`.
    fine_levels : int
        How many of the finest levels the masked chest-wall refinement runs. Its start is
        already close (the fiducials, or the moments start after a whole-body pass over the
        coarser levels), and a coarse level's blurred optimum would pull it away along the
        directions a smooth chest wall leaves loose.

    Returns
    -------
    RigidResult
        ``status`` is ``"ok"`` when the checks passed, ``"flagged"`` when one failed (the
        reasons are in ``warnings``) and ``"unchecked"`` without fiducials to check against.
    """
    _check_seed(seed)
    notes: list[str] = []
    fid, used = None, ()
    if fixed_points and moving_points:
        fid, used, more = landmark_transform(
            fixed_points, moving_points, max_residual_mm=max_residual_mm
        )
        notes += more
    else:
        notes.append("no fiducials")
    opts = dict(iterations=iterations, sampling=sampling, learning_rate_mm=learning_rate_mm,
                seed=seed, threads=threads)
    if initial is not None:
        how = "given"
        init = _to_euler(initial, np.zeros(3) if fid is None else np.asarray(fid.GetCenter()))
    elif fid is not None:
        how, init = "fiducials", fid
    else:
        how = "moments"
        notes.append("falling back to a moments/multi-start initialisation: check the result")
        init = moments_transform(fixed, moving, fixed_mask=fixed_mask)
        # Coarse whole-image pass first: a chest wall alone can be nearly symmetric (e.g.
        # along the body axis), so far from the answer the whole body guides better.
        init, _ = refine_rigid(fixed, moving, init, fixed_mask=None, shrink=shrink[:-1] or shrink,
                               smooth_mm=smooth_mm[:-1] or smooth_mm, **opts)
    for n in notes:
        log.warning("%s: %s", STAGE, n)
    chest = fixed_mask
    if fixed_mask is not None and fid is not None and marker_mask_mm > 0:
        fixed_mask = add_balls(fixed_mask, [fixed_points[k] for k in used], marker_mask_mm)
    # Either start is close by now (the fiducials, or the moments start after the
    # whole-body pass): the masked refinement runs the finest levels only.
    k = max(1, int(fine_levels))
    tfm, metric = refine_rigid(fixed, moving, init, fixed_mask=fixed_mask,
                               shrink=tuple(shrink)[-k:], smooth_mm=tuple(smooth_mm)[-k:], **opts)
    res = fiducial_residuals(tfm, fixed_points or {}, moving_points or {})
    if fid is None:
        checks, status = {}, "unchecked"
        notes.append("no consistent fiducials to check the registration against: unchecked")
    else:
        pts = {k: fixed_points[k] for k in used}
        # A marker's centre is found to a fraction of a voxel at best: half a voxel
        # diagonal bounds the localisation error from below on coarse grids.
        voxel = max(max(fixed.GetSpacing()), max(moving.GetSpacing()))
        checks = check_registration(
            tfm, fid, pts, fiducial_residuals(fid, pts, {k: moving_points[k] for k in used}),
            chest_points=None if chest is None else mask_points(chest),
            fiducial_error_mm=max(float(fiducial_error_mm), 0.5 * np.sqrt(3.0) * voxel),
        )
        status = "ok" if checks["passed"] else "flagged"
        for w in checks["failures"]:
            log.warning("%s: %s", STAGE, w)
            notes.append(w)
    return RigidResult(tfm, how, res, used, metric, tuple(notes), status=status,
                       checks=checks, fiducial_transform=fid)


def mask_points(mask: sitk.Image, *, max_points: int = 4000) -> np.ndarray:
    """(N,3) physical points (mm) of at most ``max_points`` voxels of a binary mask, evenly
    strided in memory order (deterministic)."""
    idx = np.flatnonzero(sitk.GetArrayViewFromImage(mask).ravel() > 0)
    if len(idx) == 0:
        return np.zeros((0, 3))
    idx = idx[:: max(1, len(idx) // max_points)]
    zyx = np.stack(np.unravel_index(idx, sitk.GetArrayViewFromImage(mask).shape), axis=1)
    d = np.asarray(mask.GetDirection(), float).reshape(3, 3)
    return (zyx[:, ::-1] * np.asarray(mask.GetSpacing())) @ d.T + np.asarray(mask.GetOrigin())


def predicted_tre(points: np.ndarray, fiducials: np.ndarray, fle_mm: float) -> np.ndarray:
    """Expected target registration error (mm) of a point-based rigid fit at ``points``.

    Fitzpatrick, West & Maurer (1998): TRE^2(r) = FLE^2 / N (1 + 1/3 sum_k d_k^2 / f_k^2),
    with d_k the distance of r from the k-th principal axis of the N fiducials and f_k the
    RMS distance of the fiducials from that axis.

    Parameters
    ----------
    points : (M, 3) float
        Targets, mm.
    fiducials : (N, 3) float
        Fiducial positions, mm (N >= 3).
    fle_mm : float
        Fiducial localisation error (RMS), mm.

    Returns
    -------
    (M,) float, mm
    """
    f = np.asarray(fiducials, float)
    c = f.mean(axis=0)
    _, _, vt = np.linalg.svd(f - c)
    fp = (f - c) @ vt.T
    rp = (np.asarray(points, float).reshape(-1, 3) - c) @ vt.T
    # squared distance from axis k = sum of the squared other two coordinates
    d2 = (rp ** 2).sum(axis=1, keepdims=True) - rp ** 2
    f2 = np.maximum(((fp ** 2).sum(axis=1, keepdims=True) - fp ** 2).mean(axis=0), 1e-6)
    return fle_mm * np.sqrt((1.0 + (d2 / f2).sum(axis=1) / 3.0) / len(f))


def check_registration(
    refined: sitk.Transform,
    fiducial_only: sitk.Transform,
    fixed_points: Mapping[str, np.ndarray],
    fiducial_only_residuals: Mapping[str, float],
    *,
    chest_points: np.ndarray | None = None,
    fiducial_error_mm: float = 1.0,
    sigmas: float = 3.0,
) -> dict:
    """Check a refined registration against the fiducial-only solution.

    Two rules, both in the reference frame:

    - at the markers, the refined transform may not move a fiducial by more than the
      localisation error (FLE) away from where the fiducial-only solution puts it;
    - on the chest wall (``chest_points``), the two may not differ by more than ``sigmas``
      times the error expected of the fiducial-only fit there (:func:`predicted_tre`).

    The FLE is ``fiducial_error_mm`` or the one the fiducial fit's residuals imply
    (``FRE_rms / sqrt(1 - 2/N)``), whichever is larger.

    Parameters
    ----------
    refined, fiducial_only : SimpleITK.Transform
        Reference -> moving transforms.
    fixed_points : mapping label -> (3,) mm
        The fiducials that made ``fiducial_only``, in the reference frame.
    fiducial_only_residuals : mapping label -> float
        Residuals (mm) of the fiducial-only fit.
    chest_points : (M, 3) float, optional
        Chest-wall points of the reference, mm.
    fiducial_error_mm : float
        Smallest FLE assumed, mm.
    sigmas : float
        Tolerance on the chest wall in units of the predicted TRE.

    Returns
    -------
    dict
        ``passed``, ``failures`` (messages), ``fle_mm``, ``fiducial_shift_mm`` per label and,
        with ``chest_points``, ``chest_wall_shift_mm`` (mean, max) and
        ``chest_wall_worst_ratio`` (shift / predicted TRE, worst point).
    """
    labels = sorted(fixed_points)
    f = np.asarray([fixed_points[k] for k in labels], float)
    n = len(f)
    fre = np.sqrt(np.mean([float(fiducial_only_residuals[k]) ** 2 for k in labels]))
    fle = max(float(fiducial_error_mm), fre / np.sqrt(max(1.0 - 2.0 / n, 1e-3)))
    shift = np.linalg.norm(transform_points(refined, f) - transform_points(fiducial_only, f),
                           axis=1)
    out: dict = {"fle_mm": float(fle),
                 "fiducial_shift_mm": {k: float(v) for k, v in zip(labels, shift)}}
    failures = []
    if shift.max() > fle:
        worst = labels[int(shift.argmax())]
        failures.append(
            f"the refined registration moves fiducial {worst!r} {shift.max():.2f} mm away "
            f"from the fiducial-only solution (more than the localisation error {fle:.2f} "
            "mm): the correlation refinement walked away from the markers")
    if chest_points is not None and len(chest_points):
        d = np.linalg.norm(transform_points(refined, chest_points)
                           - transform_points(fiducial_only, chest_points), axis=1)
        ratio = d / predicted_tre(chest_points, f, fle)
        out["chest_wall_shift_mm"] = {"mean": float(d.mean()), "max": float(d.max())}
        out["chest_wall_worst_ratio"] = float(ratio.max())
        if ratio.max() > sigmas:
            failures.append(
                f"on the chest wall the refined registration differs from the fiducial-only "
                f"solution by up to {d.max():.2f} mm ({ratio.max():.1f} times the error "
                f"expected of the fiducials there; limit {sigmas:g})")
    out["passed"] = not failures
    out["failures"] = failures
    return out


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
    labels: sitk.Image, *, margin_mm: float = 6.0, breast_margin_mm: float = 0.0
) -> sitk.Image:
    """Mask (uint8) of what is rigid on a label map: the chest wall, breasts masked out.

    The muscle (label 2), the band within ``margin_mm`` of it on the side away from the
    breasts (thorax interior, or the air behind a muscle slab), and only the breast tissue
    (1, 3) within ``breast_margin_mm`` in front of it. The breasts deform between positions
    and the space in front of the muscle (air between the breasts, subcutaneous fat) is where
    they swing, so neither may drive a rigid fit.

    Parameters
    ----------
    labels : SimpleITK.Image
        Reference label map (0 background, 1 breast, 2 muscle, 3 gland).
    margin_mm, breast_margin_mm : float
        Widths of the band behind the muscle and of the tissue layer in front of it, mm.

    Returns
    -------
    SimpleITK.Image
        uint8 0/1 on the label map's grid.
    """
    lab = sitk.Cast(labels, sitk.sitkUInt8)
    muscle = lab == 2
    if sitk.GetArrayViewFromImage(muscle).max() == 0:
        raise ValueError(f"{STAGE}: the reference label map has no muscle (label 2) for the "
                         "chest-wall mask")
    dist = sitk.SignedMaurerDistanceMap(muscle, insideIsPositive=False, squaredDistance=False,
                                        useImageSpacing=True)
    a = sitk.GetArrayFromImage(lab)
    d = sitk.GetArrayFromImage(dist)
    breast = (a == 1) | (a == 3)
    band = (d <= margin_mm) & (a != 2)
    # Band components that reach the breasts hold the space in front of the muscle (a
    # closed chest wall separates it from the thorax interior). Where the band wraps round
    # the edge of a muscle slab, the side is the one the distance gradient faces: toward the
    # breasts (front) or away from them.
    comp, n = ndimage.label(band)
    touches = np.zeros(n + 1, bool)
    touches[np.unique(comp[breast & band])] = True
    touches[0] = False
    front = touches[comp]
    if front.any():
        spz = np.asarray(lab.GetSpacing(), float)[::-1]
        cm = np.argwhere(a[::2, ::2, ::2] == 2).mean(axis=0)
        cb = np.argwhere(breast[::2, ::2, ::2]).mean(axis=0)
        toward = (cb - cm) * spz  # (z, y, x) mm, muscle -> breasts
        toward /= max(np.linalg.norm(toward), 1e-9)
        facing = np.zeros(d.shape, np.float32)
        for i in range(3):
            facing += toward[i] * np.gradient(d, spz[i], axis=i).astype(np.float32)
        front &= facing > -0.5  # not clearly facing away from the breasts
    keep = (a == 2) | (band & ~front) | (breast & (d <= breast_margin_mm))
    out = sitk.GetImageFromArray(keep.astype(np.uint8))
    out.CopyInformation(lab)
    return out
