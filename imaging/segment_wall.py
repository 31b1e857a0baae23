"""What the muscle's region takes in front of the chest wall, given back to the breast
(:mod:`imaging.segment`): glands thicker than the wall that sit on its front, and the
breast's skin at the breast's rim (the wedge where skin meets the wall's front at a shallow
angle, and skin over a breast the contour climbed from there). Both find the wall by its
depth from its back along the posterior axis."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from imaging.segment_regions import _components, bounding_box

#: Largest volume (voxels) whose glands are found on its own grid: on bench/mri.py's 256^3
#: phantom (11 M voxels cropped) the three distance maps took 4.8 of the segmentation's 26 s;
#: on a 2 mm grid the blobs lose about one fine voxel of their rim (suite: breast Dice -0.004
#: to -0.009 where glands touch the wall).
GLAND_FINE_MAX_VOXELS = 4_000_000


def glands_off_muscle(muscle: np.ndarray, body: np.ndarray, thorax: np.ndarray,
                      spacing_zyx: np.ndarray, *, min_mm3: float, thickness_factor: float = 1.6,
                      breast_share: float = 0.8, grid_mm: float = 2.0,
                      posterior: tuple[int, bool] = (1, False)
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Take off the muscle the glands that touch it (on a volume of more than
    :data:`GLAND_FINE_MAX_VOXELS`, found on a grid of about ``grid_mm``: every k-th voxel
    along an axis with spacing ``grid_mm / k``; the blobs then take the muscle's voxels of
    their coarse cells).

    Where a gland meets the chest wall and is as bright as the muscle (fat suppressed) or
    joins it through the partial volume of its rim, the muscle's region takes the gland in
    (on the validation suite: 9248 of 9248 gland voxels on one subject). The chest wall is a
    sheet; a gland is a blob on the sheet's front. So: the sheet's half thickness is the
    median of the muscle's distance map at its ridge; the parts of the muscle that hold a
    ball of ``thickness_factor`` times that radius (an opening, by two distance maps) and
    that lie more than a wall's thickness from the wall's back (thorax interior, air, the
    field of view's edge), and whose surroundings outside the muscle are breast tissue for
    at least ``breast_share`` (not a thick stretch of the wall itself), are blobs, taken off
    with the partial-volume rim the muscle drew round them, and with what of the muscle near
    them lies beyond a wall's thickness from the wall's back counted along the posterior
    axis ``posterior`` (array axis, whether its index grows anterior: see
    :func:`imaging.segment_contrast._posterior_axis`; default an LPS volume's y), so that a
    gland reaching the skin comes off whole.

    Returns
    -------
    (muscle, blobs)
        The muscle less the blobs, and the blobs (to be breast tissue; gland when labelled).
    """
    sp = np.asarray(spacing_zyx, float)
    k = np.maximum(1, np.round(grid_mm / sp)).astype(int)
    if (k > 1).any() and muscle.size > GLAND_FINE_MAX_VOXELS:  # seconds per distance map
        sl = tuple(slice(None, None, int(j)) for j in k)
        coarse = _glands_off(muscle[sl], body[sl], thorax[sl], sp * k, min_mm3=min_mm3,
                             thickness_factor=thickness_factor, breast_share=breast_share,
                             posterior=posterior)
        blobs = coarse
        for axis, j in enumerate(k):
            blobs = np.repeat(blobs, j, axis=axis)
        blobs = blobs[: muscle.shape[0], : muscle.shape[1], : muscle.shape[2]] & muscle
        return muscle & ~blobs, blobs
    blobs = _glands_off(muscle, body, thorax, sp, min_mm3=min_mm3,
                        thickness_factor=thickness_factor, breast_share=breast_share,
                        posterior=posterior)
    return muscle & ~blobs, blobs


