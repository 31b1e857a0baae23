"""The tetrahedral mesh that passes from meshing to mechanics: an immutable value.

Region codes are fixed project-wide (see ``REGIONS``); named sets carry everything the
effects need (skin faces, interface faces, fixed nodes, ligament anchor pairs).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType

import numpy as np

#: Region code of each tissue in ``Mesh.region``. Label maps use 1 breast, 2 muscle, 3 gland.
REGIONS: Mapping[str, int] = MappingProxyType(
    {
        "breast_left": 1,
        "muscle": 2,
        "breast_right": 3,
        "gland_left": 4,
        "gland_right": 5,
        # the breast's outermost tets, one element thick under the skin, given their own law
        # only by a truth model whose skin is a solid layer (never by the pipeline's meshes)
        "skin_layer_left": 6,
        "skin_layer_right": 7,
        # the breast's deepest tets, one element thick on the breast-muscle interface: the
        # loose retromammary tissue the breast slides on, given its own law only by a truth
        # model (see ``LAYER_REGIONS``)
        "interface_layer_left": 8,
        "interface_layer_right": 9,
    }
)
BREAST_REGIONS = (1, 3, 4, 5, 6, 7, 8, 9)
#: Face set -> the codes (left, right) of the layer of breast tets on it, see
#: :func:`with_layer`.
LAYER_REGIONS: Mapping[str, tuple[int, int]] = MappingProxyType({
    "skin": (REGIONS["skin_layer_left"], REGIONS["skin_layer_right"]),
    "interface": (REGIONS["interface_layer_left"], REGIONS["interface_layer_right"]),
})
#: Layers made of every breast tet with a node on the set (not only those owning a face): a
#: soft layer must separate the breast from what lies beyond it, see :func:`with_layer`.
LAYER_BY_NODE = frozenset({"interface"})
#: Breast region code -> its side's bulk code (breast_left 1 or breast_right 3).
BREAST_SIDE: Mapping[int, int] = MappingProxyType(
    {1: 1, 4: 1, 6: 1, 8: 1, 3: 3, 5: 3, 7: 3, 9: 3})


def _frozen(a, dtype) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def _frozen_map(m: Mapping[str, np.ndarray] | None, dtype) -> Mapping[str, np.ndarray]:
    return MappingProxyType({str(k): _frozen(v, dtype) for k, v in (m or {}).items()})


@dataclass(frozen=True, eq=False)
class Mesh:
    """Linear tetrahedral mesh in physical mm.

    Parameters
    ----------
    nodes : (N, 3) float64, mm
    tets : (M, 4) int64, node indices, positive orientation (det of edge matrix > 0)
    region : (M,) int32, codes from ``REGIONS``
    node_sets : name -> (k,) int64 node indices, e.g. ``"fixed"``, ``"skin_superior"``
    face_sets : name -> (k, 3) int64 triangles, e.g. ``"skin"``, ``"interface"``; ordered so
        that the right-hand normal points out of the breast (skin) or from muscle to breast
        (interface)
    node_pairs : name -> (k, 2) int64 (breast node, muscle node), e.g. ``"ligament_medial"``
    """

    nodes: np.ndarray
    tets: np.ndarray
    region: np.ndarray
    node_sets: Mapping[str, np.ndarray] = field(default_factory=dict)
    face_sets: Mapping[str, np.ndarray] = field(default_factory=dict)
    node_pairs: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        nodes = _frozen(self.nodes, np.float64)
        tets = _frozen(self.tets, np.int64)
        region = _frozen(self.region, np.int32)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise ValueError(f"mesh: nodes must be (N, 3), got {nodes.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ValueError(f"mesh: tets must be (M, 4), got {tets.shape}")
        if region.shape != (len(tets),):
            raise ValueError(f"mesh: region must be ({len(tets)},), got {region.shape}")
        if len(tets) and (tets.min() < 0 or tets.max() >= len(nodes)):
            raise ValueError("mesh: tets reference nodes that do not exist")
        if not np.all(np.isfinite(nodes)):
            raise ValueError("mesh: nodes contain NaN or inf")
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "region", region)
        object.__setattr__(self, "node_sets", _frozen_map(self.node_sets, np.int64))
        object.__setattr__(self, "face_sets", _frozen_map(self.face_sets, np.int64))
        object.__setattr__(self, "node_pairs", _frozen_map(self.node_pairs, np.int64))

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def with_nodes(self, nodes: np.ndarray) -> Mesh:
        """Same topology and sets on new node positions (mm)."""
        return replace(self, nodes=nodes)

    def signed_volumes(self, nodes: np.ndarray | None = None) -> np.ndarray:
        """(M,) signed tet volumes in mm^3 (positive for correctly oriented tets)."""
        x = self.nodes if nodes is None else np.asarray(nodes, dtype=np.float64)
        e = x[self.tets[:, 1:]] - x[self.tets[:, :1]]
        return np.linalg.det(e) / 6.0

    def save_npz(self, path: str | Path) -> None:
        """Write the mesh with all sets to one ``.npz`` (lossless, for caching)."""
        arrays = {"nodes": self.nodes, "tets": self.tets, "region": self.region}
        for kind in ("node_sets", "face_sets", "node_pairs"):
            for k, v in getattr(self, kind).items():
                arrays[f"{kind}/{k}"] = v
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        tmp.replace(path)

    @classmethod
    def load_npz(cls, path: str | Path) -> Mesh:
        """Read a mesh written by :meth:`save_npz`."""
        with np.load(path) as z:
            sets: dict[str, dict[str, np.ndarray]] = {
                "node_sets": {},
                "face_sets": {},
                "node_pairs": {},
            }
            for key in z.files:
                if "/" in key:
                    kind, name = key.split("/", 1)
                    sets[kind][name] = z[key]
            return cls(nodes=z["nodes"], tets=z["tets"], region=z["region"], **sets)


#: Kuhn split of a hexahedral cell into 6 tets sharing the main diagonal; corners numbered
#: i + 2 j + 4 k. Neighbouring cells split this way conform.
KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7],
                 [0, 4, 6, 7]])


def orient_tets(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Copy of ``tets`` with two nodes of every negatively oriented tet swapped."""
    tets = np.array(tets, dtype=np.int64)
    e = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    neg = np.linalg.det(e) < 0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    return tets


