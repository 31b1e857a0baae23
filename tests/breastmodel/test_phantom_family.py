"""The phantom family: each variety option changes what it should, draws are deterministic,
specs round-trip through JSON, and FEBio computes plausible, cached truths."""

import json
from dataclasses import replace

import numpy as np
import pytest
import SimpleITK as sitk

from breastmodel.phantom import make_phantom, truth_folder
from breastmodel.phantom.anatomy import AIR, FAT, GLAND, MARKER, MUSCLE, SKIN, reference_volumes
from breastmodel.phantom.family import (
    FOV_KINDS,
    SubjectSpec,
    draw_spec,
    make_subject,
    truth_model,
)
from breastmodel.phantom.rendering import render
from breastmodel.phantom.voxelize import Grid, voxelize

TISSUE = (FAT, MUSCLE, GLAND, SKIN)


def _fine(spec: SubjectSpec, spacing=2.0):
    an = spec.anatomy()
    grid = Grid.from_box(an.fov_min, an.fov_max, spacing)
    return an, grid, voxelize(an, grid)


# --- draws and serialisation --------------------------------------------------------------


def test_draws_are_deterministic_per_seed_and_differ_across_seeds():
    assert draw_spec(3) == draw_spec(3)
    assert draw_spec(3, size="full") == draw_spec(3, size="full")
    specs = [draw_spec(s) for s in range(12)]
    assert len({sp.to_json() for sp in specs}) == 12
    # the draws cover the options: every field of view, both contrasts, fat suppression on
    # and off, several cups and voxel spacings
    assert {sp.fov for sp in specs} == set(FOV_KINDS)
    assert {sp.contrast for sp in specs} == {"t1", "t2"}
    assert {sp.fat_suppressed for sp in specs} == {True, False}
    assert len({sp.cup for sp in specs}) >= 3
    assert len({sp.voxel_size for sp in specs}) >= 3
    for sp in specs:
        assert 10 <= sp.snr <= 40 and 0.1 <= sp.bias <= 0.4
        tilt = float(sp.positions[-1].rsplit("_", 1)[1])
        assert 0 <= tilt <= 60


def test_overrides_change_only_what_they_name():
    a = draw_spec(5)
    b = draw_spec(5, cup="D", fov="slab")
    assert (b.cup, b.fov) == ("D", "slab")
    assert replace(b, cup=a.cup, fov=a.fov) == a
    with pytest.raises(ValueError, match="unknown field"):
        draw_spec(5, colour="red")
    with pytest.raises(ValueError, match="fov must be one of"):
        draw_spec(5, fov="helmet")


def test_the_soft_band_draws_the_same_subjects_with_the_soft_moduli():
    """``band="soft"`` maps the seed's draw into the soft band (half for half-size
    subjects): every other field is the same subject's, the modulus lies in the band and keeps
    its place in it, and a truth that soft starts FEBio from more load steps."""
    from breastmodel.phantom.family import MODULUS_BANDS
    from breastmodel.phantom.truth_solvers import FEBIO_STEPS

    for seed, size, scale in ((0, "small", 0.5), (3, "small", 0.5), (1, "full", 1.0)):
        std, soft = draw_spec(seed, size=size), draw_spec(seed, size=size, band="soft")
        assert replace(soft, breast_E_kpa=std.breast_E_kpa) == std
        (lo, hi), (slo, shi) = MODULUS_BANDS["standard"], MODULUS_BANDS["soft"]
        assert scale * slo <= soft.breast_E_kpa <= scale * shi
        at = (std.breast_E_kpa / scale - lo) / (hi - lo)
        assert soft.breast_E_kpa == pytest.approx(scale * (slo + at * (shi - slo)), abs=0.011)
        assert std.truth_model().load_steps is None  # FEBio's FEBIO_STEPS, as before
        assert soft.truth_model().load_steps == 2 * FEBIO_STEPS
        assert soft.truth_model().to_dict()["load_steps"] == 2 * FEBIO_STEPS
        assert type(soft.truth_model()).from_dict(soft.truth_model().to_dict()) \
            == soft.truth_model()
    with pytest.raises(ValueError, match="band must be one of"):
        draw_spec(0, band="jelly")


