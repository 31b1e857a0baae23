"""Surface distances and metrics against closed-form cases and a brute-force reference."""

import numpy as np
import pytest

from breastmodel.evaluation import (
    TriangleSurface,
    closest_point_on_triangles,
    is_closed,
    landmark_errors,
    normal_tangential,
    per_region_metrics,
    point_to_surface,
    surface_metrics,
    vertex_normals,
)

# ---------------------------------------------------------------- test geometry and reference


def icosphere(radius: float, level: int):
    """Icosahedron refined by midpoint subdivision, vertices projected on the sphere."""
    t = (1 + 5**0.5) / 2
    v = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]

    def midpoint(i, j, mid):
        key = (min(i, j), max(i, j))
        if key not in mid:
            m = verts[i] + verts[j]
            verts.append(m / np.linalg.norm(m))
            mid[key] = len(verts) - 1
        return mid[key]

    for _ in range(level):
        mid, new = {}, []
        for a, b, c in f:
            ab, bc, ca = midpoint(a, b, mid), midpoint(b, c, mid), midpoint(c, a, mid)
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        f = new
    return radius * np.array(verts), np.array(f)


def max_sag(vertices, triangles, radius):
    """Largest chordal error of a sphere triangulation with vertices on the sphere.

    Every point of a triangle lies at least as far from the centre as the circumcentre of its
    vertices (the foot of the perpendicular from the centre to its plane), at
    sqrt(r^2 - R^2), R the circumradius.
    """
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (b - c, c - a, a - b))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    circ = la * lb * lc / (4 * area)
    return float(np.max(radius - np.sqrt(radius**2 - circ**2)))


def grid_square(n: int, size: float = 1.0, *, x0: float = 0.0):
    """(n x n) vertices on [x0, x0 + size] x [0, size] at z = 0, two triangles per cell."""
    x, y = np.meshgrid(np.linspace(x0, x0 + size, n), np.linspace(0, size, n), indexing="ij")
    verts = np.column_stack([x.ravel(), y.ravel(), np.zeros(n * n)])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    tris = np.concatenate([np.column_stack([a.ravel(), b.ravel(), c.ravel()]),
                           np.column_stack([a.ravel(), c.ravel(), d.ravel()])])
    return verts, tris  # normals +z


def _seg_dist(p, s, e):
    """Distance from points p (n,1,3) to segments s->e (1,k,3)."""
    d = e - s
    t = np.clip(np.sum((p - s) * d, -1) / np.sum(d * d, -1), 0, 1)
    return np.linalg.norm(p - (s + t[..., None] * d), axis=-1)


