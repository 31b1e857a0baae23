"""Closed tissue surfaces from label maps (marching cubes + repair + remeshing) and the
measured skin surface that predictions are scored against."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk
from scipy import ndimage as ndi

from meshing import _meshlab
from meshing._fresh import run_module
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
    f = _without_debris(v, f, _outside_component(v, f, masks))
    used = np.unique(f)
    remap = np.full(len(v), -1, np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[f]


#: Pieces of a measured skin with less than this share of its largest piece's area are
#: dropped as crumbs: a few triangles left on the rim once the faces near muscle and on the
#: field of view's cut are taken off (looking onto the outside air, at most 0.8 % of the
#: largest on the own segmentations of small-000, -001, -002, -006, -009 and full-000).
#: Bigger pieces are real skin cut off where the fat over the muscle is thinner than a voxel
#: (the full-size subject full-000's right breast: 2.4-4.8 % in prone and tilted, 2000-3000
#: mm^2 that a 5 % rule dropped, and its prone MHD read 2.45 mm for 1.05), unless they look
#: onto other air (:func:`_without_debris`).
SKIN_CRUMB_SHARE = 0.01


def _outside_component(v: np.ndarray, f: np.ndarray, masks) -> np.ndarray:
    """(m,) the background component (``scipy.ndimage.label`` of the voxels outside the
    tissue) that each triangle looks onto, 1.5 voxels out along its normal; 0 where that is
    tissue or outside the grid."""
    grid = masks.grid
    comp, _ = ndi.label(~(masks.breast | masks.muscle))
    out = v[f].mean(1) + 1.5 * grid.spacing.max() * triangle_normals(v, f)
    ijk = np.rint(grid.to_index(out)).astype(np.int64)
    inside = np.all((ijk >= 0) & (ijk < np.asarray(grid.size)), axis=1)
    got = np.zeros(len(f), np.int64)
    i, j, k = ijk[inside].T
    got[inside] = comp[k, j, i]
    return got


def _without_debris(v: np.ndarray, f: np.ndarray, outside: np.ndarray) -> np.ndarray:
    """The triangles ``f`` without the edge-connected pieces that are debris (a repair
    warning says how many): crumbs under :data:`SKIN_CRUMB_SHARE` of the largest piece's
    area, and pieces that look onto other air than the largest does (``outside``, per
    triangle, from :func:`_outside_component`): the surface of thorax interior the
    segmentation called breast behind a gap in the muscle. On the suite's 2 mm, SNR 13 coil
    subject (small-002) the supine skin had such pieces (1.4 % of the main one's area at
    most, 9-18 mm behind the model's skin, every one looking onto the thorax's enclosed
    background) which the main piece matched to 0.19 mm: its calibrated MHD read 1.56 mm."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.vstack([f[:, [0, 1]], f[:, [1, 2]]])
    n, lab = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])),
                                             shape=(len(v), len(v))), directed=False)
    if n == 1:
        return f
    piece = lab[f[:, 0]]
    area = np.bincount(piece, weights=triangle_areas(v, f), minlength=n)

    def looks_onto(k):  # the background component most of piece k's triangles face
        seen = np.bincount(outside[(piece == k) & (outside > 0)])
        return int(seen.argmax()) if seen.size else 0

    air = looks_onto(int(area.argmax()))
    crumb = (area < SKIN_CRUMB_SHARE * area.max()) & (area > 0)
    # (air 0: the largest piece sees no background, and nothing is called a cavity)
    behind = np.array([air > 0 and area[k] > 0 and not crumb[k]
                       and looks_onto(k) not in (0, air) for k in range(n)])
    for drop, why in ((crumb, f"under {SKIN_CRUMB_SHARE:.0%} of its largest's area: crumbs "
                              "on the rim"),
                      (behind, "looking onto other air than the skin does: the surface of "
                               "a cavity, not skin")):
        if drop.any():
            repaired(f"surface: dropped {int(drop.sum())} piece(s) of the measured skin "
                     f"{why} ({area[drop].sum():.3g} mm^2 in all)")
    return f[~(crumb | behind)[piece]]


#: Label maps of at least this many voxels get their skins remeshed in parallel processes
#: (:func:`skin_surfaces`); below it, a worker's start (about 2 s of imports) costs more
#: than it saves.
PARALLEL_VOXELS = 4_000_000


