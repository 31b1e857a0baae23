"""A zoo of tiny canonical tet meshes for tests (numpy only, deterministic).

Every builder returns a :class:`mechanics.mesh.Mesh` with positively oriented tets, region 1
and a few named node sets.
"""

from __future__ import annotations

import numpy as np

from mechanics.mesh import KUHN, Mesh, orient_tets

# Kuhn split of the unit cube along its 0-7 diagonal: six tets, conforming between cells.
_CORNERS = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)], float)
_KUHN = KUHN
_FIVE = np.array([[0, 1, 2, 4], [1, 3, 2, 7], [1, 4, 5, 7], [2, 7, 6, 4], [1, 2, 4, 7]])


orient = orient_tets


def _face_sets_by_plane(nodes, tol=1e-9):
    lo, hi = nodes.min(axis=0), nodes.max(axis=0)
    sets = {}
    for axis, name in enumerate("xyz"):
        sets[f"{name}min"] = np.flatnonzero(np.abs(nodes[:, axis] - lo[axis]) < tol)
        sets[f"{name}max"] = np.flatnonzero(np.abs(nodes[:, axis] - hi[axis]) < tol)
    return sets


def single_tet() -> Mesh:
    """The unit right tetrahedron (1 mm legs)."""
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    return Mesh(nodes, [[0, 1, 2, 3]], [1], node_sets={"base": [0, 1, 2]})


def cube6() -> Mesh:
    """Unit cube split into 6 tets (Kuhn)."""
    return Mesh(_CORNERS, orient(_CORNERS, _KUHN), np.ones(6),
                node_sets=_face_sets_by_plane(_CORNERS))


def cube5() -> Mesh:
    """Unit cube split into 5 tets (one central tet)."""
    return Mesh(_CORNERS, orient(_CORNERS, _FIVE), np.ones(5),
                node_sets=_face_sets_by_plane(_CORNERS))


def box(shape=(2, 2, 2), size=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)) -> Mesh:
    """Structured box of nx*ny*nz cells, 6 Kuhn tets each. Node sets xmin..zmax."""
    nx, ny, nz = shape
    g = np.stack(np.meshgrid(*(np.linspace(0, s, n + 1) for s, n in zip(size, shape)),
                             indexing="ij"), axis=-1)
    nodes = g.reshape(-1, 3) + np.asarray(origin, float)
    idx = np.arange(len(nodes)).reshape(nx + 1, ny + 1, nz + 1)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    corner = np.stack([idx[i + a, j + b, k + c] for c in (0, 1) for b in (0, 1)
                       for a in (0, 1)], axis=1)  # (cells, 8) in _CORNERS order
    tets = corner[:, _KUHN].reshape(-1, 4)
    return Mesh(nodes, orient(nodes, tets), np.ones(len(tets)),
                node_sets=_face_sets_by_plane(nodes))


def irregular_cube(n: int = 3, *, seed: int = 0, amplitude: float = 0.2) -> Mesh:
    """Unit cube, n^3 cells, interior nodes moved randomly by up to amplitude * h."""
    m = box((n, n, n))
    rng = np.random.default_rng(seed)
    nodes = m.nodes.copy()
    interior = np.all((nodes > 1e-9) & (nodes < 1 - 1e-9), axis=1)
    nodes[interior] += amplitude / n * rng.uniform(-1, 1, (int(interior.sum()), 3))
    return Mesh(nodes, orient(nodes, m.tets), m.region, node_sets=m.node_sets)


def hemisphere(radius: float = 60.0, n: int = 8) -> Mesh:
    """Half ball z in [-radius, 0] (flat face at z = 0), mapped from a structured half cube.

    ``n`` cells across the diameter and n // 2 through the depth: 6 n^2 (n // 2) tets
    (n = 19: 20k tets, n = 37: 150k).
    The cube [-1,1]^2 x [-1,0] is mapped to the ball by the smooth elliptical map
    x' = x sqrt(1 - y^2/2 - z^2/2 + y^2 z^2/3) (cyclic), which keeps the flat face flat.
    Node set ``"fixed"``: the flat face.
    """
    nz = max(1, n // 2)
    m = box((n, n, nz), size=(2.0, 2.0, 1.0), origin=(-1.0, -1.0, -1.0))
    p = m.nodes
    q = p**2
    nodes = np.empty_like(p)
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        nodes[:, a] = p[:, a] * np.sqrt(1 - q[:, b] / 2 - q[:, c] / 2 + q[:, b] * q[:, c] / 3)
    nodes *= radius
    fixed = np.flatnonzero(np.abs(p[:, 2]) < 1e-12)
    return Mesh(nodes, orient(nodes, m.tets), m.region, node_sets={"fixed": fixed})
