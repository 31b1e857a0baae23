"""Mesh improvement: sliding boundary nodes along the surface and collapsing short edges
remove flat tets without moving the boundary off its surface."""

import numpy as np
import pytest

from meshing.improve import (
    _defects,
    _unique_rows,
    collapse_short_edges,
    relocate_boundary_nodes,
)
from meshing.quality import element_quality
from meshing.sets import tet_faces
from meshing.sizing import grid_tets


def _cube(n=4, h=5.0):
    pts, tets = grid_tets(np.zeros(3), np.full(3, n * h), h)
    e = pts[tets[:, 1:]] - pts[tets[:, :1]]
    neg = np.linalg.det(e) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return pts, tets.astype(np.int64)


def _on_top_face(pts, top):
    """A top-face node that is not on the cube's rim, and its +x neighbour."""
    i = np.flatnonzero((np.abs(pts[:, 2] - top) < 1e-9) & (pts[:, 0] == 5.0)
                       & (pts[:, 1] == 10.0))[0]
    j = np.flatnonzero((np.abs(pts[:, 2] - top) < 1e-9) & (pts[:, 0] == 10.0)
                       & (pts[:, 1] == 10.0))[0]
    return i, j


def test_sliding_a_squeezed_top_node_back_restores_quality():
    pts, tets = _cube()
    top = pts[:, 2].max()
    i, j = _on_top_face(pts, top)
    bad = pts.copy()
    bad[i] = pts[j] + np.array([-0.6, 0.0, 0.0])  # squeezed against its neighbour
    before = element_quality(bad, tets)["skewness"].max()
    assert before > 0.9
    bf = tet_faces(tets)[0]
    movable = np.zeros(len(pts), bool)
    movable[bf.ravel()] = True

    def project(p):  # the cube's top plane is the surface here
        q = np.array(p, float)
        q[:, 2] = top
        return q

    x = relocate_boundary_nodes(bad, tets, bf, movable, project, max_deviation=0.1)
    q = element_quality(x, tets)
    assert q["skewness"].max() < 0.85 and (q["volume"] > 0).all()
    # the boundary stayed on its plane and the volume is unchanged
    assert np.abs(x[i, 2] - top) < 1e-9
    assert q["volume"].sum() == pytest.approx(20.0**3)


def _split(pts, tets, i, j, dist):
    """Split edge (i, j) at ``dist`` mm from j: the tets around it become needles."""
    p = pts[j] + dist * (pts[i] - pts[j]) / np.linalg.norm(pts[i] - pts[j])
    n = len(pts)
    around = (tets == i).any(1) & (tets == j).any(1)
    a, b = tets[around].copy(), tets[around].copy()
    a[a == j] = n
    b[b == i] = n
    return np.vstack([pts, p]), np.vstack([tets[~around], a, b])


def test_collapse_removes_a_short_boundary_edge_and_keeps_the_volume():
    pts, tets = _cube()
    top = pts[:, 2].max()
    i, j = _on_top_face(pts, top)
    x, t = _split(pts, tets, i, j, 0.3)  # a 0.3 mm edge on the top face
    q0 = element_quality(x, t)
    assert q0["skewness"].max() > 0.9 and (q0["volume"] > 0).all()
    bf = tet_faces(t)[0]
    new, kept = collapse_short_edges(x, t, [bf])
    q = element_quality(x, new)
    # the needles are gone (one end of the short edge took the other's place): the cube's
    # tet count, good quality, the same volume, no topological defect
    assert len(new) == len(tets) == len(kept) and (np.diff(kept) > 0).all()
    assert q["skewness"].max() < 0.75 and (q["volume"] > 0).all()
    assert q["volume"].sum() == pytest.approx(20.0**3)
    assert _defects(new) == _defects(t) == 0


def test_collapse_leaves_a_good_mesh_alone():
    pts, tets = _cube(n=2)
    new, kept = collapse_short_edges(pts, tets, [tet_faces(tets)[0]])
    assert np.array_equal(new, tets) and np.array_equal(kept, np.arange(len(tets)))


def test_collapse_that_changes_no_other_tet_removes_the_flat_cap():
    """A flat cap tet whose apex belongs to it alone, on a face that may not move (an
    interface): the only admissible collapse merges the apex into a base node and changes no
    other tet. It removes the cap (before, the quality check took the max of nothing and
    raised)."""
    from mechanics.mesh import orient_tets

    nodes = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [3.5, 3.5, 3.6]], float)
    tets = orient_tets(nodes, np.array([[0, 1, 2, 3], [4, 1, 2, 3]]))
    out, kept = collapse_short_edges(nodes, tets, [tet_faces(tets)[0], np.array([[1, 2, 3]])])
    assert kept.tolist() == [0] and np.array_equal(out, tets[:1])


@pytest.mark.parametrize("width, high", [(2, 50), (3, 50), (3, 1 << 22)])
def test_unique_rows_matches_numpys_unique_over_rows(width, high):
    # one int64 key per row, or numpy's own where the indices do not fit (1 << 22 > 21 bits)
    rows = np.random.default_rng(width).integers(0, high, size=(3000, width))
    rows[::7] = rows[1::7]  # repeats
    got, cnt = _unique_rows(rows)
    want, wcnt = np.unique(rows, axis=0, return_counts=True)
    assert np.array_equal(got, want) and np.array_equal(cnt, wcnt)
