"""Split a conforming breast-muscle interface so that the two sides can slide."""

from __future__ import annotations

import numpy as np

from mechanics.mesh import BREAST_REGIONS, Mesh

#: Node sets that belong to the breast side (they follow the breast copies of the nodes).
BREAST_NODE_SETS = ("skin_superior", "skin_inferior", "skin_lateral", "fascia_superior",
                    "fascia_inferior")
#: Face sets that belong to the breast side.
BREAST_FACE_SETS = ("skin", "interface")


def split_interface(mesh: Mesh, *, breast_node_sets=BREAST_NODE_SETS,
                    breast_face_sets=BREAST_FACE_SETS) -> Mesh:
    """Duplicate the interface nodes of a conforming mesh; the breast side gets new nodes.

    Parameters
    ----------
    mesh : Mesh with face set ``"interface"`` (triangles shared by breast and muscle tets,
        normal from muscle into breast)
    breast_node_sets, breast_face_sets : sets whose interface nodes move to the breast copies;
        ligament pairs (``node_pairs``) move their first (breast) column. Every other set keeps
        the original (muscle side) nodes.

    Returns
    -------
    Mesh with ``n_nodes + k`` nodes (k interface nodes; the copies are appended in ascending
    order of the original index, at the same positions), breast tets renumbered, face set
    ``"interface"`` on the breast copies and ``"interface_muscle"`` on the original muscle
    nodes (same triangles, same orientation: normal from muscle into breast).
    """
    if "interface" not in mesh.face_sets:
        raise ValueError("split_interface: the mesh has no face set 'interface'")
    if "interface_muscle" in mesh.face_sets:
        raise ValueError("split_interface: the mesh is already split ('interface_muscle' exists)")
    faces = np.asarray(mesh.face_sets["interface"], np.int64)
    shared = np.unique(faces)
    n = mesh.n_nodes
    new_id = np.arange(n, dtype=np.int64)
    new_id[shared] = n + np.arange(len(shared))
    breast = np.isin(mesh.region, np.asarray(BREAST_REGIONS))
    tets = mesh.tets.copy()
    tets[breast] = new_id[tets[breast]]
    nodes = np.concatenate([mesh.nodes, mesh.nodes[shared]])
    node_sets = {k: (new_id[v] if k in breast_node_sets else v) for k, v in mesh.node_sets.items()}
    face_sets = {k: (new_id[v] if k in breast_face_sets else v) for k, v in mesh.face_sets.items()}
    face_sets["interface_muscle"] = faces
    face_sets["interface"] = new_id[faces]
    node_pairs = {}
    for k, v in mesh.node_pairs.items():
        p = np.array(v, np.int64).reshape(-1, 2)
        p[:, 0] = new_id[p[:, 0]]
        node_pairs[k] = p
    return Mesh(nodes, tets, mesh.region, node_sets=node_sets, face_sets=face_sets,
                node_pairs=node_pairs)
