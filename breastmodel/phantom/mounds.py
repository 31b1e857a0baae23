"""A structured two-mound breast model (numpy only): fast problems for tests, benchmarks,
the diagnosis notebook and hidden-effect studies without imaging.

:func:`mound_mesh` is two Gaussian breast mounds on a muscle slab with every named set the
effects read; :func:`mound_problem` writes it as a problem folder (see
:mod:`breastmodel.pipeline.problem`) whose measured skins are what a truth model predicts, so
that :func:`breastmodel.pipeline.run.run_problem`, ``breastmodel diagnose`` and
``breastmodel compare`` run on it in seconds.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mechanics.mesh import KUHN, REGIONS, Mesh, orient_tets

__all__ = ["GRAVITY", "boundary_faces", "mound_mesh", "mound_problem"]

#: Unit gravity per position (LPS): prone pulls anteriorly (-y), supine posteriorly, the
#: tilted position 45 deg towards the patient's left.
GRAVITY = {"prone": (0.0, -1.0, 0.0), "supine": (0.0, 1.0, 0.0),
           "supine_tilted": (math.sqrt(0.5), math.sqrt(0.5), 0.0)}

_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def boundary_faces(tets: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(F, 3) outward triangles of the sub-mesh ``tets[mask]`` (faces used once)."""
    f = tets[mask][:, _TET_FACES].reshape(-1, 3)
    key = np.sort(f, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return f[cnt[inv.ravel()] == 1]


def mound_mesh(*, cells: tuple[int, int, int, int] = (12, 8, 4, 2),
                    half_width: float = 100.0, half_height: float = 60.0,
                    mound: float = 40.0, base: float = 6.0, sigma: float = 28.0,
                    muscle: float = 10.0, gland: bool = True) -> Mesh:
    """Two Gaussian breast mounds (left at x > 0) on a flat muscle slab, LPS mm.

    Parameters
    ----------
    cells : (nx, nz, n_breast_layers, n_muscle_layers); 6 tets per cell
        ((12, 8, 4, 2): 3456 tets; (26, 16, 6, 2): 19968 tets)
    half_width, half_height : extent in x (left-right) and z (superior), mm
    mound, base, sigma : breast thickness h = base + mound * (two Gaussian bumps of width
        sigma centred at x = +-half_width / 2), mm; breasts protrude anteriorly (-y)
    muscle : slab thickness (posterior, 0 <= y <= muscle), mm
    gland : tag an ellipsoidal core of each mound as glandular (regions 4 and 5)

    Returns
    -------
    Mesh with regions breast_left 1, muscle 2, breast_right 3 (gland 4, 5), face sets
    ``skin`` and ``interface`` (conforming, muscle -> breast normal), node sets ``fixed``
    (posterior slab face), ``skin_superior``/``skin_inferior`` (skin nodes on the z ends),
    ``skin_lateral`` (skin nodes on the x ends, where the skin would go on around the torso),
    ``fascia_superior``/``fascia_inferior`` (interface nodes on the z ends) and node pairs
    ``ligament_inframammary``, ``ligament_medial``, ``ligament_lateral``.
    """
    nx, nz, nb, nm = (int(c) for c in cells)
    xs = np.linspace(-half_width, half_width, nx + 1)
    zs = np.linspace(-half_height, half_height, nz + 1)
    c = half_width / 2.0

    def height(x, z):
        return base + mound * (np.exp(-((x - c) ** 2 + z**2) / (2 * sigma**2))
                               + np.exp(-((x + c) ** 2 + z**2) / (2 * sigma**2)))

    X, Z = np.meshgrid(xs, zs, indexing="ij")
    h = height(X, Z)
    layers = []
    for layer in range(nm + nb + 1):
        if layer <= nm:
            y = np.full_like(X, muscle * (nm - layer) / nm)
        else:
            y = -h * (layer - nm) / nb
        layers.append(np.stack([X, y, Z], axis=-1))
    P = np.stack(layers, axis=2)  # (nx+1, nz+1, L, 3)
    nodes = P.reshape(-1, 3)
    idx = np.arange(len(nodes)).reshape(P.shape[:3])
    i, k, m = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(nz),
                                               np.arange(nm + nb), indexing="ij"))
    corner = np.stack([idx[i + a, k + b, m + cc] for cc in (0, 1) for b in (0, 1)
                       for a in (0, 1)], axis=1)
    tets = orient_tets(nodes, corner[:, KUHN].reshape(-1, 4))
    layer_of_tet = np.repeat(m, 6)
    cen = nodes[tets].mean(axis=1)
    region = np.where(layer_of_tet < nm, REGIONS["muscle"],
                      np.where(cen[:, 0] > 0, REGIONS["breast_left"], REGIONS["breast_right"]))
    if gland:
        region = _tag_glands(region, cen, layer_of_tet >= nm, c, sigma, height)
    breast = layer_of_tet >= nm
    bf = boundary_faces(tets, breast)
    layer_of_node = np.broadcast_to(np.arange(nm + nb + 1), P.shape[:3]).ravel()
    on_interface = np.all(layer_of_node[bf] == nm, axis=1)
    interface = bf[on_interface][:, ::-1]  # reverse: normal from muscle into breast
    skin = bf[~on_interface]
    zn = nodes[:, 2]
    skin_nodes, if_nodes = np.unique(skin), np.unique(interface)
    tol = 1e-9
    node_sets = {
        "fixed": idx[:, :, 0].ravel(),
        "skin_superior": skin_nodes[zn[skin_nodes] > half_height - tol],
        "skin_inferior": skin_nodes[zn[skin_nodes] < -half_height + tol],
        "skin_lateral": skin_nodes[np.abs(nodes[skin_nodes, 0]) > half_width - tol],
        "fascia_superior": if_nodes[zn[if_nodes] > half_height - tol],
        "fascia_inferior": if_nodes[zn[if_nodes] < -half_height + tol],
    }
    pairs = _ligament_pairs(idx, int(np.argmin(np.abs(xs - c))), nx, nz, nm)
    return Mesh(nodes, tets, region, node_sets=node_sets,
                face_sets={"skin": skin, "interface": interface},
                node_pairs={f"ligament_{g}": np.array(p) for g, p in pairs.items()})


