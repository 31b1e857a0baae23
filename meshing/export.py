"""Writing meshes and surfaces: VTU (ParaView, 3D Slicer), FEBio ``.feb`` 4.0, PLY."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mechanics.mesh import REGIONS, Mesh

#: Placeholder neo-Hookean Young's moduli (kPa) for the FEBio file: the paper's optimum
#: order of magnitude; the user sets the real ones in FEBio.
FEB_YOUNG_KPA = {"breast_left": 0.3, "breast_right": 0.3, "gland_left": 0.3,
                 "gland_right": 0.3, "muscle": 10.0}
FEB_POISSON = 0.49
FEB_DENSITY = 1e-6  # kg/mm^3 (1000 kg/m^3) in the mm-kg-s system (forces mN, stresses kPa)


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


def _ids(a) -> str:
    return ",".join(str(int(i) + 1) for i in np.asarray(a).ravel())


def feb_text(mesh: Mesh) -> str:
    """FEBio 4.0 input text: nodes, one tet4 domain per region with a neo-Hookean
    placeholder material, the face sets as surfaces, node sets, node pairs as discrete sets,
    and a zero-displacement condition on ``fixed``. Element ids follow the region order."""
    names = {v: k for k, v in REGIONS.items()}
    codes = [int(c) for c in np.unique(mesh.region)]
    out = ['<?xml version="1.0" encoding="ISO-8859-1"?>', '<febio_spec version="4.0">',
           "\t<!-- breastmodel mesh; units mm, kPa, s, kg (forces mN) -->",
           '\t<Module type="solid"/>', "\t<Control>", "\t\t<analysis>STATIC</analysis>",
           "\t\t<time_steps>10</time_steps>", "\t\t<step_size>0.1</step_size>", "\t</Control>",
           "\t<Material>"]
    for mid, c in enumerate(codes, start=1):
        name = names.get(c, f"region_{c}")
        out += [f'\t\t<material id="{mid}" name="{name}" type="neo-Hookean">',
                f"\t\t\t<density>{FEB_DENSITY:g}</density>",
                f"\t\t\t<E>{FEB_YOUNG_KPA.get(name, 1.0):g}</E>",
                f"\t\t\t<v>{FEB_POISSON:g}</v>", "\t\t</material>"]
    out += ["\t</Material>", "\t<Mesh>", '\t\t<Nodes name="all">']
    out += [f'\t\t\t<node id="{i + 1}">{x:.6f},{y:.6f},{z:.6f}</node>'
            for i, (x, y, z) in enumerate(mesh.nodes)]
    out.append("\t\t</Nodes>")
    eid = 1
    for c in codes:
        name = names.get(c, f"region_{c}")
        out.append(f'\t\t<Elements type="tet4" name="{name}">')
        for t in mesh.tets[mesh.region == c]:
            out.append(f'\t\t\t<elem id="{eid}">{_ids(t)}</elem>')
            eid += 1
        out.append("\t\t</Elements>")
    for k, f in mesh.face_sets.items():
        out.append(f'\t\t<Surface name="{k}">')
        out += [f'\t\t\t<tri3 id="{i + 1}">{_ids(t)}</tri3>' for i, t in enumerate(f)]
        out.append("\t\t</Surface>")
    for k, ids in mesh.node_sets.items():
        out.append(f'\t\t<NodeSet name="{k}">{_ids(ids)}</NodeSet>')
    for k, pairs in mesh.node_pairs.items():
        out.append(f'\t\t<DiscreteSet name="{k}">')
        out += [f"\t\t\t<delem>{_ids(p)}</delem>" for p in pairs]
        out.append("\t\t</DiscreteSet>")
    out.append("\t</Mesh>")
    out.append("\t<MeshDomains>")
    for c in codes:
        name = names.get(c, f"region_{c}")
        out.append(f'\t\t<SolidDomain name="{name}" mat="{name}"/>')
    out.append("\t</MeshDomains>")
    if "fixed" in mesh.node_sets and len(mesh.node_sets["fixed"]):
        out += ["\t<Boundary>",
                '\t\t<bc name="fixed" node_set="fixed" type="zero displacement">',
                "\t\t\t<x_dof>1</x_dof>", "\t\t\t<y_dof>1</y_dof>", "\t\t\t<z_dof>1</z_dof>",
                "\t\t</bc>", "\t</Boundary>"]
    out.append("</febio_spec>")
    return "\n".join(out) + "\n"


def write_feb(mesh: Mesh, path: str | Path) -> Path:
    """Write :func:`feb_text` to ``path``."""
    text = feb_text(mesh)
    return _atomic(Path(path), lambda p: p.write_text(text, encoding="latin-1"))
