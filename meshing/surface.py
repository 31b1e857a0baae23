"""Closed tissue surfaces from label maps (marching cubes + repair + remeshing) and the
measured skin surface that predictions are scored against."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy import ndimage as ndi

from meshing import _meshlab
from meshing.labels import Grid, repaired, tissue_masks


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) triangle areas, mm^2."""
    t = np.asarray(vertices, float)[np.asarray(faces)]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def triangle_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 3) unit right-hand normals."""
    t = np.asarray(vertices, float)[np.asarray(faces)]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def enclosed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by a closed surface, mm^3 (positive for outward normals)."""
    t = np.asarray(vertices, float)[np.asarray(faces)]
    t = t - t.reshape(-1, 3).mean(0)  # better conditioned far from the origin
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def marching_cubes_surface(
    mask: np.ndarray, grid: Grid, *, presmooth_voxels: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """Closed raw iso-surface of a (z, y, x) boolean mask, in physical mm, normals outward.

    The mask is padded by one empty voxel so that the surface closes with flat caps on the
    field-of-view planes; a light Gaussian (``presmooth_voxels`` sigma, in voxels) halves
    the staircase before Taubin smoothing removes the rest.
    """
    from skimage.measure import marching_cubes

    if not mask.any():
        raise ValueError("meshing: empty mask, nothing to extract")
    field = np.pad(mask.astype(np.float32), 1)
    if presmooth_voxels > 0:
        field = ndi.gaussian_filter(field, presmooth_voxels)
    verts_kji, faces, _, _ = marching_cubes(field, 0.5, allow_degenerate=False)
    ijk = verts_kji[:, ::-1] - 1.0
    vertices = grid.to_physical(ijk)
    faces = faces.astype(np.int64)
    if enclosed_volume(vertices, faces) < 0:
        faces = faces[:, ::-1].copy()
    return vertices, faces


def tissue_surface(
    mask: np.ndarray, grid: Grid, *, target_edge_mm: float, taubin_steps: int = 10, what=""
) -> tuple[np.ndarray, np.ndarray]:
    """Repaired, smoothed, isotropically remeshed closed surface of a mask (mm, outward).

    Raises
    ------
    RuntimeError
        When the repaired surface is still open or non-manifold.
    """
    v, f = marching_cubes_surface(mask, grid)
    v, f, repairs = _meshlab.repair_and_remesh(
        v, f, target_edge_mm=target_edge_mm, taubin_steps=taubin_steps
    )
    if repairs:
        repaired(f"meshing: surface of {what or 'tissue'} repaired ({'; '.join(repairs)})")
    topo = _meshlab.topology(v, f)
    if topo["boundary_edges"] or topo["non_two_manifold_edges"]:
        raise RuntimeError(
            f"meshing: surface of {what or 'tissue'} is not closed and manifold after repair "
            f"({topo['boundary_edges']} boundary, {topo['non_two_manifold_edges']} non-manifold "
            "edges)"
        )
    if enclosed_volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return v, f


def fov_faces(vertices: np.ndarray, faces: np.ndarray, grid: Grid, *, tol_voxels=0.6):
    """(m,) bool: triangles lying on a field-of-view plane (a cut, not anatomy)."""
    ijk = grid.to_index(np.asarray(vertices, float)[faces].reshape(-1, 3)).reshape(-1, 3, 3)
    hi = np.asarray(grid.size, float) - 0.5
    on = np.zeros(len(faces), bool)
    for a in range(3):
        lo_plane = np.all(np.abs(ijk[:, :, a] + 0.5) < tol_voxels, axis=1)
        hi_plane = np.all(np.abs(ijk[:, :, a] - hi[a]) < tol_voxels, axis=1)
        on |= lo_plane | hi_plane
    return on


def distance_to_mask_mm(mask: np.ndarray, grid: Grid, points: np.ndarray) -> np.ndarray:
    """(n,) distance (mm) from points to the nearest voxel centre of a (z, y, x) mask,
    trilinearly interpolated from a Euclidean distance transform (inf if the mask is empty)."""
    if not mask.any():
        return np.full(len(points), np.inf)
    edt = ndi.distance_transform_edt(~mask, sampling=grid.spacing[::-1])
    kji = grid.to_index(points)[:, ::-1].T
    return ndi.map_coordinates(edt, kji, order=1, mode="nearest")


def skin_surface(
    labels: sitk.Image, *, target_edge_mm: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """Measured skin: the outer surface of breast tissue without the breast-muscle interface
    and without the field-of-view cut planes.

    Parameters
    ----------
    labels : sitk.Image
        Label map (0 background, 1 breast, 2 muscle, 3 gland), physical LPS mm.
    target_edge_mm : float
        Target triangle edge length, mm.

    Returns
    -------
    vertices : (n, 3) float64, mm (physical LPS)
    triangles : (m, 3) int64, right-hand normals pointing out of the body
    """
    masks = tissue_masks(labels, require_muscle=False)
    v, f = tissue_surface(masks.breast, masks.grid, target_edge_mm=target_edge_mm, what="breast")
    c = v[f].mean(1)
    # A triangle touching muscle voxels (within ~one voxel) is interface, not skin.
    near_muscle = distance_to_mask_mm(masks.muscle, masks.grid, c) < 1.0 * masks.grid.spacing.max()
    keep = ~near_muscle & ~fov_faces(v, f, masks.grid)
    if not keep.any():
        raise ValueError("surface: the breast tissue has no skin (all of it touches muscle)")
    f = f[keep]
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]
