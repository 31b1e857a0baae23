"""The collector of one FEBio 4.0 file (:class:`FebBuilder`): named node sets, surfaces and
surface pairs, material blocks, shell domains, discrete springs, body force, prescribed and
zero displacements, nodal forces, contact, and the approximations a caller allowed. Effect
and material hooks add to it; :mod:`mechanics.febio_document` renders the file."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from mechanics.febio_document import document
from mechanics.febio_xml import (
    ELEMENTS,
    _ids,
    _num,
    _param_lines,
    _rows,
    tet10_nodes,
    unsupported,
)
from mechanics.mesh import REGIONS

if TYPE_CHECKING:
    from mechanics.model import Model


class FebBuilder:
    """Collects the sections of one FEBio 4.0 file; effect and material hooks add to it.

    Attributes read by hooks: ``model``, ``mesh``, ``X`` ((N, 3) reference positions, mm),
    ``element``. Node indices passed to the builder are the mesh's (0-based); the builder
    writes FEBio's 1-based ids and, for tet10, extends node sets to the mid-edge nodes.
    """

    SECTIONS = ("Mesh", "MeshData", "Boundary", "Loads", "Contact", "Discrete")

    def __init__(self, model: Model, X: np.ndarray, *, element: str = "ut4",
                 approximate: bool = False):
        if element not in ELEMENTS:
            raise ValueError(f"FEBio export: element must be one of {ELEMENTS}, got {element!r}")
        self.model, self.mesh, self.element = model, model.mesh, element
        self.X = np.asarray(X, np.float64)
        if self.X.shape != (self.mesh.n_nodes, 3):
            raise ValueError(f"FEBio export: X must be ({self.mesh.n_nodes}, 3), "
                             f"got {self.X.shape}")
        self.allow_approximations = bool(approximate)
        self.approximations: list[str] = []
        self.notes: list[str] = []  # how an effect is written, where FEBio's words differ
        self.lines: dict[str, list[str]] = {s: [] for s in self.SECTIONS}
        self.materials: list[str] = []  # material blocks (lines), in id order
        self.material_names: list[str] = []
        self.density: dict[int, float] = {}  # region -> kg/mm^3 (gravity sets it)
        self.body_force: np.ndarray | None = None  # (3,) mm/s^2, times density
        names = {v: k for k, v in REGIONS.items()}
        # one namespace per kind of FEBio list; solid parts are named after their regions
        self._names: dict[str, set[str]] = {"part": {names.get(int(c), f"region_{int(c)}")
                                                     for c in np.unique(self.mesh.region)}}
        self._next_elem = 1 + self.mesh.n_tets
        self.shell_domains: list[tuple[str, str, float]] = []  # (name, material, thickness)
        self.shell_elements: list[str] = []
        self._discrete_materials: list[str] = []
        self._discrete: list[str] = []
        if element == "tet10":
            self.nodes_out, self.tets_out, self._edges = tet10_nodes(self.X, self.mesh.tets)
        else:
            self.nodes_out, self.tets_out, self._edges = self.X, self.mesh.tets, None

    # -- names and sets ------------------------------------------------------------------
    def unique(self, base: str, kind: str) -> str:
        """A name not used yet for this ``kind`` of list ("node_set", "surface", "part",
        "discrete_set", "data", ...), from ``base``."""
        used = self._names.setdefault(kind, set())
        name, k = base, 1
        while name in used:
            k += 1
            name = f"{base}_{k}"
        used.add(name)
        return name

    def _extend(self, nodes: np.ndarray) -> np.ndarray:
        """Node indices in the written mesh: for tet10, plus the mid-edge nodes of edges whose
        both ends are in ``nodes``."""
        nodes = np.unique(np.asarray(nodes, np.int64).ravel())
        if self._edges is None:
            return nodes
        both = np.isin(self._edges, nodes).all(axis=1)
        return np.concatenate([nodes, self.mesh.n_nodes + np.flatnonzero(both)])

    def node_set(self, base: str, nodes) -> str:
        """Add a node set (0-based mesh node indices); returns its name."""
        name = self.unique(base, "node_set")
        ids = self._extend(nodes)
        self.lines["Mesh"].append(f'\t\t<NodeSet name="{name}">{_ids(ids)}</NodeSet>')
        return name

    def require_linear_faces(self, owner: str) -> None:
        """Refuse surface-based effects on quadratic tets (their faces have mid-edge nodes)."""
        if self.element == "tet10":
            raise unsupported(owner, "surfaces, shells and contact are written for linear "
                              "faces only; use element 'ut4' or 'tet4'")

    def export_sets(self) -> None:
        """Write every named set of the mesh under its own name (node sets, face sets as
        surfaces, node pairs as discrete sets), for users who edit the file further."""
        mesh = self.mesh
        for k, ids in mesh.node_sets.items():
            self.node_set(k, ids)
        for k, f in mesh.face_sets.items():
            self.surface(k, f, owner=f"face set {k!r}")
        for k, pairs in mesh.node_pairs.items():
            name = self.unique(k, "discrete_set")
            self.lines["Mesh"] += ([f'\t\t<DiscreteSet name="{name}">']
                                   + [f"\t\t\t<delem>{_ids(p)}</delem>" for p in pairs]
                                   + ["\t\t</DiscreteSet>"])

    def surface(self, base: str, faces, *, owner: str = "surface") -> str:
        """Add a tri3 surface (faces (k, 3), 0-based, right-hand normal = outward); returns
        its name."""
        self.require_linear_faces(owner)
        name = self.unique(base, "surface")
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        lines = [f'\t\t<Surface name="{name}">']
        lines += _rows("tri3", faces, 1)
        lines.append("\t\t</Surface>")
        self.lines["Mesh"] += lines
        return name

    def surface_pair(self, base: str, primary: str, secondary: str) -> str:
        """Add a contact surface pair of two surfaces added before; returns its name."""
        name = self.unique(base, "surface_pair")
        self.lines["Mesh"] += [f'\t\t<SurfacePair name="{name}">',
                               f"\t\t\t<primary>{primary}</primary>",
                               f"\t\t\t<secondary>{secondary}</secondary>",
                               "\t\t</SurfacePair>"]
        return name

    # -- materials, domains --------------------------------------------------------------
    def material(self, base: str, ftype: str, params: Mapping[str, Any]) -> str:
        """Add a material block (FEBio type and parameters); returns its name (``mat`` of a
        domain). Its id is its position."""
        name, k = base, 1
        while name in self.material_names:
            k += 1
            name = f"{base}_{k}"
        mid = len(self.materials) + 1
        block = [f'\t\t<material id="{mid}" name="{name}" type="{ftype}">']
        block += _param_lines(params, "\t\t\t")
        block.append("\t\t</material>")
        self.materials.append("\n".join(block))
        self.material_names.append(name)
        return name

    def shell_domain(self, base: str, faces, material: str, thickness: float, *,
                     owner: str = "shell") -> str:
        """Add tri3 shell elements (faces (k, 3), 0-based) of one thickness (mm) with a material
        added before; returns the domain name."""
        self.require_linear_faces(owner)
        name = self.unique(base, "part")
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        lines = [f'\t\t<Elements type="tri3" name="{name}">']
        lines += _rows("elem", faces, self._next_elem)
        self._next_elem += len(faces)
        lines.append("\t\t</Elements>")
        self.shell_elements += lines
        self.shell_domains.append((name, material, float(thickness)))
        return name

    def discrete(self, base: str, pairs, ftype: str, params: Mapping[str, Any]) -> str:
        """Add two-node discrete elements (pairs (k, 2), 0-based) with one discrete material;
        returns the discrete set's name."""
        name = self.unique(base, "discrete_set")
        pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
        self.lines["Mesh"] += ([f'\t\t<DiscreteSet name="{name}">']
                               + [f"\t\t\t<delem>{_ids(p)}</delem>" for p in pairs]
                               + ["\t\t</DiscreteSet>"])
        did = len(self._discrete_materials) + 1
        mname = self.unique(f"{name}_material", "discrete_material")
        block = [f'\t\t<discrete_material id="{did}" name="{mname}" type="{ftype}">']
        block += _param_lines(params, "\t\t\t")
        block.append("\t\t</discrete_material>")
        self._discrete_materials.append("\n".join(block))
        self._discrete.append(f'\t\t<discrete dmat="{did}" discrete_set="{name}"/>')
        return name

    # -- loads and conditions ------------------------------------------------------------
    def set_body_force(self, acceleration: np.ndarray, density_by_region: Mapping[int, float],
                       *, owner: str = "gravity") -> None:
        """Set the body force: ``acceleration`` (3,) mm/s^2 acting on every region with its
        density (kg/mm^3; regions not listed weigh nothing). One per model."""
        if self.body_force is not None:
            raise unsupported(f"effect {owner!r}", "FEBio takes one body force per model here "
                              "and another was set already")
        self.body_force = np.asarray(acceleration, float).reshape(3)
        self.density = {int(k): float(v) for k, v in density_by_region.items()}

    def fix(self, base: str, nodes, components: Iterable[int], values=None) -> None:
        """Dirichlet condition: components (subset of 0, 1, 2) of ``nodes`` (0-based) are zero
        (``values`` None) or reach ``values`` ((k, len(components)) mm) at full load."""
        comps = tuple(int(c) for c in components)
        nodes = np.asarray(nodes, np.int64).ravel()
        if len(nodes) == 0:
            return
        if values is None:
            name = self.node_set(base, nodes)
            dofs = "".join(f"\t\t\t<{'xyz'[c]}_dof>1</{'xyz'[c]}_dof>\n" for c in comps)
            self.lines["Boundary"].append(
                f'\t\t<bc name="{name}" node_set="{name}" type="zero displacement">\n'
                f"{dofs}\t\t</bc>")
            return
        values = np.broadcast_to(np.asarray(values, float), (len(nodes), len(comps)))
        order = np.argsort(nodes, kind="stable")
        nodes, values = nodes[order], values[order]
        if len(np.unique(nodes)) != len(nodes):
            raise ValueError(f"FEBio export: {base}: a node is prescribed twice")
        # tet10: a mid-edge node of an edge with both ends prescribed gets their mean.
        ext = self._extend(nodes)
        vals = np.zeros((len(ext), len(comps)))
        vals[:len(nodes)] = values
        if len(ext) > len(nodes):
            pos = {int(n): i for i, n in enumerate(nodes)}
            ends = self._edges[ext[len(nodes):] - self.mesh.n_nodes]
            vals[len(nodes):] = 0.5 * (values[[pos[int(a)] for a in ends[:, 0]]]
                                       + values[[pos[int(b)] for b in ends[:, 1]]])
        name = self.unique(base, "node_set")
        self.lines["Mesh"].append(f'\t\t<NodeSet name="{name}">{_ids(ext)}</NodeSet>')
        for j, c in enumerate(comps):
            data = self.unique(f"{name}_{'xyz'[c]}", "data")
            self.lines["MeshData"].append(
                f'\t\t<NodeData name="{data}" node_set="{name}" data_type="scalar">\n'
                + "".join(f'\t\t\t<node lid="{i + 1}">{_num(v)}</node>\n'
                          for i, v in enumerate(vals[:, j])) + "\t\t</NodeData>")
            self.lines["Boundary"].append(
                f'\t\t<bc name="{data}" node_set="{name}" type="prescribed displacement">\n'
                f"\t\t\t<dof>{'xyz'[c]}</dof>\n"
                f'\t\t\t<value lc="1" type="map">{data}</value>\n'
                f"\t\t\t<relative>0</relative>\n\t\t</bc>")

    def nodal_force(self, base: str, nodes, force) -> None:
        """Dead nodal forces ``force`` ((k, 3) mN) on ``nodes`` (0-based), ramped with the
        load."""
        nodes = np.asarray(nodes, np.int64).ravel()
        force = np.broadcast_to(np.asarray(force, float), (len(nodes), 3))
        keep = np.any(force != 0.0, axis=1)
        nodes, force = nodes[keep], force[keep]
        if len(nodes) == 0:
            return
        name = self.unique(base, "node_set")
        self.lines["Mesh"].append(f'\t\t<NodeSet name="{name}">{_ids(nodes)}</NodeSet>')
        data = self.unique(f"{name}_force", "data")
        self.lines["MeshData"].append(
            f'\t\t<NodeData name="{data}" node_set="{name}" data_type="vec3">\n'
            + "".join(f'\t\t\t<node lid="{i + 1}">{",".join(_num(c) for c in f)}</node>\n'
                      for i, f in enumerate(force)) + "\t\t</NodeData>")
        self.lines["Loads"].append(
            f'\t\t<nodal_load name="{name}" type="nodal_force" node_set="{name}">\n'
            f'\t\t\t<value lc="1" type="map">{data}</value>\n\t\t</nodal_load>')

    def contact(self, ftype: str, pair: str, params: Mapping[str, Any]) -> None:
        """Add a contact interface of FEBio type ``ftype`` on a surface pair."""
        block = [f'\t\t<contact type="{ftype}" surface_pair="{pair}">']
        block += _param_lines(params, "\t\t\t")
        block.append("\t\t</contact>")
        self.lines["Contact"].append("\n".join(block))

    def approximate(self, owner: str, why: str) -> None:
        """Record that ``owner`` is written approximately; refused unless the caller allowed
        approximations (``approximate=True``)."""
        if not self.allow_approximations:
            raise unsupported(owner, f"{why} (pass approximate=True to write it anyway)")
        self.approximations.append(f"{owner}: {why}")

    def note(self, owner: str, text: str) -> None:
        """Say in the file how ``owner`` is written, where that is not read off its values
        (a comment, ``<!-- note: ... -->``)."""
        self.notes.append(f"{owner}: {text}")

    # -- the file ------------------------------------------------------------------------
    def must_points(self, steps: int) -> list[float]:
        """Times in (0, 1] where FEBio must converge a step: the step ends k / steps and the
        effects' path points (friction history), when an effect has any; else none."""
        path = sorted({float(p) for e in self.model.effects for p in e.path_points()})
        if not path:
            return []
        return sorted({round(k / steps, 12) for k in range(1, steps + 1)} | set(path))

    def text(self, *, steps: int, solver: str, tol: Mapping[str, float]) -> str:
        """The complete file (:func:`mechanics.febio_document.document`)."""
        return document(self, steps=steps, solver=solver, tol=tol)
