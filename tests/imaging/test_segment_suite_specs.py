"""The segmentation on the validation suite's subjects (issue 14): contrast read right on
every spec, and glands that touch the chest wall given back to the breast.

Volumes: each spec of the suite (``draw_spec(seed, size="small")``: its field of view,
anatomy, voxel shape, contrast, SNR and bias) rendered by the renderer ``make_subject``
uses, with rigid motion only (no FE truth is needed to score a segmentation; the FEBio-
deformed scans of ``bench/segment_suite.py`` give the same figures within 0.01).

Before this change the contrast was misread on 16 of the suite's 33 scans (seeds 1, 2, 6, 8,
9, 10, 11) without a warning, and the muscle took in every gland that touches it (seeds 1,
4, 6, 9, 10).
"""

import numpy as np
import pytest

from imaging.io import read_volume
from imaging.qa import dice
from imaging.segment import segment_volume
from imaging.segment_regions import glands_off_muscle


def render_supine(seed: int, root):
    from breastmodel.phantom import make_phantom
    from breastmodel.phantom.family import draw_spec

    spec = draw_spec(seed, size="small")
    out = root / "subject"
    make_phantom(out, seed=spec.seed, anatomy=spec.anatomy(), voxel_size=spec.voxel_size,
                 snr=spec.snr, bias=spec.bias, positions=("supine",), contrast=spec.contrast,
                 fat_suppressed=spec.fat_suppressed, max_rotation_deg=spec.max_rotation_deg,
                 max_translation_mm=spec.max_translation_mm, progress=False)
    return (spec, read_volume(out / "supine.nii.gz"),
            read_volume(root / "subject_truth" / "supine_labels.nii.gz"))


@pytest.mark.parametrize("seed", range(12))
def test_contrast_is_read_right_on_every_suite_spec(seed, tmp_path):
    spec, img, _ = render_supine(seed, tmp_path)
    res = segment_volume(img, name=f"seed{seed}/supine.nii.gz")
    want = "fat_suppressed" if spec.fat_suppressed else "fat_bright"
    assert res.contrast == want, res.notes
    assert res.notes and any(n.startswith(f"contrast detected: {want}") for n in res.notes)


# Measured when written (supine, rendered as here): seed 10, torso T1, gland on the wall:
# breast / muscle / gland 0.886 / 0.855 / 0.01 before, 0.973 / 0.976 / 0.935 after; seed 4,
# slab T1 fat suppressed: 0.796 / 0.832 / no gland before, 0.934 / 0.930 / 0.981 after.
@pytest.mark.parametrize("seed, breast, muscle", [(10, 0.95, 0.90), (4, 0.92, 0.90)])
def test_a_gland_on_the_chest_wall_is_breast_not_muscle(seed, breast, muscle, tmp_path):
    _, img, truth = render_supine(seed, tmp_path)
    res = segment_volume(img, gland=True, name=f"seed{seed}/supine.nii.gz")
    d = dice(res.labels, truth)
    assert d["breast"] >= breast and d["muscle"] >= muscle, d
    assert d["gland"] >= 0.80, d  # issue 14's gland target
    assert any("taken off the muscle as gland" in n for n in res.notes), res.notes


def test_glands_off_muscle_keeps_the_wall_and_its_thick_stretches():
    # a 8 mm wall along y = 40..48 (1 mm voxels), a gland (half ball, radius 12 mm) on its
    # front, breast tissue in front, thorax interior behind; and a stretch of the wall
    # twice as thick at the far end, against the thorax: the wall, not a gland
    sp = np.ones(3)
    z, y, x = np.mgrid[:40, :70, :90]
    wall = (y >= 40) & (y < 48)
    thick = (x >= 75) & (y >= 40) & (y < 56)
    gland = ((x - 35) ** 2 + (y - 40) ** 2 + (z - 20) ** 2 <= 12 ** 2) & (y < 40)
    body = y >= 10
    thorax = body & (y >= 48) & ~thick
    muscle = wall | thick | gland
    kept, blobs = glands_off_muscle(muscle, body, thorax, sp, min_mm3=500.0)
    assert np.count_nonzero(blobs & gland) >= 0.9 * np.count_nonzero(gland)
    assert np.count_nonzero(kept & wall) >= 0.97 * np.count_nonzero(wall)
    assert kept[thick].all()
    # without a gland nothing is taken
    kept, blobs = glands_off_muscle(wall | thick, body, thorax, sp, min_mm3=500.0)
    assert not blobs.any() and kept[wall | thick].all()


# The gland's levels from the breast's interior (Otsu), not defaults: measured when written
# (supine, rendered as here), gland Dice before / after: seed 7 (torso T2) 0.700 / 0.971,
# seed 3 (torso T2 fat suppressed) 0.784 / 0.924.
@pytest.mark.parametrize("seed", [7, 3])
def test_gland_meets_its_target_on_t2_torso_subjects(seed, tmp_path):
    _, img, truth = render_supine(seed, tmp_path)
    res = segment_volume(img, gland=True, name=f"seed{seed}/supine.nii.gz")
    d = dice(res.labels, truth)
    assert d["gland"] >= 0.80, d
    assert d["breast"] >= 0.95 and d["muscle"] >= 0.90, d


def test_glands_off_a_thin_wall_alone_takes_nothing():
    # no voxel deeper than the ball: the opening is empty (a distance map of an array with
    # no zero is undefined, and once marked the whole wall as a blob's core)
    sp = np.ones(3)
    z, y, x = np.mgrid[:20, :40, :40]
    wall = (y >= 20) & (y < 23)
    body = y >= 5
    thorax = body & (y >= 23)
    kept, blobs = glands_off_muscle(wall, body, thorax, sp, min_mm3=10.0)
    assert not blobs.any() and (kept == wall).all()
