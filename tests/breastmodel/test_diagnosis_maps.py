"""Where the model fails: skin regions, error maps, strain, tables, pictures, compare.

A fake run folder (the files ``breastmodel run`` writes, with synthetic predictions on the
breast-like mesh) stands in for a pipeline run, so that every number has a closed form.
"""

from __future__ import annotations

import base64
import copy
import json
import re
from pathlib import Path

import numpy as np
import pytest
import tomli_w
from breastlike import breastlike_mesh

from breastmodel.cli import main
from breastmodel.diagnosis import load_run
from breastmodel.diagnosis.compare import compare_runs, model_changes, write_compare
from breastmodel.diagnosis.maps import (
    QUADRANTS,
    failure_map,
    failure_tables,
    node_strain,
    skin_regions,
)
from breastmodel.diagnosis.views import error_maps_figure, error_vs_strain_figure, png_bytes
from breastmodel.errors import StageError


def write_run(out: Path, mesh, X, xs, *, model=None, subject="fake", key="k") -> Path:
    """A run folder as ``breastmodel run`` leaves it: stages.json, config.toml, params.json,
    metrics.json and the cached problem / stress_free / predict stages. The measured skin of
    every position is the skin of X."""
    from breastmodel.pipeline.config import DEFAULTS
    from breastmodel.pipeline.problem import load_problem, score_position

    model = copy.deepcopy(model or DEFAULTS["model"])
    faces = np.asarray(mesh.face_sets["skin"])
    nodes = np.unique(faces)
    remap = np.full(mesh.n_nodes, -1)
    remap[nodes] = np.arange(len(nodes))
    prob = out / "cache" / "problem" / "p0"
    prob.mkdir(parents=True)
    mesh.save_npz(prob / "mesh.npz")
    for pos in xs:
        np.savez(prob / f"{pos}_skin.npz", vertices=X[nodes], triangles=remap[faces])
    (prob / "problem.json").write_text(json.dumps({
        "reference": next(iter(xs)), "gravity": {p: [0, 1, 0] for p in xs}, "landmarks": {}}))
    sf = out / "cache" / "stress_free" / key
    sf.mkdir(parents=True)
    np.save(sf / "X.npy", X)
    stages = [{"name": "problem", "label": "problem", "key": "p0", "status": "ran"},
              {"name": "stress_free", "label": "stress-free", "key": key, "status": "ran"}]
    problem = load_problem(prob)
    metrics = {"subject": subject, "reference": next(iter(xs)), "units": "mm",
               "positions": {}}
    for pos, x in xs.items():
        d = out / "cache" / "predict" / f"{key}{pos}"
        d.mkdir(parents=True)
        m = score_position(problem, x, pos, details=True)
        np.savez(d / "predicted.npz", x=x, signed_error=m.pop("signed_error"),
                 skin_nodes=m.pop("skin_nodes"))
        metrics["positions"][pos] = m
        stages.append({"name": "predict", "label": f"predict {pos}", "key": f"{key}{pos}",
                       "status": "ran"})
    # a mesh-refinement check's stages come last under the same names (their folders are
    # not made here: the loader must not take them for the run's own)
    stages += [{"name": "problem", "label": "refinement: problem 6 mm", "key": "fine",
                "status": "ran"},
               {"name": "stress_free", "label": "refinement: stress-free", "key": "fine",
                "status": "ran"}]
    (out / "stages.json").write_text(json.dumps({"stages": stages}))
    (out / "metrics.json").write_text(json.dumps(metrics))
    (out / "params.json").write_text(json.dumps({"parameters": {}, "model": model,
                                                 "fitted": False}))
    (out / "config.toml").write_text(tomli_w.dumps({"model": model}))
    return out


@pytest.fixture(scope="module")
def mesh():
    return breastlike_mesh()


def test_regions_partition_the_skin(mesh):
    X = np.asarray(mesh.nodes)
    R = skin_regions(mesh, X)
    nodes = np.unique(mesh.face_sets["skin"])
    P = X[nodes]
    assert R["left"].shape == (len(nodes),)
    assert not np.any(R["left"] & R["right"])
    assert np.all(R["left"] | R["right"])
    # the mesh's left breast is at x > 0 (patient's left in LPS); the midline goes to one
    assert np.array_equal(R["left"][P[:, 0] != 0], P[P[:, 0] != 0, 0] > 0)
    for side, outer_sign in (("left", 1), ("right", -1)):
        quads = np.stack([R[f"{side}.{q}"] for q in QUADRANTS])
        assert np.array_equal(quads.sum(axis=0), R[side].astype(int))  # a partition
        ids = np.flatnonzero(R[side])
        nip = P[ids[np.argmin(P[ids, 1])]]
        # the nipple of the Gaussian mound is its apex, at x = +-50, z = 0
        assert nip[0] == pytest.approx(50.0 * outer_sign) and nip[2] == pytest.approx(0.0)
        uo = R[f"{side}.upper_outer"]
        assert np.all(P[uo, 2] >= 0) and np.all(outer_sign * (P[uo, 0] - nip[0]) >= 0)
        li = R[f"{side}.lower_inner"]
        assert np.all(P[li, 2] < 0) and np.all(outer_sign * (P[li, 0] - nip[0]) < 0)
        na = R[f"{side}.nipple_area"]
        assert np.array_equal(na, R[side] & (np.linalg.norm(P - nip, axis=1) <= 20.0))
        fold = R[f"{side}.inframammary_fold"]
        # thickness 6 + 40 exp(-r^2 / 2 28^2) falls below a third of the apex's 46 mm only
        # past r = 48 mm from the apex: on this 15 mm grid, the rows z = -45 (at the sides of
        # the inferior sector) and z = -60 below the nipple, which is all the fold band holds
        assert np.all(np.isin(P[fold, 2], (-45.0, -60.0)))
        assert not np.any(fold & ~(R[f"{side}.lower_outer"] | R[f"{side}.lower_inner"]))
        assert np.all(np.abs(P[fold, 0] - nip[0]) <= nip[2] - P[fold, 2])
        below = R[side] & (P[:, 2] == -60.0) & (np.abs(P[:, 0] - nip[0]) <= 30.0)
        assert below.sum() >= 5 and np.all(fold[below])
        assert not np.any(fold & (P[:, 2] > -45.0))


