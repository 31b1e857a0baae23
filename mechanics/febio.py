"""FEBio 4.0 input files from a :class:`mechanics.model.Model`: one writer for every use.

FEBio (febio.org) is an independent finite-element code; a ``.feb`` file written here lets it
solve the same problem as :func:`mechanics.solver.solve` (a validation truth) or carries a
fitted model to other users. Units are the project's: mm, kPa, mN, with mass in kg and time
in s (density 1000 kg/m^3 = 1e-6 kg/mm^3, g = 9810 mm/s^2).

The knowledge of how a physical unit reads in FEBio lives with that unit: every material
implements ``to_febio(self)`` (FEBio type and parameters) and every effect
``to_febio(self, feb)``, which adds what it needs to the :class:`FebBuilder` ``feb`` (node
sets, surfaces, shells, springs, contact, loads, boundary conditions). A unit without the
hook, or whose options FEBio cannot express, raises :class:`FebioUnsupported` naming itself
and why, before any file is written. Hooks that can only approximate (e.g. a membrane's
tension-field wrinkling) call :meth:`FebBuilder.approximate`, which refuses unless the caller
passed ``approximate=True`` and otherwise records the approximation as a comment in the file.

Element technology (``element``):

- ``"tet4"``: FEBio's standard displacement tet (one Gauss point); locks volumetrically at
  nu near 1/2 (too stiff).
- ``"ut4"``: FEBio's nodally integrated UT4 tet (locking-free, like our "anp").
- ``"tet10"``: quadratic tets; a mid-edge node is added on every edge (appended after the
  mesh nodes, straight edges). The displacements of the mesh nodes are the first N rows of
  FEBio's output. Effects on surfaces (shells, contact) are refused with tet10.

Output: FEBio writes the displacement of every node to the plain-text logfile
``displacement.txt`` (``id,ux,uy,uz`` per node after every converged time step), read by
:func:`read_node_data`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from mechanics.mesh import REGIONS

if TYPE_CHECKING:
    from mechanics.model import Model

ELEMENTS = ("tet4", "ut4", "tet10")
SOLVERS = ("newton", "bfgs")
#: File (relative to FEBio's working folder) that receives the node displacements.
DISPLACEMENT_FILE = "displacement.txt"
#: Density 1000 kg/m^3 in kg/mm^3, the unit FEBio sees in a mm-kg-s model.
KG_M3_TO_KG_MM3 = 1e-9
#: m/s^2 -> mm/s^2.
M_TO_MM = 1e3
#: FEBio solid-domain type of each element technology.
_DOMAIN_TYPE = {"tet4": "elastic-solid", "ut4": "ut4-solid", "tet10": "elastic-solid"}
#: Edges of a tet in FEBio's tet10 node order (nodes 5..10).
TET10_EDGES = np.array([[0, 1], [1, 2], [2, 0], [0, 3], [1, 3], [2, 3]])


class FebioUnsupported(ValueError):
    """A material, effect or option that FEBio cannot express (the message names it and why)."""


def unsupported(owner: str, why: str) -> FebioUnsupported:
    """The error a unit raises when FEBio cannot express it."""
    return FebioUnsupported(f"FEBio export: {owner} cannot be expressed in FEBio: {why}")


def _num(v: float) -> str:
    return repr(float(v))


def _ids(a) -> str:
    return ",".join(str(int(i) + 1) for i in np.asarray(a).ravel())


def _param_lines(params: Mapping[str, Any], indent: str) -> list[str]:
    """XML lines of parameters: a key may carry attributes (``'force type="point"'``); a value
    is a number, a string, or a list of pre-formatted child lines."""
    out = []
    for k, v in params.items():
        tag = k.split()[0]
        if isinstance(v, str):
            out.append(f"{indent}<{k}>{v}</{tag}>")
        elif isinstance(v, list | tuple):
            out.append(f"{indent}<{k}>")
            out += [f"{indent}\t{line}" for line in v]
            out.append(f"{indent}</{tag}>")
        else:
            out.append(f"{indent}<{k}>{_num(v)}</{tag}>")
    return out


def tet10_nodes(X: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mid-edge nodes for quadratic tets.

    Parameters
    ----------
    X : (N, 3) node positions, mm
    tets : (M, 4) node indices

    Returns
    -------
    X10 : (N + E, 3) positions, mm: the N corner nodes, then one node at the middle of each
        of the E distinct edges
    tets10 : (M, 10) node indices in FEBio's tet10 order (corners, then edges 01 12 20 03 13
        23)
    edges : (E, 2) corner nodes of each mid-edge node (sorted pair)
    """
    tets = np.asarray(tets, np.int64)
    e = np.sort(tets[:, TET10_EDGES].reshape(-1, 2), axis=1)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    n = len(X)
    X10 = np.concatenate([X, 0.5 * (X[edges[:, 0]] + X[edges[:, 1]])])
    tets10 = np.concatenate([tets, n + inv.reshape(-1, 6)], axis=1)
    return X10, tets10, edges


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
        lines += [f'\t\t\t<tri3 id="{i + 1}">{_ids(f)}</tri3>' for i, f in enumerate(faces)]
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
        for f in faces:
            lines.append(f'\t\t\t<elem id="{self._next_elem}">{_ids(f)}</elem>')
            self._next_elem += 1
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

    # -- the file ------------------------------------------------------------------------
    def _control(self, steps: int, solver: str, tol: Mapping[str, float]) -> list[str]:
        if solver not in SOLVERS:
            raise ValueError(f"FEBio export: solver must be one of {SOLVERS}, got {solver!r}")
        if steps < 1:
            raise ValueError(f"FEBio export: steps must be >= 1, got {steps}")
        dt = 1.0 / steps
        qn = ('\t\t\t<qn_method type="full Newton"/>' if solver == "newton" else
              f'\t\t\t<qn_method type="BFGS">\n\t\t\t\t<max_ups>{int(tol["max_ups"])}'
              "</max_ups>\n\t\t\t</qn_method>")
        return ["\t<Control>", "\t\t<analysis>STATIC</analysis>",
                f"\t\t<time_steps>{steps}</time_steps>", f"\t\t<step_size>{_num(dt)}</step_size>",
                "\t\t<plot_level>PLOT_NEVER</plot_level>",
                "\t\t<output_level>OUTPUT_MAJOR_ITRS</output_level>",
                '\t\t<solver type="solid">',
                f"\t\t\t<dtol>{_num(tol['dtol'])}</dtol>",
                f"\t\t\t<etol>{_num(tol['etol'])}</etol>",
                f"\t\t\t<rtol>{_num(tol['rtol'])}</rtol>",
                f"\t\t\t<lstol>{_num(tol['lstol'])}</lstol>",
                f"\t\t\t<max_refs>{int(tol['max_refs'])}</max_refs>", qn, "\t\t</solver>",
                '\t\t<time_stepper type="default">',
                f"\t\t\t<max_retries>{int(tol['max_retries'])}</max_retries>",
                f"\t\t\t<opt_iter>{int(tol['opt_iter'])}</opt_iter>",
                f"\t\t\t<dtmin>{_num(dt * tol['dtmin_fraction'])}</dtmin>",
                f"\t\t\t<dtmax>{_num(dt)}</dtmax>", "\t\t</time_stepper>", "\t</Control>"]

    def text(self, *, steps: int, solver: str, tol: Mapping[str, float]) -> str:
        """The complete file."""
        mesh = self.mesh
        codes = [int(c) for c in np.unique(mesh.region)]
        names = {v: k for k, v in REGIONS.items()}
        part = {c: names.get(c, f"region_{c}") for c in codes}
        # bulk materials (their density is set by the body force, if any)
        from mechanics.materials import MATERIALS

        solid_mats = {}
        for c in codes:
            spec = self.model.materials[c]
            ftype, params = MATERIALS[spec.name].from_params(spec.params).to_febio()
            params = {"density": self.density.get(c, 0.0), **params}
            solid_mats[c] = self.material(part[c], ftype, params)
        out = ['<?xml version="1.0" encoding="ISO-8859-1"?>', '<febio_spec version="4.0">',
               "\t<!-- breastmodel: units mm, kPa, mN, kg, s -->"]
        out += [f"\t<!-- approximation: {a} -->" for a in self.approximations]
        out.append('\t<Module type="solid"/>')
        out += self._control(steps, solver, tol)
        out += ["\t<Material>"] + self.materials + ["\t</Material>"]
        out += ["\t<Mesh>", '\t\t<Nodes name="all">']
        out += [f'\t\t\t<node id="{i + 1}">{_num(x)},{_num(y)},{_num(z)}</node>'
                for i, (x, y, z) in enumerate(self.nodes_out)]
        out.append("\t\t</Nodes>")
        etype = "tet10" if self.element == "tet10" else "tet4"
        eid = 1
        for c in codes:
            out.append(f'\t\t<Elements type="{etype}" name="{part[c]}">')
            for t in self.tets_out[mesh.region == c]:
                out.append(f'\t\t\t<elem id="{eid}">{_ids(t)}</elem>')
                eid += 1
            out.append("\t\t</Elements>")
        out += self.shell_elements
        out += self.lines["Mesh"]
        out.append("\t</Mesh>")
        out.append("\t<MeshDomains>")
        for c in codes:
            out.append(f'\t\t<SolidDomain name="{part[c]}" mat="{solid_mats[c]}" '
                       f'type="{_DOMAIN_TYPE[self.element]}"/>')
        for name, mat, h in self.shell_domains:
            out += [f'\t\t<ShellDomain name="{name}" mat="{mat}">',
                    f"\t\t\t<shell_thickness>{_num(h)}</shell_thickness>", "\t\t</ShellDomain>"]
        out.append("\t</MeshDomains>")
        for sec in ("MeshData", "Boundary"):
            if self.lines[sec]:
                out += [f"\t<{sec}>"] + self.lines[sec] + [f"\t</{sec}>"]
        loads = list(self.lines["Loads"])
        if self.body_force is not None and np.any(self.body_force != 0.0):
            f = ",".join(_num(v) for v in self.body_force)
            loads.append(f'\t\t<body_load type="body force">\n\t\t\t<force lc="1">{f}</force>'
                         "\n\t\t</body_load>")
        if loads:
            out += ["\t<Loads>"] + loads + ["\t</Loads>"]
        if self.lines["Contact"]:
            out += ["\t<Contact>"] + self.lines["Contact"] + ["\t</Contact>"]
        if self._discrete:
            out += ["\t<Discrete>"] + self._discrete_materials + self._discrete + ["\t</Discrete>"]
        out += ["\t<LoadData>", '\t\t<load_controller id="1" name="ramp" type="loadcurve">',
                "\t\t\t<interpolate>LINEAR</interpolate>",
                "\t\t\t<points>", "\t\t\t\t<pt>0,0</pt>", "\t\t\t\t<pt>1,1</pt>", "\t\t\t</points>",
                "\t\t</load_controller>", "\t</LoadData>"]
        out += ["\t<Output>", "\t\t<logfile>",
                f'\t\t\t<node_data data="ux;uy;uz" delim="," file="{DISPLACEMENT_FILE}"/>',
                "\t\t</logfile>", "\t</Output>", "</febio_spec>"]
        return "\n".join(out) + "\n"


