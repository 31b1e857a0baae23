"""The complete FEBio 4.0 file from a :class:`mechanics.febio_builder.FebBuilder`: the bulk
materials of the regions, the control section (steps, solver, tolerances), the mesh with its
domains, the conditions and loads the hooks added, the load curves (a ramp, and the must
points of path-dependent effects) and the displacement logfile."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from mechanics.febio_xml import _DOMAIN_TYPE, DISPLACEMENT_FILE, SOLVERS, _num, _rows
from mechanics.mesh import REGIONS

if TYPE_CHECKING:
    from mechanics.febio_builder import FebBuilder


def control(feb: FebBuilder, steps: int, solver: str, tol: Mapping[str, float]) -> list[str]:
    """The ``Control`` section: ``steps`` equal time steps, full Newton or BFGS, FEBio's
    tolerances ``tol`` (see :data:`mechanics.febio.TOLERANCES`); dtmax follows the must-point
    curve when the model has path points."""
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
            (f'\t\t\t<dtmax lc="2">{_num(dt)}</dtmax>' if feb.must_points(steps) else
             f"\t\t\t<dtmax>{_num(dt)}</dtmax>"), "\t\t</time_stepper>", "\t</Control>"]


def _solid_materials(feb: FebBuilder, codes: list[int], part: dict[int, str]) -> dict[int, str]:
    """Add the bulk material of every region (its density set by the body force, if any);
    returns region -> material name."""
    from mechanics.materials import MATERIALS

    solid_mats = {}
    for c in codes:
        spec = feb.model.materials[c]
        ftype, params = MATERIALS[spec.name].from_params(spec.params).to_febio()
        params = {"density": feb.density.get(c, 0.0), **params}
        solid_mats[c] = feb.material(part[c], ftype, params)
    return solid_mats


def _mesh(feb: FebBuilder, codes: list[int], part: dict[int, str]) -> list[str]:
    """The ``Mesh`` section: nodes, one solid part per region, shells and the hooks' sets."""
    out = ["\t<Mesh>", '\t\t<Nodes name="all">']
    out += [f'\t\t\t<node id="{i + 1}">{x!r},{y!r},{z!r}</node>'
            for i, (x, y, z) in enumerate(np.asarray(feb.nodes_out, float).tolist())]
    out.append("\t\t</Nodes>")
    etype = "tet10" if feb.element == "tet10" else "tet4"
    eid = 1
    for c in codes:
        out.append(f'\t\t<Elements type="{etype}" name="{part[c]}">')
        conn = feb.tets_out[feb.mesh.region == c]
        out += _rows("elem", conn, eid)
        eid += len(conn)
        out.append("\t\t</Elements>")
    out += feb.shell_elements
    out += feb.lines["Mesh"]
    out.append("\t</Mesh>")
    return out


def _domains(feb: FebBuilder, codes: list[int], part: dict[int, str],
             solid_mats: dict[int, str]) -> list[str]:
    """The ``MeshDomains`` section: a solid domain per region, the shell domains."""
    out = ["\t<MeshDomains>"]
    for c in codes:
        out.append(f'\t\t<SolidDomain name="{part[c]}" mat="{solid_mats[c]}" '
                   f'type="{_DOMAIN_TYPE[feb.element]}"/>')
    for name, mat, h in feb.shell_domains:
        out += [f'\t\t<ShellDomain name="{name}" mat="{mat}">',
                f"\t\t\t<shell_thickness>{_num(h)}</shell_thickness>", "\t\t</ShellDomain>"]
    out.append("\t</MeshDomains>")
    return out


def _conditions(feb: FebBuilder) -> list[str]:
    """The sections the hooks filled, where not empty: ``MeshData``, ``Boundary``,
    ``Loads`` (with the body force), ``Contact``, ``Discrete``."""
    out = []
    for sec in ("MeshData", "Boundary"):
        if feb.lines[sec]:
            out += [f"\t<{sec}>"] + feb.lines[sec] + [f"\t</{sec}>"]
    loads = list(feb.lines["Loads"])
    if feb.body_force is not None and np.any(feb.body_force != 0.0):
        f = ",".join(_num(v) for v in feb.body_force)
        loads.append(f'\t\t<body_load type="body force">\n\t\t\t<force lc="1">{f}</force>'
                     "\n\t\t</body_load>")
    if loads:
        out += ["\t<Loads>"] + loads + ["\t</Loads>"]
    if feb.lines["Contact"]:
        out += ["\t<Contact>"] + feb.lines["Contact"] + ["\t</Contact>"]
    if feb._discrete:
        out += ["\t<Discrete>"] + feb._discrete_materials + feb._discrete + ["\t</Discrete>"]
    return out


def _load_data(feb: FebBuilder, steps: int) -> list[str]:
    """The ``LoadData`` section: the linear ramp of every load, and the must points."""
    out = ["\t<LoadData>", '\t\t<load_controller id="1" name="ramp" type="loadcurve">',
           "\t\t\t<interpolate>LINEAR</interpolate>",
           "\t\t\t<points>", "\t\t\t\t<pt>0,0</pt>", "\t\t\t\t<pt>1,1</pt>", "\t\t\t</points>",
           "\t\t</load_controller>"]
    must = feb.must_points(steps)
    if must:  # dtmax follows this curve; its points are must points
        out += ['\t\t<load_controller id="2" name="must_points" type="loadcurve">',
                "\t\t\t<interpolate>STEP</interpolate>", "\t\t\t<points>"]
        out += [f"\t\t\t\t<pt>{_num(t)},{_num(1.0 / steps)}</pt>" for t in must]
        out += ["\t\t\t</points>", "\t\t</load_controller>"]
    out.append("\t</LoadData>")
    return out


def document(feb: FebBuilder, *, steps: int, solver: str, tol: Mapping[str, float]) -> str:
    """The complete ``.feb`` text of what ``feb`` collected (adds the bulk materials)."""
    codes = [int(c) for c in np.unique(feb.mesh.region)]
    names = {v: k for k, v in REGIONS.items()}
    part = {c: names.get(c, f"region_{c}") for c in codes}
    solid_mats = _solid_materials(feb, codes, part)
    out = ['<?xml version="1.0" encoding="ISO-8859-1"?>', '<febio_spec version="4.0">',
           "\t<!-- breastmodel: units mm, kPa, mN, kg, s -->"]
    out += [f"\t<!-- approximation: {a} -->" for a in feb.approximations]
    out += [f"\t<!-- note: {a} -->" for a in feb.notes]
    out.append('\t<Module type="solid"/>')
    out += control(feb, steps, solver, tol)
    out += ["\t<Material>"] + feb.materials + ["\t</Material>"]
    out += _mesh(feb, codes, part)
    out += _domains(feb, codes, part, solid_mats)
    out += _conditions(feb)
    out += _load_data(feb, steps)
    out += ["\t<Output>", "\t\t<logfile>",
            f'\t\t\t<node_data data="ux;uy;uz" delim="," file="{DISPLACEMENT_FILE}"/>',
            "\t\t</logfile>", "\t</Output>", "</febio_spec>"]
    return "\n".join(out) + "\n"