def _glands_off(muscle, body, thorax, sp, *, min_mm3, thickness_factor, breast_share,
                posterior=(1, False)):
    """:func:`glands_off_muscle` on one grid; returns the blobs."""
    none = np.zeros(muscle.shape, bool)
    dt = ndimage.distance_transform_edt(muscle, sampling=sp)
    half = _wall_half(dt, sp, posterior[0])
    if half is None:
        return none
    r = thickness_factor * half
    core = _opening(dt, r, sp)
    if not core.any():
        return none
    # under a broad gland the balls reach through the wall: keep what lies beyond a wall's
    # thickness from the wall's back (thorax interior, air, the field of view's edge)
    back = np.pad(~muscle & ~(body & ~thorax), 1, constant_values=True)
    from_back = ndimage.distance_transform_edt(~back, sampling=sp)[1:-1, 1:-1, 1:-1]
    front = core & (from_back > 2.0 * half)  # in front of the wall
    lab, n = _components(core & (from_back > 2.0 * half + float(sp.max())))
    if n == 0:
        return none
    # a blob's size is that of its part in front of the wall, not of its tip past a voxel
    # more: on the family's T1 slab small-048 (2 mm voxels, a 4-voxel wall) the glands' tips
    # held 360 and 424 mm^3, and both glands stayed in the muscle
    flab = _components(front)[0]
    tip_front = np.zeros(n + 1, np.int64)
    tip_front[lab[lab > 0]] = flab[lab > 0]  # every tip lies in front
    sizes = np.bincount(flab.ravel())[tip_front] * float(np.prod(sp))
    sizes[0] = 0.0
    breast = body & ~thorax & ~muscle
    ring = ndimage.binary_dilation(lab > 0, iterations=2) & ~muscle
    near = ndimage.distance_transform_edt(lab == 0, sampling=sp, return_distances=False,
                                          return_indices=True)
    owner = lab[tuple(near)][ring]  # the blob each surrounding voxel belongs to
    n_ring = np.bincount(owner, minlength=n + 1)
    n_breast = np.bincount(owner[breast[ring]], minlength=n + 1)
    keep = (sizes >= min_mm3) & (n_breast >= breast_share * np.maximum(n_ring, 1))
    keep[0] = False
    if not keep.any():
        return none
    hit = np.zeros(flab.max() + 1, bool)
    hit[np.unique(flab[keep[lab]])] = True
    hit[0] = False
    blobs = hit[flab]
    rest = muscle & ~blobs  # the rim: what of the rest near a blob is thinner than the sheet
    thin = ~_opening(ndimage.distance_transform_edt(rest, sampling=sp), 0.5 * half, sp)
    around = ndimage.distance_transform_edt(~blobs, sampling=sp) <= r + 2.0 * float(sp.max())
    blobs |= rest & thin & around
    # and what of the rest near a blob lies beyond a wall's thickness from the wall's back
    # counted along the posterior axis (a gland that reaches the skin is near the air in
    # front of it, which is not the wall's back), joined to the blob
    wall = _wall_along(muscle, back[1:-1, 1:-1, 1:-1], sp, posterior,
                       2.0 * half + float(sp.max()))
    glab = _components(muscle & ~wall & around | blobs)[0]
    return np.isin(glab, np.unique(glab[blobs])) & (glab > 0)


#: Depth below the air (mm) within which muscle beyond the wall's thickness (or in front of
#: breast tissue), touching the breast, is the breast's skin (:func:`skin_rim_off_muscle`):
#: the skin is 1.5-2 mm thick on the suite's half-size phantoms, 2 on the full-size
#: full-000, and a voxel of partial volume lies over it.
SKIN_RIM_MM = 3.0

#: Voxels of breast tissue (a run along the posterior axis) that must lie between a climbed
#: skin and the wall behind it (:func:`_in_front_of_breast`): a hole of one voxel in a thin
#: wall's end is not breast (seed 9's rendered slab: with 1 the rule took 113 of the truth's
#: muscle voxels, with 2 none); full-000's tilted skin left uncovered: 2.4 % with 2, 5.1 %
#: with 3 (17.9 % without the rule).
SKIN_FAT_RUN = 2


