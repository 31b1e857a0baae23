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

from registration.checks import check_registration, mask_points, predicted_tre
from registration.directions import blend_loose, loose_directions
from registration.initialise import _to_euler, landmark_transform, moments_transform
from registration.masks import add_balls, chest_wall_mask
from registration.qa import fiducial_residuals
from registration.refine import DEFAULT_SEED, _check_seed, refine_rigid
from registration.transforms import STAGE

__all__ = [
    "DEFAULT_SEED", "RigidResult", "add_balls", "check_registration", "chest_wall_mask",
    "landmark_transform", "mask_points", "moments_transform", "predicted_tre", "refine_rigid",
    "register_rigid",
]

log = logging.getLogger(__name__)

#: A refined transform that fails the fiducial check gives way to the fiducial-only one only
#: where it moves the least-moved marker by at least this share of the most-moved one's
#: shift (see :func:`_checked`).
COHERENT_SHIFT = 0.5


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
        loose directions were taken from the markers.
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
        The correlation's answer, whether or not it is ``transform``.
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


def register_rigid(
    fixed: sitk.Image, moving: sitk.Image, *,
    fixed_points: Mapping[str, np.ndarray] | None = None,
    moving_points: Mapping[str, np.ndarray] | None = None,
    fixed_mask: sitk.Image | None = None, initial: sitk.Transform | None = None,
    max_residual_mm: float = 3.0, marker_mask_mm: float = 8.0, fiducial_error_mm: float = 1.0,
    shrink: tuple[int, ...] = (4, 2, 1), smooth_mm: tuple[float, ...] = (2.0, 1.0, 0.0),
    iterations: int = 50, sampling: float = 0.1, learning_rate_mm: float = 0.5,
    fine_levels: int = 2, seed: int = DEFAULT_SEED, threads: int = 1,
    fiducial_fallback: bool = True, base_mask: sitk.Image | None = None,
) -> RigidResult:
    """Register ``moving`` onto ``fixed`` (the reference) rigidly, then check the result
    against the fiducial-only solution.

    Parameters
    ----------
    fixed, moving : SimpleITK.Image
        Reference and position volumes (preprocessed: bias-corrected, normalised).
    fixed_points, moving_points : mapping label -> (3,) mm, optional
        Fiducials of each volume in its own physical frame.
    fixed_mask : SimpleITK.Image, optional
        Chest-wall mask on the reference grid (:func:`chest_wall_mask`): drives the fit.
    initial : SimpleITK.Transform, optional
        A start that replaces the fiducial initialisation (the fiducials still check it).
    max_residual_mm : float
        Fiducial consistency threshold for the landmark initialisation.
    marker_mask_mm : float
        Radius of balls around the used reference fiducials (0: none), for those whose
        fiducial-only residual is within ``fiducial_error_mm`` (the others moved with the
        skin: a note names them). Where the chest wall leaves a direction loose (e.g. a
        torso's body axis, :func:`registration.directions.loose_directions`), a second
        refinement over the mask and these balls (without them, over ``base_mask``) sets it;
        every other direction stays the chest wall's (:func:`_set_loose`).
    fiducial_error_mm : float
        Fiducial localisation error (FLE) assumed at least, mm; the check allows more where
        the fiducial fit's residuals imply it higher (:func:`check_registration`).
    shrink, smooth_mm, iterations, sampling, learning_rate_mm, seed, threads
        Multi-resolution schedule (shrink factors, Gaussian sigmas in mm), optimiser
        iterations per level, fraction of mask voxels sampled, first step (mm), the sampling
        seed and the metric's threads; see :func:`refine_rigid`.
    fine_levels : int
        How many of the finest levels of at most :data:`MAX_VOXEL_MM` the masked chest-wall
        refinement runs (its start is close; a coarse level's optimum pulls along loose ones).
    fiducial_fallback : bool
        When the refined transform fails a check by moving every marker alike and differs
        from the fiducial-only one on the chest wall by more than the markers' error makes
        it 9 times in 10, return the fiducial-only one (``"fiducials"``, :func:`_checked`).
    base_mask : SimpleITK.Image, optional
        The wall and the breasts' base: sets loose directions without markers (see above).

    Returns
    -------
    RigidResult
        ``status`` "ok" (checks passed), "fiducials" or "flagged" (one failed, see
        ``warnings``), "unchecked" (no fiducials to check against).
    """
    _check_seed(seed)
    notes: list[str] = []
    fid, used = _fiducial_fit(fixed_points, moving_points, notes, max_residual_mm=max_residual_mm)
    opts = dict(iterations=iterations, sampling=sampling, learning_rate_mm=learning_rate_mm,
                seed=seed, threads=threads)
    how, starts = _start(fixed, moving, fid, initial, notes, fixed_mask=fixed_mask,
                         shrink=shrink, smooth_mm=smooth_mm, opts=opts)
    k = max(1, int(fine_levels))  # the start is close (fiducials, or moments + whole body)
    levels = dict(_fine(fixed, shrink[-k:], smooth_mm[-k:]), **opts)
    init, tfm, metric = _best_refined(fixed, moving, starts, notes, fixed_mask, levels)
    for n in notes:
        log.warning("%s: %s", STAGE, n)
    if fixed_mask is not None:
        pinned = [] if fid is None or marker_mask_mm <= 0 else _rigid_markers(
            fid, used, fixed_points, moving_points, notes, fiducial_error_mm=fiducial_error_mm)
        tfm = _set_loose(fixed, moving, init, tfm, fixed_mask, notes, levels=levels,
                         balls=[fixed_points[k] for k in pinned], radius_mm=marker_mask_mm,
                         base=base_mask)
    chosen, checks, status = _checked(tfm, fid, used, fixed_points, moving_points, notes,
                                      chest=fixed_mask, fiducial_error_mm=fiducial_error_mm,
                                      fallback=fiducial_fallback)
    res = fiducial_residuals(chosen, fixed_points or {}, moving_points or {})
    return RigidResult(chosen, how, res, used, metric, tuple(notes), status=status,
                       checks=checks, fiducial_transform=fid, refined_transform=tfm)


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