def test_spec_round_trips_through_json():
    for seed, size in ((0, "small"), (1, "full"), (2, "small")):
        sp = draw_spec(seed, size=size)
        text = sp.to_json()
        assert SubjectSpec.from_json(text) == sp
        assert json.loads(text)["voxel_size"] == list(sp.voxel_size)
        # equal specs make equal anatomies and truth physics
        back = SubjectSpec.from_json(text)
        assert back.anatomy() == sp.anatomy() and back.truth_model() == sp.truth_model()
    with pytest.raises(ValueError, match="unknown subject spec key"):
        SubjectSpec.from_dict({**draw_spec(0).to_dict(), "extra": 1})


# --- variety options ----------------------------------------------------------------------


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.5, 0.5, 0.6), (0.7, 0.7, 1.5)])
def test_written_volume_has_the_spacing(tmp_path, spacing):
    spec = draw_spec(0, voxel_size=spacing)
    an = spec.anatomy()
    # a thin crop keeps the finest grid quick
    an = an.with_fov(an.fov_min, (an.fov_max[0], an.fov_max[1], an.fov_min[2] + 6.0))
    out = make_phantom(tmp_path / "s", seed=0, anatomy=an, voxel_size=spacing,
                       positions=("supine",), max_rotation_deg=0, max_translation_mm=0,
                       progress=False)
    img = sitk.ReadImage(str(out / "supine.nii.gz"))
    assert img.GetSpacing() == pytest.approx(spacing, abs=1e-6)
    expected = np.round((np.subtract(an.fov_max, an.fov_min)) / np.asarray(spacing))
    assert img.GetSize() == tuple(int(v) for v in expected)
    assert sitk.ReadImage(str(truth_folder(out) / "supine_labels.nii.gz")).GetSpacing() == \
        pytest.approx(spacing, abs=1e-6)


def test_scalar_spacing_still_works():
    g = Grid.from_box((0, 0, 0), (10, 20, 30), 2.0)
    assert g.spacing == 2.0 and g.size == (5, 10, 15)
    assert g.spacing_xyz.tolist() == [2.0, 2.0, 2.0] and g.voxel_volume == 8.0
    g3 = Grid.from_box((0, 0, 0), (10, 20, 30), (1.0, 2.0, 3.0))
    assert g3.size == (10, 10, 10) and g3.voxel_volume == 6.0
    np.testing.assert_allclose(g3.points(np.array([1])), [[1.5, 1.0, 1.5]])
    with pytest.raises(ValueError, match="voxel spacing"):
        Grid((0, 0, 0), (1.0, 0.0, 1.0), (1, 1, 1))


def test_slab_chest_wall_meets_air():
    spec = draw_spec(2, fov="slab")
    an, grid, tv = _fine(spec, 1.5)
    f = tv.fine
    y = grid.origin[1] + grid.spacing * np.arange(grid.size[1])
    behind = y > 0.75  # posterior of the slab's posterior face (y = 0), past partial volume
    assert np.all(f[:, behind, :] == AIR)
    assert not np.any(f == 6)  # no thorax
    # muscle at the slab's posterior face, and air beside the slab at its sides
    assert np.any(f[:, (y > -1.5) & (y < 0), :] == MUSCLE)
    x = grid.origin[0] + grid.spacing * np.arange(grid.size[0])
    side = np.abs(x) > an.slab_half_width + 1.0
    assert side.any() and np.all(f[:, :, side][f[:, :, side] != MARKER] == AIR)
    # no skin outside the breasts: every skin voxel is within a breast's box
    skin_x = x[np.nonzero(f == SKIN)[2]]
    assert np.all(np.abs(skin_x) <= an.left.center_x + max(an.left.radius_x,
                                                           an.right.radius_x) + 1.5)
    # the body touches no image boundary
    for ax in range(3):
        for i in (0, -1):
            face = np.take(f, i, axis=ax)
            assert not np.isin(face, TISSUE).any()