#: Default solver tolerances and limits (FEBio's names; ``dtmin_fraction`` of a step).
TOLERANCES = {"dtol": 1e-6, "etol": 1e-8, "rtol": 0.0, "lstol": 0.9, "max_refs": 25,
              "max_ups": 10, "max_retries": 8, "opt_iter": 10, "dtmin_fraction": 1e-3}


def feb_text(model: Model, *, X: np.ndarray | None = None, element: str = "ut4",
             steps: int = 10, solver: str = "newton", approximate: bool = False,
             export_sets: bool = False, **tolerances: float) -> str:
    """FEBio 4.0 input text for ``model``.

    Parameters
    ----------
    model : Model (mesh, materials per region, effects)
    X : (N, 3) reference positions, mm (default the mesh nodes)
    element : "ut4" (locking-free, default), "tet4" or "tet10" (see the module docstring)
    steps : number of equal load steps (time 0 -> 1); FEBio's auto time stepper may cut them
    solver : "newton" (full Newton) or "bfgs" (FEBio's quasi-Newton)
    approximate : allow hooks to write approximations (listed as comments in the file)
    export_sets : also write every named set of the mesh under its own name (node sets,
        face sets as surfaces, node pairs as discrete sets)
    **tolerances : FEBio solver settings overriding ``TOLERANCES``: ``dtol`` (displacement),
        ``etol`` (energy), ``rtol`` (residual), ``lstol``, ``max_refs``, ``max_ups`` (BFGS),
        ``max_retries``, ``opt_iter``, ``dtmin_fraction``

    Returns
    -------
    str : the ``.feb`` file; node i of the mesh is FEBio node i + 1

    Raises
    ------
    FebioUnsupported
        A material or effect that FEBio cannot express (named in the message).
    """
    unknown = sorted(set(tolerances) - set(TOLERANCES))
    if unknown:
        raise ValueError(f"FEBio export: unknown solver setting(s) {unknown}; "
                         f"known: {sorted(TOLERANCES)}")
    tol = {**TOLERANCES, **tolerances}
    feb = FebBuilder(model, model.mesh.nodes if X is None else X, element=element,
                     approximate=approximate)
    if export_sets:
        feb.export_sets()
    for eff in model.effects:
        eff.to_febio(feb)
    return feb.text(steps=steps, solver=solver, tol=tol)