def _checked(tfm, fid, used, fixed_points, moving_points, notes, *, chest,
             fiducial_error_mm, fallback):
    """(the transform to use, :func:`_check`'s checks, status): the refined ``tfm`` when it
    passes; when it fails and ``fallback`` is set, the fiducial-only ``fid`` (status
    ``"fiducials"``, a note with its expected chest-wall error) if the two disagree at every
    marker alike (:data:`COHERENT_SHIFT`): the refinement slid as a whole. Where they
    disagree at one marker mostly, that marker moved with the skin and bent the fiducial
    fit, so the refined one is kept ("flagged", a note names the marker). It is kept too
    (flagged, with a note) where on the chest wall the two differ (mean over the wall) by no
    more than the fiducial-only fit would differ from a right one 9 times in 10 under the
    markers' localisation error (the 90th percentile of
    :func:`registration.checks.wall_difference_null`): nothing then shows that the
    refinement walked away.

    Measured (``bench/register_suite.py``, the demo's subject): the two suite positions that
    fail the check shift every marker alike (small-002 prone 1.72-1.90 mm, full-000's tilted
    position with its own segmentation 1.01-1.06 mm) and the fiducials are the better answer
    (chest-wall TRE 1.45 -> 0.91 mm and 1.17 -> 0.19 mm), as on small-002's tilted position
    since the localisation error comes from the markers' residuals (1.28-1.48 mm; max TRE
    1.88 -> 0.40 mm, truth labels, 2026-12-02); the demo's prone position shifts
    imf_left by 2.05 mm and the others by 0.11-0.43 mm, and there the refined transform is
    right (0.27 mm against the fiducials' 3.34 mm). On the wall, the suite's fallbacks
    differ from the markers' fit by 1.09-1.46 times that 90th percentile (small-002, truth
    labels, 2026-12-04); where the refined transform is right, by 0.65-0.71 times (the CI
    slice's small-003 tilted position, 0.94 mm against 1.32: max TRE 0.53 mm against the
    fiducials' 1.68; the unit tests' pipeline phantom with either schedule, 2.49-2.54 mm
    against 3.85: 0.79-0.84 mm against 3.78)."""
    checks, status = _check(tfm, fid, used, fixed_points, moving_points, notes,
                            chest=chest, fiducial_error_mm=fiducial_error_mm)
    if status != "flagged" or not fallback:
        return tfm, checks, status
    shift = checks["fiducial_shift_mm"]
    worst = max(shift, key=shift.get)
    if min(shift.values()) < COHERENT_SHIFT * shift[worst]:
        notes.append(f"the refined transform disagrees with the fiducials mostly at {worst!r} "
                     f"({shift[worst]:.2f} mm, the others {min(shift.values()):.2f}-"
                     f"{sorted(shift.values())[-2]:.2f} mm): that marker may have moved with "
                     "the skin; the refined transform is kept")
        log.warning("%s: %s", STAGE, notes[-1])
        return tfm, checks, status
    wall, null = checks.get("chest_wall_shift_mm"), checks.get("chest_wall_null_mm")
    if wall is not None and wall["mean"] <= null["p90"]:
        notes.append(f"the refined transform moves every marker alike, but on the chest wall "
                     f"it differs from the fiducial-only one by {wall['mean']:.2f} mm mean, "
                     "within what the markers' own localisation error gives 9 times in 10 "
                     f"were the refined transform right ({null['p90']:.2f} mm): nothing shows "
                     "that the refinement walked away; the refined transform is kept")
        log.warning("%s: %s", STAGE, notes[-1])
        return tfm, checks, status
    notes.append(_fallback_note(checks))
    log.warning("%s: %s", STAGE, notes[-1])
    return fid, checks, "fiducials"


def _fallback_note(checks: dict) -> str:
    """The warning that the fiducial-only transform replaces a refined one that failed."""
    exp, wall, null = (checks.get(k) for k in ("expected_tre_mm", "chest_wall_shift_mm",
                                               "chest_wall_null_mm"))
    where = ("" if exp is None else f" (on the chest wall the two differ by {wall['mean']:.2f} "
             f"mm mean, more than the {null['p90']:.2f} mm that the markers' localisation error "
             f"of {checks['fle_mm']:.2f} mm gives 9 times in 10), expected error on the chest "
             f"wall {exp['mean']:.2f} mm mean, {exp['max']:.2f} mm max")
    return ("the refinement moved every marker alike: using the fiducial-only transform "
            "instead of the refined one" + where
            + " ([register] fiducial_fallback = false keeps the refined one)")


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