def test_coil_fov_cuts_the_body_at_the_sides_and_behind():
    coil = _fine(draw_spec(4, fov="coil"))[2].fine
    torso = _fine(draw_spec(4, fov="torso"))[2].fine
    for f, touches in ((coil, True), (torso, False)):
        sides = np.isin(f[:, :, 0], TISSUE).any() and np.isin(f[:, :, -1], TISSUE).any()
        assert sides == touches
        assert np.isin(f[:, -1, :], TISSUE).any()  # cut behind in both
    a_coil, a_torso = draw_spec(4, fov="coil").anatomy(), draw_spec(4, fov="torso").anatomy()
    assert a_coil.fov_max[1] < a_torso.fov_max[1] - 10.0  # cut closer behind the breasts
    assert a_coil.fov_max[0] < a_coil.torso_half_width < a_torso.fov_max[0]


def test_the_body_goes_on_past_every_cut_of_the_scan():
    """The truth's mesh spans the body beyond the field of view where a scan cuts it (behind,
    above and below; a coil's box at the sides too), so FEBio's truth has no free face where
    the model has one; a slab, which the field of view holds whole, stays as it is."""
    from breastmodel.phantom.simulated import stress_free_labels
    from breastmodel.phantom.subject_spec import BODY_BEYOND_MM

    beyond = BODY_BEYOND_MM * 0.5  # small subjects
    for fov in ("coil", "torso"):
        an = draw_spec(4, fov=fov).anatomy()
        (lo, hi), fov_lo, fov_hi = an.body_box, np.array(an.fov_min), np.array(an.fov_max)
        assert hi[1] >= fov_hi[1] + beyond - 1e-9  # behind (the coil's cut lies further in)
        assert hi[2] == pytest.approx(fov_hi[2] + beyond) and lo[2] == pytest.approx(
            fov_lo[2] - beyond)
        assert lo[1] == pytest.approx(fov_lo[1])  # air in front: nothing to go on
        assert hi[0] > an.torso_half_width  # the torso's whole width
    coil = draw_spec(4, fov="coil").anatomy()
    assert coil.body_box[1][0] > coil.fov_max[0] + 10.0  # the coil cuts the sides
    slab = draw_spec(4, fov="slab").anatomy()
    assert slab.body_box == (slab.fov_min, slab.fov_max)
    # the truth's label map (what its mesh is made from) covers the body box
    labels = stress_free_labels(coil, voxel_size=2.0)
    extent = np.array(labels.GetSize()) * 2.0
    assert np.allclose(extent, np.subtract(*coil.body_box[::-1]), atol=2.0)


def test_cup_fat_gland_ptosis_and_asymmetry_change_the_anatomy():
    def vols(**kw):
        an = draw_spec(6, fov="torso", **{"ptosis": 0.0, **kw}).anatomy()
        return an, reference_volumes(an, step=1.5)

    vol = {c: vols(cup=c, asymmetry=0.0)[1] for c in "ABCD"}
    breast = [vol[c]["fat"] + vol[c]["gland"] for c in "ABCD"]
    assert np.all(np.diff(breast) > 0)
    thin, thick = vols(subcutaneous_fat_mm=2.0)[1], vols(subcutaneous_fat_mm=7.0)[1]
    assert thick["fat"] > thin["fat"] and thick["muscle"] < thin["muscle"]
    lo, hi = vols(gland_scale=0.35)[1], vols(gland_scale=0.7)[1]
    assert hi["gland"] / (hi["gland"] + hi["fat"]) > 2 * lo["gland"] / (lo["gland"] + lo["fat"])
    flat, droop = vols(ptosis=0.0)[0], vols(ptosis=0.4)[0]
    for side in ("left", "right"):
        drop = flat.landmarks()[f"nipple_{side}"][2] - droop.landmarks()[f"nipple_{side}"][2]
        assert drop == pytest.approx(0.4 * getattr(droop, side).projection)
        # the drooping breast really hangs: its lowest tissue near the tip is lower
        tip = droop.landmarks()[f"nipple_{side}"]
        pts = np.array([[tip[0], tip[1] + 3.0, z] for z in np.arange(-60.0, 60.0, 0.25)])
        zs_d = pts[np.isin(droop.classify(pts), TISSUE), 2]
        zs_f = pts[np.isin(flat.classify(pts), TISSUE), 2]
        assert zs_d.min() < zs_f.min() - 5.0
    sym, asym = vols(asymmetry=0.0)[0], vols(asymmetry=0.2)[0]
    assert sym.left.projection == sym.right.projection
    assert asym.left.projection / asym.right.projection == pytest.approx(1.1 / 0.9)


