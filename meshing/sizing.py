"""Target element size over the meshing box: fine where the mechanics is, coarse elsewhere.

The target size ``size_mm`` holds at every tissue surface (skin, breast-muscle interface,
thorax side of the muscle) of the breast mounds. Away from them the size grows, up to
``coarse * size_mm``:

- inside thick tissue, with the depth below the nearest surface (a graded mesh: the
  interior of a breast mound needs no surface resolution);
- in the thin tissue layers away from the breast mounds (the fat and muscle of the rest of
  the torso, which carry no measured skin of interest and little deformation).

A breast mound is breast tissue more than ``2 * size_mm`` from the muscle (the anterior fat
layer of the torso is thinner than that at the usual sizes); when there is none, every
breast voxel counts as mound and only the depth grading applies. Near a sharply curved part
of the tissue surface (a rounded edge, a fold, the rim of a field-of-view cut) the size stays
small enough for the chord of an element to stay within the envelope half-width: a chord of
length h on a radius R sags h^2 / (8 R). Outside the tissue the size grows with the distance
to it, so that fTetWild spends little on the empty bounding box.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from meshing import _occupancy
from meshing.labels import TissueMasks

#: Largest element size, as a multiple of the target size.
COARSE = 1.75
#: Size growth per mm of depth below the nearest tissue surface (mm / mm).
DEPTH_GRADE = 0.5


#: ``size_mm = "auto"``: elements this many times smaller than the largest inscribed radius
#: of the breast tissue, within :data:`AUTO_SIZE_RANGE_MM`. Measured on the validation suite
#: (half-size subjects, radius 8-18 mm; truth label maps; fitted breast modulus at 8 / 6 / 5
#: / 4 mm edges): small-000 (radius 12 mm) 0.734 / 0.857 / 1.000 / 1.051 kPa, small-004
#: (15 mm) 1.19 / 1.28 / 1.35, small-008 (15.3 mm) 0.90 / 0.96 / 1.00 / 1.05, small-003 (18 mm)
#: 1.04 / 1.08 / 1.10. A coarse mesh is too stiff; once the radius spans 3 elements the
#: next refinement changes the modulus by 2.6 % (small-003, 6 -> 5 mm) and 5.1 % (small-008,
#: 5 -> 4 mm). The adult-size family's breasts (radius 19.9-35.4 mm on four drawn
#: subjects) get 6.5-8 mm.
AUTO_ELEMENTS_PER_RADIUS = 3.0
#: Bounds of the "auto" size, mm: 8 mm is the paper-like size of an adult breast model.
AUTO_SIZE_RANGE_MM = (4.0, 8.0)


def auto_size_mm(breast: np.ndarray, spacing_zyx) -> tuple[float, float]:
    """The "auto" element size of a breast mask (z, y, x bool, labels 1 and 3) on a grid of
    ``spacing_zyx`` mm: (size in mm, rounded down to 0.5 mm and within
    :data:`AUTO_SIZE_RANGE_MM`; the largest inscribed radius it came from, mm)."""
    if not np.any(breast):
        raise ValueError("meshing: no breast tissue to size the mesh by")
    radius = float(ndi.distance_transform_edt(np.pad(breast, 1),
                                              sampling=tuple(spacing_zyx)).max())
    lo, hi = AUTO_SIZE_RANGE_MM
    size = np.floor(2.0 * radius / AUTO_ELEMENTS_PER_RADIUS) / 2.0
    return float(min(hi, max(lo, size))), radius


def mesh_size(value, labels) -> tuple[float, str]:
    """The element size (mm) of a ``size_mm`` setting (a number, or "auto": from the breast
    tissue, labels 1 and 3, of the SimpleITK label map ``labels``, :func:`auto_size_mm`) and
    how it was chosen."""
    if value != "auto":
        return float(value), "given"
    import SimpleITK as sitk

    from imaging.labels import BREAST, GLAND

    a = sitk.GetArrayViewFromImage(labels)
    size, radius = auto_size_mm((a == BREAST) | (a == GLAND), labels.GetSpacing()[::-1])
    return size, (f"auto: {AUTO_ELEMENTS_PER_RADIUS:g} elements across the breast tissue's "
                  f"largest inscribed radius, {radius:.1f} mm")


def grid_tets(lo: np.ndarray, hi: np.ndarray, step: float):
    """Structured tet mesh of the box [lo, hi] (mm): each cube split into six tets.

    Returns
    -------
    points : (n, 3) float, mm
    tets : (m, 4) int32
    """
    n = np.maximum(np.ceil((hi - lo) / step).astype(int), 1)
    axes = [lo[a] + (hi[a] - lo[a]) * np.arange(n[a] + 1) / n[a] for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange(len(pts)).reshape(n + 1)
    corner = [idx[i : i + n[0], j : j + n[1], k : k + n[2]].ravel()
              for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    c = np.stack(corner, 1)  # cube corners, bit order (i, j, k)
    kuhn = [[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]]
    return pts, np.vstack([c[:, t] for t in kuhn]).astype(np.int32)


def tissue_size_map(masks: TissueMasks, size_mm: float, *, coarse: float = COARSE,
                    depth_grade: float = DEPTH_GRADE) -> np.ndarray:
    """(z, y, x) target element size (mm) on the label grid (tissue voxels; ``size_mm``
    on background voxels)."""
    sp = masks.grid.spacing[::-1]
    s = float(size_mm)
    breast, muscle = masks.breast, masks.muscle
    mound = breast & (ndi.distance_transform_edt(~muscle, sampling=sp) > 2.0 * s) \
        if muscle.any() else breast
    if not mound.any():
        mound = breast
    d_mound = ndi.distance_transform_edt(~mound, sampling=sp)
    # depth below the nearest voxel of another label (background or the other tissue)
    depth = np.where(breast, ndi.distance_transform_edt(breast, sampling=sp),
                     ndi.distance_transform_edt(muscle, sampling=sp))
    top = coarse * s
    away = s + (top - s) * np.clip((d_mound - s) / (2.0 * s), 0.0, 1.0)
    deep = np.minimum(s + depth_grade * np.maximum(depth - 0.5 * s, 0.0), top)
    out = np.maximum(away, deep)
    out[~masks.union] = s
    return out


def curvature_radius(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) radius of curvature at each vertex of a closed surface, mm: the inverse of the
    mean turn of the vertex normal per mm along its edges (large where flat)."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # area-weighted
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
    e = f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    turn = np.linalg.norm(vn[e[:, 0]] - vn[e[:, 1]], axis=1)
    kappa = turn / np.maximum(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1), 1e-300)
    k_sum = np.bincount(e.ravel(), np.repeat(kappa, 2), minlength=len(v))
    k_mean = k_sum / np.maximum(np.bincount(e.ravel(), minlength=len(v)), 1)
    return 1.0 / np.maximum(k_mean, 1e-300)


def sizing_field(vu: np.ndarray, fu: np.ndarray, masks: TissueMasks, size_mm: float, *,
                 coarse: float = COARSE, epsilon_mm: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Background tet mesh with a target edge length at its nodes, for fTetWild.

    Parameters
    ----------
    vu, fu : closed surface of all tissue (mm)
    masks : the tissue masks on the label grid
    size_mm : target element size at the breast mounds' surfaces, mm
    coarse : largest size inside the tissue, as a multiple of ``size_mm``
    epsilon_mm : envelope half-width, mm (default ``0.1 * size_mm``): within ``coarse *
        size_mm`` of the surface, the size is at most sqrt(8 R epsilon) (R the radius of
        curvature of the nearest surface vertex), and never below ``size_mm``

    Returns
    -------
    points : (k, 3) mm; tets : (l, 4) int32; values : (k,) target edge length, mm
    """
    s = float(size_mm)
    lo, hi = vu.min(0), vu.max(0)
    pad = 0.25 * np.linalg.norm(hi - lo)
    pts, tets = grid_tets(lo - pad, hi + pad, s)
    inside = _occupancy.inside(vu, fu, pts)
    d = _occupancy.distance(vu, fu, pts)
    d[inside] = 0.0
    # outside: size at the surface, growing to 5 sizes far from it
    val = s * np.clip(1.0 + (d - 1.5 * s) / (1.125 * s), 1.0, 5.0)
    if inside.any():
        size_map = tissue_size_map(masks, s, coarse=coarse)
        kji = masks.grid.to_index(pts[inside])[:, ::-1].T
        val[inside] = ndi.map_coordinates(size_map, kji, order=1, mode="nearest")
    eps = 0.1 * s if epsilon_mm is None else float(epsilon_mm)
    allowed = np.maximum(np.sqrt(8.0 * curvature_radius(vu, fu) * eps), s)
    dist, nearest = cKDTree(vu).query(pts, distance_upper_bound=coarse * s)
    near = np.isfinite(dist)
    val[near] = np.minimum(val[near], allowed[nearest[near]])
    return pts, tets, val
