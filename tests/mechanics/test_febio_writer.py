"""The FEBio 4.0 writer, without FEBio: the XML parses, ids are 1-based, sets and conditions
land on the right nodes, and what FEBio cannot express is refused by name."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest
from zoo import box

from mechanics.effects import Effect, register_effect
from mechanics.effects.base import EFFECTS
from mechanics.effects.membrane import FEBIO_THINNING
from mechanics.febio import FebioUnsupported, feb_comments, feb_text, read_node_data, tet10_nodes
from mechanics.mesh import Mesh
from mechanics.model import build_model


def two_region_box() -> Mesh:
    m = box((2, 2, 2), size=(10.0, 10.0, 10.0))
    z = m.nodes[m.tets].mean(axis=1)[:, 2]
    region = np.where(z < 5.0, 2, 1)
    return Mesh(m.nodes, m.tets, region, node_sets={"fixed": m.node_sets["zmin"],
                                                    "top": m.node_sets["zmax"]})


def hanging(mesh, **effects):
    eff = {"gravity": {"direction": (0, 0, -1)}, "fixed": {"node_set": "fixed"}, **effects}
    return build_model(mesh, {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.49},
                              2: {"name": "gent", "E": 10.0, "nu": 0.45, "Jm": 5.0}}, eff)


def test_xml_parses_with_one_based_ids_and_domains_per_region():
    mesh = two_region_box()
    root = ET.fromstring(feb_text(hanging(mesh), element="ut4"))
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    nodes = root.findall("./Mesh/Nodes/node")
    assert [int(n.get("id")) for n in nodes] == list(range(1, mesh.n_nodes + 1))
    xyz = np.array([[float(v) for v in n.text.split(",")] for n in nodes])
    assert np.array_equal(xyz, mesh.nodes)  # repr() round-trips floats exactly
    elems = root.findall("./Mesh/Elements")
    ids = [int(e.get("id")) for part in elems for e in part]
    assert ids == list(range(1, mesh.n_tets + 1))
    conn = {part.get("name"): np.array([[int(v) - 1 for v in e.text.split(",")] for e in part])
            for part in elems}
    for code, part in ((1, "breast_left"), (2, "muscle")):
        assert np.array_equal(conn[part], mesh.tets[mesh.region == code])
    doms = root.findall("./MeshDomains/SolidDomain")
    assert {d.get("type") for d in doms} == {"ut4-solid"}
    mats = {m.get("name"): m for m in root.findall("./Material/material")}
    assert {d.get("mat") for d in doms} == set(mats)
    # the laws map to the same energies: c1 = mu/2, G = mu, k = E / (3 (1 - 2 nu))
    nh, gent = mats["breast_left"], mats["muscle"]
    assert nh.get("type") == "Mooney-Rivlin" and gent.get("type") == "Gent"
    assert float(nh.find("c1").text) == pytest.approx(0.5 / 2.98)
    assert float(nh.find("k").text) == pytest.approx(1.0 / (3 * 0.02))
    assert float(gent.find("G").text) == pytest.approx(10.0 / 2.9)
    assert float(gent.find("Jm").text) == 5.0
    assert nh.find("pressure_model").text == gent.find("pressure_model").text == "Abaqus"
    assert float(nh.find("density").text) == pytest.approx(1e-6)


def test_gravity_and_supports_land_on_the_right_nodes():
    mesh = two_region_box()
    model = hanging(mesh, **{"gravity": {"direction": (1, 0, 0), "g": 9.81,
                                         "density_by_region": {2: 500.0}}})
    root = ET.fromstring(feb_text(model, element="tet4"))
    (bc,) = root.findall("./Boundary/bc")
    assert bc.get("type") == "zero displacement"
    ns = root.find(f"./Mesh/NodeSet[@name='{bc.get('node_set')}']")
    assert sorted(int(i) - 1 for i in ns.text.split(",")) == sorted(mesh.node_sets["fixed"])
    assert [c.tag for c in bc] == ["x_dof", "y_dof", "z_dof"]
    (load,) = root.findall("./Loads/body_load")
    f = np.array([float(v) for v in load.find("force").text.split(",")])
    # FEBio adds -rho b to the residual, so b = -g along the direction (mm/s^2)
    assert np.allclose(f, [-9810.0, 0.0, 0.0])
    mats = {m.get("name"): float(m.find("density").text)
            for m in root.findall("./Material/material")}
    assert mats == pytest.approx({"breast_left": 1e-6, "muscle": 5e-7})


def test_prescribed_values_become_node_maps():
    mesh = two_region_box()
    top = mesh.node_sets["top"]
    vals = np.arange(len(top) * 2, dtype=float).reshape(-1, 2) / 7.0
    model = build_model(mesh, {1: {"name": "neo_hookean"}, 2: {"name": "neo_hookean"}},
                        {"fixed": [{"node_set": "fixed"},
                                   {"nodes": top, "components": (0, 2), "values": vals}]})
    root = ET.fromstring(feb_text(model))
    bcs = [b for b in root.findall("./Boundary/bc") if b.get("type") == "prescribed displacement"]
    assert [b.find("dof").text for b in bcs] == ["x", "z"]
    for j, b in enumerate(bcs):
        data = root.find(f"./MeshData/NodeData[@name='{b.find('value').text}']")
        ns = root.find(f"./Mesh/NodeSet[@name='{data.get('node_set')}']")
        nodes = [int(i) - 1 for i in ns.text.split(",")]
        got = {nodes[int(n.get("lid")) - 1]: float(n.text) for n in data}
        assert got == {int(n): v for n, v in zip(top, vals[:, j])}


def test_point_loads_are_nodal_force_maps():
    mesh = two_region_box()
    top = mesh.node_sets["top"]
    model = build_model(mesh, {1: {"name": "neo_hookean"}, 2: {"name": "neo_hookean"}},
                        {"fixed": {"node_set": "fixed"},
                         "point_load": {"nodes": top, "force": (0.0, 1.5, -2.0)}})
    root = ET.fromstring(feb_text(model))
    (load,) = root.findall("./Loads/nodal_load")
    assert load.get("type") == "nodal_force"
    data = root.find(f"./MeshData/NodeData[@name='{load.find('value').text}']")
    assert data.get("data_type") == "vec3" and len(data) == len(top)
    assert {n.text for n in data} == {"0.0,1.5,-2.0"}


def test_tet10_adds_mid_edge_nodes_and_extends_sets():
    mesh = two_region_box()
    X10, t10, edges = tet10_nodes(mesh.nodes, mesh.tets)
    assert np.allclose(X10[t10[:, 4]], 0.5 * (X10[t10[:, 0]] + X10[t10[:, 1]]))
    assert np.allclose(X10[t10[:, 9]], 0.5 * (X10[t10[:, 2]] + X10[t10[:, 3]]))
    root = ET.fromstring(feb_text(hanging(mesh), element="tet10"))
    assert len(root.findall("./Mesh/Nodes/node")) == len(X10)
    assert {e.get("type") for e in root.findall("./Mesh/Elements")} == {"tet10"}
    bc = root.find("./Boundary/bc")
    ns = root.find(f"./Mesh/NodeSet[@name='{bc.get('node_set')}']")
    ids = np.array([int(i) - 1 for i in ns.text.split(",")])
    on_face = np.flatnonzero(np.isclose(X10[:, 2], 0.0))  # the fixed face z = 0
    assert sorted(ids) == sorted(on_face)


def test_unsupported_effect_and_material_are_refused_by_name():
    @register_effect
    class Telepathy(Effect):
        name = "test_telepathy"

    try:
        mesh = two_region_box()
        model = hanging(mesh, test_telepathy={})
        with pytest.raises(FebioUnsupported, match="test_telepathy"):
            feb_text(model)
    finally:
        EFFECTS.pop("test_telepathy")
    lin = build_model(mesh, {1: {"name": "linear"}, 2: {"name": "neo_hookean"}},
                      {"fixed": {"node_set": "fixed"}})
    with pytest.raises(FebioUnsupported, match="'linear'.*geometrically linear"):
        feb_text(lin)


def test_options_are_checked():
    model = hanging(two_region_box())
    with pytest.raises(ValueError, match="element"):
        feb_text(model, element="hex8")
    with pytest.raises(ValueError, match="unknown solver setting"):
        feb_text(model, dtoll=1e-3)
    root = ET.fromstring(feb_text(model, solver="bfgs", steps=4, dtol=1e-4))
    assert root.find("./Control/solver/qn_method").get("type") == "BFGS"
    assert root.find("./Control/time_steps").text == "4"
    assert float(root.find("./Control/solver/dtol").text) == 1e-4


def test_read_node_data_takes_the_last_record_by_id():
    text = ("*Step  = 1\n*Time  = 0.5\n*Data  = ux;uy;uz\n1,0,0,0\n2,0,0,0\n"
            "*Step  = 2\n*Time  = 1\n*Data  = ux;uy;uz\n2,4,5,6\n1,1,2,3\n3,9,9,9\n")
    u, t = read_node_data(text, 2)
    assert t == 1.0 and np.array_equal(u, [[1, 2, 3], [4, 5, 6]])
    with pytest.raises(ValueError, match="lacks nodes"):
        read_node_data(text.replace("2,4,5,6\n", ""), 2)


def test_ligaments_are_grouped_by_modulus_and_skin_is_shells():
    m = two_region_box()
    pairs = np.array([[0, 5], [1, 6], [2, 7]])
    mesh = Mesh(m.nodes, m.tets, m.region, node_sets=m.node_sets,
                face_sets={"skin": [[0, 1, 4], [1, 5, 4]]},
                node_pairs={"ligament_medial": pairs[:2], "ligament_lateral": pairs[2:]})
    model = hanging(mesh, ligaments={"E": 50.0, "area": 2.0, "E_by_group": {"lateral": 100.0}},
                    skin={"E": 4.0, "thickness": 2.0, "wrinkling": "none"})
    root = ET.fromstring(feb_text(model))
    dmats = {d.get("id"): d for d in root.findall("./Discrete/discrete_material")}
    got = {}
    for d in root.findall("./Discrete/discrete"):
        mat = dmats[d.get("dmat")]
        assert mat.get("type") == "nonlinear spring" and mat.find("measure").text == "strain"
        ds = root.find(f"./Mesh/DiscreteSet[@name='{d.get('discrete_set')}']")
        got[float(mat.find("scale").text)] = [[int(v) - 1 for v in e.text.split(",")]
                                              for e in ds]
    assert got == {100.0: pairs[:2].tolist(), 200.0: pairs[2:].tolist()}
    (shell,) = [e for e in root.findall("./Mesh/Elements") if e.get("type") == "tri3"]
    assert [int(e.get("id")) for e in shell] == [mesh.n_tets + 1, mesh.n_tets + 2]
    dom = root.find("./MeshDomains/ShellDomain")
    h = float(dom.find("shell_thickness").text)
    assert h == pytest.approx(2.0 / FEBIO_THINNING)
    mat = root.find(f"./Material/material[@name='{dom.get('mat')}']")
    assert float(mat.find("density").text) == 0.0
    # the membrane's stiffness E H (c1 = E / (2 (1 + nu)) / 2) is the skin's 4 kPa x 2 mm
    assert float(mat.find("c1").text) * h == pytest.approx(4.0 / 2.98 / 2 * 2.0)
    assert feb_comments(feb_text(model), "note") == [
        "effect 'skin': a membrane of E 4 kPa and thickness 2 mm, written as shells "
        f"{FEBIO_THINNING:g} times thinner and stiffer (same E x thickness, so that the "
        "shells' bending vanishes)"]
    assert feb_comments(feb_text(model), "approximation") == []


def test_reference_positions_and_surface_effects_on_tet10():
    mesh = two_region_box()
    X = mesh.nodes * 1.5 + 2.0
    root = ET.fromstring(feb_text(hanging(mesh), X=X))
    xyz = np.array([[float(v) for v in n.text.split(",")]
                    for n in root.findall("./Mesh/Nodes/node")])
    assert np.array_equal(xyz, X)
    skinned = Mesh(mesh.nodes, mesh.tets, mesh.region, node_sets=mesh.node_sets,
                   face_sets={"skin": [[0, 1, 4]]})
    model = hanging(skinned, skin={"wrinkling": "none"})
    with pytest.raises(FebioUnsupported, match="'skin'.*linear faces"):
        feb_text(model, element="tet10")