def test_ptosis_reference_volume_matches_voxels():
    """Sheared (ptotic) breasts keep exact chords: reference volumes agree with a fine
    voxelisation."""
    an = draw_spec(3, fov="slab", ptosis=0.4, exponent=2.4).anatomy()
    ref = reference_volumes(an, step=0.5)
    grid = Grid.from_box(an.fov_min, an.fov_max, 1.0)
    tv = voxelize(an, grid, supersample=3)
    counts = np.bincount(tv.fine.ravel(), minlength=7) * grid.voxel_volume
    for code, name in ((FAT, "fat"), (GLAND, "gland")):
        assert counts[code] == pytest.approx(ref[name], rel=0.03), name
    # The slab is a box (its 1 mm voxels would be off by up to half a voxel per face); the
    # reference's lines are exact along y and miss at most half a line step at each x/z edge.
    w, h = an.slab_half_width, an.slab_half_height
    slab = 4 * w * h * an.muscle
    assert abs(ref["muscle"] - slab) <= slab * 0.25 * (1 / w + 1 / h)


def _tissue_mean(img, fine, code):
    return float(img[fine == code].mean())


def test_fat_suppression_darkens_fat_and_t1_inverts_gland_contrast():
    spec = draw_spec(1, fov="torso")
    _, _, tv = _fine(spec, 2.0)

    def img(**kw):
        return render(tv, np.random.default_rng(0), snr=1e6, bias=0.0, blur_sigma_voxels=0,
                      **kw).image

    t2, t2fs = img(contrast="t2"), img(contrast="t2", fat_suppressed=True)
    t1 = img(contrast="t1")
    f = tv.fine
    assert _tissue_mean(t2fs, f, FAT) < 0.2 * _tissue_mean(t2, f, FAT)
    assert _tissue_mean(t2fs, f, FAT) < _tissue_mean(t2fs, f, GLAND)
    assert _tissue_mean(t2, f, GLAND) > _tissue_mean(t2, f, MUSCLE)
    assert _tissue_mean(t1, f, GLAND) < _tissue_mean(t1, f, MUSCLE)
    # SNR refers to gland when fat is suppressed
    r = render(tv, np.random.default_rng(0), snr=20.0, bias=0.0, fat_suppressed=True)
    assert r.noise_sigma == pytest.approx(r.mean_reference / 20.0)
    assert r.mean_reference > r.mean_fat


