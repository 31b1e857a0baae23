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
import SimpleITK as sitk
from mri_synth import render_family_supine

from imaging.io import read_volume
from imaging.labels import BREAST, MUSCLE
from imaging.qa import dice
from imaging.segment import SegmentationError, _breast_specks_off, segment_volume
from imaging.segment_fat_bright import _darker_mode
from imaging.segment_fat_suppressed import _muscle_air_edge
from imaging.segment_regions import _interior_median, _muscle_start
from imaging.segment_wall import _half_thickness, glands_off_muscle, skin_rim_off_muscle


@pytest.mark.parametrize("seed", range(12))
def test_contrast_is_read_right_on_every_suite_spec(seed, tmp_path):
    spec, img, _ = render_family_supine(seed, tmp_path)
    res = segment_volume(img, name=f"seed{seed}/supine.nii.gz")
    want = "fat_suppressed" if spec.fat_suppressed else "fat_bright"
    assert res.contrast == want, res.notes
    assert res.notes and any(n.startswith(f"contrast detected: {want}") for n in res.notes)


# The contrast from the columns' own ratios, not from their median profile (bench/
# contrast_family.py, measured when written): T1 fat-suppressed coil small-041 (2 mm) read fat
# bright in prone and supine (profile ratios 1.012, 0.952; the columns' 0.909, 0.882), T2
# fat-suppressed torso small-054 in every position (1.079, 1.195, 0.976; now 0.948, 1.044 and
# 0.915: supine still misread, and so flagged by the subject's disagreement).
@pytest.mark.parametrize("seed, position", [(41, "prone"), (41, "supine"),
                                            (54, "supine_tilted_28")])
def test_contrast_is_read_from_the_columns_where_glands_reach_under_the_skin(seed, position,
                                                                             tmp_path):
    spec, img, _ = render_family_supine(seed, tmp_path, position=position)
    res = segment_volume(img, name=f"seed{seed}/{position}.nii.gz")
    assert spec.fat_suppressed and res.contrast == "fat_suppressed", res.notes


# Measured when written (supine, rendered as here): seed 10, torso T1, gland on the wall:
# breast / muscle / gland 0.886 / 0.855 / 0.01 before, 0.973 / 0.976 / 0.935 after; seed 4,
# slab T1 fat suppressed: 0.796 / 0.832 / no gland before, 0.934 / 0.930 / 0.981 after the
# glands came off the wall, 0.980 / 0.958 / 0.978 once the muscle's start no longer took the
# skin seen edge-on in 2 mm slices and the muscle-air edge went by the muscle's level.
# Slabs fat suppressed, T2, 1 x 1 x 2 mm: seed 6 (a gland touching wall and skin)
# 0.961 / 0.955 / 0.981 (0.87 / 0.91 before those two rules and the wall counted along the
# posterior axis), seed 9 0.955 / 0.949 / 0.971 (0.89 / 0.92 before). Seed 1, slab T1 fat
# suppressed, 1.5 mm voxels, glands 7-9 voxels thick on a 5-voxel wall: 0.961 / 0.948 /
# 0.961 once the wall's half thickness was read to the voxel (its glands stayed muscle
# before: 0.61-0.83 / 0.86-0.90 on the FEBio suite's three scans).
@pytest.mark.parametrize("seed", [10, 4, 6, 9, 1])
def test_a_gland_on_the_chest_wall_is_breast_not_muscle(seed, tmp_path):
    _, img, truth = render_family_supine(seed, tmp_path)
    res = segment_volume(img, gland=True, name=f"seed{seed}/supine.nii.gz")
    d = dice(res.labels, truth)
    assert d["breast"] >= 0.95 and d["muscle"] >= 0.90, d  # issue 14's targets
    assert d["gland"] >= 0.80, d
    assert d["gland"] >= 0.80, d  # issue 14's gland target
    assert any("taken off the muscle as gland" in n for n in res.notes), res.notes


