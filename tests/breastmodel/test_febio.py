"""FEBio 4 driven by our writer: the instrument is right, the reader maps nodes, refusals come
before FEBio runs. Needs FEBio (../shared/febio/febio4 or $FEBIO); skipped without it."""

import os
import time

import numpy as np
import pytest
from zoo import box

from breastmodel.febio import (
    FebioError,
    find_febio,
    run_febio,
    shared_path,
    solve_with_febio,
)
from mechanics.effects import Effect, register_effect
from mechanics.effects.base import EFFECTS
from mechanics.febio import FebioUnsupported, feb_text
from mechanics.mesh import Mesh
from mechanics.model import build_model
from mechanics.solver import SolverOptions, solve

HEMI = next((p for p in shared_path("febio", "hemisphere", "hemi_20k.npz") if p.exists()),
            shared_path("febio", "hemisphere", "hemi_20k.npz")[0])


@pytest.fixture(scope="module")
def febio():
    try:
        return find_febio()
    except FebioError as exc:
        pytest.skip(f"FEBio not available: {exc}")


def rotation(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.radians(deg)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def test_find_febio_explains_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.delenv("FEBIO", raising=False)
    with pytest.raises(FebioError, match="--febio.*FEBIO"):
        find_febio(tmp_path / "no-such-febio")


def test_reader_maps_a_rigid_motion_onto_every_node(febio, tmp_path):
    """A block whose bottom face is turned 40 degrees and moved follows rigidly (no load): FEBio's
    displacement, read back, is R X + t - X at every node, in a shuffled node order."""
    m = box((3, 2, 2), size=(30.0, 20.0, 20.0))
    perm = np.random.default_rng(1).permutation(m.n_nodes)
    inv = np.argsort(perm)
    mesh = Mesh(m.nodes[perm], inv[m.tets], m.region,
                node_sets={"bottom": inv[m.node_sets["zmin"]]})
    R, t = rotation((1.0, 2.0, 0.5), 40.0), np.array([3.0, -7.0, 11.0])
    want = mesh.nodes @ R.T + t - mesh.nodes
    bottom = mesh.node_sets["bottom"]
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.3}},
                        {"fixed": {"nodes": bottom, "values": want[bottom]}})
    run = solve_with_febio(model, work_dir=tmp_path, febio=febio, element="tet4", dtol=1e-9,
                           etol=1e-12)
    assert run.converged
    assert run.displacement.shape == (mesh.n_nodes, 3)
    # FEBio prints 12 significant digits; the free nodes sit at equilibrium to dtol
    assert np.abs(run.displacement - want).max() < 1e-6 * np.abs(want).max()


def test_unsupported_effect_is_refused_before_febio_runs(tmp_path):
    @register_effect
    class Telekinesis(Effect):
        name = "test_telekinesis"

    try:
        m = box((1, 1, 1))
        model = build_model(m, {1: {"name": "neo_hookean"}},
                            {"fixed": {"node_set": "zmin"}, "test_telekinesis": {}})
        with pytest.raises(FebioUnsupported, match="test_telekinesis"):
            solve_with_febio(model, work_dir=tmp_path, febio="/nonexistent/febio4")
    finally:
        EFFECTS.pop("test_telekinesis")
    assert not any(tmp_path.iterdir())  # nothing written, FEBio never looked for


def test_febio_failure_names_the_file_and_quotes_febio(febio, tmp_path):
    text = feb_text(build_model(box((1, 1, 1)), {1: {"name": "neo_hookean"}},
                                {"fixed": {"node_set": "zmin"}}))
    bad = text.replace('type="Mooney-Rivlin"', 'type="no-such-material"')
    with pytest.raises(FebioError, match=r"(?s)model\.feb.*invalid value.*no-such-material"):
        run_febio(bad, work_dir=tmp_path, febio=febio, timeout_s=60)


def hemisphere_model(law: str, formulation: str):
    z = np.load(HEMI)
    mesh = Mesh(z["nodes"], z["tets"], np.ones(len(z["tets"])), node_sets={"base": z["base"]})
    mat = {"name": "neo_hookean", "E": 1.0, "nu": 0.49}
    if law == "gent":
        mat = {"name": "gent", "E": 1.0, "nu": 0.49, "Jm": 5.0}
    model = build_model(mesh, {1: mat}, {"gravity": {"direction": (0, 0, -1), "g": 9.81,
                                                     "density": 1000.0},
                                         "fixed": {"node_set": "base"}}, formulation=formulation)
    return model, int(z["tip"])