def brute_force_distance(points, vertices, triangles):
    """Reference: for every (point, triangle) pair, the plane distance when the projection
    falls inside the triangle (barycentric test), else the nearest of the three edges."""
    p = points[:, None, :]
    a, b, c = (vertices[triangles[:, i]][None] for i in range(3))
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    h = np.sum((p - a) * n, -1)
    q = p - h[..., None] * n  # projection on the plane
    inside = np.ones(h.shape, bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.sum(np.cross(v - u, q - u) * n, -1) >= 0
    edge = np.minimum(np.minimum(_seg_dist(p, a, b), _seg_dist(p, b, c)), _seg_dist(p, c, a))
    return np.where(inside, np.abs(h), edge)  # (n, k)


# ---------------------------------------------------------------- distances


def test_matches_brute_force_on_random_triangles():
    rng = np.random.default_rng(0)
    # offset 100 mm: the float32 BVH must not cost the float64 precision
    verts = rng.uniform(0, 10, size=(120, 3)) + 100.0
    tris = rng.permutation(120).reshape(40, 3)
    pts = rng.uniform(-2, 12, size=(500, 3)) + 100.0
    ref = brute_force_distance(pts, verts, tris)
    d, closest = point_to_surface(pts, verts, tris)
    np.testing.assert_allclose(d, ref.min(axis=1), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(pts - closest, axis=1), d, rtol=0, atol=1e-9)
    # closest points themselves, where the nearest triangle is unambiguous
    two = np.sort(ref, axis=1)[:, :2]
    clear = two[:, 1] - two[:, 0] > 1e-3
    best = np.argmin(ref, axis=1)
    ref_closest = closest_point_on_triangles(
        pts, *(verts[tris[best, i]] for i in range(3)))
    assert clear.sum() > 400
    np.testing.assert_allclose(closest[clear], ref_closest[clear], rtol=0, atol=1e-6)


def test_closest_point_kernel_matches_reference_pairwise():
    rng = np.random.default_rng(1)
    n = 2000
    p, a, b, c = (rng.normal(size=(n, 3)) for _ in range(4))
    c[:5] = a[:5] + 0.5 * (b[:5] - a[:5])  # degenerate (collinear) triangles
    c[5:10] = a[5:10]
    q = closest_point_on_triangles(p, a, b, c)
    got = np.linalg.norm(p - q, axis=1)
    ok = slice(10, None)
    ref = np.array([brute_force_distance(p[i:i + 1], np.stack([a[i], b[i], c[i]]),
                                         np.array([[0, 1, 2]]))[0, 0] for i in range(10, n)])
    np.testing.assert_allclose(got[ok], ref, rtol=0, atol=1e-12)
    # degenerate: nearest point of the segment(s)
    for i in range(10):
        seg = min(_seg_dist(p[i][None, None], s[i][None, None], e[i][None, None])[0, 0]
                  for s, e in ((a, b), (b, c), (c, a)) if np.linalg.norm(e[i] - s[i]) > 0)
        assert abs(got[i] - seg) < 1e-12


def test_plane_and_shifted_plane():
    meas_v, tris = grid_square(11, 10.0)
    d_normal, s = 1.5, 2.0
    pred_v = meas_v + [s, 0.0, d_normal]  # shifted along the normal and sideways
    d, closest = point_to_surface(pred_v, meas_v, tris)
    overhang = np.maximum(pred_v[:, 0] - 10.0, 0.0)
    np.testing.assert_allclose(d, np.hypot(d_normal, overhang), rtol=0, atol=1e-9)
    np.testing.assert_allclose(closest[:, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(closest[:, 0], np.minimum(pred_v[:, 0], 10.0), atol=1e-9)
    # signed from the +z normals of an open surface
    ds, _ = point_to_surface(pred_v, meas_v, tris, signed=True)
    np.testing.assert_allclose(ds, d, atol=1e-12)
    ds, _ = point_to_surface(pred_v, meas_v, tris[:, ::-1], signed=True)
    np.testing.assert_allclose(ds, -d, atol=1e-12)
    m = surface_metrics(pred_v, tris, meas_v, tris)
    back = np.maximum(-(meas_v[:, 0] - s), 0.0)  # meas vertices left of the shifted plane
    assert m["mean_pred_to_meas_mm"] == pytest.approx(np.hypot(d_normal, overhang).mean(), abs=1e-9)
    assert m["mean_meas_to_pred_mm"] == pytest.approx(np.hypot(d_normal, back).mean(), abs=1e-9)
    assert m["hausdorff_mm"] == pytest.approx(np.hypot(d_normal, s), abs=1e-9)
    assert m["rmse_mm"] == pytest.approx(np.sqrt(np.mean(d_normal**2 + overhang**2)), abs=1e-9)


def test_concentric_spheres_mhd_is_radius_gap():
    r1, r2 = 50.0, 53.0
    v1, t1 = icosphere(r1, 4)
    v2, t2 = icosphere(r2, 4)
    # rotate the outer sphere so that its vertices do not sit radially above inner ones
    q, _ = np.linalg.qr(np.random.default_rng(5).normal(size=(3, 3)))
    v2 = v2 @ q.T
    sag1, sag2 = max_sag(v1, t1, r1), max_sag(v2, t2, r2)
    assert 0 < sag1 < 0.1 and 0 < sag2 < 0.1  # fine enough for the bounds to mean something
    m = surface_metrics(v1, t1, v2, t2)
    gap = r2 - r1
    # inner vertices (on r1) to the outer polyhedron (inside the r2 sphere by <= sag2)
    assert gap - sag2 - 1e-9 <= m["mean_pred_to_meas_mm"] <= gap + 1e-9
    # outer vertices to the inner polyhedron (inside the r1 sphere by <= sag1)
    assert gap - 1e-9 <= m["mean_meas_to_pred_mm"] <= gap + sag1 + 1e-9
    assert m["mhd_mm"] == max(m["mean_pred_to_meas_mm"], m["mean_meas_to_pred_mm"])
    assert m["mhd_mm"] == pytest.approx(gap, abs=max(sag1, sag2))
    assert gap - 1e-9 <= m["hausdorff_mm"] <= gap + sag1 + 1e-9
    assert m["n_pred"] == len(v1) and m["n_meas"] == len(v2)


def test_sphere_point_cloud_signed_inside_outside():
    r = 40.0
    v, t = icosphere(r, 4)
    sag = max_sag(v, t, r)
    assert is_closed(t)
    rng = np.random.default_rng(2)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    rho = rng.uniform(0.5 * r, 1.5 * r, size=len(u))
    d, closest = point_to_surface(rho[:, None] * u, v, t, signed=True)
    # the polyhedron lies between the spheres of radius r - sag and r
    excess = d - (rho - r)
    assert excess.min() >= -1e-9 and excess.max() <= sag + 1e-9
    far = np.abs(rho - r) > sag
    np.testing.assert_array_equal(np.sign(d[far]), np.sign(rho[far] - r))
    assert np.all(np.abs(np.linalg.norm(closest, axis=1) - r) <= sag + 1e-9)
    # the closed-surface sign does not depend on the triangle orientation
    d_flip, _ = point_to_surface(rho[:, None] * u, v, t[:, ::-1], signed=True)
    np.testing.assert_array_equal(np.sign(d_flip[far]), np.sign(d[far]))


def test_open_cap_sign_from_normals():
    r = 40.0
    v, t = icosphere(r, 4)
    cap = t[v[t].mean(axis=1)[:, 2] > 0]  # upper hemisphere, outward normals
    assert not is_closed(cap)
    rng = np.random.default_rng(3)
    u = rng.normal(size=(2000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] > 0.3]  # away from the rim
    rho = rng.uniform(0.8 * r, 1.2 * r, size=len(u))
    far = np.abs(rho - r) > max_sag(v, cap, r)
    d, _ = TriangleSurface(v, cap).distance(rho[:, None] * u, signed=True)
    np.testing.assert_array_equal(np.sign(d[far]), np.sign(rho[far] - r))


def test_square_with_pulled_node_hausdorff_is_the_pull():
    meas_v, tris = grid_square(11)
    pull = 0.3
    pred_v = meas_v.copy()
    k = 5 * 11 + 5  # centre node
    pred_v[k, 2] += pull
    m = surface_metrics(pred_v, tris, meas_v, tris)
    assert m["hausdorff_mm"] == pytest.approx(pull, abs=1e-9)
    assert m["max_pred_to_meas_mm"] == pytest.approx(pull, abs=1e-9)
    assert m["max_meas_to_pred_mm"] < pull - 1e-3  # the tent lies above its own base
    assert m["mean_pred_to_meas_mm"] == pytest.approx(pull / len(pred_v), abs=1e-12)
    assert m["rmse_mm"] == pytest.approx(pull / np.sqrt(len(pred_v)), abs=1e-12)
    assert m["mhd_mm"] == pytest.approx(pull / len(pred_v), abs=1e-12)


def test_mhd_takes_the_larger_direction():
    pred_v, pred_t = grid_square(11, 1.0)
    meas_v, meas_t = grid_square(11, 2.0)  # [0,2]^2: contains the predicted patch
    m = surface_metrics(pred_v, pred_t, meas_v, meas_t)
    assert m["mean_pred_to_meas_mm"] == pytest.approx(0.0, abs=1e-12)
    x, y = meas_v[:, 0], meas_v[:, 1]
    out = np.hypot(np.maximum(x - 1, 0), np.maximum(y - 1, 0))
    assert m["mean_meas_to_pred_mm"] == pytest.approx(out.mean(), abs=1e-9)
    assert m["mhd_mm"] == pytest.approx(out.mean(), abs=1e-9)
    assert m["hausdorff_mm"] == pytest.approx(np.sqrt(2.0), abs=1e-9)


def test_bad_input_names_the_problem():
    v, t = grid_square(3)
    with pytest.raises(ValueError, match="evaluation: .*shape"):
        point_to_surface(np.zeros((4, 2)), v, t)
    with pytest.raises(ValueError, match="evaluation: triangle indices"):
        point_to_surface(np.zeros((4, 3)), v, t + 100)
    with pytest.raises(ValueError, match="NaN"):
        point_to_surface(np.full((1, 3), np.nan), v, t)


# ---------------------------------------------------------------- tables and splits


def test_per_region_metrics_table():
    d = np.array([1.0, 2.0, 3.0, -4.0])
    regions = np.array([1, 1, 2, 2])
    tab = per_region_metrics(d, regions, {1: "breast_left"})
    assert list(tab) == ["breast_left", "region_2", "all"]
    assert tab["breast_left"]["mean_mm"] == pytest.approx(1.5)
    assert tab["breast_left"]["rmse_mm"] == pytest.approx(np.sqrt(2.5))
    assert tab["region_2"]["mean_mm"] == pytest.approx(3.5)
    assert tab["region_2"]["mean_signed_mm"] == pytest.approx(-0.5)
    assert tab["region_2"]["max_mm"] == pytest.approx(4.0)
    assert tab["all"]["n"] == 4 and tab["all"]["mean_mm"] == pytest.approx(2.5)
    with pytest.raises(ValueError, match="same length"):
        per_region_metrics(d, regions[:3])


def test_landmark_errors():
    meas = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    pred = meas + np.array([[3.0, 4, 0], [0, 0, 0], [0, 0, -2]])
    out = landmark_errors(pred, meas, ["nipple_l", "sternum", "axilla"])
    assert out["per_landmark"]["nipple_l"]["error_mm"] == pytest.approx(5.0)
    assert out["per_landmark"]["axilla"]["dz_mm"] == pytest.approx(-2.0)
    assert out["mean_mm"] == pytest.approx(7.0 / 3)
    assert out["max_mm"] == pytest.approx(5.0)
    assert out["rmse_mm"] == pytest.approx(np.sqrt(29.0 / 3))


def test_normal_tangential_split():
    n, t = normal_tangential(np.array([[1.0, 2.0, 3.0]]), np.array([[0.0, 0.0, 2.0]]))
    assert n[0] == pytest.approx(3.0) and t[0] == pytest.approx(np.sqrt(5.0))
    rng = np.random.default_rng(4)
    e, nn = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    n, t = normal_tangential(e, nn)
    np.testing.assert_allclose(n**2 + t**2, np.sum(e**2, axis=1), rtol=1e-12)
    assert np.all(t >= 0)
    n_flip, _ = normal_tangential(e, -nn)
    np.testing.assert_allclose(n_flip, -n, rtol=1e-12)


def test_vertex_normals_of_sphere_are_radial():
    v, t = icosphere(30.0, 3)
    nrm = vertex_normals(v, t)
    cosang = np.sum(nrm * v / 30.0, axis=1)
    # symmetric vertex stars: area-weighted normals within ~1 deg of radial at this level
    assert cosang.min() > np.cos(np.radians(1.0))


def grid_sheet(x0: float, x1: float, y0: float, y1: float, z: float, step: float = 1.0):
    """A flat open sheet z = const over [x0, x1] x [y0, y1], triangulated on a square grid."""
    xs, ys = np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])
    n = len(ys)
    ij = np.array([(i, j) for i in range(len(xs) - 1) for j in range(n - 1)])
    a = ij[:, 0] * n + ij[:, 1]
    f = np.vstack([np.column_stack([a, a + n, a + 1]), np.column_stack([a + 1, a + n, a + n + 1])])
    return v, f


def test_the_overlap_mhd_leaves_out_the_skin_one_surface_shows_past_the_others_edge():
    # The measured sheet lies 1 mm above the predicted one and reaches 20 mm further along x
    # (a field of view that shows more of the body): there the measured vertices are
    # 1-20 mm from the predicted sheet's edge, and the all-vertex MHD grows with that
    # stretch, while over the skin both show every distance is the 1 mm offset.
    pv, pf = grid_sheet(0, 40, 0, 40, 0.0)
    mv, mf = grid_sheet(0, 60, 0, 40, 1.0)
    m = surface_metrics(pv, pf, mv, mf)
    assert m["mhd_overlap_mm"] == pytest.approx(1.0, abs=1e-4)
    past = mv[:, 0] > 40.0 + 1e-9
    # the vertices over the predicted sheet's edges (x = 0, 40; y = 0, 40) have their
    # closest point on its rim too: their side is undefined, and they are left out as well
    on_edge = ~past & (np.isin(mv[:, 0], [0.0, 40.0]) | np.isin(mv[:, 1], [0.0, 40.0]))
    assert m["uncovered_meas_fraction"] == pytest.approx((past | on_edge).mean(), abs=1e-9)
    # the model's vertices over the edges the two sheets share (x = 0; y = 0, 40) likewise
    shared_edge = (pv[:, 0] == 0.0) | np.isin(pv[:, 1], [0.0, 40.0])
    assert m["uncovered_pred_fraction"] == pytest.approx(shared_edge.mean(), abs=1e-9)
    # the vertices left out are those past the edge, with their true distances
    expected_all = np.where(past, np.hypot(mv[:, 0] - 40.0, 1.0), 1.0).mean()
    assert m["mean_meas_to_pred_mm"] == pytest.approx(expected_all, rel=1e-4)
    assert m["mhd_mm"] > 3.0 * m["mhd_overlap_mm"]
    # the other way round: the model shows the skin the measurement cuts off
    r = surface_metrics(mv, mf, pv, pf)
    assert r["mhd_overlap_mm"] == pytest.approx(1.0, abs=1e-4)
    assert r["uncovered_pred_fraction"] == pytest.approx((past | on_edge).mean(), abs=1e-9)
    # sheets side by side share no skin: every pair ends on an edge, and there is no figure
    far = surface_metrics(pv, pf, mv + [60.0, 0.0, 0.0], mf)
    assert far["uncovered_pred_fraction"] == far["uncovered_meas_fraction"] == 1.0
    assert np.isnan(far["mhd_overlap_mm"]) and np.isfinite(far["mhd_mm"])
    # a closed surface has no edge: nothing is left out
    v, f = icosphere(10.0, 2)
    s = surface_metrics(v * 1.05, f, v, f)
    assert s["uncovered_pred_fraction"] == s["uncovered_meas_fraction"] == 0.0
    assert s["mhd_overlap_mm"] == pytest.approx(s["mhd_mm"])