def test_truth_physics_presets():
    bulk = truth_model(draw_spec(0, breast_E_kpa=2.0))
    assert bulk.materials[1]["E"] == 2.0 and bulk.materials[2]["E"] == 10.0
    assert dict(bulk.effects) == {"fixed": {"node_set": "fixed"}} and not bulk.split_interface
    assert bulk.mesh_size_mm == 5.0
    asym = truth_model(draw_spec(0, breast_E_kpa=2.0, physics="asymmetric"))
    assert asym.materials[1]["E"] == pytest.approx(1.4) and asym.materials[3]["E"] == 2.8
    gland = truth_model(draw_spec(0, physics="gland+skin"))
    assert gland.has_gland and "skin" in gland.effects
    strong = truth_model(draw_spec(0, breast_E_kpa=2.0, physics="gland_10x"))
    assert strong.materials[4]["E"] == pytest.approx(20.0) and strong.materials[3]["E"] == 2.0
    for physics, jm in (("gent_breast", 1.0), ("gent_breast_weak", 3.0)):
        gent = truth_model(draw_spec(0, breast_E_kpa=2.0, physics=physics))
        assert all(gent.materials[c]["name"] == "gent" and gent.materials[c]["Jm"] == jm
                   and gent.materials[c]["E"] == 2.0 for c in (1, 3))
    for physics, f, face_set, codes in (("skin_layer", 10.0, "skin", (6, 7)),
                                        ("skin_layer_weak", 3.0, "skin", (6, 7)),
                                        ("sliding_layer", 0.5, "interface", (8, 9)),
                                        ("sliding_layer_weak", 0.8, "interface", (8, 9))):
        layer = truth_model(draw_spec(0, breast_E_kpa=2.0, physics=physics))
        assert layer.layers == (face_set,) and bulk.layers == () and not layer.has_gland
        assert [layer.materials[c]["E"] for c in (1, 3, *codes)] == [2.0, 2.0, 2 * f, 2 * f]
        assert layer.materials[codes[0]]["name"] == "neo_hookean"
        assert dict(layer.effects) == dict(bulk.effects) and not layer.split_interface
    with pytest.raises(ValueError, match="unknown physics"):
        draw_spec(0, physics="magic")


def test_a_layer_is_the_breast_tets_that_own_a_face_of_its_set():
    """The skin layer (the skin as a solid) is exactly the breast tets owning a skin face, the
    interface layer (the tissue the breast slides on) those with a node on the interface,
    sides kept; a second layer leaves the first one's tets as they are."""
    from breastmodel.phantom.mounds import mound_mesh
    from mechanics.mesh import REGIONS, with_layer

    mesh = mound_mesh(cells=(8, 6, 3, 2))
    owned = {}
    for face_set in ("skin", "interface"):
        layer = with_layer(mesh, face_set)
        faces = {tuple(sorted(f)) for f in mesh.face_sets[face_set].tolist()}
        owns = np.array([any(tuple(sorted(np.delete(t, k))) in faces for k in range(4))
                         for t in mesh.tets.tolist()])
        if face_set == "skin":
            assert set(mesh.region[owns].tolist()) <= {1, 3}  # skin faces: breast tets'
        else:  # a soft layer: every tet with a node on the interface
            touch = np.isin(mesh.tets, mesh.face_sets[face_set]).any(axis=1)
            assert (touch & ~owns).any()
            owns |= touch
        owns &= np.isin(mesh.region, (1, 3))
        changed = layer.region != mesh.region
        assert owns.any() and np.array_equal(changed, owns)  # exactly the tets on the set
        name = "skin_layer" if face_set == "skin" else "interface_layer"
        for side, code in (("left", 1), ("right", 3)):  # each keeps its side
            assert np.all(layer.region[owns & (mesh.region == code)]
                          == REGIONS[f"{name}_{side}"])
        assert np.array_equal(layer.face_sets[face_set], mesh.face_sets[face_set])
        owned[face_set] = owns
    both = with_layer(with_layer(mesh, "skin"), "interface")
    assert np.isin(both.region[owned["skin"]], (6, 7)).all()
    assert np.isin(both.region[owned["interface"] & ~owned["skin"]], (8, 9)).all()
    with pytest.raises(ValueError, match="no layer codes for face set 'fixed'"):
        with_layer(mesh, "fixed")


# --- FEBio truth --------------------------------------------------------------------------


def _febio_or_skip():
    try:
        from breastmodel.febio import find_febio

        return find_febio()
    except Exception as exc:  # noqa: BLE001 - any failure to find it means: skip
        pytest.skip(f"FEBio 4 is not available ({exc}); set $FEBIO to run the FEBio truth test")


