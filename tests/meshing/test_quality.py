"""ANSYS-style element quality on single tets with known values."""

import numpy as np
import pytest

from meshing.quality import element_quality, volume_skewness

REGULAR = np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], float)


def q1(nodes):
    q = element_quality(np.asarray(nodes, float), np.array([[0, 1, 2, 3]]))
    return {k: v[0] for k, v in q.items()}


def test_regular_tet_is_ideal():
    q = q1(REGULAR)
    assert q["skewness"] == pytest.approx(0.0, abs=1e-12)
    assert q["aspect_ratio"] == pytest.approx(1.0, rel=1e-12)
    assert q["radius_ratio"] == pytest.approx(1.0, rel=1e-12)
    assert q["min_dihedral_deg"] == pytest.approx(np.degrees(np.arccos(1 / 3)), rel=1e-12)
    assert q["volume"] == pytest.approx(8 / 3)


def test_measures_are_invariant_to_rigid_motion_and_scale():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(4, 3))
    if np.linalg.det(x[1:] - x[0]) < 0:
        x = x[[0, 2, 1, 3]]
    r, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    r *= np.sign(np.linalg.det(r))
    a, b = q1(x), q1(3.0 * x @ r.T + 5.0)
    for k in ("skewness", "aspect_ratio", "radius_ratio", "min_dihedral_deg"):
        assert a[k] == pytest.approx(b[k], rel=1e-9)
    assert b["volume"] == pytest.approx(27.0 * a["volume"], rel=1e-9)


def test_flattening_worsens_every_measure_monotonically():
    prev = None
    for h in (1.0, 0.3, 0.1, 0.01):
        x = REGULAR * [1, 1, h]
        q = q1(x)
        if prev is not None:
            assert q["skewness"] > prev["skewness"]
            assert q["aspect_ratio"] > prev["aspect_ratio"]
            assert q["min_dihedral_deg"] < prev["min_dihedral_deg"]
        prev = q
    assert prev["skewness"] > 0.95 and prev["min_dihedral_deg"] < 5.0


def test_triangle_aspect_of_a_2_to_1_right_triangle():
    # Face (0,0), (2,0), (0,1), by hand. From (2,0): the median to (0,0.5) has length
    # sqrt(4.25); the mid-line (1,0)-(1,0.5) spans 1/sqrt(4.25) across it, so that
    # rectangle is sqrt(4.25) x 1/sqrt(4.25): ratio 4.25. The other two vertices give
    # 1.25 and 2. Normalised by sqrt(3) (the equilateral value).
    from meshing.quality import _triangle_aspect

    tri = np.array([[[0, 0, 0], [2, 0, 0], [0, 1, 0]]], float)
    assert _triangle_aspect(tri)[0] == pytest.approx(4.25 / np.sqrt(3), rel=1e-9)


def test_volume_and_skewness_alone_on_known_tets():
    # what the mesh improvement's local moves ask for, tens of thousands of times
    tets = np.array([[0, 1, 2, 3], [1, 0, 2, 3]])
    vol, skew = volume_skewness(REGULAR, tets)
    assert vol == pytest.approx([8 / 3, -8 / 3]) and skew == pytest.approx([0.0, 0.0], abs=1e-12)
    squashed = REGULAR * np.array([1.0, 1.0, 1e-3])  # all four nodes near the plane z = 0
    vol, skew = volume_skewness(squashed, tets[:1])
    assert vol[0] == pytest.approx(8e-3 / 3) and skew[0] > 0.99


def test_a_tet_with_two_coincident_nodes_is_as_flat_as_a_tet_gets():
    """No circumsphere (0 / 0): its skewness was 0, "perfect", and the mesh improvement
    kept two such tets of zero volume in a fine mesh the solver then refused."""
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    vol, skew = volume_skewness(x, np.array([[0, 1, 2, 3]]))
    assert vol[0] == 0.0 and skew[0] == 1.0
    assert q1(x)["skewness"] == 1.0
