"""Gland (label 3) is meshed as breast by default and as its own regions on request."""

import numpy as np
import SimpleITK as sitk

from mechanics.mesh import REGIONS
from meshing import mesh_labels
from meshing.analytic import touching_boxes_labels
from meshing.labels import tissue_masks


def test_gland_is_breast_by_default_and_tagged_on_request():
    img = touching_boxes_labels(size=(50.0, 30.0, 40.0), split_y=16.0, spacing=1.5)
    arr = sitk.GetArrayFromImage(img)
    z, y, x = np.indices(arr.shape)
    c = np.argwhere(arr == 1).mean(0)
    ball = ((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2) * 1.5**2 <= 6.0**2
    arr[ball & (arr == 1)] = 3
    lab = sitk.GetImageFromArray(arr)
    lab.CopyInformation(img)
    masks = tissue_masks(lab)  # by default the gland is breast tissue
    assert masks.breast[ball].all() and masks.gland.sum() == (arr == 3).sum()
    kept = mesh_labels(lab, size_mm=4.0, keep_gland=True)
    gland = np.isin(kept.region, [REGIONS["gland_left"], REGIONS["gland_right"]])
    vol = kept.signed_volumes()
    # a 6 mm ball: 905 mm^3; tagged by tet centroids at 4 mm elements, so within 40 %
    assert 0.6 * 905 < vol[gland].sum() < 1.4 * 905
    centre = kept.nodes[kept.tets[gland]].mean((0, 1))
    phys = np.array(img.TransformContinuousIndexToPhysicalPoint(c[::-1].tolist()))
    assert np.linalg.norm(centre - phys) < 2.0
