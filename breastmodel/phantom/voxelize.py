"""Tissue label volumes with partial-volume accuracy from the implicit anatomy.

Every voxel centre is classified; voxels whose 26-neighbourhood holds another label (the only
places where a boundary can cross a voxel) are re-sampled on an s x s x s sub-grid and take the
majority label (ties go to the centre's label, which keeps the vote unbiased). The sub-sample
label counts are kept so that rendering can mix intensities by tissue fraction.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from breastmodel.phantom.anatomy import TISSUE_NAMES, Anatomy, segmentation_codes

__all__ = ["Grid", "TissueVolume", "voxelize"]

_N_FINE = len(TISSUE_NAMES)
_N_SEG = 4


@dataclass(frozen=True)
class Grid:
    """Axis-aligned image grid (identity direction).

    Attributes
    ----------
    origin : (3,) float
        Physical position of voxel (0, 0, 0)'s centre, mm (x, y, z).
    spacing : float or (3,) float
        Voxel size, mm: one number (isotropic) or (x, y, z); see :attr:`spacing_xyz`.
    size : (3,) int
        Number of voxels along x, y, z.
    """

    origin: tuple[float, float, float]
    spacing: float | tuple[float, float, float]
    size: tuple[int, int, int]

    def __post_init__(self):
        s = np.asarray(self.spacing, dtype=float)
        if s.shape not in ((), (3,)) or not np.all(s > 0):
            raise ValueError(f"phantom: voxel spacing must be one number or three, all > 0 mm; "
                             f"got {self.spacing!r}")
        object.__setattr__(
            self, "spacing", float(s) if s.shape == () else tuple(map(float, s)))

    @classmethod
    def from_box(cls, box_min, box_max, spacing) -> Grid:
        """Grid whose voxels tile the box [box_min, box_max] (mm) at ``spacing`` mm (one
        number, or (x, y, z))."""
        lo, hi = np.asarray(box_min, float), np.asarray(box_max, float)
        s = np.asarray(spacing, dtype=float)
        size = np.maximum(1, np.round((hi - lo) / s).astype(int))
        origin = lo + 0.5 * s
        sp = float(s) if s.shape == () else tuple(map(float, s))
        return cls(tuple(map(float, origin)), sp, tuple(map(int, size)))

    @property
    def spacing_xyz(self) -> np.ndarray:
        """Voxel size along x, y, z, (3,) float mm."""
        return np.broadcast_to(np.asarray(self.spacing, dtype=float), (3,)).copy()

    @property
    def voxel_volume(self) -> float:
        """Volume of one voxel, mm^3."""
        return float(np.prod(self.spacing_xyz))

    @property
    def shape_zyx(self) -> tuple[int, int, int]:
        return (self.size[2], self.size[1], self.size[0])

    def points(self, flat_index: np.ndarray) -> np.ndarray:
        """Physical centres (n, 3) mm of voxels given by flat (z, y, x) C-order indices."""
        k, j, i = np.unravel_index(flat_index, self.shape_zyx)
        ijk = np.stack([i, j, k], axis=1).astype(float)
        return np.asarray(self.origin) + self.spacing_xyz * ijk


@dataclass(frozen=True)
class TissueVolume:
    """Voxelised anatomy on a grid.

    Attributes
    ----------
    grid : Grid
    fine : (nz, ny, nx) uint8
        Majority fine tissue code per voxel (see ``anatomy.TISSUE_NAMES``).
    seg : (nz, ny, nx) uint8
        Majority label in the segmentation convention (0 background, 1 breast, 2 muscle,
        3 gland).
    boundary : (m,) int64
        Flat indices of the voxels that were sub-sampled.
    counts : (m, 7) uint8
        Number of sub-samples of each fine code in those voxels.
    samples : int
        Sub-samples per boundary voxel (s^3).
    """

    grid: Grid
    fine: np.ndarray
    seg: np.ndarray
    boundary: np.ndarray
    counts: np.ndarray
    samples: int


def voxelize(
    anatomy: Anatomy,
    grid: Grid,
    *,
    image_to_patient: np.ndarray | None = None,
    displacement: Callable[[np.ndarray], np.ndarray] | None = None,
    supersample: int = 2,
    chunk: int = 1_000_000,
    progress: Callable[[float], None] | None = None,
) -> TissueVolume:
    """Label every voxel of ``grid`` with partial-volume majority voting.

    Parameters
    ----------
    anatomy
        The anatomy, evaluated in the patient frame.
    grid
        Image grid (image physical frame, mm).
    image_to_patient : (4, 4) float, optional
        Affine map of image-frame points to (deformed) patient-frame points (the inverse rigid
        motion). Identity if None.
    displacement
        Optional deformation: takes deformed patient-frame points x (n, 3) mm and returns
        u (n, 3) mm; the anatomy is evaluated at the material points X = x - u(x).
    supersample
        Sub-samples per axis in boundary voxels (2 gives 8 per voxel).
    chunk
        Points classified per batch (bounds memory).
    progress
        Optional callback receiving the finished fraction (0..1).

    Returns
    -------
    TissueVolume
    """
    classify = _classifier(anatomy, grid, image_to_patient, displacement)
    fine, ante = _classify_centres(classify, grid, chunk, progress)
    seg = segmentation_codes(fine, ante)
    bidx = _boundary_voxels(fine, ante)
    counts, seg_counts, ns = _subsample(classify, grid, bidx, int(supersample), chunk, progress)
    fine_flat, seg_flat = fine.reshape(-1), seg.reshape(-1)
    fine_flat[bidx] = _vote(counts, fine_flat[bidx])
    seg_flat[bidx] = _vote(seg_counts, seg_flat[bidx])
    return TissueVolume(grid, fine, seg, bidx, counts, ns)


def _classifier(anatomy: Anatomy, grid: Grid, image_to_patient, displacement):
    """``classify(i, j, k) -> (fine codes, anterior)`` of (fractional) voxel indices given as
    broadcastable float32 arrays, flattened: the points are mapped to the patient frame
    (and pulled back through ``displacement``) in float32."""
    m = np.eye(4) if image_to_patient is None else np.asarray(image_to_patient, dtype=float)
    rot, shift = m[:3, :3], m[:3, :3] @ np.asarray(grid.origin) + m[:3, 3]
    # Patient point of voxel index (i, j, k) (+ sub-voxel offset) = a @ (i, j, k) + shift.
    a = rot * grid.spacing_xyz[None, :]

    def classify(i, j, k) -> tuple[np.ndarray, np.ndarray]:
        # Every term carries i, j and k, so each coordinate has the full broadcast shape.
        xyz = [
            (
                (np.float32(a[r, 0]) * i + np.float32(a[r, 1]) * j)
                + (np.float32(a[r, 2]) * k + np.float32(shift[r]))
            ).ravel()
            for r in range(3)
        ]
        if displacement is not None:
            pts = np.stack(xyz, axis=1).astype(float)
            pts = pts - displacement(pts)
            xyz = [np.ascontiguousarray(pts[:, r], dtype=np.float32) for r in range(3)]
        return anatomy.classify_xyz(*xyz), xyz[1] < 0.0  # anterior: in front of the torso axis

    return classify


def _classify_centres(classify, grid: Grid, chunk: int, progress):
    """Fine codes and anterior flags (nz, ny, nx) of every voxel centre, slab by slab (the
    first half of the progress)."""
    nx, ny, nz = grid.size
    fine = np.empty(grid.shape_zyx, dtype=np.uint8)
    ante = np.empty(grid.shape_zyx, dtype=bool)
    ii = np.arange(nx, dtype=np.float32)[None, None, :]
    jj = np.arange(ny, dtype=np.float32)[None, :, None]
    per_slab = max(1, chunk // (nx * ny))
    for k0 in range(0, nz, per_slab):
        k1 = min(nz, k0 + per_slab)
        kk = np.arange(k0, k1, dtype=np.float32)[:, None, None]
        f, an = classify(ii, jj, kk)
        fine[k0:k1] = f.reshape(k1 - k0, ny, nx)
        ante[k0:k1] = an.reshape(k1 - k0, ny, nx)
        if progress:
            progress(0.5 * k1 / nz)
    return fine, ante


def _boundary_voxels(fine: np.ndarray, ante: np.ndarray) -> np.ndarray:
    """Flat indices of the voxels with another label among their 26 neighbours (the only
    ones a boundary may cross)."""
    key = fine + np.uint8(_N_FINE) * ante.astype(np.uint8)
    boundary = (ndimage.maximum_filter(key, size=3) != key) | (
        ndimage.minimum_filter(key, size=3) != key
    )
    return np.flatnonzero(boundary)


def _subsample(classify, grid: Grid, bidx: np.ndarray, s: int, chunk: int, progress):
    """Counts of fine codes (m, 7) and of segmentation labels (m, 4) over an s x s x s
    sub-grid of each boundary voxel, and the samples per voxel (the second half of the
    progress)."""
    off1 = (np.arange(s) + 0.5) / s - 0.5  # in voxels
    offsets = np.stack(np.meshgrid(off1, off1, off1, indexing="ij"), axis=-1).reshape(-1, 3)
    offsets = offsets.astype(np.float32)
    ns = len(offsets)
    counts = np.zeros((len(bidx), _N_FINE), dtype=np.uint8)
    seg_counts = np.zeros((len(bidx), _N_SEG), dtype=np.uint8)
    per = max(1, chunk // ns)
    for start in range(0, len(bidx), per):
        sl = slice(start, min(len(bidx), start + per))
        k, j, i = (v.astype(np.float32) for v in np.unravel_index(bidx[sl], grid.shape_zyx))
        f, an = classify(
            i[:, None] + offsets[None, :, 0],
            j[:, None] + offsets[None, :, 1],
            k[:, None] + offsets[None, :, 2],
        )
        sg = segmentation_codes(f, an)
        nb = sl.stop - sl.start
        rows = np.repeat(np.arange(nb), ns)
        counts[sl] = np.bincount(rows * _N_FINE + f, minlength=nb * _N_FINE).reshape(nb, -1)
        seg_counts[sl] = np.bincount(rows * _N_SEG + sg, minlength=nb * _N_SEG).reshape(nb, -1)
        if progress:
            progress(0.5 + 0.5 * sl.stop / max(1, len(bidx)))
    return counts, seg_counts, ns


def _vote(counts: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Majority code per row; a tie goes to the centre sample's code."""
    score = counts.astype(np.float32)
    score[np.arange(len(centre)), centre] += 0.5
    return np.argmax(score, axis=1).astype(np.uint8)