@pytest.mark.parametrize("law", ["neo_hookean", "gent"])
def test_hemisphere_tet4_matches_our_standard_tets(febio, tmp_path, law):
    """The same discrete problem in both codes (1-point linear tets, the same energy through
    FEBio's uncoupled Mooney-Rivlin / Gent with the (J-1)^2 bulk term, gravity as a body
    force, the base fixed): the whole displacement field agrees to solver tolerance.
    Measured: max difference 1.1e-10 mm (neo-Hookean) on a 11.55 mm tip displacement."""
    if not os.path.exists(HEMI):
        pytest.skip(f"hemisphere reference mesh not found at {HEMI}")
    model, tip = hemisphere_model(law, "standard")
    ours = solve(model, options=SolverOptions(tol=1e-10))
    t0 = time.perf_counter()
    run = solve_with_febio(model, work_dir=tmp_path, febio=febio, element="tet4",
                           etol=1e-10)
    print(f"{law}: tip ours {np.linalg.norm(ours.u[tip]):.5f} FEBio tet4 "
          f"{np.linalg.norm(run.displacement[tip]):.5f} mm, FEBio {time.perf_counter() - t0:.1f} s")
    assert ours.converged and run.converged
    assert np.abs(run.displacement - ours.u).max() < 1e-5 * np.linalg.norm(ours.u[tip])


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """(k, 3) boundary triangles of positively oriented tets, normals outward."""
    local = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[count[inv.ravel()] == 1]


def hanging_block(**effects):
    """A 20 mm cube (4^3 cells, 384 tets) held at its top face, E 1 kPa, nu 0.49, under
    gravity; ``standard`` tets in our solver and tet4 in FEBio (the same bulk discretisation),
    so what differs is the effect under test."""
    m = box((4, 4, 4), size=(20.0, 20.0, 20.0), origin=(-10.0, -10.0, -20.0))
    faces = boundary_faces(m.tets)
    on_top = np.isin(faces, m.node_sets["zmax"]).all(axis=1)
    bottom = int(np.argmin(np.linalg.norm(m.nodes - [0.0, 0.0, -20.0], axis=1)))
    top = int(np.argmin(np.linalg.norm(m.nodes - [0.0, 0.0, 0.0], axis=1)))
    corners = [int(np.argmin(np.linalg.norm(m.nodes - [sx * 10, sy * 10, -20.0], axis=1)))
               for sx in (-1, 1) for sy in (-1, 1)]
    tops = [int(np.argmin(np.linalg.norm(m.nodes - [sx * 10, sy * 10, 0.0], axis=1)))
            for sx in (-1, 1) for sy in (-1, 1)]
    mesh = Mesh(m.nodes, m.tets, m.region, node_sets={"fixed": m.node_sets["zmax"]},
                face_sets={"skin": faces[~on_top]},
                node_pairs={"ligament_medial": np.array([[bottom, top]] + list(zip(corners,
                                                                                     tops)))})
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.49}},
                        {"gravity": {"direction": (0, 0, -1)}, "fixed": {"node_set": "fixed"},
                         **effects}, formulation="standard")
    return model, bottom


def sag(febio, tmp_path, **effects):
    model, bottom = hanging_block(**effects)
    ours = solve(model, options=SolverOptions(tol=1e-10))
    run = solve_with_febio(model, work_dir=tmp_path, febio=febio, element="tet4", etol=1e-10)
    assert ours.converged and run.converged
    return -ours.u[bottom, 2], -run.displacement[bottom, 2], ours.u, run.displacement


def test_ligaments_as_tension_only_springs(febio, tmp_path):
    """Five cables (EA 100 mN) from the bottom to the held top face carry part of the weight:
    FEBio's nonlinear springs of the strain give our cables' result (same bulk discretisation),
    to solver tolerance."""
    free, free_f, _, _ = sag(febio, tmp_path / "free")
    hung, hung_f, u, uf = sag(febio, tmp_path / "hung",
                              ligaments={"E": 100.0, "area": 1.0})
    print(f"bottom sag: free ours {free:.5f} FEBio {free_f:.5f}; hung ours {hung:.5f} "
          f"FEBio {hung_f:.5f} mm")
    assert hung < 0.8 * free  # the cables do carry weight
    assert np.abs(uf - u).max() < 1e-5 * free


def test_skin_as_shells(febio, tmp_path):
    """A 0.5 mm, 20 kPa skin (plain law, no wrinkling) on the free faces of the hanging cube.
    FEBio's tri3 shells are stiffer than our membrane: they also bend and take their thickness
    change from the 3D law. Measured share of the bare sag the skin removes: ours 0.520,
    FEBio 0.581 (x 1.12); at 1 mm / 10 kPa (same E H) FEBio is x 1.20, at 0.25 mm / 10 kPa
    x 1.13 -- the gap shrinks with the thickness, as a bending share does. Asserted: FEBio's
    skin carries more than ours, by at most 15 %."""
    free, free_f, _, _ = sag(febio, tmp_path / "free")
    skin, skin_f, _, _ = sag(febio, tmp_path / "skin",
                             skin={"E": 20.0, "thickness": 0.5, "wrinkling": "none"})
    ratio = (free_f - skin_f) / (free - skin)
    print(f"bottom sag: bare ours {free:.5f} FEBio {free_f:.5f}; skin ours {skin:.5f} "
          f"FEBio {skin_f:.5f} mm; FEBio/ours share carried by the skin {ratio:.3f}")
    assert skin < 0.6 * free
    assert 1.0 < ratio < 1.15