def test_a_t2_fat_bright_slab_keeps_its_wall_and_both_breasts(tmp_path):
    # seed 5: a muscle slab 6 mm thick meeting air, T2 (muscle 0.25 of fat, glands 0.6),
    # 1.5 mm voxels. Measured when written (supine, rendered as here): breast / muscle
    # 0.551 / 0.003 before (the glands joined the wall's start, its level rose to theirs, the
    # wall went to the air, and the left breast, cut off by the marker search's opening, lost
    # every bright blob as a "marker"); 0.983 / 0.905 / gland 0.963 after
    _, img, truth = render_family_supine(5, tmp_path)
    res = segment_volume(img, gland=True, name="seed5/supine.nii.gz")
    d = dice(res.labels, truth)
    assert d["breast"] >= 0.95 and d["muscle"] >= 0.90 and d["gland"] >= 0.80, d
    assert res.contrast == "fat_bright"


def test_a_t2_fat_bright_slab_s_tilted_scan_keeps_its_wall_and_both_breasts(tmp_path):
    # seed 5 tilted 49 deg (rendered as here; the suite's FEBio-deformed scan gave the same):
    # the wall's start took as many gland as muscle voxels, their plain median (0.41 of fat
    # against the muscle's 0.18) set the next dark threshold inside the wall, and the glands
    # became the muscle: breast / muscle 0.542 / 0.014 before the start's darker mode set the
    # muscle's level, 0.966 / 0.914 after (the FEBio scan 0.649 / 0.024 -> 0.967 / 0.914)
    _, img, truth = render_family_supine(5, tmp_path, position="supine_tilted_49")
    res = segment_volume(img, gland=True, name="seed5/supine_tilted_49.nii.gz")
    d = dice(res.labels, truth)
    assert d["breast"] >= 0.95 and d["muscle"] >= 0.90, d  # issue 14's targets


# Beyond the suite's seeds (bench/segment_suite.py --family 0-59 --contrast fat_bright, rendered
# as here): seed 18, a T2 slab at SNR 11 whose wall reads 0.15 of the fat once normalised (the
# background's Rician floor taken off): breast / muscle 0.643 / 0.001 from the nominal levels,
# 0.982 / 0.932 from where the magnitude image shows them; seed 19 prone, a T1 torso whose
# levels had not settled after two passes: gland 0.722 (0.875 before either change), 0.934
# after three (its breast, 0.949, still misses 0.95 unflagged: not asserted, an open miss).
@pytest.mark.parametrize("seed, position, tissues", [
    (18, "supine", ("breast", "muscle", "gland")), (19, "prone", ("muscle", "gland"))])
def test_dark_levels_where_the_magnitude_image_shows_them(seed, position, tissues, tmp_path):
    _, img, truth = render_family_supine(seed, tmp_path, position=position)
    res = segment_volume(img, gland=True, name=f"seed{seed}/{position}.nii.gz")
    d = dice(res.labels, truth)
    bound = {"breast": 0.95, "muscle": 0.90, "gland": 0.80}  # issue 14's targets
    assert all(d[k] >= bound[k] for k in tissues), d


# The thorax interior of fat-suppressed torsos (bench/segment_suite.py --family 0-59
# --contrast fat_suppressed), measured when written (prone, rendered as here):
# - seed 53 (T2, 2 mm slices): the 3-4 voxel wall crosses the scan's posterior face at a
#   slant, and once eroded the thorax interior still met the fat outside the wall there, so
#   no dark region was deep, the thorax interior became breast and the wall under the
#   breasts gland: breast / muscle 0.543 / 0.915 (flagged); 0.986 / 0.978 when a second
#   erosion is tried where one leaves none deep;
# - seed 45 (T1, SNR 13): the thorax interior lies between fat and muscle, and noise riddles
#   it below the lower Otsu threshold, which left 19 ml of deep fragments there (364 ml
#   below the higher one); from the fragments' threshold the muscle took most of the thorax
#   interior and lost the wall to the glands: 0.623 / 0.365 before, 0.987 / 0.971 with the
#   higher threshold's whole region.
@pytest.mark.parametrize("seed", [53, 45])
def test_a_fat_suppressed_torso_finds_its_thorax_interior(seed, tmp_path):
    _, img, truth = render_family_supine(seed, tmp_path, position="prone")
    res = segment_volume(img, gland=True, name=f"seed{seed}/prone.nii.gz")
    d = dice(res.labels, truth)
    assert d["breast"] >= 0.95 and d["muscle"] >= 0.90, d  # issue 14's targets
    assert not any(n.startswith("no thorax interior found") for n in res.notes), res.notes


