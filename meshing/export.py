"""Writing meshes and surfaces: VTU (ParaView, 3D Slicer), PLY. (FEBio ``.feb`` files come from
the one writer, :mod:`mechanics.febio`; ``breastmodel.febio.write_mesh_feb`` for a mesh.)"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mechanics.mesh import Mesh


def _atomic(path: Path, write) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def point_data(mesh: Mesh) -> dict[str, np.ndarray]:
    """Per-node arrays for viewers: 1 on each node set; node pairs 1 breast / 2 muscle node."""
    out = {}
    for k, ids in mesh.node_sets.items():
        a = np.zeros(mesh.n_nodes, np.int8)
        a[ids] = 1
        out[k] = a
    for k, pairs in mesh.node_pairs.items():
        a = np.zeros(mesh.n_nodes, np.int8)
        if len(pairs):
            a[pairs[:, 1]] = 2
            a[pairs[:, 0]] = 1
        out[k] = a
    return out


def write_vtu(mesh: Mesh, path: str | Path) -> Path:
    """VTK unstructured grid: tets with cell data ``region`` and point data for every named
    node set and node pair (see :func:`point_data`). Face sets appear through their nodes."""
    import meshio

    m = meshio.Mesh(
        points=np.asarray(mesh.nodes),
        cells=[("tetra", np.asarray(mesh.tets))],
        cell_data={"region": [np.asarray(mesh.region, np.int32)]},
        point_data=point_data(mesh),
    )
    return _atomic(Path(path), lambda p: meshio.write(p, m, file_format="vtu"))


def write_ply(vertices: np.ndarray, triangles: np.ndarray, path: str | Path) -> Path:
    """Triangle surface as binary PLY (vertices in mm)."""
    import meshio

    m = meshio.Mesh(np.asarray(vertices, float), [("triangle", np.asarray(triangles, np.int64))])
    return _atomic(Path(path), lambda p: meshio.write(p, m, file_format="ply"))