def test_tension_field_skin_needs_approximate(tmp_path):
    model, _ = hanging_block(skin={"E": 20.0, "thickness": 0.5})
    with pytest.raises(FebioUnsupported, match="'skin'.*wrinkling.*approximate=True"):
        feb_text(model)
    assert "approximation: effect 'skin'" in feb_text(model, approximate=True)


def layered_block(split: bool):
    """A 20 mm cube: muscle (region 2) below z = -10 held at its bottom face, breast (region 1)
    above, face set ``interface`` between them (normal from muscle into breast); ``split``
    duplicates the interface nodes so that the breast may slide."""
    from mechanics.effects._interface import split_interface

    m = box((4, 4, 4), size=(20.0, 20.0, 20.0), origin=(-10.0, -10.0, -20.0))
    zc = m.nodes[m.tets].mean(axis=1)[:, 2]
    region = np.where(zc < -10.0, 2, 1)
    faces = boundary_faces(m.tets[region == 2])
    interface = faces[np.all(np.isclose(m.nodes[faces, 2], -10.0), axis=1)]
    mesh = Mesh(m.nodes, m.tets, region, node_sets={"fixed": m.node_sets["zmin"]},
                face_sets={"interface": interface})
    return split_interface(mesh) if split else mesh


def layered_model(mesh, direction, **effects):
    return build_model(mesh, {1: {"name": "neo_hookean", "E": 1.0, "nu": 0.49},
                              2: {"name": "neo_hookean", "E": 10.0, "nu": 0.49}},
                       {"gravity": {"direction": direction}, "fixed": {"node_set": "fixed"},
                        **effects}, formulation="standard")


def top_centre(mesh):
    return int(np.argmin(np.linalg.norm(mesh.nodes - [0.0, 0.0, 0.0], axis=1)))


def test_tied_split_interface_as_tied_contact(febio, tmp_path):
    """Breast bonded to the muscle through a split interface, gravity tilted: FEBio's
    tied-elastic and our tie springs (both penalty 1000 kPa/mm) against the conforming mesh."""
    direction = (1.0, 0.0, -1.0)
    conf = layered_model(layered_block(False), direction)
    ref = solve(conf, options=SolverOptions(tol=1e-10)).u[top_centre(conf.mesh)]
    model = layered_model(layered_block(True), direction, tied={})
    top = top_centre(model.mesh)
    ours = solve(model, options=SolverOptions(tol=1e-10)).u[top]
    run = solve_with_febio(model, work_dir=tmp_path, febio=febio, element="tet4", etol=1e-10)
    print(f"top centre: conforming {ref}, ours tied {ours}, FEBio tied {run.displacement[top]}")
    assert run.converged
    scale = np.linalg.norm(ref)
    assert np.linalg.norm(ours - ref) < 0.01 * scale
    assert np.linalg.norm(run.displacement[top] - ref) < 0.01 * scale


def test_sliding_is_written_as_sliding_elastic_only_when_allowed():
    """Sliding is always an approximation in FEBio (its own contact points and edges; with
    friction no tension, another stick stiffness). Not run in FEBio here: on this cube, where
    the breast rests on the contact alone, FEBio's sliding-elastic diverged from the first
    iteration (singular: no contact stiffness at zero gap), with and without friction, penalty
    or augmented Lagrangian, small offsets, either face orientation."""
    import xml.etree.ElementTree as ET

    model = layered_model(layered_block(True), (1.0, 0.0, -4.0), sliding={"friction": 0.5})
    with pytest.raises(FebioUnsupported, match="'sliding'.*separate"):
        feb_text(model)
    root = ET.fromstring(feb_text(model, approximate=True))
    (c,) = root.findall("./Contact/contact")
    assert c.get("type") == "sliding-elastic"
    assert float(c.find("fric_coeff").text) == 0.5 and c.find("tension").text == "0"
    pair = root.find(f"./Mesh/SurfacePair[@name='{c.get('surface_pair')}']")
    prim = root.find(f"./Mesh/Surface[@name='{pair.find('primary').text}']")
    first = [int(v) - 1 for v in prim[0].text.split(",")]
    assert first == model.mesh.face_sets["interface"][0][::-1].tolist()  # out of the breast
