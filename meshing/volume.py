"""Label map -> conforming tetrahedral mesh of breast and muscle with region tags and sets."""

from __future__ import annotations

import logging
import time

import numpy as np
import SimpleITK as sitk

from mechanics.mesh import REGIONS, Mesh, face_components, sorted_tet_faces
from meshing import _occupancy, _tetwild
from meshing.improve import collapse_short_edges, relocate_boundary_nodes, relocate_free_nodes
from meshing.labels import Grid, TissueMasks, repaired, tissue_masks
from meshing.quality import volume_skewness
from meshing.sets import named_sets, tet_faces
from meshing.sizing import COARSE, sizing_field
from meshing.surface import distance_to_mask_mm, tissue_surface

log = logging.getLogger(__name__)


def midline_x(breast: np.ndarray, grid: Grid) -> float:
    """Physical x (mm) of the sagittal plane that separates the left and right breast.

    The plane sits where the breast tissue is thinnest (fewest voxels per x-slice) in the
    central 40 % of its x-extent; two separate breasts give a gap of empty slices, whose
    middle is taken.
    """
    counts = breast.sum(axis=(0, 1)).astype(float)  # per i (x index)
    idx = np.flatnonzero(counts)
    lo, hi = idx.min(), idx.max()
    a = int(lo + 0.3 * (hi - lo))
    b = max(int(np.ceil(lo + 0.7 * (hi - lo))), a + 1)
    window = counts[a : b + 1]
    mins = np.flatnonzero(window == window.min())
    # middle of the longest run of minimal slices
    runs = np.split(mins, np.flatnonzero(np.diff(mins) > 1) + 1)
    run = max(runs, key=len)
    i_mid = a + 0.5 * (run[0] + run[-1])
    if window.min() > 0:
        repaired(
            "meshing: left and right breast tissue touch; split on the sagittal plane where "
            f"it is thinnest (index i={i_mid:.1f})"
        )
    centre = np.array([[i_mid, (grid.size[1] - 1) / 2, (grid.size[2] - 1) / 2]])
    return float(grid.to_physical(centre)[0, 0])


def _interface_patch(vb, fb, vu, fu, masks: TissueMasks, *, gap_mm: float) -> np.ndarray:
    """Triangles of the breast surface that lie on muscle and away from the union's skin."""
    c = vb[fb].mean(1)
    near_muscle = distance_to_mask_mm(masks.muscle, masks.grid, c) < masks.grid.spacing.max()
    off_skin = _occupancy.distance(vu, fu, c) > gap_mm
    return fb[near_muscle & off_skin]


def _drop_unused(nodes, tets):
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    return nodes[used], remap[tets]


