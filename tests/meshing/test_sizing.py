"""Sizing field: target size at the breast surfaces, graded inside, coarse away from the
mounds; curvature radius of a sphere."""

import numpy as np
import pytest
from scipy import ndimage as ndi

from meshing.analytic import ellipsoid_labels, torso_labels
from meshing.labels import tissue_masks
from meshing.sizing import COARSE, curvature_radius, grid_tets, tissue_size_map
from meshing.surface import tissue_surface


def test_curvature_radius_of_a_sphere():
    m = tissue_masks(ellipsoid_labels((30.0, 30.0, 30.0), spacing=1.0), require_muscle=False)
    v, f = tissue_surface(m.breast, m.grid, target_edge_mm=3.0)
    r = curvature_radius(v, f)
    assert np.median(r) == pytest.approx(30.0, rel=0.05)
    assert np.percentile(r, 5) > 20.0


def test_grid_tets_fill_the_box():
    pts, tets = grid_tets(np.zeros(3), np.array([10.0, 20.0, 30.0]), 5.0)
    e = pts[tets[:, 1:]] - pts[tets[:, :1]]
    vol = np.linalg.det(e) / 6.0
    assert np.abs(vol).sum() == pytest.approx(6000.0)
    assert (np.abs(vol) > 0).all()


def test_size_map_is_fine_at_the_breasts_and_coarse_elsewhere():
    s = 8.0
    masks = tissue_masks(torso_labels(spacing=2.0))
    h = tissue_size_map(masks, s)
    assert h.min() == pytest.approx(s)
    assert h.max() == pytest.approx(COARSE * s)
    grid = masks.grid
    z, y, x = (np.indices(h.shape) * grid.spacing[::-1, None, None, None]
               + grid.origin[::-1, None, None, None])
    # the breast skin (tissue voxels next to air) around the breast centres keeps the size
    skin = masks.breast & ~ndi.binary_erosion(masks.union)
    mound = skin & (np.abs(z + 10.0) < 10.0) & (np.abs(np.abs(x) - 70.0) < 10.0)
    assert mound.any() and np.allclose(h[mound], s)
    # thin layers far from the breasts (top of the field of view) are coarse
    far = masks.union & (z > 80.0)
    assert far.any() and np.median(h[far]) == pytest.approx(COARSE * s)
    # the deep inside of a breast mound is coarser than its skin
    deep = masks.breast & (ndi.distance_transform_edt(masks.breast, sampling=2.0) > 20.0)
    assert deep.any() and (h[deep] > s).all()


def test_uniform_when_coarse_is_one():
    masks = tissue_masks(torso_labels(spacing=2.0))
    h = tissue_size_map(masks, 8.0, coarse=1.0)
    assert np.allclose(h, 8.0)
