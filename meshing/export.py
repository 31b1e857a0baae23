"""Writing meshes and surfaces: VTU (ParaView, 3D Slicer), VTP, PLY. (FEBio ``.feb`` files come from
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


def _vtk_array(name: str, a: np.ndarray) -> str:
    a = np.asarray(a)
    k = 1 if a.ndim == 1 else a.shape[1]
    if a.dtype.kind in "iub":
        kind, text = "Int64", " ".join(str(int(x)) for x in a.ravel())
    else:
        kind, text = "Float64", " ".join(repr(float(x)) for x in a.ravel())
    return (f'<DataArray type="{kind}" Name="{name}" NumberOfComponents="{k}" '
            f'format="ascii">{text}</DataArray>')


def write_vtp(vertices: np.ndarray, triangles: np.ndarray, path: str | Path, *,
              point_data: dict[str, np.ndarray] | None = None) -> Path:
    """Triangle surface as VTK XML PolyData (``.vtp``, ASCII), the format ParaView opens
    with its point data ready to colour by.

    Parameters
    ----------
    vertices : (n, 3) mm
    triangles : (m, 3) int, 0-based
    path : output file
    point_data : name -> (n,) or (n, k) array (float or int); the first is the active
        scalar
    """
    v = np.asarray(vertices, float).reshape(-1, 3)
    f = np.asarray(triangles, np.int64).reshape(-1, 3)
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"write_vtp: triangle indices outside 0..{len(v) - 1}")
    point_data = dict(point_data or {})
    for k, a in point_data.items():
        if len(a) != len(v):
            raise ValueError(f"write_vtp: point data {k!r} has {len(a)} values for "
                             f"{len(v)} points")
    pd = "".join(_vtk_array(k, a) for k, a in point_data.items())
    scalars = f' Scalars="{next(iter(point_data))}"' if point_data else ""
    doc = ('<?xml version="1.0"?>\n<VTKFile type="PolyData" version="1.0" '
           'byte_order="LittleEndian" header_type="UInt64">\n<PolyData>\n'
           f'<Piece NumberOfPoints="{len(v)}" NumberOfPolys="{len(f)}">\n'
           f"<PointData{scalars}>{pd}</PointData>\n"
           f"<Points>{_vtk_array('Points', v)}</Points>\n"
           f"<Polys>{_vtk_array('connectivity', f.ravel())}"
           f"{_vtk_array('offsets', 3 * np.arange(1, len(f) + 1))}</Polys>\n"
           "</Piece>\n</PolyData>\n</VTKFile>\n")
    return _atomic(Path(path), lambda p: p.write_text(doc))
