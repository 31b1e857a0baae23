"""The faces on the reference scan's cut held as the body beyond them would hold them
(mechanics.effects.cut_faces), on the two-mound mesh whose x ends stand for a scan's cut."""

import numpy as np
import pytest
from breastlike import breastlike_mesh

from mechanics.effects import EFFECTS
from mechanics.model import build_model
from mechanics.solver import solve

NH = {"name": "neo_hookean", "nu": 0.49}


@pytest.fixture(scope="module")
def mesh():
    """The two-mound mesh with its x ends named as a scan's cut (the mesher names the faces
    on a label map's field-of-view planes so, ``meshing.sets.named_sets``)."""
    from mechanics.mesh import Mesh

    m = breastlike_mesh(cells=(6, 4, 2, 2))
    end = np.abs(np.abs(m.nodes[:, 0]) - np.abs(m.nodes[:, 0]).max()) < 1e-9
    in_tissue = {code: np.zeros(m.n_nodes, bool) for code in (1, 2)}
    for code, on in in_tissue.items():
        on[m.tets[(m.region == 2) == (code == 2)].ravel()] = True
    sets = {**m.node_sets, "cut_muscle": np.flatnonzero(end & in_tissue[2]),
            "cut_breast": np.flatnonzero(end & in_tissue[1])}
    return Mesh(m.nodes, m.tets, m.region, node_sets=sets, face_sets=m.face_sets,
                node_pairs=m.node_pairs)


def _held(effect):
    """{component: set of nodes} the effect's constraints hold."""
    out = {0: set(), 1: set(), 2: set()}
    for c in effect.constraints():
        assert c.values is None
        for k in c.components:
            out[k] |= set(np.asarray(c.nodes).tolist())
    return out


def test_the_muscle_cut_is_fixed_and_the_breast_cut_left_free_by_default(mesh):
    held = _held(EFFECTS["cut_faces"](mesh))
    muscle = set(mesh.node_sets["cut_muscle"].tolist()) - set(mesh.node_sets["fixed"].tolist())
    assert muscle and all(held[k] == muscle for k in range(3))
    assert not set(mesh.node_sets["cut_breast"].tolist()) - set(
        mesh.node_sets["cut_muscle"].tolist()) & held[0]


def test_the_breast_cut_is_held_along_its_plane_normal_or_whole(mesh):
    breast = set(mesh.node_sets["cut_breast"].tolist()) - set(mesh.node_sets["fixed"].tolist())
    normal = _held(EFFECTS["cut_faces"](mesh, breast="normal", muscle="free"))
    assert normal[0] == breast and not normal[1] and not normal[2]  # the cut planes are x = +-w
    fixed = _held(EFFECTS["cut_faces"](mesh, breast="fixed"))
    assert all(breast <= fixed[k] for k in range(3))
    with pytest.raises(ValueError, match="breast must be one of"):
        EFFECTS["cut_faces"](mesh, breast="roller")


def test_the_muscle_cut_may_slide_along_its_plane_or_be_left_free(mesh):
    muscle = set(mesh.node_sets["cut_muscle"].tolist()) - set(mesh.node_sets["fixed"].tolist())
    breast = set(mesh.node_sets["cut_breast"].tolist()) - set(mesh.node_sets["fixed"].tolist())
    normal = _held(EFFECTS["cut_faces"](mesh, muscle="normal"))
    assert normal[0] == muscle and not normal[1] and not normal[2]
    assert not _held(EFFECTS["cut_faces"](mesh, muscle="free"))[0]
    # where the muscle's cut is not fixed, a node on both cuts is held as the breast's
    both = _held(EFFECTS["cut_faces"](mesh, muscle="normal", breast="fixed"))
    assert breast & muscle and all(breast <= both[k] for k in range(3))
    with pytest.raises(ValueError, match="muscle must be one of"):
        EFFECTS["cut_faces"](mesh, muscle=True)


def test_a_mesh_without_cut_sets_knows_no_cut(mesh):
    from mechanics.mesh import Mesh

    sets = {k: v for k, v in mesh.node_sets.items() if not k.startswith("cut_")}
    bare = Mesh(mesh.nodes, mesh.tets, mesh.region, node_sets=sets, face_sets=mesh.face_sets)
    assert EFFECTS["cut_faces"](bare, breast="fixed").constraints() == []


def test_gravity_towards_the_cut_moves_its_muscle_only_without_the_effect(mesh):
    mats = {r: {**NH, "E": 1.0} for r in (1, 3, 4, 5)} | {2: {**NH, "E": 10.0}}
    base = {"gravity": {"direction": (1.0, 0.0, 0.0)}, "fixed": {"node_set": "fixed"}}
    free = solve(build_model(mesh, mats, base))
    held = solve(build_model(mesh, mats, {**base, "cut_faces": {}}))
    assert free.converged and held.converged
    cut = mesh.node_sets["cut_muscle"]
    assert np.abs(held.u[cut]).max() < 1e-9
    assert np.abs(free.u[cut]).max() > 0.05  # mm: the muscle's free end gives way
    breast = mesh.node_sets["cut_breast"]
    assert np.abs(held.u[np.setdiff1d(breast, cut)]).max() > 0.05  # the breast's is free