@pytest.mark.slow
def test_febio_truth_is_plausible_and_cached(tmp_path):
    """A small subject whose truth FEBio computes: fixed nodes stay, breasts sag along
    gravity (opposite in prone and supine), and a second make hits the cache."""
    febio = _febio_or_skip()
    spec = draw_spec(11, fov="slab", cup="C", voxel_size=(2.0, 2.0, 2.0),
                     positions=("prone", "supine"), breast_E_kpa=1.0)
    cache = tmp_path / "cache"
    out = make_subject(spec, tmp_path / "a", febio=febio, cache_dir=cache)
    truth = truth_folder(out)
    assert SubjectSpec.from_json((truth / "spec.json").read_text()) == spec
    doc = json.loads((truth / "truth_model.json").read_text())
    from mechanics.mesh import Mesh

    mesh = Mesh.load_npz(truth / "stress_free_mesh.npz")
    breast = np.unique(mesh.tets[np.isin(mesh.region, (1, 3))])
    fixed = mesh.node_sets["fixed"]
    assert len(fixed) > 0 and len(breast) > 0
    u = {p: np.load(truth / f"{p}_displacement.npy") for p in spec.positions}
    for p, g in (("prone", -1.0), ("supine", 1.0)):
        info = doc["solves"][p]
        assert info["solver"] == "febio" and info["converged"] and not info["cached"]
        assert u[p].shape == (mesh.n_nodes, 3)
        assert np.abs(u[p][fixed]).max() < 1e-9
        # breasts move along gravity (y): mean displacement of breast nodes has gravity's sign
        # and dominates the other components
        m = u[p][breast].mean(0)
        assert np.sign(m[1]) == g and abs(m[1]) > 2 * max(abs(m[0]), abs(m[2]))
        assert 0.2 < np.linalg.norm(u[p], axis=1).max() < 30.0
    # prone and supine sag in opposite directions, node by node in the breasts
    anterior = breast[np.abs(u["prone"][breast, 1]) > 0.5 * np.abs(u["prone"][:, 1]).max()]
    assert np.all(u["prone"][anterior, 1] * u["supine"][anterior, 1] < 0)
    # second make: the mesh and FEBio's results come from the cache, the truth is identical
    out2 = make_subject(spec, tmp_path / "b", febio=febio, cache_dir=cache)
    doc2 = json.loads((truth_folder(out2) / "truth_model.json").read_text())
    for p in spec.positions:
        assert doc2["solves"][p]["cached"]
        np.testing.assert_array_equal(np.load(truth_folder(out2) / f"{p}_displacement.npy"),
                                      u[p])
    assert (out / "prone.nii.gz").read_bytes() == (out2 / "prone.nii.gz").read_bytes()


def test_febio_truth_without_febio_says_so(tmp_path, monkeypatch):
    monkeypatch.setenv("FEBIO", str(tmp_path / "nowhere" / "febio4"))
    spec = draw_spec(0, positions=("supine",))
    with pytest.raises(RuntimeError, match="needs FEBio 4.*--febio"):
        make_subject(spec, tmp_path / "s", febio=tmp_path / "nowhere" / "febio4")


def test_cli_truth_solver_febio_without_febio_says_so(tmp_path, monkeypatch):
    import argparse

    from breastmodel.commands import phantom

    monkeypatch.setenv("FEBIO", str(tmp_path / "none"))
    parser = argparse.ArgumentParser(prog="breastmodel")
    phantom.add_parser(parser.add_subparsers(dest="command"))
    missing = str(tmp_path / "no" / "febio4")
    for extra in (["--small", "--voxel-size", "3", "--positions", "supine"],
                  ["--family", "small"]):
        args = parser.parse_args(["phantom", str(tmp_path / "s"), "--truth-solver", "febio",
                                  "--febio", missing, *extra])
        with pytest.raises(RuntimeError, match="needs FEBio 4.*--febio PATH"):
            phantom.run(args)
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(draw_spec(4, size="full").to_json())
    args = parser.parse_args(["phantom", str(tmp_path / "s"), "--spec", str(spec_file),
                              "--febio", missing])
    with pytest.raises(RuntimeError, match="needs FEBio 4"):
        phantom.run(args)