def _clean_isolated(tets: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Give a tet the region of its face neighbours when all of them disagree with it
    (single misclassified tets at the fuzzy end of the interface)."""
    faces = sorted_tet_faces(tets)
    owner = np.repeat(np.arange(len(tets)), 4)
    _, inv, cnt = np.unique(faces, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    shared = cnt[inv] == 2
    order = np.argsort(inv[shared], kind="stable")
    pairs = owner[shared][order].reshape(-1, 2)
    out = region.copy()
    for _ in range(2):
        n_same = np.zeros(len(tets), int)
        n_nb = np.zeros(len(tets), int)
        same = out[pairs[:, 0]] == out[pairs[:, 1]]
        for k in (0, 1):
            np.add.at(n_nb, pairs[:, k], 1)
            np.add.at(n_same, pairs[:, k], same)
        flip = (n_nb >= 3) & (n_same == 0)
        if not flip.any():
            break
        # the region most of the neighbours have (two tissues only: just the other one)
        nb_region = np.zeros(len(tets), out.dtype)
        nb_region[pairs[:, 0]] = out[pairs[:, 1]]
        nb_region[pairs[:, 1]] = out[pairs[:, 0]]
        out[flip] = nb_region[flip]
    return out


def _main_body(tets: np.ndarray) -> np.ndarray:
    """(M,) bool: the tets of the largest face-connected component.

    fTetWild's envelope filter, the sliver removal and the edge collapses can leave a tet that
    hangs on the rest by an edge or a vertex: a zero-stiffness rotation that makes every
    Newton step singular (measured: 1 fTetWild mesh in 12 of the half-size phantom at 7 mm,
    a lone boundary tet on an edge; every solve of it stalled at the first load step)."""
    label = face_components(tets)
    return label == np.bincount(label).argmax()


def _fragments(tets: np.ndarray, members: np.ndarray, min_fraction: float) -> np.ndarray:
    """Indices into ``members`` (tets of one tissue) of the face-connected groups that hold
    less than ``min_fraction`` of them."""
    label = face_components(tets[members])
    size = np.bincount(label)
    return np.flatnonzero(size[label] < min_fraction * len(members))


def _absorb_fragments(tets: np.ndarray, region: np.ndarray, *,
                      min_fraction: float = 0.01) -> np.ndarray:
    """Give tiny fragments of one tissue, which share no face with the rest of it, to the
    other tissue.

    fTetWild leaves a few one- or two-tet fragments at the fuzzy rim of the interface. Once
    the interface is split for sliding, a muscle fragment is held by contact alone, a
    mechanism: on a 20k-tet phantom mesh three of them (1-2 tets each) kept every sliding
    solve from its first load step. A muscle fragment takes the region of a breast tet it
    shares a node with.
    """
    muscle = region == REGIONS["muscle"]
    out = region.copy()
    for tissue in (~muscle, muscle):
        members = np.flatnonzero(tissue)
        if len(members) == 0:
            continue
        small = members[_fragments(tets, members, min_fraction)]
        if len(small) == 0:
            continue
        if tissue is muscle:
            node_region = np.zeros(tets.max() + 1, np.int32)
            for code in np.unique(region[~muscle]):  # a breast code per node
                node_region[tets[region == code].ravel()] = code
            codes = node_region[tets[small]]
            fallback = REGIONS["breast_left"]
            out[small] = [np.bincount(c[c > 0]).argmax() if (c > 0).any() else fallback
                          for c in codes]
        else:
            out[small] = REGIONS["muscle"]
        log.info("meshing: %d %s tets in fragments that share no face with the rest of their "
                 "tissue; given to the other tissue", len(small),
                 "muscle" if tissue is muscle else "breast")
    return out


def _drop_boundary_slivers(nodes, tets, *, max_skew: float = 0.9, rounds: int = 4):
    """(M,) bool: tets to keep after removing flat tets that lie on the boundary.

    A flat tet that hangs on the boundary by two faces, or by one face with its fourth node
    on the boundary too (a cap over a shallow dip), carries almost no volume; these are
    the typical worst elements of an envelope-constrained mesher.
    """
    keep = np.ones(len(tets), bool)
    for _ in range(rounds):
        sub = np.flatnonzero(keep)
        bf, owner, _, _ = tet_faces(tets[sub])
        n_bnd = np.bincount(owner, minlength=len(sub))
        on_bnd = np.zeros(len(nodes), bool)
        on_bnd[bf.ravel()] = True
        all_on = on_bnd[tets[sub]].all(1)
        skew = volume_skewness(nodes, tets[sub])[1]
        drop = (skew > max_skew) & ((n_bnd >= 2) | ((n_bnd == 1) & all_on))
        if not drop.any():
            break
        keep[sub[drop]] = False
    return keep


def _surfaces(tets, region):
    """Outer boundary faces and breast-muscle interface faces (oriented out of the muscle)."""
    bf, _, sf, so = tet_faces(tets)
    muscle = region == REGIONS["muscle"]
    between = muscle[so[:, 0]] != muscle[so[:, 1]]
    iface = np.where(muscle[so[between, 0]][:, None], sf[between], sf[between][:, ::-1])
    return bf, iface


def _improve(nodes, tets, region, vu, fu, vb, fb, *, epsilon: float, passes: int = 6):
    """Repeat :func:`_improve_once` while a tet is flatter than skewness 0.9 (a collapse
    frees nodes that the next relocation can move); flat tets still left where the
    interface meets the skin are carved out (:func:`_carve_caps`)."""
    for _ in range(passes):
        nodes, tets, region = _improve_once(nodes, tets, region, vu, fu, vb, fb, epsilon)
        skew = volume_skewness(nodes, tets)[1]
        if skew.max() <= 0.9:
            break
    else:
        nodes, tets, region = _carve_caps(nodes, tets, region, skew > 0.9)
        skew = volume_skewness(nodes, tets)[1]
    if skew.max() > 0.9:
        log.warning("meshing: %d tets keep a skewness above 0.9 (worst %.3f)",
                    int((skew > 0.9).sum()), float(skew.max()))
    return nodes, tets, region


def _carve_caps(nodes, tets, region, flat):
    """Remove flat tets that no node move mends and that can go without harm: those with
    exactly one face on the outer boundary and the opposite node inside (removing one
    leaves a manifold boundary). They sit where the interface meets the skin, all four
    nodes on the interface and three on the skin, where every node is pinned."""
    bf, owner, _, _ = tet_faces(tets)
    n_bnd = np.bincount(owner, minlength=len(tets))
    on_bnd = np.zeros(len(nodes), bool)
    on_bnd[bf.ravel()] = True
    carve = flat & (n_bnd == 1) & (on_bnd[tets].sum(1) == 3)
    if not carve.any():
        return nodes, tets, region
    log.debug("meshing: carved %d flat tets at the skin", int(carve.sum()))
    tets, region = tets[~carve], region[~carve]
    nodes, tets = _drop_unused(nodes, tets)
    return nodes, tets, region


def _improve_once(nodes, tets, region, vu, fu, vb, fb, epsilon):
    """Remove flat tets: move interior nodes (interface nodes included: they move by a
    fraction of an element, inside the flat tets' span), slide outer-boundary nodes along
    the tissue surface and interface nodes along the breast surface (the badly shaped
    surface triangles that interior moves cannot mend), move interior nodes again, and
    collapse the short edge of any tet still flatter than skewness 0.9."""
    bf, iface = _surfaces(tets, region)
    on_boundary = np.zeros(len(nodes), bool)
    on_boundary[bf.ravel()] = True
    on_interface = np.zeros(len(nodes), bool)
    on_interface[iface.ravel()] = True
    x = relocate_free_nodes(nodes, tets, ~on_boundary)
    x = relocate_boundary_nodes(x, tets, bf, on_boundary & ~on_interface,
                                _occupancy.projector(vu, fu),
                                max_deviation=epsilon)
    x = relocate_boundary_nodes(x, tets, iface, on_interface & ~on_boundary,
                                _occupancy.projector(vb, fb),
                                max_deviation=epsilon)
    x = relocate_free_nodes(x, tets, ~on_boundary)
    tets, kept = collapse_short_edges(x, tets, [bf, iface])
    region = region[kept]
    x, tets = _drop_unused(x, tets)
    return x, tets, region


def mesh_labels(
    labels: sitk.Image, *, size_mm: float = 8.0, seed: int | None = None,
    progress: bool = False, keep_gland: bool = False, surface_edge_mm: float | None = None,
    threads: int = 0, coarse: float = COARSE,
) -> Mesh:
    """Tetrahedral mesh of breast and muscle tissue from a label map.

    Breast (label 1, and gland 3 unless ``keep_gland``) and muscle (label 2) get one
    conforming mesh: their common interface is a set of shared tet faces. The clean-up aims at
    an ANSYS skewness of at most 0.9 for every tet (fTetWild's rare flat tets are mended by
    node moves and edge collapses, see :func:`_improve`; a warning in the log says when some
    remain). Regions follow
    ``mechanics.mesh.REGIONS``; the left breast (larger x) and the right one are split on the
    sagittal plane where the breast tissue is thinnest.

    Parameters
    ----------
    labels : sitk.Image
        Label map (0 background, 1 breast, 2 muscle, 3 gland), physical LPS mm.
    size_mm : float
        Target tet edge length at the breast mounds' surfaces, mm (see ``coarse``).
    seed : int, optional
        Unused: fTetWild runs with a fixed seed (see ``meshing._tetwild``), so one label map
        gives one mesh; kept for the pipeline's uniform signature.
    progress : bool
        Log the stages at INFO level.
    keep_gland : bool
        Tag tets inside the gland (label 3) as gland_left / gland_right.
    surface_edge_mm : float, optional
        Edge length of the intermediate surfaces (default ``0.75 * size_mm``).
    threads : int
        fTetWild threads (0: all cores).
    coarse : float
        Largest element size as a multiple of ``size_mm`` (1 gives a uniform size). The
        size is ``size_mm`` at the tissue surfaces of the breast mounds and grows with the
        depth below them and in the thin tissue layers away from the mounds (see
        :mod:`meshing.sizing`).

    Returns
    -------
    Mesh
        With face sets ``skin``, ``interface``; node sets ``fixed``, ``skin``, ``interface``,
        ``skin_superior``, ``skin_inferior``, ``fascia_superior``, ``fascia_inferior``,
        ``cut_breast``, ``cut_muscle`` (the nodes on the label map's field-of-view planes);
        node pairs ``ligament_inframammary``, ``ligament_medial``, ``ligament_lateral``.

    Raises
    ------
    ValueError
        Bad label map (see :func:`meshing.labels.tissue_masks`).
    RuntimeError
        Surfaces that cannot be repaired, or a tet mesh that misses a tissue.
    """
    del seed
    _check_sizes(size_mm, coarse)
    say = log.info if progress else log.debug
    t0 = time.perf_counter()
    masks = tissue_masks(labels)
    (vu, fu), (vb, fb), gland, (v_all, f_all) = _tissue_surfaces(
        masks, edge_mm=surface_edge_mm or 0.75 * size_mm, size_mm=size_mm,
        keep_gland=keep_gland, say=lambda *a: say(*a, time.perf_counter() - t0))

    epsilon = 0.1 * size_mm  # tet faces stay within this of the surfaces
    # fTetWild's main passes run at edge_mm over the whole bounding box and the sizing field
    # refines afterwards: a coarse edge_mm halves the time (see _tetwild.tetrahedralize).
    nodes, tets = _tetwild.tetrahedralize(
        v_all, f_all, edge_mm=3.0 * size_mm, epsilon_mm=epsilon, threads=threads,
        sizing=sizing_field(vu, fu, masks, size_mm, coarse=coarse),
    )
    say("meshing: fTetWild %d tets (%.1f s)", len(tets), time.perf_counter() - t0)
    tets, region, x_mid = _tissue_regions(nodes, tets, vu, fu, vb, fb, gland, masks)
    nodes, tets = _drop_unused(nodes, tets)
    nodes, tets, region = _improve(nodes, tets, region, vu, fu, vb, fb, epsilon=epsilon)
    nodes, tets, region = _keep_main_body(nodes, tets, region)
    region = _absorb_fragments(tets, region)
    sets = named_sets(nodes, tets, region, grid=masks.grid, masks=masks, x_mid=x_mid,
                      size_mm=size_mm)
    mesh = Mesh(nodes=nodes, tets=tets, region=region, **sets)
    say("meshing: %d nodes, %d tets (%.1f s)", mesh.n_nodes, mesh.n_tets, time.perf_counter() - t0)
    return mesh


def _check_sizes(size_mm: float, coarse: float) -> None:
    """Refuse a non-positive element size or a grading below 1."""
    if not size_mm > 0:
        raise ValueError(f"meshing: size_mm must be positive, got {size_mm}")
    if not coarse >= 1:
        raise ValueError(f"meshing: coarse must be at least 1, got {coarse}")


def _keep_main_body(nodes, tets, region):
    """Drop the tets outside the largest face-connected component (:func:`_main_body`)."""
    body = _main_body(tets)
    if not body.all():
        log.info("meshing: dropped %d tets that hang on the mesh by an edge or a vertex",
                 int((~body).sum()))
        tets, region = tets[body], region[body]
        nodes, tets = _drop_unused(nodes, tets)
    return nodes, tets, region


def _tissue_surfaces(masks: TissueMasks, *, edge_mm, size_mm, keep_gland, say):
    """The tissue surfaces and fTetWild's input: the union's surface, the breast surface's
    patch on the muscle (away from the skin), and the gland's surface when it is kept, with
    unused vertices dropped. Surfaces have edges of ``edge_mm``, at least 0.75 voxel.
    Returns ((vu, fu) union, (vb, fb) breast, gland surface or None, (vertices, faces) of
    the input); ``say(message, *args)`` logs the surfaces' sizes, its caller appending the
    time as the message's last argument."""
    grid = masks.grid
    edge_mm = max(edge_mm, 0.75 * float(grid.spacing.min()))
    vu, fu = tissue_surface(masks.union, grid, target_edge_mm=edge_mm, what="breast and muscle")
    vb, fb = tissue_surface(masks.breast, grid, target_edge_mm=edge_mm, what="breast")
    say("meshing: surfaces %d + %d triangles (%.1f s)", len(fu), len(fb))
    voxel = float(masks.grid.spacing.max())
    gap = max(1.5 * voxel, 0.2 * size_mm)
    fi = _interface_patch(vb, fb, vu, fu, masks, gap_mm=gap)
    soup_v = [vu, vb]
    soup_f = [fu, fi + len(vu)]
    gland = None
    if keep_gland and masks.gland.any():
        gland = tissue_surface(masks.gland, masks.grid, target_edge_mm=edge_mm, what="gland")
        soup_v.append(gland[0])
        soup_f.append(gland[1] + len(vu) + len(vb))
    v_all, f_all = np.vstack(soup_v), np.vstack(soup_f)
    used = np.unique(f_all)
    remap = np.full(len(v_all), -1, np.int64)
    remap[used] = np.arange(len(used))
    return (vu, fu), (vb, fb), gland, (v_all[used], remap[f_all])


def _tissue_regions(nodes, tets, vu, fu, vb, fb, gland, masks: TissueMasks):
    """Keep the tets inside the union (less the boundary slivers) and tag each with its
    region: breast (left of the midline at larger x, or right) or muscle, and gland inside
    the gland's surface when given. Returns (tets, region, midline x mm)."""
    centroids = nodes[tets].mean(1)
    in_union = _occupancy.inside(vu, fu, centroids)
    tets, centroids = tets[in_union], centroids[in_union]
    keep = _drop_boundary_slivers(nodes, tets)
    if (~keep).any():
        log.debug("meshing: dropped %d boundary slivers", int((~keep).sum()))
    tets, centroids = tets[keep], centroids[keep]
    is_breast = _occupancy.inside(vb, fb, centroids)
    tissue = np.where(is_breast, 1, 2)
    tissue = _clean_isolated(tets, tissue)
    if not (tissue == 1).any() or not (tissue == 2).any():
        raise RuntimeError("meshing: the tet mesh lost a tissue (breast or muscle); try a smaller "
                           "--size")
    x_mid = midline_x(masks.breast, masks.grid)
    region = np.full(len(tets), REGIONS["muscle"], np.int32)
    left = centroids[:, 0] > x_mid
    region[(tissue == 1) & left] = REGIONS["breast_left"]
    region[(tissue == 1) & ~left] = REGIONS["breast_right"]
    if gland is not None:
        in_gland = _occupancy.inside(gland[0], gland[1], centroids) & (tissue == 1)
        region[in_gland & left] = REGIONS["gland_left"]
        region[in_gland & ~left] = REGIONS["gland_right"]
    return tets, region, x_mid
