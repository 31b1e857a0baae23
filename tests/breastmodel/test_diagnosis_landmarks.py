"""The internal landmarks as the diagnosis' witness (:mod:`breastmodel.diagnosis.landmarks`):
which candidates are re-fitted, when one is named, and that a misregistered position's
landmarks move with its skin when the diagnosis corrects it."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from breastmodel.diagnosis import landmarks as lmod
from breastmodel.diagnosis import verify as vmod
from breastmodel.diagnosis.candidates import Candidate
from breastmodel.diagnosis.landmarks import check_landmarks, landmark_rms
from breastmodel.diagnosis.scoring import answer, verdict_sentence

POS = ["prone", "supine_tilted"]
BASE_MHD = {"supine": 0.2, "prone": 0.9, "supine_tilted": 0.7}
#: the fitted model's landmark errors: RMS 1 mm over both positions
BASE_ERRORS = {"prone": [1.0, 1.0], "supine_tilted": [1.0, 1.0]}


def _entry(name, delta_bic, measurement="", significant=False):
    return {"name": name, "measurement": measurement, "delta_bic": delta_bic,
            "explained": 0.1, "significant": significant, "doc": name, "estimate": {},
            "predicted_rms_mm": 0.3}


def _check(monkeypatch, ranking, after, *, worst=0.8):
    """check_landmarks on ``ranking`` where the re-fit of candidate X brings every landmark
    to ``after[X]`` mm (or to after[X][position]) and the worst scored MHD to ``worst``;
    returns the check and the names re-fitted."""
    refitted = []

    def refit(c, entry, run, fitted, obj_pos, positions, work_dir, budget, progress):
        refitted.append(c.name)
        a = after[c.name]
        a = a if isinstance(a, dict) else {p: a for p in POS}
        return {"mhd_mm": {"prone": worst, "supine_tilted": worst - 0.1},
                "landmark_errors_mm": {p: [a[p]] * 2 for p in POS}, "evaluations": 3}

    monkeypatch.setattr(vmod, "verify_effect", refit)
    monkeypatch.setattr(vmod, "verify_measurement", refit)
    monkeypatch.setattr(lmod, "base_errors", lambda problem, state, positions: BASE_ERRORS)
    cands = [Candidate(r["name"], "effect", r["name"]) for r in ranking]
    run = SimpleNamespace(problem=None)
    out = check_landmarks(ranking, cands, run, [], POS, ["supine", *POS], None, state={},
                          base_mhd=BASE_MHD, budget=4, progress=False)
    return out, refitted


def test_landmark_rms_pools_the_positions_asked_for():
    assert landmark_rms({"prone": [3.0, 4.0], "supine": [100.0]}, ["prone"]) == \
        pytest.approx(np.sqrt(12.5))
    assert landmark_rms({"prone": []}, ["prone", "other"]) is None


def test_the_physical_candidate_that_brings_the_landmarks_home_is_named(monkeypatch):
    """Of the physical candidates the skin favours (Delta BIC < 0), the one whose re-fit
    lowers the landmarks' RMS most, by 20 % and 0.1 mm at least, becomes the answer and the
    verdict says why; a candidate the skin does not favour is not re-fitted."""
    ranking = [_entry("misregistration:prone", -30.0, "rigid"), _entry("strain_stiffening", -5.0),
               _entry("skin", -4.0), _entry("fascia", 3.0)]
    out, refitted = _check(monkeypatch, ranking, {"strain_stiffening": 0.95, "skin": 0.6,
                                                  "misregistration:prone": 0.9})
    assert refitted == ["strain_stiffening", "skin", "misregistration:prone"]
    assert out["named"] == "skin" and out["rms_before_mm"] == pytest.approx(1.0)
    best = answer(ranking)
    assert best["name"] == "skin" and ranking[0] is best
    assert best["landmarks"]["rms_after_mm"] == pytest.approx(0.6)
    sentence = verdict_sentence(best, 0.5)
    assert "internal landmarks" in sentence and "from 1.00 to 0.60 mm" in sentence
    assert "the next best, misregistration:prone: 0.90 mm" in sentence


@pytest.mark.parametrize("after, worst, why", [
    ({"skin": 0.85}, 0.8, "a drop of 15 % is under the 20 %"),
    ({"skin": 0.6}, 0.95, "its re-fit raises the worst skin MHD (0.9 mm before)"),
    ({"skin": {"prone": 0.2, "supine_tilted": 1.05}}, 0.8,
     "one position's landmarks move away (RMS 1 -> 0.76 mm in all)"),
])
def test_no_candidate_is_named_on_too_little_or_at_the_skins_cost(monkeypatch, after, worst,
                                                                   why):
    ranking = [_entry("skin", -4.0)]
    out, _ = _check(monkeypatch, ranking, after, worst=worst)
    assert "named" not in out, why
    assert answer(ranking) is None


def test_a_misregistration_that_explains_the_landmarks_better_names_nothing(monkeypatch):
    """The landmarks of a misregistered position are off with its skin: where correcting it
    brings them closer than any effect, the check names no effect."""
    ranking = [_entry("misregistration:prone", -30.0, "rigid"), _entry("skin", -4.0)]
    out, _ = _check(monkeypatch, ranking, {"skin": 0.6, "misregistration:prone": 0.4})
    assert "named" not in out and answer(ranking) is None


def test_the_check_stays_out_of_a_clear_verdict_and_of_runs_without_landmarks(monkeypatch):
    ranking = [_entry("regions:asymmetry", -40.0, significant=True), _entry("skin", -4.0)]
    out, refitted = _check(monkeypatch, ranking, {"skin": 0.1})
    assert out is None and refitted == []
    monkeypatch.setattr(lmod, "base_errors", lambda problem, state, positions: {})
    assert check_landmarks([_entry("skin", -4.0)], [], SimpleNamespace(problem=None), [], POS,
                           POS, None, state={}, base_mhd=BASE_MHD, budget=4,
                           progress=False) is None
    # nothing the skin favours: no re-fit at all
    out, refitted = _check(monkeypatch, [_entry("skin", 2.0)], {"skin": 0.1})
    assert refitted == [] and out["refits"] == [] and "named" not in out


def test_a_corrected_misregistration_moves_the_positions_landmarks_too(tmp_path):
    """verify_measurement's corrected problem: the rigid motion moves the position's measured
    skin and landmarks alike (one image, one registration); an offset moves the skin only."""
    src = tmp_path / "problem"
    src.mkdir()
    v = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
    np.savez(src / "prone_skin.npz", vertices=v, triangles=np.array([[0, 1, 2]]))
    lm = {"prone": {"nipple": [1.0, 2.0, 3.0]}, "supine": {"nipple": [1.0, 2.0, 3.0]}}
    (src / "problem.json").write_text(json.dumps({"landmarks": lm}))
    shift = {"prone": lambda x, t: x + [0.0, 0.0, 4.0]}
    out = vmod.corrected_problem(src, tmp_path / "rigid", shift, rigid=True)
    meta = json.loads((out / "problem.json").read_text())
    assert meta["landmarks"]["prone"]["nipple"] == [1.0, 2.0, 7.0]
    assert meta["landmarks"]["supine"]["nipple"] == [1.0, 2.0, 3.0]
    with np.load(out / "prone_skin.npz") as z:
        assert np.allclose(z["vertices"][:, 2], 4.0)
    out = vmod.corrected_problem(src, tmp_path / "offset", shift)
    assert json.loads((out / "problem.json").read_text())["landmarks"] == lm


def test_a_refit_stored_before_landmark_errors_were_recorded_says_so(monkeypatch):
    """A resumed diagnosis whose re-fit was stored by an earlier version has no landmark
    errors for it: the check names that re-fit's reason instead of silently passing it by."""
    def refit(c, entry, run, fitted, obj_pos, positions, work_dir, budget, progress):
        return {"mhd_mm": {"prone": 0.8}, "landmark_errors_mm": None, "evaluations": 3}

    monkeypatch.setattr(vmod, "verify_effect", refit)
    monkeypatch.setattr(lmod, "base_errors", lambda problem, state, positions: BASE_ERRORS)
    ranking = [_entry("skin", -4.0)]
    out = check_landmarks(ranking, [Candidate("skin", "effect", "skin")],
                          SimpleNamespace(problem=None), [], POS, POS, None, state={},
                          base_mhd=BASE_MHD, budget=4, progress=False)
    (row,) = out["refits"]
    assert row["rms_after_mm"] is None and row["error"] == lmod.STALE
    assert "named" not in out


def test_the_report_shows_the_landmark_check(monkeypatch):
    from breastmodel.diagnosis.diagnose import _landmark_section

    ranking = [_entry("skin", -4.0)]
    out, _ = _check(monkeypatch, ranking, {"skin": 0.6})
    html = "".join(_landmark_section({"landmark_check": out}))
    assert "<b>skin</b>" in html and "1.00 mm" in html and "0.6" in html
    out, _ = _check(monkeypatch, [_entry("skin", 2.0)], {"skin": 0.1})
    assert "none was re-fitted" in "".join(_landmark_section({"landmark_check": out}))
    assert _landmark_section({"landmark_check": None}) == []