def test_node_strain_of_a_homogeneous_deformation(mesh):
    X = np.asarray(mesh.nodes)
    F = np.array([[1.1, 0.05, 0.0], [0.0, 0.95, 0.0], [0.02, 0.0, 1.03]])
    Q, _ = np.linalg.qr(np.array([[1.0, 2, 0], [0, 1, 3], [1, 0, 1]]))  # a rotation
    Q *= np.sign(np.linalg.det(Q))
    x = X @ (Q @ F).T + [3.0, -2.0, 1.0]
    E = 0.5 * (F.T @ F - np.eye(3))  # rotation-free: E of QF = E of F
    e = node_strain(mesh.tets, X, x)
    assert np.max(np.abs(e - np.linalg.eigvalsh(E)[-1])) < 1e-12
    assert np.max(np.abs(node_strain(mesh.tets, X, X @ Q.T))) < 1e-12  # rigid: zero


def test_normal_offset_is_a_normal_error(tmp_path):
    """A flat-fronted slab moved d mm anteriorly: on the front face (outward normal -y) the
    error is purely normal, d mm, and the strain is zero (a rigid motion)."""
    flat = breastlike_mesh(mound=0.0, base=20.0)
    X = np.asarray(flat.nodes)
    d = 2.5
    run = load_run(write_run(tmp_path / "run", flat, X, {"supine": X + [0.0, -d, 0.0]}))
    fm = failure_map(run, "supine")
    P = fm["X"]
    front = np.isclose(P[:, 1], -20.0) & (np.abs(P[:, 0]) < 100 - d) & (
        np.abs(P[:, 2]) < 60 - d)
    assert front.sum() > 20
    assert np.allclose(fm["signed_error"][front], d, atol=1e-9)
    assert np.allclose(fm["normal"][front], d, atol=1e-9)
    assert np.max(fm["tangential"][front]) < 1e-9
    assert np.allclose(fm["error_vector"][front], [0.0, -d, 0.0], atol=1e-9)
    assert np.max(np.abs(fm["strain"])) < 1e-12
    assert np.max(np.abs(fm["skin_area_change"])) < 1e-12
    # the table over those nodes, through a region of its own
    tab = failure_tables(run, regions={"front": front})
    row = tab["positions"]["supine"]["regions"]["front"]
    assert row["n"] == front.sum()
    for k in ("mean_signed_mm", "mean_abs_mm", "rmse_mm", "p95_mm", "max_mm",
              "normal_rms_mm"):
        assert row[k] == pytest.approx(d, abs=1e-9), k
    assert row["tangential_rms_mm"] < 1e-9
    es = tab["positions"]["supine"]["error_vs_strain"]
    assert es["spearman_abs"] is None  # strain is constant: no correlation to speak of
    assert tab["regions"]["all"] == len(P)
    json.dumps(tab)  # JSON-ready


def test_tables_of_a_stretch(tmp_path, mesh):
    X = np.asarray(mesh.nodes)
    x = X @ np.diag([1.1, 1.0, 1.0]).T  # E_xx = (1.21 - 1) / 2 = 0.105 everywhere
    sag = X.copy()
    sag[:, 2] -= 0.2 * np.maximum(-X[:, 1], 0.0)  # anterior tissue drops: a shear
    run = load_run(write_run(tmp_path / "run", mesh, X, {"supine": x, "prone": sag}))
    tab = failure_tables(run)
    assert list(tab["positions"]) == ["supine", "prone"]
    st = tab["positions"]["supine"]["regions"]
    assert st["all"]["mean_strain"] == pytest.approx(0.105, abs=1e-12)
    assert st["left.nipple_area"]["mean_strain"] == pytest.approx(0.105, abs=1e-12)
    fm = failure_map(run, "supine")
    a = np.abs(fm["signed_error"])
    assert st["all"]["rmse_mm"] == pytest.approx(np.sqrt(np.mean(a**2)))
    assert st["all"]["p95_mm"] == pytest.approx(np.percentile(a, 95))
    # |e|^2 = normal^2 + tangential^2 node by node
    assert np.allclose(np.linalg.norm(fm["error_vector"], axis=1) ** 2,
                       fm["normal"] ** 2 + fm["tangential"] ** 2)
    assert np.allclose(np.linalg.norm(fm["error_vector"], axis=1), a)
    # the skin's stretch in x: area change 0.1 on faces whose normal is perpendicular to x
    assert np.max(fm["skin_area_change"]) <= 0.1 + 1e-12
    es = tab["positions"]["prone"]["error_vs_strain"]
    assert es["spearman_abs"] is not None and -1 <= es["spearman_abs"] <= 1
    assert sum(b["n"] for b in es["bins"]) == es["n"] == len(a)
    json.dumps(tab)


