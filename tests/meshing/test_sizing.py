"""Sizing field: target size at the breast surfaces, graded inside, coarse away from the
mounds; curvature radius of a sphere."""

import numpy as np
import pytest
from scipy import ndimage as ndi

from meshing.analytic import ellipsoid_labels, torso_labels
from meshing.labels import tissue_masks
from meshing.sizing import (
    AUTO_SIZE_RANGE_MM,
    COARSE,
    auto_size_mm,
    curvature_radius,
    grid_tets,
    tissue_size_map,
)
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


def test_auto_size_follows_the_largest_inscribed_radius():
    """3 elements across the breast's largest inscribed radius, within 4-8 mm; anisotropic
    voxels are measured in mm."""
    z, y, x = np.mgrid[-40:41, -40:41, -40:41].astype(float)
    for radius, want in ((18.0, 6.0), (16.0, 5.0), (35.0, 8.0), (8.0, 4.0)):
        ball = x ** 2 + y ** 2 + z ** 2 <= radius ** 2
        size, r = auto_size_mm(ball, (1.0, 1.0, 1.0))
        assert r == pytest.approx(radius, abs=1.0)
        assert size == want and AUTO_SIZE_RANGE_MM[0] <= size <= AUTO_SIZE_RANGE_MM[1]
    ball = x ** 2 + y ** 2 + (0.5 * z) ** 2 <= 16.0 ** 2  # a ball of 16 mm on 0.5 mm slices
    assert auto_size_mm(ball, (0.5, 1.0, 1.0))[0] == 5.0
    with pytest.raises(ValueError, match="no breast"):
        auto_size_mm(np.zeros((4, 4, 4), bool), (1.0, 1.0, 1.0))


def test_the_pipeline_sizes_an_auto_mesh_by_the_breast():
    """``[mesh] size_mm = "auto"`` reads the breast tissue (labels 1 and 3) of the reference
    label map and says how it chose; a number is taken as given."""
    import SimpleITK as sitk

    from meshing.sizing import mesh_size

    z, y, x = np.mgrid[-30:31, -30:31, -30:31].astype(float)
    a = np.where(x ** 2 + y ** 2 + z ** 2 <= 15.0 ** 2, 1, 0).astype(np.uint8)
    a[(x ** 2 + y ** 2 + z ** 2 <= 5.0 ** 2)] = 3  # a gland inside counts as breast
    a[:, :, :4] = 2
    labels = sitk.GetImageFromArray(a)
    size, why = mesh_size("auto", labels)
    assert size == 5.0 and why.startswith("auto") and "15." in why
    assert mesh_size(7, labels) == (7.0, "given")
