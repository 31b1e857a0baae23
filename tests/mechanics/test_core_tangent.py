"""Material derivatives and the assembled consistent tangent against finite differences."""

import numpy as np
import pytest
from zoo import cube5, irregular_cube

from mechanics.effects.base import MaterialSpec
from mechanics.materials import MATERIALS
from mechanics.model import build_model
from mechanics.solver import residual_and_tangent

PARAMS = {
    "neo_hookean": {"E": 3.0, "nu": 0.49},
    "gent": {"E": 3.0, "nu": 0.49, "Jm": 2.0},
    "linear": {"E": 3.0, "nu": 0.49},
}


def _random_F(n, rng, amp=0.25):
    return np.eye(3) + amp * rng.standard_normal((n, 3, 3))


@pytest.mark.parametrize("name", sorted(PARAMS))
def test_material_stress_and_tangent_match_finite_differences(name):
    # Central differences: truncation O(h^2) ~ 1e-12, round-off ~ eps/h ~ 1e-10; 1e-7 is safe.
    law = MATERIALS[name](**PARAMS[name])
    rng = np.random.default_rng(1)
    F = _random_F(4, rng)
    W, P, A = law.deviatoric(F)
    h = 1e-6
    P_fd = np.zeros_like(P)
    A_fd = np.zeros_like(A)
    for i in range(3):
        for J in range(3):
            dF = np.zeros((3, 3))
            dF[i, J] = h
            Wp, Pp, _ = law.deviatoric(F + dF, tangent=False)
            Wm, Pm, _ = law.deviatoric(F - dF, tangent=False)
            P_fd[:, i, J] = (Wp - Wm) / (2 * h)
            A_fd[:, :, :, i, J] = (Pp - Pm) / (2 * h)
    assert np.max(np.abs(P_fd - P)) <= 1e-7 * np.max(np.abs(P))
    assert np.max(np.abs(A_fd - A)) <= 1e-7 * np.max(np.abs(A))


@pytest.mark.parametrize("name", ["neo_hookean", "gent"])
def test_zero_stress_in_reference_and_objective(name):
    law = MATERIALS[name](**PARAMS[name])
    _, P0, _ = law.deviatoric(np.eye(3)[None], tangent=False)
    assert np.max(np.abs(P0)) < 1e-14
    rng = np.random.default_rng(2)
    F = _random_F(3, rng, 0.2)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    W, P, _ = law.deviatoric(F, tangent=False)
    Wq, Pq, _ = law.deviatoric(Q @ F, tangent=False)
    np.testing.assert_allclose(Wq, W, rtol=1e-12)
    np.testing.assert_allclose(Pq, Q @ P, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("formulation", ["anp", "standard"])
@pytest.mark.parametrize("name", sorted(PARAMS))
@pytest.mark.parametrize("make", [cube5, lambda: irregular_cube(2)])
def test_assembled_tangent_matches_finite_difference_of_residual(name, formulation, make):
    mesh = make()
    model = build_model(mesh, {1: MaterialSpec(name, PARAMS[name])},
                        {"gravity": {"direction": (0, 1, 0)}}, formulation=formulation)
    rng = np.random.default_rng(3)
    X = mesh.nodes
    x = X + 0.03 * rng.standard_normal(X.shape)  # ~6% strain, no inversion
    R, K = residual_and_tangent(model, X, x, 1.0)
    K = K.toarray()
    assert R.shape == (3 * mesh.n_nodes,)
    # Directional derivatives along unit dofs (first columns) and random directions: a
    # wrong entry anywhere shows up in a random direction with probability one.
    h = 1e-6
    dirs = [np.eye(K.shape[1])[j] for j in range(6)]
    dirs += list(rng.standard_normal((6, K.shape[1])))
    for d in dirs:
        Rp, _ = residual_and_tangent(model, X, x + h * d.reshape(-1, 3), 1.0)
        Rm, _ = residual_and_tangent(model, X, x - h * d.reshape(-1, 3), 1.0)
        fd = (Rp - Rm) / (2 * h)
        assert np.linalg.norm(fd - K @ d) <= 1e-6 * np.linalg.norm(K @ d)
    np.testing.assert_allclose(K, K.T, atol=1e-9 * np.abs(K).max())  # energy => symmetric
