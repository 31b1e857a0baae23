"""The segmentation's morphology on its objects' boxes gives what the whole volume gives."""

import numpy as np
from scipy import ndimage

from imaging.segment_regions import _ball, bounding_box, dilated
from imaging.segment_wall import _near


def _blobs(shape=(30, 34, 38), seed=0):
    """Random blobs, some of them cut by the array's faces."""
    rng = np.random.default_rng(seed)
    f = ndimage.gaussian_filter(rng.normal(size=shape), 2.0)
    m = f > 1.5 * f.std()
    m[:, :, :5] = False
    return m


def test_dilation_on_the_box_equals_the_whole_volume_s():
    ball = _ball(3.0, np.array([1.0, 1.5, 0.8]))
    for seed in range(4):
        m = _blobs(seed=seed)
        assert m.any()
        assert np.array_equal(dilated(m, ball), ndimage.binary_dilation(m, structure=ball))
    empty = np.zeros((8, 9, 10), bool)
    assert bounding_box(empty, np.ones(3, int)) is None
    assert not dilated(empty, ball).any()


def test_a_box_is_the_object_s_grown_within_the_array():
    m = np.zeros((10, 12, 14), bool)
    m[0, 5:7, 12:] = True
    assert bounding_box(m, np.array([2, 1, 3])) == (slice(0, 3), slice(4, 8), slice(9, 14))
    # any non-zero counts, whatever the array's type
    assert bounding_box(m.astype(np.int64) * 7, np.zeros(3, int)) == (
        slice(0, 1), slice(5, 7), slice(12, 14))


def test_near_is_the_whole_volume_s_distance_on_the_voxels_asked_about():
    sp = np.array([1.0, 1.5, 0.8])
    for seed in range(3):
        air, asked = _blobs(seed=seed), _blobs(seed=seed + 10)
        box = bounding_box(asked, np.ceil(3.0 / sp).astype(int) + 1)
        whole = ndimage.distance_transform_edt(~air, sampling=sp) <= 3.0
        assert np.array_equal(_near(air, box, sp, 3.0) & asked, whole & asked)