def test_glands_on_a_thin_slab_of_coarse_voxels_come_off_its_wall(tmp_path):
    # seed 48 prone (T1 slab, 2 mm voxels, a 4-voxel wall): the glands on the wall held the
    # wall's balls, but their tips past the wall's thickness and a voxel held 360 and 424
    # mm^3, under the 500 mm^3 a blob needs, so both stayed in the muscle: breast / muscle
    # 0.764 / 0.872 and no gland before; 0.927 / 0.918 / gland 0.834 with a blob sized by
    # its part in front of the wall (the breast, 0.927, still misses and is flagged: the
    # body's two estimates agree to 0.962)
    _, img, truth = render_family_supine(48, tmp_path, position="prone")
    res = segment_volume(img, gland=True, name="seed48/prone.nii.gz")
    d = dice(res.labels, truth)
    assert d["muscle"] >= 0.90 and d["gland"] >= 0.80, d  # issue 14's targets
    assert any("taken off the muscle as gland" in n for n in res.notes), res.notes
    assert d["breast"] >= 0.95 or not res.confidence["confident"], (d, res.confidence)


def test_darker_mode_is_the_muscle_under_the_glands_and_the_median_of_one_mode():
    rng = np.random.default_rng(0)
    muscle, glands = rng.normal(0.18, 0.05, 8000), rng.normal(0.59, 0.05, 7500)
    assert _darker_mode(np.r_[muscle, glands]) == pytest.approx(0.18, abs=0.01)
    one = rng.normal(0.3, 0.05, 10000)  # T1: muscle and glands alike
    assert _darker_mode(one) == pytest.approx(np.median(one), abs=1e-12)


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
    _, img, truth = render_family_supine(seed, tmp_path)
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


def test_skin_seen_edge_on_in_thick_slices_cannot_start_the_muscle():
    # 2 mm slices: a wall 8 mm thick (y), and joined to it a skin sheet one slice thick that
    # runs in the slice's plane (the top of a breast): 3 voxels and more across in-plane, so
    # an in-plane ball (what a 1.5 mm ball is on 2 mm slices) held it, and the skin went to
    # the muscle (on the suite's slabs, 2296 breast voxels of 52k on one scan)
    sp = np.array([2.0, 1.0, 1.0])
    z, y, x = np.mgrid[:30, :60, :60]
    wall = (y >= 40) & (y < 48)
    sheet = (z == 15) & (y >= 10) & (y < 40) & (x >= 10) & (x < 50)
    start, largest = _muscle_start(wall | sheet, np.zeros(wall.shape, bool), sp, 3.0)
    assert largest
    assert not (start & sheet & (y < 37)).any()  # beyond the ball's reach from the wall
    inner = wall & (x >= 2) & (x < 58) & (z >= 1) & (z < 29)  # the opening's border
    assert np.count_nonzero(start & inner) >= 0.95 * np.count_nonzero(inner)


def test_the_muscle_air_edge_goes_by_the_muscle_level():
    # fat suppressed, muscle 0.25, fat 0.1, air 0: a voxel half muscle and half air (0.125)
    # is as dark as fat; it is muscle above the muscle-air midpoint, air below it
    a = np.zeros((5, 12, 5), np.float32)
    a[:, 6:] = 0.25
    a[:, 5] = [[0.2], [0.14], [0.11], [0.05], [0.2]]  # the edge, voxel by voxel (z)
    muscle = np.zeros(a.shape, bool)
    muscle[:, 6:] = True
    air = np.zeros(a.shape, bool)
    air[:, :5] = True
    lv = {"muscle": 0.25, "air": 0.0}
    m, ai = _muscle_air_edge(a, muscle, air, np.zeros(a.shape, bool), lv)
    assert m[:, 5].tolist() == [[True] * 5, [True] * 5, [False] * 5, [False] * 5, [True] * 5]
    assert (ai[:, 5] == ~m[:, 5]).all()
    assert m[:, 6:].all() and ai[:, :5].all()


