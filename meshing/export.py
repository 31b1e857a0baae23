"""Reading and writing meshes and surfaces: VTU (ParaView, 3D Slicer), VTP, PLY.

FEBio ``.feb`` files come from the one writer, :mod:`mechanics.febio`
(``breastmodel.febio.write_mesh_feb`` for a mesh).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imaging.atomic import write_atomic_with
from mechanics.mesh import Mesh


def _atomic(path: Path, write) -> Path:
    """Run ``write(tmp)`` on a uniquely named temporary file in the target folder, then
    rename it to ``path`` (readers never see a partial file; two writers never share a
    temporary name); the temporary file is removed on failure."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_atomic_with(path, write, suffix=path.suffix)


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


def write_vtu(path: str | Path, mesh: Mesh, *, points: np.ndarray | None = None,
              fields: dict[str, np.ndarray] | None = None,
              cell_fields: dict[str, np.ndarray] | None = None) -> Path:
    """VTK unstructured grid of a tet mesh: the one VTU writer.

    Parameters
    ----------
    path : output file (.vtu)
    mesh : the mesh; cell data ``region`` and point data for every named node set and node
        pair (see :func:`point_data`) are always written. Face sets appear through their
        nodes.
    points : (N, 3) positions to write, mm (default the mesh nodes; e.g. deformed positions)
    fields : further point data, name -> (N,) or (N, k) array
    cell_fields : further cell data, name -> (M,) or (M, k) array
    """
    import meshio

    pd = point_data(mesh)
    pd.update({k: np.asarray(v) for k, v in (fields or {}).items()})
    cd = {"region": [np.asarray(mesh.region, np.int32)]}
    cd.update({k: [np.asarray(v)] for k, v in (cell_fields or {}).items()})
    pts = np.asarray(mesh.nodes if points is None else points, float)
    if pts.shape != (mesh.n_nodes, 3):
        raise ValueError(f"write_vtu: points must be ({mesh.n_nodes}, 3), got {pts.shape}")
    m = meshio.Mesh(points=pts, cells=[("tetra", np.asarray(mesh.tets))], cell_data=cd,
                    point_data=pd)
    return _atomic(Path(path), lambda p: meshio.write(p, m, file_format="vtu"))


def read_vtu(path: str | Path) -> Mesh:
    """Read a tet mesh: cell data ``region`` (int; all 1 if absent) and every 1-D point-data
    array whose values are all 0 or 1 as a node set of the same name.

    Raises
    ------
    OSError
        The file does not exist.
    ValueError
        The file is not a readable mesh, has no linear tets, or its mesh is invalid (names
        the file).
    """
    import logging

    import meshio

    log = logging.getLogger("meshing.export")
    path = Path(path)
    if not path.is_file():
        raise OSError(f"mesh file {path} does not exist")
    try:
        m = meshio.read(path)
    except (Exception, SystemExit) as exc:  # meshio raises many types (even SystemExit)
        raise ValueError(f"cannot read mesh {path}: {exc}") from None
    blocks = [i for i, c in enumerate(m.cells) if c.type == "tetra"]
    if not blocks:
        kinds = sorted({c.type for c in m.cells})
        raise ValueError(f"mesh {path} has no linear tetrahedra (cell types: {kinds})")
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
    nodes = np.asarray(m.points, float)[:, :3]
    try:
        return Mesh(nodes, tets, region, node_sets=node_sets)
    except ValueError as exc:
        raise ValueError(f"invalid mesh in {path}: {exc}") from None


def write_ply(vertices: np.ndarray, triangles: np.ndarray, path: str | Path) -> Path:
    """Triangle surface as binary PLY (vertices in mm; vertex indices as PLY's 32-bit int,
    which meshio would otherwise cast to with a warning on every file)."""
    import meshio

    m = meshio.Mesh(np.asarray(vertices, float), [("triangle", np.asarray(triangles, np.int32))])
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
