"""fTetWild adapter: conforming mesh of a closed surface, and no debug file in the cwd."""

import numpy as np
import pytest

from meshing import _tetwild
from meshing.analytic import ellipsoid_labels
from meshing.labels import tissue_masks
from meshing.quality import element_quality
from meshing.surface import enclosed_volume, tissue_surface


@pytest.fixture(scope="module")
def sphere():
    m = tissue_masks(ellipsoid_labels((12.0, 12.0, 12.0), spacing=1.0), require_muscle=False)
    return tissue_surface(m.breast, m.grid, target_edge_mm=3.0)


def test_inside_filter_leaves_no_file_in_the_working_directory(sphere, tmp_path,
                                                                monkeypatch):
    monkeypatch.chdir(tmp_path)
    v, f = sphere
    nodes, tets = _tetwild.tetrahedralize(v, f, edge_mm=4.0, epsilon_mm=0.3,
                                          keep_background=False, threads=1)
    # fTetWild's winding-number filter writes __tracked_surface.stl into the cwd
    assert list(tmp_path.iterdir()) == []
    vol = element_quality(nodes, tets)["volume"]
    assert (vol > 0).all()
    # the filtered mesh fills the surface: the 0.3 mm envelope bounds the volume error by
    # 3 * 0.3 / 12 = 7.5 %; the faces sit much closer than the envelope allows
    assert vol.sum() == pytest.approx(enclosed_volume(v, f), rel=0.02)


def test_background_is_kept_by_default(sphere, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    v, f = sphere
    nodes, tets = _tetwild.tetrahedralize(v, f, edge_mm=4.0, epsilon_mm=0.3, threads=1)
    vol = element_quality(nodes, tets)["volume"]
    # the whole padded bounding box: more than the sphere
    assert vol.sum() > 1.5 * enclosed_volume(v, f)
    assert np.all(vol > 0)