def test_a_gland_reaching_the_skin_comes_off_whole():
    # the wall (y 40..48, thorax behind), a gland on its front that reaches the skin
    # (y 16..40), the skin in front of it joined (y 14..16), all in the muscle's region as
    # on a fat-suppressed scan: the gland and its skin are breast, near the air in front
    # though they are (a distance to any air counted the gland's front as the wall's back)
    sp = np.ones(3)
    z, y, x = np.mgrid[:40, :70, :90]
    wall = (y >= 40) & (y < 48)
    gland = ((x - 45) ** 2 / 14 ** 2 + (z - 20) ** 2 / 12 ** 2 <= 1) & (y >= 16) & (y < 40)
    skin = ((x - 45) ** 2 / 16 ** 2 + (z - 20) ** 2 / 14 ** 2 <= 1) & (y >= 14) & (y < 16)
    body = (y >= 14) & (((x - 45) ** 2 / 32 ** 2 + (z - 20) ** 2 / 19 ** 2 <= 1) | (y >= 40))
    thorax = body & (y >= 48)
    kept, blobs = glands_off_muscle(wall | gland | skin, body, thorax, sp, min_mm3=500.0)
    assert np.count_nonzero(blobs & gland) >= 0.95 * np.count_nonzero(gland)
    assert np.count_nonzero(blobs & skin) >= 0.9 * np.count_nonzero(skin)
    assert np.count_nonzero(kept & wall) >= 0.97 * np.count_nonzero(wall)


# The suite's coil subject at 2 mm voxels and SNR 13 (seed 2, T2 fat suppressed), measured
# when written on its FEBio-deformed scans (bench/segment_suite.py): breast / muscle Dice
# 0.54-0.75 / 0.00-0.05 before (the thin muscle's level was read off the glands it touches;
# the noise let the air into the thorax interior); 0.93-0.94 / 0.91-0.94 after, its two
# estimates agreeing (the scan's noise flags it). The breast target (0.95) is still
# missed there: the body's surface at 2 mm voxels takes about 800 air voxels and the breast
# and muscle trade about 400 voxels each way; the bound below is what is met, not the target.
def test_the_noisy_coarse_coil_scan_finds_its_thin_muscle(tmp_path):
    spec, img, truth = render_family_supine(2, tmp_path)
    assert spec.voxel_size == (2.0, 2.0, 2.0) and spec.snr < 15
    res = segment_volume(img, gland=True, name="seed2/supine.nii.gz")
    d = dice(res.labels, truth)
    assert d["muscle"] >= 0.90 and d["breast"] >= 0.92, d
    assert min(res.confidence["agreement"].values()) >= 0.9, res.confidence
    assert any(n.startswith("noisy scan") for n in res.notes), res.notes
    # and says it is of low confidence all the same: the noise, not the two estimates
    assert not res.confidence["confident"] and res.confidence["noise"] > 0.03
    assert any("noisy scan" in w for w in res.confidence["warnings"]), res.confidence


def test_a_thin_layer_is_its_own_level_beside_a_thick_blob_it_touches():
    # a muscle 3 voxels thick (level 0.5) touching a gland blob (1.6): two voxels in, only
    # the blob is left, and it made the muscle's level 1.6 (its active contour then kept the
    # blob alone)
    a = np.full((40, 30, 40), 0.5, np.float32)
    layer = np.zeros(a.shape, bool)
    layer[:, 20:23] = True
    blob = np.zeros(a.shape, bool)
    blob[14:26, 8:20, 14:26] = True
    a[blob] = 1.6
    assert _interior_median(a, layer | blob, 0.0) == pytest.approx(0.5)
    assert _interior_median(a, blob, 0.0) == pytest.approx(1.6)  # a thick mask: as before


def test_breast_specks_take_their_surroundings_label():
    labels = np.zeros((20, 30, 30), np.uint8)
    labels[:, :10] = BREAST  # the breast
    labels[:, 14:17] = MUSCLE
    labels[5, 15, 5] = BREAST  # a speck in the muscle
    labels[10, 25, 20] = BREAST  # and two behind it
    labels[10:12, 22, 10:12] = BREAST
    moved = _breast_specks_off(labels, 500.0)
    assert moved == 6
    assert labels[5, 15, 5] == MUSCLE and labels[10, 25, 20] == 0
    assert (labels[10:12, 22, 10:12] == 0).all() and (labels[:, :10] == BREAST).all()