def test_figures_render(tmp_path, mesh):
    X = np.asarray(mesh.nodes)
    run = load_run(write_run(tmp_path / "run", mesh, X, {"supine": X * 1.05, "prone": X}))
    maps = {p: failure_map(run, p) for p in run.x}
    for fig in (error_maps_figure(maps, limit=3.0), error_vs_strain_figure(maps)):
        png = png_bytes(fig)
        assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_model_changes():
    a = {"formulation": "anp", "materials": {"breast_left": {"E": 1.0}},
         "effects": {"fixed": {"node_set": "fixed"}, "ligaments": {"E": 100.0}}}
    b = {"formulation": "anp", "materials": {"breast_left": {"E": 0.8}},
         "effects": {"fixed": {"node_set": "fixed"}, "sliding": {"friction": 0.1}}}
    assert model_changes(a, b) == ["+ sliding", "- ligaments",
                                   "materials.breast_left.E: 1 -> 0.8"]


def test_compare_runs_and_cli(tmp_path, mesh, capsys):
    from breastmodel.pipeline.config import DEFAULTS

    X = np.asarray(mesh.nodes)
    base = copy.deepcopy(DEFAULTS["model"])
    plus = copy.deepcopy(base)
    plus["effects"]["sliding"] = {"friction": 0.1}
    r1 = write_run(tmp_path / "r1", mesh, X, {"supine": X * 1.04, "prone": X + [0, -3, 0]},
                   model=base)
    r2 = write_run(tmp_path / "r2", mesh, X, {"supine": X * 1.01, "prone": X + [0, -1, 0]},
                   model=plus)
    assert main(["compare", str(r1), str(r2), "--out", str(tmp_path / "cmp")]) == 0
    printed = capsys.readouterr().out
    assert "+ sliding" in printed and "supine" in printed
    cmp = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    m1 = json.loads((r1 / "metrics.json").read_text())["positions"]
    m2 = json.loads((r2 / "metrics.json").read_text())["positions"]
    for p in ("supine", "prone"):
        for k in ("mhd_mm", "rmse_mm", "p95_mm"):
            t = cmp["positions"][p][k]
            assert t["values"] == [m1[p][k], m2[p][k]]
            assert t["delta_previous"][1] == pytest.approx(m2[p][k] - m1[p][k], abs=1e-12)
            assert t["delta_first"] == pytest.approx([0.0, m2[p][k] - m1[p][k]], abs=1e-12)
    assert cmp["mean"]["mhd_mm"]["values"][1] == pytest.approx(
        (m2["supine"]["mhd_mm"] + m2["prone"]["mhd_mm"]) / 2)
    assert cmp["runs"][1]["changes"] == ["+ sliding"]
    assert "sliding" in cmp["runs"][1]["effects"] and "sliding" not in cmp["runs"][0]["effects"]
    assert cmp["regions"]["prone"]["all"]["rmse_mm"] == pytest.approx(
        [m1["prone"]["rmse_mm"], m2["prone"]["rmse_mm"]], rel=1e-9)
    doc = (tmp_path / "cmp" / "compare.html").read_text()
    pngs = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', doc)
    assert len(pngs) == 1 + 2  # MHD per revision + one map figure per position
    assert all(base64.b64decode(s)[:4] == b"\x89PNG" for s in pngs)


def test_compare_rejects_bad_folders(tmp_path, mesh):
    X = np.asarray(mesh.nodes)
    r1 = write_run(tmp_path / "r1", mesh, X, {"supine": X})
    r2 = write_run(tmp_path / "r2", mesh, X, {"supine": X}, subject="other")
    with pytest.raises(StageError, match="different subjects"):
        compare_runs([r1, r2])
    small = breastlike_mesh(cells=(6, 4, 2, 2))
    Xs = np.asarray(small.nodes)
    r3 = write_run(tmp_path / "r3", small, Xs, {"supine": Xs})
    with pytest.raises(StageError, match="different meshes"):
        compare_runs([r1, r3])
    (tmp_path / "empty").mkdir()
    with pytest.raises(StageError, match="stages.json is missing"):
        write_compare([r1, tmp_path / "empty"], tmp_path / "cmp")
    assert main(["compare", str(r1), str(tmp_path / "empty"), "--out",
                 str(tmp_path / "cmp")]) == 1
