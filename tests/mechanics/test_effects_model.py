"""The assembled paper-like model (every effect on) on the breast-like test mesh."""

import numpy as np
import pytest
from breastlike import breastlike_mesh, paper_model

from mechanics.effects._interface import split_interface
from mechanics.solver import solve


@pytest.fixture(scope="module")
def mesh():
    return split_interface(breastlike_mesh(cells=(8, 6, 3, 2)))


def test_paper_model_prone_structures_carry_load(mesh):
    """Prone (breast 1 kPa): converges; the skin stiffens the breast; ligaments only
    pull; the breast hangs anteriorly (-y) and slides on the muscle."""
    st = solve(paper_model(mesh, 1.0, 4.0, 120.0, "prone"))
    st_noskin = solve(paper_model(mesh, 1.0, 4.0, 120.0, "prone", skin=None))
    assert st.converged and st_noskin.converged
    breast = np.unique(mesh.tets[mesh.region != 2])
    sag = -st.u[breast, 1].max(initial=0) + -st.u[breast, 1].min()
    assert sag > 1.0  # mm: the breast hangs anteriorly
    assert st.max_displacement() < st_noskin.max_displacement()
    model = paper_model(mesh, 1.0, 4.0, 120.0, "prone")
    lig = next(e for e in model.effects if e.name == "ligaments")
    N = lig.forces(mesh.nodes, st.x)
    assert np.all(N >= 0) and N.max() > 0


def test_tied_interface_does_not_slide(mesh):
    """Supine, stiff corner: with 'tied' the breast side follows the muscle side."""
    st_tied = solve(paper_model(mesh, 4.0, 20.0, 250.0, "supine", sliding=None, tied={}))
    faces_b, faces_m = mesh.face_sets["interface"], mesh.face_sets["interface_muscle"]
    rel = np.linalg.norm(st_tied.u[faces_b.ravel()] - st_tied.u[faces_m.ravel()], axis=1)
    assert rel.max() < 0.01 * st_tied.max_displacement()


# The sweep over the paper's search box (9 points x 3 gravity directions) is a benchmark,
# not a test: bench/effects_box.py.
