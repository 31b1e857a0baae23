"""Rigid registration of one position onto the reference: fiducial (landmark) initialisation,
or a moments/multi-start initialisation when the fiducials are missing or inconsistent,
refined by maximising normalised correlation (multi-resolution) inside a chest-wall mask.

The returned transform maps reference points to the moving position's image frame
(SimpleITK's resampling convention: fixed = reference, moving = the position).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from registration.checks import (
    check_registration,
    choose_checked,
    mask_points,
    predicted_tre,
)
from registration.directions import blend_loose, loose_directions
from registration.initialise import _to_euler, landmark_transform, moments_transform
from registration.masks import add_balls, chest_wall_mask
from registration.qa import fiducial_residuals
from registration.refine import DEFAULT_SEED, refine_rigid, refine_rigid_seeds
from registration.repeats import (
    REPEATS,
    SPREAD_WARN_MM,
    mean_transform,
    point_errors,
    repeat_seeds,
    seed_spread,
)
from registration.transforms import STAGE

__all__ = [
    "DEFAULT_SEED", "RigidResult", "add_balls", "check_registration", "chest_wall_mask",
    "landmark_transform", "mask_points", "moments_transform", "predicted_tre", "refine_rigid",
    "register_rigid",
]

log = logging.getLogger(__name__)

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
        Correlation of the chest-wall refinement (negative: -1 is perfect), before its
        loose directions were taken from the markers; the mean over its repeats.
    warnings : tuple of str
        Human-readable notes (fallbacks, dropped markers, failed checks).
    status : str
        ``"ok"`` (checked against the fiducials and passed), ``"fiducials"`` (the refined
        transform failed a check, so ``transform`` is the fiducial-only solution),
        ``"flagged"`` (a check failed and the refined transform was kept) or
        ``"unchecked"`` (no consistent fiducials).
    checks : dict
        Outcome of :func:`check_registration` of the refined transform (empty when
        unchecked).
    fiducial_transform : SimpleITK.Euler3DTransform or None
        The fiducial-only solution.
    refined_transform : SimpleITK.Transform or None
        The correlation's answer (the mean of its repeats), whether or not it is
        ``transform``.
    spread : dict
        The repeats' scatter on the chest wall (:func:`registration.repeats.seed_spread`).
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
    refined_transform: sitk.Transform | None = None
    spread: dict = field(default_factory=dict)


def register_rigid(
    fixed: sitk.Image, moving: sitk.Image, *,
    fixed_points: Mapping[str, np.ndarray] | None = None,
    moving_points: Mapping[str, np.ndarray] | None = None,
    fixed_mask: sitk.Image | None = None, initial: sitk.Transform | None = None,
    max_residual_mm: float = 3.0, marker_mask_mm: float = 8.0, fiducial_error_mm: float = 1.0,
    shrink: tuple[int, ...] = (4, 2, 1), smooth_mm: tuple[float, ...] = (2.0, 1.0, 0.0),
    iterations: int = 50, sampling: float = 0.1, learning_rate_mm: float = 0.5,
    fine_levels: int = 2, seed: int = DEFAULT_SEED, threads: int | None = None,
    fiducial_fallback: bool = True, base_mask: sitk.Image | None = None,
    repeats: int = REPEATS, spread_warn_mm: float = SPREAD_WARN_MM,
) -> RigidResult:
    """Register ``moving`` onto ``fixed`` (the reference) rigidly, then check the result
    against the fiducial-only solution.

    Parameters
    ----------
    fixed, moving : SimpleITK.Image
        Reference and position volumes (preprocessed: bias-corrected, normalised).
    fixed_points, moving_points : mapping label -> (3,) mm, optional
        Fiducials of each volume in its own physical frame.
    fixed_mask, base_mask : SimpleITK.Image, optional
        Chest-wall mask on the reference grid (:func:`chest_wall_mask`), which drives the
        fit; the wall and the breasts' base, which sets loose directions without markers.
    initial : SimpleITK.Transform, optional
        A start that replaces the fiducial initialisation (the fiducials still check it).
    max_residual_mm : float
        Fiducial consistency threshold for the landmark initialisation.
    marker_mask_mm : float
        Radius of balls around the used reference fiducials whose fiducial-only residual is
        within ``fiducial_error_mm`` (0: none). A direction the chest wall leaves loose
        (:func:`registration.directions.loose_directions`) is set by a refinement over the
        mask and these balls (without them, over ``base_mask``; :func:`_set_loose`).
    fiducial_error_mm : float
        Least fiducial localisation error the check assumes, mm (:func:`check_registration`).
    shrink, smooth_mm, iterations, sampling, learning_rate_mm, seed, threads
        Levels (shrink factors, Gaussian sigmas in mm), iterations per level, share of mask
        voxels sampled, first step (mm), sampling seed, threads: :func:`refine_rigid`.
    fine_levels : int
        How many of the finest levels of at most :data:`MAX_VOXEL_MM` the masked refinement
        runs (its start is close; a coarse level's optimum pulls along loose ones).
    fiducial_fallback : bool
        Where the refined transform fails a check as a whole, return the fiducial-only one
        (``"fiducials"``, :func:`registration.checks.choose_checked`).
    repeats, spread_warn_mm : int, float
        The refinement runs ``repeats`` times with seeds ``seed, seed + 1, ...`` and returns
        their mean (:mod:`registration.repeats`); a note warns where its standard error from
        the sampling (the repeats' scatter on the chest wall) exceeds ``spread_warn_mm``.

    Returns
    -------
    RigidResult
        ``status`` "ok", "fiducials", "flagged" (see ``warnings``) or "unchecked".
    """
    seeds = repeat_seeds(seed, repeats)
    notes: list[str] = []
    fid, used = _fiducial_fit(fixed_points, moving_points, notes, max_residual_mm=max_residual_mm)
    opts = dict(iterations=iterations, sampling=sampling, learning_rate_mm=learning_rate_mm,
                threads=threads)  # the seeds are the repeats'
    how, starts = _start(fixed, moving, fid, initial, notes, fixed_mask=fixed_mask,
                         shrink=shrink, smooth_mm=smooth_mm, opts=dict(opts, seed=seeds[0]))
    k = max(1, int(fine_levels))  # the start is close (fiducials, or moments + whole body)
    levels = dict(_fine(fixed, shrink[-k:], smooth_mm[-k:]), **opts)
    init, runs = _best_refined(fixed, moving, starts, notes, fixed_mask, levels, seeds)
    for n in notes:
        log.warning("%s: %s", STAGE, n)
    pinned = [] if fid is None or marker_mask_mm <= 0 or fixed_mask is None else _rigid_markers(
        fid, used, fixed_points, moving_points, notes, fiducial_error_mm=fiducial_error_mm)
    walls = _set_loose(fixed, moving, init, [t for t, _ in runs], fixed_mask, notes,
                       seeds=seeds, levels=levels, balls=[fixed_points[k] for k in pinned],
                       radius_mm=marker_mask_mm, base=base_mask)
    tfm, spread, own = _agreed(walls, fixed, fixed_mask, notes, spread_warn_mm,
                               {k: fixed_points[k] for k in used})
    chosen, checks, status = choose_checked(
        tfm, fid, used, fixed_points, moving_points, notes, chest=fixed_mask,
        fiducial_error_mm=fiducial_error_mm, fallback=fiducial_fallback, refined_error_mm=own)
    res = fiducial_residuals(chosen, fixed_points or {}, moving_points or {})
    return RigidResult(chosen, how, res, used, float(np.mean([m for _, m in runs])),
                       tuple(notes), status=status, checks=checks, fiducial_transform=fid,
                       refined_transform=tfm, spread=spread)


def _agreed(tfms, fixed, mask, notes, warn_mm, markers):
    """(the mean of the repeats' transforms, their :func:`registration.repeats.seed_spread`
    on the chest-wall mask's points, or the reference's box corners without a mask, and the
    mean's standard error at each of the ``markers`` {label: point}); a note where the
    mean's standard error from the sampling exceeds ``warn_mm``."""
    centre = np.asarray(tfms[0].GetCenter(), float)
    mean = mean_transform(tfms, centre) if len(tfms) > 1 else tfms[0]
    if mask is not None:
        pts = mask_points(mask)
    else:
        size = np.asarray(fixed.GetSize()) - 1
        pts = np.array([fixed.TransformContinuousIndexToPhysicalPoint(
            tuple(float(v) for v in size * np.array(c))) for c in np.ndindex(2, 2, 2)])
    spread = seed_spread(tfms, mean, pts)
    if spread["standard_error"] > warn_mm:
        notes.append(
            f"the chest-wall refinement's {len(tfms)} sampling seeds disagree by "
            f"{spread['rms']:.2f} mm RMS (up to {spread['max']:.2f} mm) on the chest wall: "
            f"their mean is uncertain by about {spread['standard_error']:.2f} mm from the "
            f"sampling alone, more than {warn_mm:.2f} mm; the images pin the registration "
            "less well than that (check the overlays; fiducials on the sternum, more "
            "[register] repeats or a larger sampling narrow it)")
        log.warning("%s: %s", STAGE, notes[-1])
    at = point_errors(tfms, mean, np.array(list(markers.values())).reshape(-1, 3))
    return mean, spread, dict(zip(markers, (float(v) for v in at)))


#: The chest-wall refinement's levels keep voxels of at most this size (mm, the geometric
#: mean of a shrunk voxel's sides); the finest level always runs. On the validation suite's
#: 2 mm coil subject (small-002) the level shrunk by 2 (4 mm voxels, a chest wall a few
#: voxels thick) moved a start at the truth 3 mm away (every voxel sampled), and the
#: full-resolution level alone returned to within 0.5-0.9 mm of it.
MAX_VOXEL_MM = 3.0


def _fine(fixed, shrink, smooth_mm) -> dict:
    """``shrink`` and ``smooth_mm`` of the levels whose voxels stay within
    :data:`MAX_VOXEL_MM`."""
    voxel = float(np.prod(fixed.GetSpacing())) ** (1.0 / 3.0)
    keep = [i for i, s in enumerate(shrink) if s * voxel <= MAX_VOXEL_MM] or [len(shrink) - 1]
    return {"shrink": tuple(shrink[i] for i in keep),
            "smooth_mm": tuple(smooth_mm[i] for i in keep)}


def _fiducial_fit(fixed_points, moving_points, notes, *, max_residual_mm):
    """The fiducial-only transform and the labels it used ((None, ()) without a consistent
    set of three); notes say why markers were dropped or missing."""
    if not (fixed_points and moving_points):
        notes.append("no fiducials")
        return None, ()
    fid, used, more = landmark_transform(
        fixed_points, moving_points, max_residual_mm=max_residual_mm
    )
    notes += more
    return fid, used


def _rigid_markers(fid, used, fixed_points, moving_points, notes, *,
                   fiducial_error_mm) -> list[str]:
    """The used markers whose fiducial-only residual is within ``fiducial_error_mm``: they
    moved with the others, so the skin under them is as rigid as the chest wall. A marker on
    skin that the breasts pull along (measured on the validation suite: residuals up to
    2.4 mm) would tie the refinement to tissue that deforms. (With a floor of half a voxel's
    diagonal instead, the suite's figures were the same.)"""
    res = fiducial_residuals(fid, {k: fixed_points[k] for k in used},
                             {k: moving_points[k] for k in used})
    fle = float(fiducial_error_mm)
    pinned = [k for k in used if res[k] <= fle]
    moved = sorted(set(used) - set(pinned))
    if moved:
        notes.append("marker(s) " + ", ".join(f"{k} ({res[k]:.2f} mm)" for k in moved)
                     + f" moved beyond the localisation error ({fle:.2f} mm) against the "
                     "others: left out of the correlation mask")
    return pinned


def _set_loose(fixed, moving, init, walls, chest, notes, *, seeds, levels, balls, radius_mm,
               base=None):
    """The chest-wall transforms ``walls`` (one per sampling seed of ``seeds``), each with its
    loose directions set by a refinement from ``init`` with its seed over the mask and balls
    of ``radius_mm`` around the reference markers ``balls`` (a note says which and by how
    much, on average); without markers, by a refinement over ``base`` (the wall and the breast
    tissue at its base: gravity, across the body in every lying position, moves that tissue
    little along the body axis, the direction a torso's wall leaves loose); ``walls``
    themselves where the chest wall pins every direction, or where neither is there to set a
    loose one (a note says the registration is not determined along it). Markers sit
    on skin, which the breasts pull along in a tilted position (on the validation suite a
    coherent lateral shift of about 1 mm that leaves no residual), so they may not drive the
    directions the wall pins, nor a loose rotation: the drag turns them about the body axis
    (small-000's tilted position, sternum markers 1.4-1.6 mm sideways), and where a wall's
    turn about that axis came out loose (small-003's tilted position drawn without noise,
    sharpness 0.009) the markers set it 1.20 mm off, the wall 0.33 mm. Without a mask
    (``chest`` None), ``walls``."""
    if chest is None:
        return walls
    dirs = loose_directions(fixed, chest)
    if not dirs.loose.any():
        if balls:
            notes.append("the chest wall pins every rigid direction (weakest sharpness "
                         f"{dirs.ratios[0]:.3f}): the markers only check the registration")
        return walls
    turns = dirs.turns()
    if turns.loose.any():
        notes.append("the chest wall leaves " + "; ".join(turns.describe()) + " loose: "
                     "kept as the wall sets it (markers and the breasts' base move with the "
                     "skin, which gravity drags round the body)")
    dirs = dirs.translations()
    if not dirs.loose.any():
        return walls
    if not balls and base is None:
        notes.append("the chest wall leaves " + "; ".join(dirs.describe()) + " loose and "
                     "no rigid marker sets it: the registration is not determined along it "
                     "(add fiducials on the sternum or check it by eye)")
        return walls
    second = add_balls(chest, balls, radius_mm) if balls else base
    others = refine_rigid_seeds(fixed, moving, init, seeds, fixed_mask=second, **levels)
    out, shifts = zip(*(blend_loose(w, o, dirs) for w, (o, _) in zip(walls, others)))
    moved = float(np.mean(shifts))
    how = (f": set by the markers' refinement (moved {moved:.2f} mm)" if balls else
           " and no rigid marker sets it: set by the breasts' base (moved "
           f"{moved:.2f} mm); check it by eye or add fiducials on the sternum")
    notes.append("the chest wall leaves " + "; ".join(dirs.describe()) + " loose" + how)
    return list(out)


def _start(fixed, moving, fid, initial, notes, *, fixed_mask, shrink, smooth_mm, opts):
    """How the refinement starts, and its candidate starts (name, transform): the caller's
    (about the fiducials' centre), the fiducials', or, without either, three (a note says to
    check the result): a moments start refined over the whole body on the coarser levels,
    the moments start itself and the scanner's own frame (no motion), of which
    :func:`_best_refined` chooses by their chest-wall fits."""
    if initial is not None:
        return "given", [("given", _to_euler(initial, np.zeros(3) if fid is None
                                             else np.asarray(fid.GetCenter())))]
    if fid is not None:
        return "fiducials", [("fiducials", fid)]
    notes.append("falling back to a moments/multi-start initialisation: check the result")
    init = moments_transform(fixed, moving, fixed_mask=fixed_mask)
    # Coarse whole-image pass first: a chest wall alone can be nearly symmetric (e.g.
    # along the body axis), so far from the answer the whole body guides better.
    body, _ = refine_rigid(fixed, moving, init, fixed_mask=None, shrink=shrink[:-1] or shrink,
                           smooth_mm=smooth_mm[:-1] or smooth_mm, **opts)
    still = _to_euler(sitk.Transform(3, sitk.sitkIdentity), np.asarray(init.GetCenter()))
    return "moments", [("moments and the whole body", body), ("moments", init),
                       ("the scanner's frame", still)]


#: Without fiducials, a candidate start replaces the first (the moments refined over the whole
#: body) only where its chest-wall correlation is better by more than this. On the suite's
#: standard subjects without usable markers (small-007, -008, -010; 6 positions, truth labels)
#: the three starts' refined correlations lay within 0.0031 of each other while their TREs
#: differed by up to 1.7 mm (the correlation varies by about 0.004 over +-3 mm
#: along such a direction, "Where the errors left lie" in the README), and taking the best
#: of them made three of the six worse (small-007 prone 0.81 -> 1.81 mm, small-008 prone
#: 0.38 -> 1.11, small-010 tilted 0.12 -> 0.24); where the first start fails, as on the soft
#: band's small-soft-003, the difference was 0.17.
START_MARGIN = 0.02


def _best_refined(fixed, moving, starts, notes, fixed_mask, levels, seeds):
    """(start, the chest-wall refinements [(transform, correlation)] from it, one per sampling
    seed of ``seeds``): the first candidate start, or the one whose refinement with the
    first seed correlates better than the first's by more than :data:`START_MARGIN` (a note
    says which was kept where there were several). Breasts that deform draw the whole body's
    centroid and correlation: on a soft suite subject (torso, 0.5 kPa, markers slid 20 mm, so
    none used) the moments start refined over the body came to the wall 14 mm and 11 deg off
    (correlation -0.776), the scanner's frame to 1.4 mm (-0.950; the truth's transform
    refines to -0.951)."""
    if len(starts) == 1:
        return starts[0][1], refine_rigid_seeds(fixed, moving, starts[0][1], seeds,
                                                fixed_mask=fixed_mask, **levels)
    fits = [(name, start, *refine_rigid(fixed, moving, start, fixed_mask=fixed_mask,
                                        seed=seeds[0], **levels)) for name, start in starts]
    best = min(fits, key=lambda f: f[3])
    if best[3] > fits[0][3] - START_MARGIN:
        best = fits[0]
    others = ", ".join(f"{f[0]} {f[3]:.4f}" for f in fits if f is not best)
    notes.append(f"of {len(fits)} starts the chest-wall fit from {best[0]} was kept "
                 f"(correlation {best[3]:.4f}; {others}; another replaces the first only "
                 f"where better by {START_MARGIN})")
    rest = refine_rigid_seeds(fixed, moving, best[1], seeds[1:], fixed_mask=fixed_mask,
                              **levels) if len(seeds) > 1 else []
    return best[1], [(best[2], best[3]), *rest]