def read_node_data(text: str, n_nodes: int, *, source: str = "FEBio logfile"
                   ) -> tuple[np.ndarray, float]:
    """The last record of an FEBio logfile ``node_data`` file (``id,ux,uy,uz`` lines).

    Parameters
    ----------
    text : the file's content
    n_nodes : how many nodes to return (rows 0..n_nodes-1 = FEBio ids 1..n_nodes)
    source : name used in error messages

    Returns
    -------
    u : (n_nodes, 3) displacement, mm
    time : the record's time (1.0 at full load)
    """
    blocks = text.split("*Step")
    if len(blocks) < 2:
        raise ValueError(f"{source}: no data record (FEBio converged no time step)")
    last = blocks[-1].splitlines()
    time = float("nan")
    rows = []
    for line in last:
        s = line.strip()
        if s.startswith("*Time"):
            time = float(s.split("=", 1)[1])
        elif s and not s.startswith("*") and not s.startswith("="):
            rows.append([float(v) for v in s.split(",")])
    a = np.asarray(rows, float).reshape(-1, 4)
    ids = a[:, 0].astype(np.int64)
    u = np.full((int(ids.max()) if len(ids) else 0, 3), np.nan)
    u[ids - 1] = a[:, 1:]
    if len(u) < n_nodes or np.isnan(u[:n_nodes]).any():
        raise ValueError(f"{source}: the last record lacks nodes (has {len(ids)}, "
                         f"needs {n_nodes})")
    return u[:n_nodes], time