def test_denoise_iterations_is_auto_or_a_whole_number():
    img = sitk.Image([8, 8, 8], sitk.sitkFloat32)
    for bad in ("x", -1, 2.5, True):
        with pytest.raises(SegmentationError, match="denoise_iterations"):
            segment_volume(img, denoise_iterations=bad, name="v.nii.gz")


@pytest.mark.parametrize("n", [4, 5])
def test_a_sheets_half_thickness_is_read_to_the_voxel(n):
    # a distance map reads an odd sheet half a voxel thick too many at its ridge; the
    # 5-voxel wall of the suite's slab small-001 (1.5 mm voxels) read 4.5 mm for 3.75
    from scipy import ndimage

    sp = np.array([1.5, 1.5, 1.5])
    sheet = np.zeros((20, 20, 20), bool)
    sheet[:, 6:6 + n] = True
    dt = ndimage.distance_transform_edt(sheet, sampling=sp)
    ridge = (dt > 0) & (dt >= ndimage.maximum_filter(dt, size=3))
    assert np.median(_half_thickness(dt, ridge, sp, 1)) == pytest.approx(n * 1.5 / 2)


# Measured when written (supine, rendered as here), share of the truth's muscle volume that
# the segmentation's muscle puts in the truth's thorax interior: seed 0 (coil, T1 fat
# suppressed, thorax interior brighter than fat) 0.039 before, 0.026 after the muscle's edge
# went by the muscle-thorax midpoint on that side; seed 7 (torso, T2 fat bright, 6 mm wall)
# 0.09 before (the thorax interior was taken for air, so the muscle's dark edge sat at the
# air's midpoint), 0.014 after. On the FEBio scans of bench/segment_suite.py the same rules
# raised muscle Dice 0.957-0.966 -> 0.963-0.972 (small-000) and 0.930-0.941 -> 0.952-0.961
# (small-007).
@pytest.mark.parametrize("seed", [0, 7])
def test_the_muscles_back_lies_at_the_midpoint_with_the_thorax_interior(seed, tmp_path):
    from scipy import ndimage

    _, img, truth = render_family_supine(seed, tmp_path)
    res = segment_volume(img, gland=True, name=f"seed{seed}/supine.nii.gz")
    own, t = sitk.GetArrayFromImage(res.labels), sitk.GetArrayFromImage(truth)
    lab, _ = ndimage.label(t == 0)
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    thorax = (lab > 0) & (lab != sizes.argmax())  # background that is not the outside air
    assert thorax.any()
    assert not any("no thorax interior found" in n for n in res.notes), res.notes
    share = ((own == MUSCLE) & thorax).sum() / (t == MUSCLE).sum()
    assert share < 0.03, share


