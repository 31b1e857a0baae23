"""Non-physical causes as candidates: a misregistered position, a segmentation offset.

Two-mound problems whose measured skin of one position (or of every position) is moved by a
known rigid motion (or offset along its normals) after the truth model predicted it; the
fitted model is the truth model, so the only error is the measurement's.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from breastmodel.diagnosis import load_run, rank_candidates
from breastmodel.diagnosis.diagnose import correction_rows
from breastmodel.diagnosis.measurement import _vertex_normals
from breastmodel.phantom.mounds import mound_problem
from breastmodel.pipeline.config import resolve_config
from breastmodel.pipeline.problem import move_measured_skin
from breastmodel.pipeline.run import run_problem

NH = {"name": "neo_hookean", "nu": 0.49}
BASE = {"materials": {"breast_left": {**NH, "E": 1.0}, "breast_right": {**NH, "E": 1.0},
                      "muscle": {**NH, "E": 10.0}},
        "effects": {"fixed": {"node_set": "fixed"}}}
TIED_E = "materials.breast_left.E|materials.breast_right.E"


def _config():
    return resolve_config({
        "model": copy.deepcopy(BASE), "stress_free": {"method": "none"},
        "fit": {"enabled": True, "budget": 20, "sensitivity": False, "method": "least_squares",
                "calibrate": ["prone", "supine"],
                "parameters": {TIED_E: {"min": 0.2, "max": 5.0}}}})


#: The misregistration: 4 mm mostly sideways and 1.5 deg about the anterior axis.
T0 = np.array([3.0, 1.0, -2.5])
R0 = Rotation.from_rotvec(np.radians(1.5) * np.array([0.0, 1.0, 0.0])).as_matrix()


@pytest.mark.parametrize("position", ["supine_tilted", "prone"])
def test_a_misregistered_position_is_named_with_its_motion(tmp_path, position):
    prob = mound_problem(tmp_path / "problem", BASE)
    centre = np.zeros(3)
    true = move_measured_skin(prob, position, lambda v, t: centre + (v - centre) @ R0.T + T0)
    run_problem(prob, _config(), tmp_path / "run", progress=False)
    d = rank_candidates(load_run(tmp_path / "run"), progress=False,
                        work_dir=tmp_path / "ev")
    best = d["ranking"][0]
    assert best["name"] == f"misregistration:{position}" and best["significant"]
    assert best["kind"] == "registration" and best["n_parameters"] == 6
    assert d["verdict"].startswith(f"{position} looks misregistered by about")
    assert "breastmodel register" in d["verdict"]
    # the estimated correction moves the recorded skin back onto the true one
    tr = best["transform"]
    R, t, c = (np.asarray(tr[k]) for k in ("rotation", "translation", "centre"))
    mis = centre + (true - centre) @ R0.T + T0
    back = c + (mis - c) @ R.T + t
    moved = np.linalg.norm(mis - true, axis=1)
    left = np.linalg.norm(back - true, axis=1)
    assert np.sqrt(np.mean(left**2)) < 0.25 * np.sqrt(np.mean(moved**2))
    # every physical candidate stays behind by the information criterion
    physical = [r for r in d["ranking"] if not r["measurement"]]
    assert all(r["delta_bic"] > best["delta_bic"] for r in physical)
    # its correction map is the residual's map, node by node in every position (the
    # modulus that the re-fit without it bent towards the misregistered position returns)
    rows = correction_rows(d)
    scored_pos = d["objective_positions"]
    mine = np.concatenate([rows[f"explained by {best['name']}"][p] for p in scored_pos])
    resid = np.concatenate([rows["residual"][p] for p in scored_pos])
    scored = np.isfinite(resid)
    assert scored.sum() == d["n_scored_nodes"] * len(scored_pos)
    assert np.sqrt(np.mean((mine - resid)[scored] ** 2)) < 0.1 * np.sqrt(
        np.mean(resid[scored] ** 2))
    others = [p for p in scored_pos if p != position]
    assert np.nanmax(np.abs(np.concatenate([rows["residual"][p] for p in others]))) < np.nanmax(
        np.abs(rows["residual"][position]))  # the residual itself points at the position
    # correcting the registration as estimated and re-fitting halves the worst MHD
    worst = max(d["baseline"]["mhd_mm"].values())
    assert max(best["verified"]["mhd_mm"].values()) <= 0.5 * worst


def test_a_segmentation_offset_is_named(tmp_path):
    prob = mound_problem(tmp_path / "problem", BASE)
    for p in ("prone", "supine", "supine_tilted"):
        move_measured_skin(prob, p, lambda v, t: v + 1.0 * _vertex_normals(v, t))  # 1 mm outwards
    run_problem(prob, _config(), tmp_path / "run", progress=False)
    d = rank_candidates(load_run(tmp_path / "run"), progress=False, work_dir=tmp_path / "ev")
    best = d["ranking"][0]
    assert best["name"] == "skin_offset" and best["significant"]
    assert best["estimate"]["measured.offset_mm"] == pytest.approx(-1.0, abs=0.15)
    assert "offset by" in d["verdict"] and "outwards" in d["verdict"]
    # the offset acts on the calibration positions, so it is tested on the held-out one
    assert best["held_out_improves"]
    # no candidate that makes the held-out position worse is significant, and the
    # significant ones rank first
    assert not [r["name"] for r in d["ranking"]
                if r["significant"] and r.get("held_out_improves") is False]
    flags = [r["significant"] for r in d["ranking"]]
    assert flags == sorted(flags, reverse=True)
    worst = max(d["baseline"]["mhd_mm"].values())
    assert max(best["verified"]["mhd_mm"].values()) <= 0.5 * worst


def test_the_held_out_position_does_not_judge_a_calibration_position_s_misregistration(
        tmp_path):
    """A misregistration of prone (a calibration position) predicts nothing in the held-out
    supine_tilted: with nothing re-fitted its RMS there is unchanged, which must not make the
    candidate insignificant (on a FEBio-truth subject with its prone skin moved 4 mm the old
    rule answered "none" at 88 % explained)."""
    prob = mound_problem(tmp_path / "problem", BASE)
    move_measured_skin(prob, "prone", lambda v, t: v @ R0.T + T0)
    cfg = _config()
    cfg["fit"]["enabled"] = False  # the truth's moduli, and no re-fit to move the held-out
    run_problem(prob, cfg, tmp_path / "run", progress=False)
    d = rank_candidates(load_run(tmp_path / "run"), progress=False, verify_top=0,
                        work_dir=tmp_path / "ev")
    assert d["held_out"] == ["supine_tilted"]
    best = d["ranking"][0]
    assert best["name"] == "misregistration:prone" and best["significant"]
    tilted = best["held_out"]["supine_tilted"]
    assert tilted["rms_after_mm"] == pytest.approx(tilted["rms_before_mm"], abs=1e-9)
    assert not best["held_out_improves"] and not best["held_out_tests"]
    assert d["verdict"].startswith("prone looks misregistered by about")
    # a candidate that acts on the held-out position too is still judged by it
    offset = next(r for r in d["ranking"] if r["name"] == "skin_offset")
    assert offset["held_out_tests"]


def _sphere_linearisation(t_mm: float, misfit_mm: float, floor_mm: float,
                          other_mm: float = 0.0):
    """A synthetic linearisation: two scored positions of 400 points on a 60 mm sphere; prone's
    residual is a rigid shift of ``t_mm`` along x plus a non-rigid misfit (a quadrupole of RMS
    ``misfit_mm``), supine_tilted's that quadrupole at RMS ``other_mm``; nothing fitted; the
    noise floor ``floor_mm``."""
    from breastmodel.diagnosis.residual import Baseline, Linearisation

    rng = np.random.default_rng(0)
    g = rng.normal(size=(400, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    y = 60.0 * g
    quad = g[:, 0] * g[:, 1] - g[:, 1] * g[:, 2]
    r_prone = -t_mm * g[:, 0] + misfit_mm * quad / np.sqrt(np.mean(quad**2))
    r0 = np.concatenate([r_prone, other_mm * quad / np.sqrt(np.mean(quad**2))])
    slices = {"prone": slice(0, 400), "supine_tilted": slice(400, 800)}
    lin = Linearisation({}, np.ones(400, bool), ["prone", "supine_tilted"], slices, {}, r0,
                        [], [], [], [])
    rms = float(np.sqrt(np.mean(r0**2)))
    base = Baseline(floor_mm, "given", [], [], np.zeros(800, bool), r0.copy(), {},
                    float(r0 @ r0), rms, rms, 400.0, None, {})
    geometry = {p: {"g": g, "y": y} for p in slices}
    return lin, base, geometry


@pytest.mark.parametrize("t_mm, other_mm, named", [(0.4, 0.0, False), (0.4, 0.3, False),
                                                     (2.0, 0.3, True)])
def test_a_misregistration_must_stand_out_of_the_model_s_misfit(t_mm, other_mm, named):
    """A rigid motion that lowers its position's RMS by less than the noise floor, or than
    the residual RMS the model leaves in the other position, is not named, whatever share of
    a structured misfit it absorbs. Prone moved 0.4 mm with a 0.2 mm misfit explains 57 %
    (29 % with the other position's 0.3 mm) and lowers the RMS by more than a quarter of the
    floor (the physical candidates' bar), but prone's RMS only 0.31 -> 0.20 mm: below the
    0.2 mm floor, and below the other position's 0.3 mm misfit where the floor is 0.1 mm."""
    from breastmodel.diagnosis.measurement import measurement_candidates
    from breastmodel.diagnosis.scoring import score_candidates

    lin, base, geometry = _sphere_linearisation(t_mm, 0.2, 0.2 if other_mm == 0.0 else 0.1,
                                                other_mm)
    cands = [c for c in measurement_candidates(["prone", "supine_tilted"])
             if c.name == "misregistration:prone"]
    ranking, failed, _ = score_candidates(cands, lin, base, None, geometry)
    (r,) = ranking
    assert not failed
    assert r["explained"] > 0.2 and r["delta_bic"] < -6.0
    assert r["rms_drop_mm"] > 0.25 * base.floor
    assert r["acted_rms_drop_mm"] == pytest.approx(
        np.sqrt(t_mm**2 / 3 + 0.04) - 0.2, abs=0.02)
    assert r["acted_rms_drop_mm"] > base.floor or other_mm == 0.0
    assert r["model_misfit_mm"] == pytest.approx(max(base.floor, other_mm), abs=0.01)
    assert r["significant"] is named
    assert r["transform"]["translation_mm"] == pytest.approx(t_mm, rel=0.05)
