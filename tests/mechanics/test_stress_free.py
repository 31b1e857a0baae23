"""Stress-free geometry: recover a known unloaded shape from its loaded configuration."""

import numpy as np
import pytest
from zoo import hemisphere

from mechanics.model import build_model
from mechanics.solver import solve
from mechanics.stress_free import inverse_fixed_point, paper_fixed_point

E, NU = 0.4, 0.49  # kPa; soft enough for a sag of several mm of a 30 mm half ball


def _loaded(mesh):
    mats = {int(r): {"name": "neo_hookean", "E": E, "nu": NU} for r in np.unique(mesh.region)}
    effects = {"gravity": {"direction": (0.0, 0.0, -1.0)}, "fixed": {"node_set": "fixed"}}
    return build_model(mesh, mats, effects)


@pytest.fixture(scope="module")
def truth():
    mesh = hemisphere(radius=30.0, n=6)
    state = solve(_loaded(mesh))
    assert state.converged
    return mesh, state.x


def _surface_nodes(mesh):
    faces = np.sort(mesh.tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), 1)
    uniq, counts = np.unique(faces, axis=0, return_counts=True)
    boundary = np.unique(uniq[counts == 1])
    return np.setdiff1d(boundary, mesh.node_sets["fixed"])


def test_inverse_fixed_point_recovers_unloaded_shape(truth):
    mesh, x_loaded = truth
    sag = np.linalg.norm(x_loaded - mesh.nodes, axis=1).max()
    assert sag > 4.0  # a real large-deformation case
    model = _loaded(mesh.with_nodes(x_loaded))  # the measured (loaded) geometry is all we have
    res = inverse_fixed_point(model, x_loaded, tol=1e-3)
    assert res.converged
    assert np.abs(res.X - mesh.nodes).max() < 5e-3  # mm, vs a sag of several mm
    plain = inverse_fixed_point(model, x_loaded, tol=1e-3, anderson=0, max_iter=60)
    assert len(res.history) <= len(plain.history)


def test_paper_fixed_point_reduces_surface_error(truth):
    mesh, x_loaded = truth
    active = _surface_nodes(mesh)
    model = _loaded(mesh.with_nodes(x_loaded))
    res = paper_fixed_point(
        model,
        lambda x: x_loaded[active],  # point-to-point with known correspondence, as in the paper
        active,
        mesh.node_sets["fixed"],
        lam=0.5,
        min_improvement=1e-3,
        max_iter=25,
    )
    first, last = res.history[0]["mean_error"], min(h["mean_error"] for h in res.history)
    assert first > 3.0
    assert last < 0.2 * first


def test_inverse_gives_up_after_repeated_failed_forward_solves(truth, monkeypatch):
    """A model with no equilibrium near the target: after the first good forward solve every
    damped retry fails; the inverse stops after ``max_failures`` of them, not ``max_iter``."""
    import mechanics.stress_free as sf
    from mechanics.solver import SolverError

    mesh, x_loaded = truth
    model = _loaded(mesh.with_nodes(x_loaded))
    real, calls = sf._forward, []

    def forward(*args):
        calls.append(1)
        if len(calls) > 1:
            raise SolverError("mechanics: no equilibrium (test)")
        return real(*args)

    monkeypatch.setattr(sf, "_forward", forward)
    with pytest.raises(SolverError, match="no equilibrium"):
        inverse_fixed_point(model, x_loaded, tol=1e-9, max_iter=50, max_failures=3)
    assert len(calls) == 1 + 4


def test_inverse_gives_up_after_two_solves_without_equilibrium(truth, monkeypatch):
    """Damped retries that fail with the solver's physical verdict (the body gives way) end
    the inverse at the second verdict, though ``max_failures`` would allow more; a mere
    numerical failure keeps the damped retries."""
    import mechanics.stress_free as sf
    from mechanics.solver import NoEquilibrium, SolverError

    mesh, x_loaded = truth
    model = _loaded(mesh.with_nodes(x_loaded))
    real = sf._forward
    for error, solves in ((NoEquilibrium("mechanics: no equilibrium (test)",
                                         verdict={"kind": "no equilibrium"}), 1 + 2),
                          (SolverError("mechanics: Newton diverged (test)"), 1 + 4)):
        calls = []

        def forward(*args, error=error, calls=calls):
            calls.append(1)
            if len(calls) > 1:
                raise error
            return real(*args)

        monkeypatch.setattr(sf, "_forward", forward)
        with pytest.raises(SolverError, match="test"):
            inverse_fixed_point(model, x_loaded, tol=1e-9, max_iter=50, max_failures=3)
        assert len(calls) == solves


def test_a_fixed_point_step_that_inverts_an_element_is_halved_until_none_does():
    """The inverse's next estimate never folds the mesh: a plain step that would push a tet's
    apex through its base (from z = 1 to -1) is halved until the tet keeps its orientation,
    and the step is taken along the same direction."""
    from types import SimpleNamespace

    from mechanics.mesh import Mesh
    from mechanics.stress_free import _Anderson, _next_estimate

    X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    model = SimpleNamespace(mesh=Mesh(X, [[0, 1, 2, 3]], [1]))
    f = np.zeros(12)
    f[11] = -2.0  # the apex to z = -1
    X_new = _next_estimate(model, X, f, _Anderson(0))
    assert model.mesh.signed_volumes(X_new)[0] > 0
    assert np.allclose(X_new[:3], X[:3]) and X_new[3, 2] == pytest.approx(0.5)  # half a step
    f[11] = -0.5  # a step that keeps the tet is taken whole
    assert _next_estimate(model, X, f, _Anderson(0))[3, 2] == pytest.approx(0.5)
