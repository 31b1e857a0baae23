"""A small structured breast-like test mesh (two breast mounds on a muscle slab) and the
paper-like model on it, shared by the effects tests and benchmarks.

Not a phantom of the project's subjects (the meshing stage makes those): a deterministic,
numpy-only mesh with every set the effects read, for tests and benchmarks of mechanics.
"""

from __future__ import annotations

import numpy as np
from zoo import _KUHN, orient

from mechanics.mesh import REGIONS, Mesh
from mechanics.model import build_model

_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def boundary_faces(tets: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(F, 3) outward triangles of the sub-mesh ``tets[mask]`` (faces used once)."""
    f = tets[mask][:, _TET_FACES].reshape(-1, 3)
    key = np.sort(f, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return f[cnt[inv.ravel()] == 1]


def breastlike_mesh(*, cells: tuple[int, int, int, int] = (12, 8, 4, 2),
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
    tets = orient(nodes, corner[:, _KUHN].reshape(-1, 4))
    layer_of_tet = np.repeat(m, 6)
    cen = nodes[tets].mean(axis=1)
    region = np.where(layer_of_tet < nm, REGIONS["muscle"],
                      np.where(cen[:, 0] > 0, REGIONS["breast_left"], REGIONS["breast_right"]))
    if gland:
        for side, code in ((1, REGIONS["gland_left"]), (-1, REGIONS["gland_right"])):
            hc = height(side * c, 0.0)
            r2 = (((cen[:, 0] - side * c) / (0.5 * sigma)) ** 2 + (cen[:, 2] / (0.5 * sigma)) ** 2
                  + ((cen[:, 1] + 0.5 * hc) / (0.3 * hc)) ** 2)
            region = np.where((layer_of_tet >= nm) & (r2 < 1.0), code, region)
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
        "fascia_superior": if_nodes[zn[if_nodes] > half_height - tol],
        "fascia_inferior": if_nodes[zn[if_nodes] < -half_height + tol],
    }
    # Ligaments: breast node one layer above the interface, muscle node mid-slab, offset so
    # that the cable tightens when the breast slides away from its support.
    lb, lm = nm + 1, nm // 2
    ic, kc = np.argmin(np.abs(xs - c)), nz // 2
    pairs = {"inframammary": [], "medial": [], "lateral": []}
    for side in (1, -1):
        i0 = ic if side > 0 else nx - ic
        for di in (-1, 0, 1):
            pairs["inframammary"].append((idx[i0 + di, 1, lb], idx[i0 + di, 0, lm]))
        i_med, i_mid = (nx // 2 + 2 * side), nx // 2
        i_lat, i_edge = (nx - 1, nx) if side > 0 else (1, 0)
        for dk in (-1, 0, 1):
            pairs["medial"].append((idx[i_med, kc + dk, lb], idx[i_mid, kc + dk, lm]))
            pairs["lateral"].append((idx[i_lat, kc + dk, lb], idx[i_edge, kc + dk, lm]))
    return Mesh(nodes, tets, region, node_sets=node_sets,
                face_sets={"skin": skin, "interface": interface},
                node_pairs={f"ligament_{g}": np.array(p) for g, p in pairs.items()})


GRAVITY = {"prone": (0.0, -1.0, 0.0), "supine": (0.0, 1.0, 0.0),
           "tilted": (np.sqrt(0.5), np.sqrt(0.5), 0.0)}


def paper_model(mesh, E_breast, E_skin, E_fascia, position, **changes):
    """The paper's model (all effects) on ``mesh``; ``changes`` replace effect tables, None
    drops one. Moduli in kPa; ``position`` a key of ``GRAVITY``."""
    mats = {r: {"name": "neo_hookean", "E": E_breast, "nu": 0.49} for r in (1, 3, 4, 5)}
    mats[2] = {"name": "neo_hookean", "E": 10.0, "nu": 0.49}
    effects = {
        "gravity": {"direction": GRAVITY[position]},
        "supports": {},
        "skin": {"E": E_skin},
        "fascia": {"E": E_fascia},
        "ligaments": {"E": 100.0},
        "sliding": {"friction": 0.1},
        "regions": {"E_left": E_breast, "E_right": E_breast, "gland": False},
    }
    for k, v in changes.items():
        if v is None:
            effects.pop(k)
        else:
            effects[k] = v
    return build_model(mesh, mats, effects)
