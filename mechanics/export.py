"""VTU export of a mesh and a solved state, and VTU import of a tet mesh (meshio, lazily).

Written point data: ``displacement`` (N, 3) mm, ``pressure`` (N,) kPa ("anp"), each node set
as a 0/1 ``uint8`` array; cell data: ``region``, ``stress`` (M, 9) Cauchy kPa (row-major),
``von_mises`` kPa, ``J``, ``stretch`` (M, 3) principal stretches (descending). Points are the
reference positions ("warp by vector" with ``displacement`` shows the deformed shape), or the
deformed positions with ``deformed=True`` (points minus ``displacement`` give the reference).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from mechanics.kernels import deformation_gradient, reference_geometry
from mechanics.mesh import Mesh

log = logging.getLogger("mechanics.export")


def principal_stretches(X: np.ndarray, x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M, 3) principal stretches per element, descending (sqrt of eigenvalues of C)."""
    dN, _ = reference_geometry(X, tets)
    F = deformation_gradient(x, tets, dN)
    C = np.einsum("mki,mkj->mij", F, F)
    return np.sqrt(np.clip(np.linalg.eigvalsh(C), 0.0, None))[:, ::-1]


def von_mises(stress: np.ndarray) -> np.ndarray:
    """(M,) von Mises equivalent of Cauchy stresses (M, 3, 3), kPa."""
    dev = stress - np.trace(stress, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("mij,mij->m", dev, dev))


def write_vtu(path, mesh: Mesh, state=None, *, X: np.ndarray | None = None,
              deformed: bool = False) -> None:
    """Write ``mesh`` (and ``state``'s fields) to a VTU file.

    Parameters
    ----------
    path : output file (.vtu)
    mesh : Mesh
    state : State or None
    X : (N, 3) reference positions in mm (default ``state.X`` or ``mesh.nodes``)
    deformed : write the deformed positions X + u as the points (needs ``state``)
    """
    import meshio

    if X is None:
        X = state.X if state is not None and state.X is not None else mesh.nodes
    X = np.asarray(X, float)
    point_data = {k: np.isin(np.arange(mesh.n_nodes), v).astype(np.uint8)
                  for k, v in mesh.node_sets.items()}
    cell_data = {"region": [np.asarray(mesh.region, np.int32)]}
    if state is not None:
        point_data["displacement"] = np.asarray(state.u, float)
        if state.pressure is not None and len(state.pressure) == mesh.n_nodes:
            point_data["pressure"] = np.asarray(state.pressure, float)
        stress = np.asarray(state.stress, float)
        cell_data["stress"] = [stress.reshape(-1, 9)]
        cell_data["von_mises"] = [von_mises(stress)]
        cell_data["J"] = [np.asarray(state.J, float)]
        cell_data["stretch"] = [principal_stretches(X, X + state.u, mesh.tets)]
    points = X + np.asarray(state.u, float) if deformed and state is not None else X
    out = meshio.Mesh(points, [("tetra", np.asarray(mesh.tets))], point_data=point_data,
                      cell_data=cell_data)
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    meshio.write(tmp, out)
    tmp.replace(path)


def read_vtu(path) -> Mesh:
    """Read a tet mesh: cell data ``region`` (int; all 1 if absent) and every 1-D point-data
    array whose values are all 0 or 1 as a node set of the same name."""
    import meshio

    path = Path(path)
    if not path.is_file():
        raise OSError(f"mechanics: mesh file {path} does not exist")
    try:
        m = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types (even SystemExit)
        raise ValueError(f"mechanics: cannot read mesh {path}: {exc}") from None
    blocks = [i for i, c in enumerate(m.cells) if c.type == "tetra"]
    if not blocks:
        kinds = sorted({c.type for c in m.cells})
        raise ValueError(f"mechanics: {path} has no linear tetrahedra (cell types: {kinds})")
    tets = np.concatenate([m.cells[i].data for i in blocks])
    if "region" in m.cell_data:
        region = np.concatenate([np.asarray(m.cell_data["region"][i]).reshape(-1)
                                 for i in blocks])
    else:
        log.warning("%s has no cell data 'region': all tets get region 1", path)
        region = np.ones(len(tets), np.int32)
    node_sets = {}
    for name, arr in m.point_data.items():
        a = np.asarray(arr)
        if a.ndim == 1 or (a.ndim == 2 and a.shape[1] == 1):
            a = a.reshape(-1)
            if np.all((a == 0) | (a == 1)):
                node_sets[name] = np.flatnonzero(a)
    used = np.unique(tets)
    nodes = np.asarray(m.points, float)[:, :3]
    if len(used) < len(nodes):
        log.info("%s: %d points are not in any tet", path, len(nodes) - len(used))
    try:
        return Mesh(nodes, tets, region, node_sets=node_sets)
    except ValueError as exc:
        raise ValueError(f"mechanics: invalid mesh in {path}: {exc}") from None