def worth_a_worker(path) -> bool:
    """Whether the label map in ``path`` has at least :data:`PARALLEL_VOXELS` voxels (its
    header only is read)."""
    return int(np.prod(Grid.of_file(path).size)) >= PARALLEL_VOXELS


class skin_surfaces:
    """:func:`skin_surface` of each label-map file, in order (``next``), on up to ``workers``
    processes at once when the first map has at least :data:`PARALLEL_VOXELS` voxels; a
    context manager. The processes start at once, so the caller's own work runs beside them
    (the pipeline's tet mesh, one core for most of its two minutes, runs in a worker of its
    own: :mod:`meshing.background`).

    On an adult volume (320 x 180 x 200 voxels of 1 mm) one skin is 20 s, 16 of them
    pymeshlab's remeshing, so a subject's three positions took 60 s one after the other.
    Processes (``python -m meshing.surface``, like fTetWild's), not threads: two threads gave
    identical surfaces, but glibc reported a corrupted heap at the exit of one run (pymeshlab
    and ITK's readers are not known to be thread-safe); and not a multiprocessing pool, whose
    workers import the caller's main script. A worker's repair warnings are repeated here
    when its position's turn comes; its ValueError or RuntimeError is raised then (the
    caller names the position). Below the size, each skin is made in this process when its
    turn comes."""

    def __init__(self, paths, *, target_edge_mm: float = 2.0, workers: int = 1):
        self.paths = [str(p) for p in paths]
        self.edge = float(target_edge_mm)
        self.next_index = 0
        self.jobs = None
        if workers > 1 and len(self.paths) > 1 and worth_a_worker(self.paths[0]):
            import tempfile
            from concurrent.futures import ThreadPoolExecutor

            self.tmp = tempfile.TemporaryDirectory(prefix="skin_surfaces_")
            self.pool = ThreadPoolExecutor(min(int(workers), len(self.paths)))  # they wait
            self.jobs = [self.pool.submit(_run_worker, p, self.edge,
                                          str(Path(self.tmp.name) / f"{k}.npz"))
                         for k, p in enumerate(self.paths)]

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def __iter__(self):
        return self

    def __next__(self) -> tuple[np.ndarray, np.ndarray]:
        k = self.next_index
        if k >= len(self.paths):
            raise StopIteration
        self.next_index += 1
        if self.jobs is None:
            return skin_surface(sitk.ReadImage(self.paths[k]), target_edge_mm=self.edge)
        with np.load(self.jobs[k].result()) as out:
            for message in out["said"]:
                repaired(str(message))
            if "error" in out:
                kind = ValueError if str(out["kind"]) == "ValueError" else RuntimeError
                raise kind(str(out["error"]))
            return out["vertices"], out["triangles"]

    def close(self) -> None:
        """Cancel the skins not started, wait for the running ones, remove their files."""
        if self.jobs is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
            self.tmp.cleanup()
            self.jobs = None


def _run_worker(path: str, target_edge_mm: float, out: str) -> str:
    """One ``python -m meshing.surface`` process; its output file (see :func:`_main`)."""
    run_module("meshing.surface", [path, repr(target_edge_mm), out], out,
               what=f"surface: the skin of {path}")
    return out


def _main(path: str, target_edge_mm: str, out: str) -> None:
    """The worker: the skin of ``path`` (or its error) and its repair messages, to ``out``."""
    import logging
    import warnings

    from imaging.atomic import write_atomic_with
    from meshing.labels import MeshingWarning

    logging.getLogger("meshing").setLevel(logging.ERROR)  # the caller repeats the warnings
    result: dict = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", MeshingWarning)
        try:
            v, f = skin_surface(sitk.ReadImage(path), target_edge_mm=float(target_edge_mm))
            result = {"vertices": v, "triangles": f}
        except (ValueError, RuntimeError) as exc:
            result = {"error": np.array(str(exc)), "kind": np.array(type(exc).__name__)}
    said = [str(w.message) for w in caught if issubclass(w.category, MeshingWarning)]
    write_atomic_with(out, lambda tmp: np.savez(tmp, said=np.array(said, dtype=str), **result),
                      suffix=".npz")


if __name__ == "__main__":
    import sys

    _main(*sys.argv[1:4])