def _set_loose(fixed, moving, init, wall, chest, notes, *, levels, balls, radius_mm,
               base=None):
    """The chest-wall transform ``wall`` with its loose directions set by a refinement over
    the mask and balls of ``radius_mm`` around the reference markers ``balls`` (a note says
    which and by how much); without markers, by a refinement over ``base`` (the wall and the
    breast tissue at its base: gravity, across the body in every lying position, moves
    that tissue little along the body axis, the direction a torso's wall leaves loose);
    ``wall`` itself where the chest wall pins every direction, or where neither is there to
    set a loose one (a note says the registration is not determined along it). Markers sit
    on skin, which the breasts pull along in a tilted position (on the validation suite a
    coherent lateral shift of about 1 mm that leaves no residual), so they may not drive the
    directions the wall pins, nor a loose rotation: the drag turns them about the body axis
    (small-000's tilted position, sternum markers 1.4-1.6 mm sideways), and where a wall's
    turn about that axis came out loose (small-003's tilted position drawn without noise,
    sharpness 0.009) the markers set it 1.20 mm off, the wall 0.33 mm."""
    dirs = loose_directions(fixed, chest)
    if not dirs.loose.any():
        if balls:
            notes.append("the chest wall pins every rigid direction (weakest sharpness "
                         f"{dirs.ratios[0]:.3f}): the markers only check the registration")
        return wall
    turns = dirs.turns()
    if turns.loose.any():
        notes.append("the chest wall leaves " + "; ".join(turns.describe()) + " loose: "
                     "kept as the wall sets it (markers and the breasts' base move with the "
                     "skin, which gravity drags round the body)")
    dirs = dirs.translations()
    if not dirs.loose.any():
        return wall
    if not balls and base is None:
        notes.append("the chest wall leaves " + "; ".join(dirs.describe()) + " loose and "
                     "no rigid marker sets it: the registration is not determined along it "
                     "(add fiducials on the sternum or check it by eye)")
        return wall
    second = add_balls(chest, balls, radius_mm) if balls else base
    other, _ = refine_rigid(fixed, moving, init, fixed_mask=second, **levels)
    out, moved = blend_loose(wall, other, dirs)
    how = (f": set by the markers' refinement (moved {moved:.2f} mm)" if balls else
           " and no rigid marker sets it: set by the breasts' base (moved "
           f"{moved:.2f} mm); check it by eye or add fiducials on the sternum")
    notes.append("the chest wall leaves " + "; ".join(dirs.describe()) + " loose" + how)
    return out


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


def _best_refined(fixed, moving, starts, notes, fixed_mask, levels):
    """(start, refined transform, correlation) of the first candidate start, or of the one
    whose chest-wall refinement correlates better than it by more than
    :data:`START_MARGIN` (a note says which was kept where there were several). Breasts that
    deform draw the whole body's centroid and correlation: on a soft suite subject (torso,
    0.5 kPa, markers slid 20 mm, so none used) the moments start refined over the body came
    to the wall 14 mm and 11 deg off (correlation -0.776), the scanner's frame to 1.4 mm
    (-0.950; the truth's transform refines to -0.951)."""
    fits = [(name, start, *refine_rigid(fixed, moving, start, fixed_mask=fixed_mask, **levels))
            for name, start in starts]
    best = min(fits, key=lambda f: f[3])
    if best[3] > fits[0][3] - START_MARGIN:
        best = fits[0]
    if len(fits) > 1:
        others = ", ".join(f"{f[0]} {f[3]:.4f}" for f in fits if f is not best)
        notes.append(f"of {len(fits)} starts the chest-wall fit from {best[0]} was kept "
                     f"(correlation {best[3]:.4f}; {others}; another replaces the first only "
                     f"where better by {START_MARGIN})")
    return best[1], best[2], best[3]


def _check(tfm, fid, used, fixed_points, moving_points, notes, *, chest,
           fiducial_error_mm) -> tuple[dict, str]:
    """:func:`check_registration` of ``tfm`` against the fiducial-only ``fid`` on the used
    fiducials and the chest-wall mask's points: (checks, status), each failure logged and
    noted; ``({}, "unchecked")`` without ``fid``."""
    if fid is None:
        notes.append("no consistent fiducials to check the registration against: unchecked")
        return {}, "unchecked"
    pts = {k: fixed_points[k] for k in used}
    checks = check_registration(
        tfm, fid, pts, fiducial_residuals(fid, pts, {k: moving_points[k] for k in used}),
        chest_points=None if chest is None else mask_points(chest),
        fiducial_error_mm=fiducial_error_mm,
    )
    for w in checks["failures"]:
        log.warning("%s: %s", STAGE, w)
        notes.append(w)
    return checks, "ok" if checks["passed"] else "flagged"