def _tag_glands(region: np.ndarray, cen: np.ndarray, in_breast: np.ndarray, c: float,
                sigma: float, height) -> np.ndarray:
    """``region`` with an ellipsoidal core of each mound (centred at x = +-c, half its height
    deep) tagged as gland (regions 4 and 5); ``cen`` (K, 3) tet centroids, mm."""
    for side, code in ((1, REGIONS["gland_left"]), (-1, REGIONS["gland_right"])):
        hc = height(side * c, 0.0)
        r2 = (((cen[:, 0] - side * c) / (0.5 * sigma)) ** 2 + (cen[:, 2] / (0.5 * sigma)) ** 2
              + ((cen[:, 1] + 0.5 * hc) / (0.3 * hc)) ** 2)
        region = np.where(in_breast & (r2 < 1.0), code, region)
    return region


def _ligament_pairs(idx: np.ndarray, ic: int, nx: int, nz: int,
                    nm: int) -> dict[str, list[tuple[int, int]]]:
    """Node pairs (breast node, muscle node) of the inframammary, medial and lateral
    ligaments of both mounds: the breast node one layer above the interface, the muscle node
    mid-slab, offset so that the cable tightens when the breast slides away from its support.
    ``idx`` (nx+1, nz+1, layers) node numbers, ``ic`` the x index of the left mound's centre,
    ``nm`` the muscle layers."""
    lb, lm = nm + 1, nm // 2
    kc = nz // 2
    pairs: dict[str, list[tuple[int, int]]] = {"inframammary": [], "medial": [], "lateral": []}
    for side in (1, -1):
        i0 = ic if side > 0 else nx - ic
        for di in (-1, 0, 1):
            pairs["inframammary"].append((idx[i0 + di, 1, lb], idx[i0 + di, 0, lm]))
        i_med, i_mid = (nx // 2 + 2 * side), nx // 2
        i_lat, i_edge = (nx - 1, nx) if side > 0 else (1, 0)
        for dk in (-1, 0, 1):
            pairs["medial"].append((idx[i_med, kc + dk, lb], idx[i_mid, kc + dk, lm]))
            pairs["lateral"].append((idx[i_lat, kc + dk, lb], idx[i_edge, kc + dk, lm]))
    return pairs



def mound_problem(folder: str | Path, truth_model: Mapping[str, Any], *,
                  cells: tuple[int, int, int, int] = (8, 6, 3, 2), gland: bool = False,
                  reference: str = "supine", stress_free: str = "none",
                  noise_mm: float = 0.0, seed: int = 0,
                  solver: Mapping[str, Any] | None = None) -> Path:
    """Write a problem folder whose measured skins are a truth model's predictions.

    Parameters
    ----------
    folder : the problem folder to write (replaced)
    truth_model : a ``[model]`` table (materials by region name, effects; gravity is added per
        position) with the physics that made the "measurements", hidden effects included
    cells : mesh resolution (see :func:`mound_mesh`)
    gland : tag glandular regions
    reference : the reference position
    stress_free : "none": the mesh is the stress-free geometry and every position,
        the reference included, is a prediction; "inverse": the mesh is the reference
        position's loaded shape (as with imaging) and the truth's stress-free geometry is its
        full-field inverse
    noise_mm : standard deviation of Gaussian noise added along the skin normals, mm (a
        stand-in for segmentation noise; the noise floor of the diagnosis)
    seed : noise seed

    Returns
    -------
    Path of the folder; ``truth.json`` in it records the truth model.
    """
    from breastmodel.config import write_json
    from breastmodel.pipeline.config import resolve_config
    from breastmodel.pipeline.problem import (
        forget_problem,
        load_problem,
        predict_position,
        skin_nodes,
        stress_free_geometry,
    )

    folder = Path(folder)
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    mesh = mound_mesh(cells=cells, gland=gland)
    mesh.save_npz(folder / "mesh.npz")
    write_json(folder / "problem.json", {"reference": reference, "gravity": GRAVITY,
                                         "landmarks": {}, "n_nodes": mesh.n_nodes,
                                         "n_tets": mesh.n_tets})
    faces = np.asarray(mesh.face_sets["skin"])
    nodes = np.unique(faces)
    remap = np.full(mesh.n_nodes, -1, np.int64)
    remap[nodes] = np.arange(len(nodes))
    tri = remap[faces]
    for pos in GRAVITY:  # placeholders: the problem loader reads every position's skin
        np.savez(folder / f"{pos}_skin.npz", vertices=mesh.nodes[nodes], triangles=tri)
    cfg = resolve_config({"model": dict(truth_model), "stress_free": {"method": stress_free},
                          **({"solver": dict(solver)} if solver else {})},
                         where="mound_problem truth model")
    prob = load_problem(folder)
    X, _ = stress_free_geometry(prob, cfg["model"], cfg["stress_free"], cfg["solver"])
    rng = np.random.default_rng(seed)
    for pos in GRAVITY:
        if pos == reference and stress_free == "inverse":
            v = mesh.nodes[nodes]
        else:
            x = predict_position(prob, cfg["model"], X, pos, cfg["solver"]).x
            v = x[skin_nodes(prob, len(x))]
        if noise_mm > 0:
            v = v + rng.normal(0.0, noise_mm, len(v))[:, None] * _vertex_normals(v, tri)
        np.savez(folder / f"{pos}_skin.npz", vertices=v, triangles=tri)
    write_json(folder / "truth.json", {"model": cfg["model"], "stress_free": stress_free,
                                       "noise_mm": noise_mm, "seed": seed})
    forget_problem(folder)  # the skins changed on disk
    return folder


def _vertex_normals(v: np.ndarray, tri: np.ndarray) -> np.ndarray:
    n = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    out = np.zeros_like(v)
    for k in range(3):
        np.add.at(out, tri[:, k], n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)

