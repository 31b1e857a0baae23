"""Where the reference scan's field of view cut the model's breast (meshing.field_of_view)."""

import numpy as np
import pytest
import SimpleITK as sitk

from meshing import mesh_labels
from meshing.analytic import touching_boxes_labels
from meshing.field_of_view import CUT_SHARE, breast_cut, cut_warning
from meshing.labels import Grid

SIZE = (60.0, 40.0, 50.0)  # x, y, z mm: the breast is the anterior 20 mm (y), split in x
CUT = 10  # mm of tissue the cropped field of view takes off the low-x (right) side


@pytest.fixture(scope="module")
def whole_and_cropped():
    labels = touching_boxes_labels(size=SIZE, split_y=20.0, spacing=1.0)
    margin = int(round((labels.GetSize()[0] - SIZE[0]) / 2))  # voxels of air each side
    size = list(labels.GetSize())
    size[0] -= margin + CUT
    cropped = sitk.RegionOfInterest(labels, size, [margin + CUT, 0, 0])
    with pytest.warns(UserWarning, match="touch"):
        meshes = [mesh_labels(im, size_mm=5.0) for im in (labels, cropped)]
    return list(zip((labels, cropped), meshes, strict=True))


def test_a_field_of_view_inside_the_air_cuts_nothing(whole_and_cropped):
    labels, mesh = whole_and_cropped[0]
    cut = breast_cut(mesh, Grid.of(labels))
    assert set(cut) == {"left", "right"}
    assert all(c["cut_mm2"] == 0.0 for c in cut.values())
    assert cut_warning(cut, "supine") is None


def test_a_field_of_view_through_one_breast_is_measured_and_named(whole_and_cropped):
    labels, mesh = whole_and_cropped[1]
    cut = breast_cut(mesh, Grid.of(labels))
    # the right breast (low x) ends on the image's face: 20 mm (y) x 50 mm (z) of it, less the
    # rim the surface's smoothing rounds off the box's edges (faces off the plane count as
    # skin): 828 mm^2 at 5 mm elements
    assert 0.75 * 20.0 * 50.0 < cut["right"]["cut_mm2"] <= 20.0 * 50.0
    assert cut["left"]["cut_mm2"] == 0.0
    # its skin: the anterior face, the top and bottom and no lateral face; the sides split in
    # the middle of what the field of view holds (the thinnest slices are all alike here)
    width = (SIZE[0] - CUT) / 2
    right_skin = width * SIZE[2] + 2 * width * 20.0
    assert cut["right"]["skin_mm2"] == pytest.approx(right_skin, rel=0.15)
    assert cut["right"]["share"] > CUT_SHARE
    said = cut_warning(cut, "supine")
    assert "reference scan (supine)" in said and "right breast" in said
    assert "left breast" not in said
    assert np.isclose(cut["right"]["share"], cut["right"]["cut_mm2"] / cut["right"]["skin_mm2"],
                      atol=1e-4)


def test_the_nodes_on_the_cut_are_named_by_tissue(whole_and_cropped):
    """``cut_breast`` / ``cut_muscle``: the nodes of the breast's and muscle's faces on the
    label map's field-of-view planes (what ``mechanics.effects.cut_faces`` holds)."""
    whole, cropped = (mesh for _, mesh in whole_and_cropped)
    assert len(whole.node_sets["cut_breast"]) == len(whole.node_sets["cut_muscle"]) == 0
    plane = cropped.nodes[:, 0].min()  # the cut at low x
    y = {}
    for name in ("cut_breast", "cut_muscle"):
        p = cropped.nodes[cropped.node_sets[name]]
        assert len(p) > 10, name
        assert np.abs(p[:, 0] - plane).max() < 0.6, name  # all on the cut plane
        y[name] = np.median(p[:, 1] - cropped.nodes[:, 1].min())
    # the breast is the anterior 20 mm of the 40, the muscle behind it
    assert y["cut_breast"] < 20.0 < y["cut_muscle"]
