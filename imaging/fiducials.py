"""Fiducial skin markers: detection (Laplacian-of-Gaussian blobs outside the body), sub-voxel
localisation (least-squares fit of a blurred-sphere model) and labelling, either by the
subject's ``fiducials.csv`` (nearest labelled point) or by anatomy (sternum upper/lower,
left/right inframammary fold).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np
import SimpleITK as sitk
from scipy import ndimage, optimize, special

from imaging.preprocess import check_volume, foreground_mask

STAGE = "fiducials"
log = logging.getLogger(__name__)

#: Labels given by :func:`anatomical_labels` to four markers.
ANATOMICAL_LABELS = ("sternum_upper", "sternum_lower", "imf_left", "imf_right")


def _index_to_physical(img: sitk.Image, ijk: np.ndarray) -> np.ndarray:
    """(K,3) continuous (i,j,k) indices -> (K,3) physical LPS mm."""
    d = np.asarray(img.GetDirection(), float).reshape(3, 3)
    return np.asarray(img.GetOrigin()) + (ijk * np.asarray(img.GetSpacing())) @ d.T


#: A component of the opened foreground this many times a marker's volume or larger is
#: body, not a marker: the opening also cuts a thin muscle slab meeting air, which leaves
#: each breast a component of its own (and took every bright blob in all but the largest
#: for a marker).
BODY_PART_MARKER_VOLUMES = 50.0


def body_without_markers(fg: np.ndarray, *, spacing: np.ndarray, diameter_mm: float) -> np.ndarray:
    """The foreground after an opening that erases marker-sized blobs: its components of at
    least :data:`BODY_PART_MARKER_VOLUMES` marker volumes (always the largest).

    Parameters
    ----------
    fg : (nz, ny, nx) bool
        Foreground mask.
    spacing : (3,) float
        Voxel size (x, y, z) in mm.
    diameter_mm : float
        Marker diameter in mm; the opening ball is a bit larger so markers vanish.
    """
    r = 0.5 * diameter_mm + 1.0
    rad = [max(1, int(np.ceil(r / s))) for s in spacing]
    out = np.zeros(fg.shape, bool)
    if not fg.any():
        return out
    # Only the foreground's box (plus the ball) can change: open that part alone.
    pad = np.asarray(rad[::-1]) + 1
    ext = [np.flatnonzero(fg.any(axis=tuple(j for j in range(3) if j != i))) for i in range(3)]
    lo = np.maximum([e[0] - p for e, p in zip(ext, pad)], 0)
    hi = np.minimum([e[-1] + p + 1 for e, p in zip(ext, pad)], fg.shape)
    sl = tuple(slice(a, b) for a, b in zip(lo, hi))
    m = sitk.GetImageFromArray(fg[sl].astype(np.uint8))
    m.SetSpacing(tuple(float(s) for s in spacing))
    opened = sitk.BinaryMorphologicalOpening(m, rad, sitk.sitkBall, 0, 1)
    cc = sitk.GetArrayFromImage(sitk.RelabelComponent(sitk.ConnectedComponent(opened),
                                                      sortByObjectSize=True))
    sizes = np.bincount(cc.ravel()) * float(np.prod(spacing))
    big = sizes >= BODY_PART_MARKER_VOLUMES * np.pi / 6.0 * diameter_mm ** 3
    big[0], big[1:2] = False, True
    out[sl] = big[cc]
    return out


def _sphere_model(p, pts, spacing2):
    c, r, a, b, s = p[:3], p[3], p[4], p[5], p[6]
    dist = np.sqrt(((pts - c) ** 2).sum(axis=1))
    # voxel averaging adds spacing^2/12 to the blur variance
    sig = np.sqrt(s * s + spacing2 / 12.0)
    return a + b * 0.5 * special.erfc((dist - r) / (np.sqrt(2.0) * sig))


def localise_marker(
    arr: np.ndarray,
    ijk: np.ndarray,
    *,
    spacing: np.ndarray,
    diameter_mm: float,
    exclude: np.ndarray | None = None,
) -> np.ndarray:
    """Sub-voxel centre (index units, x/y/z order) of one bright sphere near ``ijk``.

    Fits intensity = a + b * blurred-ball(centre, radius) by least squares on the voxels of
    a window around the candidate, skipping ``exclude`` voxels (the body), so a marker that
    touches the skin is fitted on its free side without bias.
    """
    spacing = np.asarray(spacing, float)
    half = np.ceil((0.5 * diameter_mm + 3.0 * spacing.max()) / spacing).astype(int)
    lo = np.maximum(np.round(ijk).astype(int) - half, 0)
    hi = np.minimum(np.round(ijk).astype(int) + half + 1, np.array(arr.shape[::-1]))
    win = arr[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]].astype(float)
    k, j, i = np.mgrid[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    keep = np.ones(win.shape, bool)
    if exclude is not None:
        keep &= ~exclude[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
    pts = np.stack([i[keep], j[keep], k[keep]], axis=1) * spacing  # mm in index frame
    vals = win[keep]
    if len(vals) < 20:
        return np.asarray(ijk, float)
    c0 = np.asarray(ijk, float) * spacing
    p0 = [*c0, 0.5 * diameter_mm, float(np.percentile(vals, 10)),
          float(vals.max() - np.percentile(vals, 10)), 0.5]
    spacing2 = float(np.mean(spacing ** 2))
    res = optimize.least_squares(
        lambda p: _sphere_model(p, pts, spacing2) - vals, p0, method="trf",
        bounds=([-np.inf] * 3 + [0.2 * diameter_mm, -np.inf, 0.0, 0.05],
                [np.inf] * 3 + [2.0 * diameter_mm, np.inf, np.inf, 3.0]),
        x_scale="jac",
    )
    c = res.x[:3] / spacing
    if np.linalg.norm((c - ijk) * spacing) > diameter_mm:  # fit ran away: keep the LoG peak
        return np.asarray(ijk, float)
    return c


def _log_peaks(
    f: sitk.Image, cand: np.ndarray, *, sigma: float, size: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima of the scale-normalised LoG response at ``cand`` voxels.

    The response is computed only in windows around the connected groups of candidates
    (padded so that the filter and the local-maximum test see no window edge): markers
    are a few small blobs, and the LoG of a whole 256^3 volume cost ~3 s for them.

    Returns
    -------
    (K, 3) int (z, y, x) indices and (K,) responses
    """
    spacing_zyx = np.asarray(f.GetSpacing(), float)[::-1]
    pad = np.ceil(4.0 * sigma / spacing_zyx).astype(int) + size // 2 + 1
    lab, n = ndimage.label(cand)
    idx, val = [np.zeros((0, 3), int)], [np.zeros(0)]
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is None:
            continue
        lo = np.maximum([s.start for s in sl] - pad, 0)
        hi = np.minimum([s.stop for s in sl] + pad, cand.shape)
        sub = sitk.RegionOfInterest(f, [int(v) for v in (hi - lo)[::-1]],
                                    [int(v) for v in lo[::-1]])
        resp = -sitk.GetArrayFromImage(sitk.LaplacianRecursiveGaussian(sub, sigma=sigma))
        resp *= sigma * sigma  # scale-normalised, positive on bright blobs
        win = tuple(slice(a, b) for a, b in zip(lo, hi))
        # separable box maximum (scipy) is much cheaper than a grey dilation
        peaks = ((resp >= ndimage.maximum_filter(resp, size=tuple(size))) & (resp > 0)
                 & (lab[win] == k))
        idx.append(np.argwhere(peaks) + lo)
        val.append(resp[peaks])
    return np.concatenate(idx), np.concatenate(val)


