"""Pull-back through a deformed tet mesh is exact for affine maps and flags outside points."""

import numpy as np
from zoo import irregular_cube

from breastmodel.phantom.warp import PullBack


def test_pullback_inverts_affine_deformation_exactly():
    mesh = irregular_cube(4, seed=1)
    rng = np.random.default_rng(0)
    A = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
    A *= np.sign(np.linalg.det(A))
    b = np.array([5.0, -2.0, 1.0])
    x = mesh.nodes @ A.T + b
    pb = PullBack(mesh.nodes, x, mesh.tets)
    X_true = rng.uniform(0.05, 0.95, (5000, 3)) * (mesh.nodes.max(0) - mesh.nodes.min(0)) + \
        mesh.nodes.min(0)
    X_back, inside = pb(X_true @ A.T + b)
    assert inside.mean() > 0.99
    assert np.abs(X_back[inside] - X_true[inside]).max() < 1e-9


def test_points_outside_are_left_alone():
    mesh = irregular_cube(3, seed=2)
    pb = PullBack(mesh.nodes, mesh.nodes, mesh.tets)
    far = mesh.nodes.max(0) + np.array([[1.0, 1.0, 1.0], [5.0, 0.0, 0.0]])
    out, inside = pb(far)
    assert not inside.any()
    np.testing.assert_array_equal(out, far)