def skin_rim_off_muscle(muscle: np.ndarray, body: np.ndarray, thorax: np.ndarray,
                        air: np.ndarray, breast: np.ndarray, spacing_zyx: np.ndarray, *,
                        posterior: tuple[int, bool] = (1, False),
                        skin_mm: float = SKIN_RIM_MM) -> tuple[np.ndarray, np.ndarray]:
    """Give the breast back the skin the muscle took at the breast's rim.

    Where the breast's skin meets the chest wall's front at a shallow angle, the breast is
    skin alone for a few voxels, and skin is as bright as muscle (fat suppressed): the
    muscle's active contour takes that wedge in, and a model built on it has a ring of muscle
    around each breast's base (on the suite's slabs 480-630 voxels a scan, which alone made
    the fitted modulus 12 % soft on one). The wedge lies in front of the wall: its voxels
    are the muscle's that lie beyond the wall's thickness plus one voxel from the wall's
    back, counted along the posterior axis ``posterior`` in a run of muscle that starts at
    the back, and within ``skin_mm`` of the air, in pieces that touch ``breast`` (the wall's
    free front between the breasts is near the air but not beyond the wall; its stretches
    thicker than the median are beyond it but not near the air: both stay muscle). On
    voxels coarser than half ``skin_mm`` along that axis nothing of a skin lies past the
    margin, and nothing is taken: on the suite's 2 mm coil at SNR 13 the rule took 76-91
    voxels of air the muscle's edge had drawn in, gave them to the breast, and its tilted
    registration moved 0.67 -> 1.21 mm from the truth.

    So is the skin over a breast that the muscle's contour climbed from the wedge: muscle
    voxels within ``skin_mm`` of the air with breast tissue behind them along the posterior
    axis (a run of at least two voxels) and muscle behind that (:func:`_in_front_of_breast`),
    in the same pieces. The chest wall has nothing but itself and the back behind it. On
    the full-size slab full-000 (D cup, fat suppressed, 1 mm) the contour had climbed the
    skin of both breasts' lower poles: in the tilted scan 33k voxels of the truth's breast
    were muscle, most of them such skin; the measured skin lost them (and the faces within
    a voxel of them: 18 % of the truth's skin more than 3 mm from it) and the held-out
    tilted MHD read 2.54 mm with the model's gland centres within 0.11 mm of the truth's.

    Returns
    -------
    (muscle, rim)
        The muscle less the rim, and the rim (to be breast tissue).
    """
    sp = np.asarray(spacing_zyx, float)
    none = np.zeros(muscle.shape, bool)
    if sp[posterior[0]] > 0.5 * skin_mm:  # no voxel of skin would lie past the margin
        return muscle, none
    # one box for both distance maps: grown past skin_mm (near the air) and by at least
    # one voxel (the muscle's own map)
    box = bounding_box(muscle, np.ceil(skin_mm / sp).astype(int) + 1)
    if box is None or not air.any():
        return muscle, none
    half = _wall_half(ndimage.distance_transform_edt(muscle[box], sampling=sp), sp,
                      posterior[0])
    if half is None:
        return muscle, none
    tissue = body & ~thorax
    depth = _depth_from_back(muscle, ~muscle & ~tissue, sp, posterior)
    near_air = _near(air, box, sp, skin_mm)
    # beyond the wall's thickness in a run from the back, or in front of breast tissue that
    # lies in front of muscle
    wedge = np.isfinite(depth) & (depth > 2.0 * half + float(sp[posterior[0]]))
    beyond = muscle & near_air & (wedge | _in_front_of_breast(muscle, tissue, posterior,
                                                              SKIN_FAT_RUN))
    lab, n = _components(beyond)
    touch = np.zeros(n + 1, bool)
    touch[np.unique(lab[ndimage.binary_dilation(breast) & beyond])] = True
    touch[0] = False
    rim = touch[lab]
    return muscle & ~rim, rim


def _near(mask: np.ndarray, box: tuple[slice, ...], sp: np.ndarray, mm: float) -> np.ndarray:
    """Voxels of ``box`` within ``mm`` of ``mask`` (False elsewhere): exact inside a box
    grown by more than ``mm`` around the voxels asked about."""
    out = np.zeros(mask.shape, bool)
    sub = mask[box]
    if sub.any():
        out[box] = ndimage.distance_transform_edt(~sub, sampling=sp) <= mm
    return out


def skin_rim_off(r: dict, sp: np.ndarray, notes: list, *,
                 posterior: tuple[int, bool]) -> None:
    """The breast's skin the muscle took at the breast's rim goes back to the breast
    (:func:`skin_rim_off_muscle`), in place (the caller leaves it out where a user's muscle
    seed has the last word)."""
    breast = r["body"] & ~r["thorax"] & ~r["muscle"] & ~r["marker_mask"]
    muscle, rim = skin_rim_off_muscle(r["muscle"], r["body"], r["thorax"], r["air"], breast,
                                      sp, posterior=posterior)
    if not rim.any():
        return
    r["muscle"], r["muscle_start"] = muscle, r["muscle_start"] & ~rim
    notes.append(f"{float(np.count_nonzero(rim) * np.prod(sp)) / 1000.0:.2f} ml of skin at "
                 "the breasts' rim taken off the muscle (in front of the wall, under the air)")


def _wall_half(dt, sp, axis) -> float | None:
    """The chest wall's half thickness (mm): the median of the muscle's distance map ``dt``
    at its ridge (:func:`_half_thickness`); None without a ridge."""
    ridge = (dt > 0) & (dt >= ndimage.maximum_filter(dt, size=3))
    if not ridge.any():
        return None
    return float(np.median(_half_thickness(dt, ridge, sp, axis)))