def detect_markers(
    img: sitk.Image,
    *,
    diameter_mm: float = 4.0,
    n_expected: int | None = 4,
    min_contrast: float = 0.5,
    localise: bool = True,
    foreground: np.ndarray | None = None,
    body: np.ndarray | None = None,
) -> np.ndarray:
    """Find bright spherical skin markers and return their centres.

    Parameters
    ----------
    img : SimpleITK.Image
        Scalar 3-D MRI volume (raw or preprocessed).
    diameter_mm : float
        Nominal marker diameter in mm (sets the LoG scale r/sqrt(3) and the fit window).
    n_expected : int, optional
        Keep at most this many (the strongest responses).
    min_contrast : float
        A candidate's peak intensity must exceed the body's median by this fraction of the
        body's 99th percentile above its median (rejects dim noise blobs).
    localise : bool
        Refine each centre to sub-voxel accuracy (False: voxel centres, faster).
    foreground, body : (nz, ny, nx) bool, optional
        Foreground (default: Otsu) and the body without markers (default:
        :func:`body_without_markers` of the foreground), when the caller has them already.

    Returns
    -------
    (K, 3) float ndarray
        Marker centres in physical LPS mm, strongest first.
    """
    check_volume(img, stage=STAGE)
    f = sitk.Cast(img, sitk.sitkFloat32)
    spacing = np.asarray(f.GetSpacing(), float)
    arr = sitk.GetArrayViewFromImage(f)
    fg = (sitk.GetArrayFromImage(foreground_mask(f)).astype(bool) if foreground is None
          else np.asarray(foreground, bool))
    if body is None:
        body = body_without_markers(fg, spacing=spacing, diameter_mm=diameter_mm)
    sigma = 0.5 * diameter_mm / np.sqrt(3.0)
    size = np.maximum(3, 2 * np.round(0.5 * diameter_mm / spacing[::-1]).astype(int) + 1)
    cand = fg & ~body
    if body.any():
        vals = arr[body]
        vals = vals[:: max(1, vals.size // 2_000_000)]  # a strided sample is plenty
        med, top = float(np.median(vals)), float(np.percentile(vals, 99))
        cand &= arr > med + min_contrast * (top - med)
    kji, resp = _log_peaks(f, cand, sigma=sigma, size=size)
    kji = kji[np.argsort(-resp, kind="stable")]
    if n_expected is not None:
        kji = kji[: 3 * n_expected]  # a few spare candidates for the distance check below
    # Enforce one peak per marker (plateaus can give neighbours).
    chosen: list[np.ndarray] = []
    for c in kji:
        if all(np.linalg.norm((c - o) * spacing[::-1]) > diameter_mm for o in chosen):
            chosen.append(c)
    if n_expected is not None:
        chosen = chosen[:n_expected]
    if not localise:
        return _index_to_physical(f, np.asarray([c[::-1] for c in chosen], float).reshape(-1, 3))
    centres = []
    for c in chosen:
        # the body near this marker only (a whole-volume dilation costs ~1 s per volume)
        half = np.ceil((0.5 * diameter_mm + 3.0 * spacing.max()) / spacing[::-1]).astype(int) + 2
        lo, hi = np.maximum(c - half, 0), np.minimum(c + half + 1, body.shape)
        near = np.zeros(body.shape, bool)
        win = tuple(slice(a, b) for a, b in zip(lo, hi))
        near[win] = ndimage.binary_dilation(body[win])
        centres.append(localise_marker(arr, c[::-1].astype(float), spacing=spacing,
                                       diameter_mm=diameter_mm, exclude=near))
    if not centres:
        return np.zeros((0, 3))
    return _index_to_physical(f, np.asarray(centres))


def anatomical_labels(points: np.ndarray) -> dict[str, np.ndarray]:
    """Label markers by anatomy so that the same marker gets the same label in every position.

    Four markers: the lowest and highest x (LPS: x -> patient left) are the right and left
    inframammary-fold markers, the other two are the sternum markers sorted by z (upper has
    the larger z). Other counts: ``m0, m1, ...`` in order of z then x.

    Parameters
    ----------
    points : (K, 3) float
        Marker centres in mm.
    """
    pts = np.asarray(points, float)
    if len(pts) == 4:
        ox = np.argsort(pts[:, 0])
        mid = ox[1:3]
        mid = mid[np.argsort(-pts[mid, 2])]
        return {
            "sternum_upper": pts[mid[0]].copy(),
            "sternum_lower": pts[mid[1]].copy(),
            "imf_left": pts[ox[3]].copy(),
            "imf_right": pts[ox[0]].copy(),
        }
    order = np.lexsort((pts[:, 0], pts[:, 2]))
    return {f"m{i}": pts[k].copy() for i, k in enumerate(order)}


def label_by_reference(
    points: np.ndarray, reference: Mapping[str, np.ndarray], *, max_distance_mm: float = 15.0
) -> dict[str, np.ndarray]:
    """Give each detected marker the label of the nearest listed fiducial (one-to-one).

    Detected markers farther than ``max_distance_mm`` from every listed fiducial stay
    unlabelled (dropped, with a warning); so do listed labels that find no marker.
    """
    from scipy.optimize import linear_sum_assignment

    labels = list(reference)
    if not labels or len(points) == 0:
        return {}
    ref = np.asarray([reference[k] for k in labels], float)
    pts = np.asarray(points, float)
    d = np.linalg.norm(pts[:, None, :] - ref[None, :, :], axis=2)
    rows, cols = linear_sum_assignment(d)
    out = {}
    for r, c in zip(rows, cols):
        if d[r, c] <= max_distance_mm:
            out[labels[c]] = pts[r].copy()
    missing = sorted(set(labels) - set(out))
    if missing:
        log.warning("%s: no detected marker within %.0f mm of listed fiducial(s) %s",
                    STAGE, max_distance_mm, missing)
    return out


def find_fiducials(
    img: sitk.Image,
    *,
    listed: Mapping[str, np.ndarray] | None = None,
    diameter_mm: float = 4.0,
    n_expected: int | None = 4,
) -> dict[str, np.ndarray]:
    """Detect, localise and label the markers of one volume.

    Parameters
    ----------
    img : SimpleITK.Image
        The position's volume.
    listed : mapping label -> (3,) mm, optional
        The subject's fiducials for this position (labels to use); default: anatomical labels.
    diameter_mm, n_expected
        See :func:`detect_markers`.

    Returns
    -------
    dict label -> (3,) float ndarray (physical mm)
    """
    n = len(listed) if listed else n_expected
    pts = detect_markers(img, diameter_mm=diameter_mm, n_expected=n)
    if listed:
        return label_by_reference(pts, listed)
    return anatomical_labels(pts)
