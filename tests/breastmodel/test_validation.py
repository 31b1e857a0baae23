"""The validation suite's bookkeeping: targets, tables, resume, failures as rows (fast; the
suite itself runs in tests/validation)."""

import json

import numpy as np
import pytest

from breastmodel.validation import (
    ARMS,
    TARGETS,
    Target,
    check_targets,
    format_table,
    run_suite,
    split_positions,
    suite_config,
)


def _arm(error=None, **figures):
    return {"error": error, "failed_stage": "segment" if error else None, "stages": [],
            "figures": {"completed": 0.0 if error else 1.0, **figures}}


def test_split_positions_fits_reference_and_prone():
    assert split_positions(["prone", "supine", "supine_tilted"], "supine") == (
        ["supine", "prone"], ["supine_tilted"])
    assert split_positions(["supine", "supine_tilted_30"], "supine") == (
        ["supine", "supine_tilted_30"], [])


def test_suite_config_arms(tmp_path):
    cfg = suite_config("truth_labels", tmp_path, ["prone", "supine", "supine_tilted"], "supine")
    assert cfg["segment"]["labels"] == str(tmp_path.resolve())
    assert cfg["fit"]["enabled"] and cfg["fit"]["calibrate"] == ["supine", "prone"]
    assert cfg["fit"]["evaluate"] == ["supine_tilted"]
    assert "labels_positions" not in cfg["segment"]
    own = suite_config("pipeline", tmp_path, ["prone", "supine"], "supine")
    assert "labels" not in own["segment"]
    ref = suite_config("reference_truth", tmp_path, ["prone", "supine"], "supine")
    assert ref["segment"] == {"labels": str(tmp_path.resolve()), "labels_positions": ["supine"]}
    with pytest.raises(ValueError, match="unknown arm"):
        suite_config("nope", tmp_path, ["prone", "supine"], "supine")
    assert set(cfg["model"]["effects"]) == {"fixed", "cut_faces"}
    free = suite_config("truth_labels", tmp_path, ["prone", "supine"], "supine",
                        effects={"cut_faces": None, "tied": {}})
    assert set(free["model"]["effects"]) == {"fixed", "tied"}  # a study's variant
    assert cfg["register"]["require_fiducials"] is True  # the run's default
    lax = suite_config("pipeline", tmp_path, ["prone", "supine"], "supine",
                       register={"require_fiducials": False})
    assert lax["register"]["require_fiducials"] is False
    with pytest.raises(ValueError, match="register"):
        suite_config("pipeline", tmp_path, ["prone", "supine"], "supine",
                     register={"require_fiducials": "no"})


def test_targets_verdicts():
    t = Target("tre_max_mm", 0.5, "max", "pipeline", 14)
    assert t.met(0.4) is True and t.met(0.6) is False and t.met(None) is None
    assert t.met(float("nan")) is None
    res = {"arms": {"pipeline": _arm(tre_max_mm=0.7, dice_breast_min=0.97),
                    "truth_labels": _arm(error="segment: boom")}}
    rows = check_targets(res)
    by = {(r["arm"], r["figure"]): r for r in rows}
    assert by[("pipeline", "tre_max_mm")]["met"] is False
    assert by[("pipeline", "dice_breast_min")]["met"] is True
    assert by[("truth_labels", "completed")]["met"] is False
    assert by[("pipeline", "mhd_held_out_max_mm")]["met"] is None  # no figure
    assert len(rows) == len(TARGETS)