def _half_thickness(dt, ridge, sp, axis):
    """Half the sheet's thickness at each ridge voxel (mm), along ``axis`` (the sheet's
    normal, about). A distance map counts to the nearest outside voxel's centre: a sheet of
    an even number n of voxels reads n / 2 on its two middle planes, an odd one (n + 1) / 2
    on its single middle plane, half a voxel too many. Uncorrected, the 5-voxel wall of the
    suite's slab small-001 (1.5 mm voxels) read 4.5 mm for 3.75, and its glands, 7-9
    voxels thick on it, held no ball of 1.6 times that: every gland stayed in the muscle."""
    twin = np.zeros(dt.shape, bool)  # a ridge neighbour of equal depth along the axis
    r, d, t = (np.moveaxis(x, axis, 0) for x in (ridge, dt, twin))  # views
    pair = r[1:] & r[:-1] & (d[1:] == d[:-1])
    t[1:] |= pair
    t[:-1] |= pair
    return dt[ridge] - 0.5 * float(sp[axis]) * ~twin[ridge]


def _wall_along(muscle, back, sp, posterior, depth_mm):
    """The muscle's voxels within ``depth_mm`` of the wall's back along the posterior axis
    (``posterior`` = (array axis, index grows anterior)): those whose run of muscle voxels
    toward the back starts at ``back`` (or the field of view's edge) no more than
    ``depth_mm`` away."""
    return _depth_from_back(muscle, back, sp, posterior) <= depth_mm


def _in_front_of_breast(muscle: np.ndarray, tissue: np.ndarray,
                        posterior: tuple[int, bool], run: int) -> np.ndarray:
    """Voxels with, behind them along the posterior axis, a run of at least ``run`` voxels
    of ``tissue`` that is not muscle, with muscle further behind it: breast tissue in front
    of the wall. Neither a rim of the body behind the wall (air behind it) nor a hole shorter
    than ``run`` in the wall (noise at a thin slab's ends) counts."""
    shape = [1] * muscle.ndim
    shape[posterior[0]] = max(1, run)  # a line along the posterior axis
    t = _back_first(ndimage.binary_erosion(tissue & ~muscle, structure=np.ones(shape, bool)),
                    posterior)
    m = _back_first(muscle, posterior)

    def behind(x):  # any voxel of x at a smaller index (further back)
        acc = np.logical_or.accumulate(x, axis=0)
        return np.concatenate([np.zeros((1,) + x.shape[1:], bool), acc[:-1]])

    return _from_back_first(behind(t & behind(m)), posterior)


def _back_first(x: np.ndarray, posterior: tuple[int, bool]) -> np.ndarray:
    """A view of ``x`` with the posterior axis first, its index growing from the back to
    the front."""
    axis, anterior = posterior
    x = np.moveaxis(x, axis, 0)
    return x if anterior else x[::-1]


def _from_back_first(x: np.ndarray, posterior: tuple[int, bool]) -> np.ndarray:
    """The inverse of :func:`_back_first`."""
    axis, anterior = posterior
    return np.moveaxis(x if anterior else x[::-1], 0, axis)


def _depth_from_back(muscle, back, sp, posterior):
    """Depth (mm) of each muscle voxel in its run of muscle voxels along the posterior axis,
    counted from the run's start when that start lies on ``back`` (or the field of view's
    edge); inf elsewhere (outside the muscle, or a run that starts elsewhere)."""
    m, b = _back_first(muscle, posterior), _back_first(back, posterior)
    n = m.shape[0]
    idx = np.arange(n).reshape((n,) + (1,) * (m.ndim - 1))
    starts = m & ~np.concatenate([np.zeros((1,) + m.shape[1:], bool), m[:-1]])
    start = np.maximum.accumulate(np.where(starts, idx, -1), axis=0)
    behind = np.concatenate([np.ones((1,) + m.shape[1:], bool), b[:-1]])  # edge = back
    from_back = np.take_along_axis(behind, np.maximum(start, 0), axis=0)
    depth = np.where(m & from_back, (idx - start + 1) * float(sp[posterior[0]]), np.inf)
    return _from_back_first(depth, posterior)


def _opening(dt: np.ndarray, radius: float, sp: np.ndarray) -> np.ndarray:
    """Morphological opening by a ball of ``radius`` mm of the region whose distance map is
    ``dt``: the voxels within ``radius`` of one deeper than ``radius`` (none if none is; a
    distance map of an array without a zero is not defined)."""
    deep = dt > radius
    if not deep.any():
        return np.zeros(dt.shape, bool)
    return (dt > 0) & (ndimage.distance_transform_edt(~deep, sampling=sp) <= radius)