def test_skin_rim_off_muscle_takes_the_wedge_in_front_of_the_wall_only():
    # a slab wall 8 mm thick along y = 40..47 (1 mm voxels; the index grows posterior, air
    # behind), a breast mound in front of it whose skin (2 mm under the air) is labelled
    # muscle where it runs into the wall's front, 3 voxels at most: the wedge. Beyond the wall's
    # thickness and one voxel (y <= 38) it goes to the breast; the wall's bare front between
    # the mounds meets air and stays muscle, as does a stretch of the wall 4 mm thicker than
    # the rest away from any breast
    from scipy import ndimage

    sp = np.ones(3)
    z, y, x = np.mgrid[:40, :70, :100]
    wall = (y >= 40) & (y < 48)
    thicker = (x >= 90) & (y >= 36) & (y < 48)
    r2 = ((x - 40) ** 2 + (z - 20) ** 2) / 15.0 ** 2
    mound = (y < 40) & (r2 + ((40 - y) / 12.0) ** 2 <= 1.0)
    body = wall | thicker | mound
    air = ~body
    skin = mound & (ndimage.distance_transform_edt(~air) <= 2.0)
    wedge = np.zeros_like(skin)  # the skin's runs that reach the wall, 3 voxels at most
    wedge[:, 37:40] = np.logical_and.accumulate(skin[:, 37:40][:, ::-1], axis=1)[:, ::-1]
    thorax = np.zeros_like(body)
    muscle = wall | thicker | wedge
    breast = mound & ~wedge
    kept, rim = skin_rim_off_muscle(muscle, body, thorax, air, breast, sp)
    assert np.count_nonzero(rim & wedge) >= 0.9 * np.count_nonzero(wedge & (y <= 38))
    assert not (rim & (wall | thicker)).any()
    assert (kept == muscle & ~rim).all()
    # voxels of 2 mm along the posterior axis: no skin lies past the margin, nothing taken
    kept, rim = skin_rim_off_muscle(muscle, body, thorax, air, breast, np.array([1., 2., 1.]))
    assert not rim.any() and (kept == muscle).all()
    # no breast next to it: nothing is taken
    kept, rim = skin_rim_off_muscle(wall | thicker, wall | thicker, thorax, ~(wall | thicker),
                                    np.zeros_like(body), sp)
    assert not rim.any()
    # the contour climbed on from the wedge over the mound's skin (its front half: the
    # breast's fat and then the wall lie behind it along the posterior axis): that skin
    # goes to the breast too, and still nothing of the wall
    climbed = wedge | (skin & (y < 30))
    kept, rim = skin_rim_off_muscle(wall | thicker | climbed, body, thorax, air,
                                    mound & ~climbed, sp)
    assert rim[skin & (y < 30)].all()
    assert not (rim & (wall | thicker)).any()


# Measured when written, supine, FEBio-deformed scans of bench/validate.py (skin voxels of
# the breast called muscle, before / after): small-009 516 / 110, small-006 483 / 94,
# small-004 (T1) 632 / 174; of the truth's muscle 12 voxels went to the breast on small-006,
# none on the others; breast and muscle Dice up (small-009 0.967 / 0.950 -> 0.975 / 0.956).
# On the rigidly moved scans rendered here (seeds 9, 4) at most 1 % of the voxels it moves
# are the truth's muscle (seed 9: 3 of 603, on the wall's surface beside a
# breast and half air; none before the air's first look got its tissue floor, 2026-11-30,
# which made them body; its breast Dice 0.977 -> 0.976).
@pytest.mark.parametrize("seed", [9, 4])
def test_the_breasts_skin_rim_is_not_muscle_on_fat_suppressed_slabs(seed, tmp_path,
                                                                    monkeypatch):
    import imaging.segment as seg
    from breastmodel.phantom.anatomy import SKIN

    _, img, truth = render_family_supine(seed, tmp_path)
    t = sitk.GetArrayFromImage(truth)
    tissue = sitk.GetArrayFromImage(read_volume(tmp_path / "subject_truth"
                                                / "supine_tissue.nii.gz"))
    res = segment_volume(img, gland=True, name=f"seed{seed}/supine.nii.gz")
    with monkeypatch.context() as m:
        m.setattr(seg, "skin_rim_off", lambda *a, **k: None)
        before = segment_volume(img, gland=True, name=f"seed{seed}/supine.nii.gz")
    own, own0 = (sitk.GetArrayFromImage(r.labels) for r in (res, before))

    def skin_spill(labels):
        return np.count_nonzero((labels == MUSCLE) & (t != MUSCLE) & (t > 0)
                                & (tissue == SKIN))

    assert skin_spill(own) <= 0.5 * skin_spill(own0), (skin_spill(own), skin_spill(own0))
    moved = own != own0
    assert moved.any()
    assert np.count_nonzero(moved & (t == MUSCLE)) <= 0.01 * np.count_nonzero(moved), (
        np.count_nonzero(moved & (t == MUSCLE)), np.count_nonzero(moved))
    assert any("skin at the breasts' rim" in n for n in res.notes), res.notes
    d, d0 = dice(res.labels, truth), dice(before.labels, truth)
    assert d["breast"] >= d0["breast"] and d["muscle"] >= d0["muscle"], (d, d0)