def sorted_tet_faces(tets: np.ndarray) -> np.ndarray:
    """(4 M, 3) the four faces of every tet, node indices sorted (tet i's in rows 4 i to
    4 i + 3): equal rows are one face."""
    tets = np.asarray(tets, np.int64)
    return np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]], axis=2).reshape(-1, 3)


def face_components(tets: np.ndarray) -> np.ndarray:
    """(M,) component label of each tet, tets joined when they share a face.

    Face-connected tets form a rigid whole: each is held by the three nodes of a shared
    face. Tets that meet the rest only at an edge or a vertex can rotate about it."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    faces = sorted_tet_faces(tets)
    owner = np.repeat(np.arange(len(tets)), 4)
    _, inv = np.unique(faces, axis=0, return_inverse=True)
    order = np.argsort(inv.ravel(), kind="stable")
    key = inv.ravel()[order]
    same = np.flatnonzero(key[1:] == key[:-1])  # consecutive owners of one face
    a, b = owner[order][same], owner[order][same + 1]
    g = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(len(tets), len(tets)))
    return connected_components(g, directed=False)[1]


def hinged_tets(tets: np.ndarray, *, max_fraction: float = 0.01) -> np.ndarray:
    """Indices of the tets in small face-connected groups (at most ``max_fraction`` of the
    tets) that share a node with another group: groups hanging on the mesh by an edge or a
    vertex, free to rotate (a singular tangent)."""
    tets = np.asarray(tets, np.int64)
    label = face_components(tets)
    size = np.bincount(label)
    n_groups = np.zeros(tets.max() + 1, np.int64)  # distinct groups touching each node
    pairs = np.unique(np.stack([tets.ravel(), np.repeat(label, 4)], axis=1), axis=0)
    np.add.at(n_groups, pairs[:, 0], 1)
    shared = (n_groups[tets] > 1).any(axis=1)
    small = size[label] <= max_fraction * len(tets)
    return np.flatnonzero(shared & small)


def with_layer(mesh: Mesh, face_set: str) -> Mesh:
    """Copy of ``mesh`` whose breast tets (fat or gland) on ``face_set`` ("skin" or
    "interface") carry that set's layer code of their side (``LAYER_REGIONS``): a layer one
    element thick, for a truth model that writes the skin as a solid layer (the tets that own
    a skin face) or the breast's base as a soft layer it slides on (the tets with a node on
    the interface: a tet that touched it by an edge or a vertex only would bridge the layer
    with the breast's stiffness; with face owners alone, 10x and 50x softer layers moved
    small-003's skin alike, p95 0.9 and 1.1 mm prone). Tets of another layer keep theirs."""
    if face_set not in LAYER_REGIONS:
        raise ValueError(f"mesh: no layer codes for face set {face_set!r} "
                         f"(known: {', '.join(LAYER_REGIONS)})")
    faces = mesh.face_sets.get(face_set, np.zeros((0, 3)))
    faces = np.sort(np.asarray(faces, np.int64), axis=1)
    if face_set in LAYER_BY_NODE:
        layer = np.isin(mesh.tets, faces).any(axis=1)
    else:
        both = np.vstack([sorted_tet_faces(mesh.tets), faces])
        _, inv = np.unique(both, axis=0, return_inverse=True)
        inv = inv.ravel()
        layer = np.isin(inv[: 4 * mesh.n_tets], inv[4 * mesh.n_tets:]).reshape(-1, 4).any(1)
    region = np.array(mesh.region)
    layers = {c for pair in LAYER_REGIONS.values() for c in pair}
    for code in set(BREAST_SIDE) - layers:  # fat and gland, left and right
        region[layer & (mesh.region == code)] = LAYER_REGIONS[face_set][BREAST_SIDE[code] != 1]
    return replace(mesh, region=region)