def test_run_suite_records_failures_and_resumes(tmp_path, monkeypatch):
    import breastmodel.validation.suite as v

    calls = []

    def make(name, folder):
        calls.append(name)
        if name == "bad":
            raise RuntimeError("FEBio did not converge")
        return folder, folder, {"label": "x"}

    def fake_eval(subject_dir, truth_dir, work_dir, **kw):
        return {"subject": "?", "arms": {a: _arm(mhd_calibrated_max_mm=0.8) for a in ARMS},
                "targets": []}

    monkeypatch.setattr(v, "evaluate_subject", fake_eval)
    res = run_suite(["good", "bad"], make, tmp_path)
    assert [r["subject"] for r in res] == ["good", "bad"]
    assert "FEBio did not converge" in res[1]["error"]
    assert json.loads((tmp_path / "results" / "bad.json").read_text())["error"] == res[1]["error"]
    table = format_table(res)
    assert "good" in table and "FEBio did not converge" in table
    assert format_table(res, markdown=True).startswith("| subject |")
    res2 = run_suite(["good", "bad"], make, tmp_path)  # resumes: nothing is made again
    assert calls == ["good", "bad"] and res2 == res
    run_suite(["good"], make, tmp_path, force=True)
    assert calls == ["good", "bad", "good"]


def test_figures_from_an_arm_result():
    from breastmodel.validation import arm_figures as _figures

    r = {"error": None, "dice": {"prone": {"breast": 0.96, "muscle": 0.91},
                                 "supine": {"breast": 0.94, "muscle": 0.93}},
         "registration": {"prone": {"tre_max_mm": 0.3, "rotation_error_deg": 0.1},
                          "tilt": {"tre_max_mm": 5.2, "rotation_error_deg": 1.0}},
         "fitted": {"breast_E": 0.405}, "truth_E": {"left": 0.3, "right": 0.3},
         "mhd_mm": {"prone": 2.78, "supine": 0.45, "tilt": 4.14}}
    f = _figures("pipeline", r, ["supine", "prone"], ["tilt"])
    assert f["dice_breast_min"] == 0.94 and f["dice_muscle_min"] == 0.91
    assert f["tre_max_mm"] == 5.2 and f["rotation_error_max_deg"] == 1.0
    assert np.isclose(f["breast_E_rel_error"], 0.35)
    assert f["mhd_calibrated_max_mm"] == 2.78 and f["mhd_held_out_max_mm"] == 4.14
    assert f["completed"] == 1.0
    assert "mhd_calibrated_overlap_max_mm" not in f  # a result written before the figure
    r["mhd_overlap_mm"] = {"prone": 0.81, "supine": 0.2, "tilt": None}
    f = _figures("pipeline", r, ["supine", "prone"], ["tilt"])
    assert f["mhd_calibrated_overlap_max_mm"] == 0.81
    assert "mhd_held_out_overlap_max_mm" not in f  # the held-out position has no figure
    assert f["mhd_calibrated_max_mm"] == 2.78


def test_family_maker_remakes_a_subject_whose_spec_changed(tmp_path, monkeypatch):
    import breastmodel.phantom.family as family
    from breastmodel.validation import family_maker

    made = []
    monkeypatch.setattr(family, "make_subject",
                        lambda spec, folder, **kw: made.append(spec.to_dict()))
    folder = tmp_path / "small-004"
    folder.mkdir()
    family_maker(size="small")("small-004", folder)
    family_maker(size="small")("small-004", folder)  # same spec: reused
    assert len(made) == 1
    _, _, info = family_maker(size="small", snr=33.0)("small-004", folder)  # another spec
    assert len(made) == 2 and made[1]["snr"] == 33.0 and info["spec"]["snr"] == 33.0


def test_truth_breast_moduli_come_from_the_materials_or_an_effect_that_sets_them(tmp_path):
    from breastmodel.phantom.truth_model import preset
    from breastmodel.validation.figures import truth_breast_E

    (tmp_path / "truth_model.json").write_text(preset("no_skin").to_json())
    plain = truth_breast_E(tmp_path)
    assert plain["left"] == plain["right"] == preset("no_skin").materials[1]["E"]
    (tmp_path / "truth_model.json").write_text(preset("asymmetric").to_json())
    regions = preset("asymmetric").effects["regions"]
    assert truth_breast_E(tmp_path) == {"left": regions["E_left"], "right": regions["E_right"]}
