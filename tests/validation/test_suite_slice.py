"""The CI slice of the validation suite: three small subjects from the phantom family, their
truth computed by FEBio, each run through the whole pipeline (own segmentation; truth labels).

It asserts that the suite reports every stage of every subject (a stage that stops is a row
with its error, never a crash) and every target of :data:`breastmodel.validation.TARGETS`
that is enforced (their issues have landed); the others are recorded in the printed table
and in ``$BREASTMODEL_VALIDATION_OUT/validation_slice.json`` when that is set. Then the
diagnosis on the torso subject's truth-labels run: the control, prone or tilted
misregistered, the skin offset (``DIAGNOSIS_CASES``), and on the same subject drawn with a
hidden left/right asymmetry.

    pytest -m validation -rP tests/validation          # about 25-30 minutes on 2 cores
"""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from breastmodel.validation import ARMS, family_maker, format_table, run_suite

pytestmark = [pytest.mark.slow, pytest.mark.validation]

#: Seeds of the slice: small subjects whose drawn field of view covers the whole torso (3), a
#: coil-cut body (0) and a muscle meeting air (1) (the family draws anatomy, voxels,
#: contrast, motion and tilt from the seed too; these are subjects of bench/validate.py).
SLICE = {3: "torso", 0: "coil", 1: "slab"}


def _febio():
    from breastmodel.febio import find_febio

    try:
        return str(find_febio())
    except (FileNotFoundError, ValueError) as exc:
        pytest.skip(f"FEBio 4 is needed for the validation suite's truths: {exc}")


@pytest.fixture(scope="module")
def slice_work(tmp_path_factory):
    out = os.environ.get("BREASTMODEL_VALIDATION_OUT")
    return Path(out) if out else tmp_path_factory.mktemp("validation")


@pytest.fixture(scope="module")
def slice_results(slice_work):
    febio = _febio()
    out = os.environ.get("BREASTMODEL_VALIDATION_OUT")
    work = slice_work
    # FEBio truths and truth meshes are cached by their inputs; CI keeps them between runs
    cache = Path(os.environ.get("BREASTMODEL_TRUTH_CACHE") or work / "truth_cache")
    make = family_maker(size="small", febio=febio, cache=cache)
    results = run_suite([f"small-{seed:03d}" for seed in SLICE], make, work)
    for res in results:
        if "info" in res:  # made: the drawn field of view is the one the slice expects
            fov = res["info"]["spec"]["fov"]
            assert fov == SLICE[int(res["subject"].rsplit("-", 1)[1])], res["subject"]
    print()
    print(format_table(results))
    for res in results:
        for t in res.get("targets", []):
            flag = "ENFORCED" if t["enforced"] else "recorded"
            print(f"{res['subject']} issue {t['issue']} {t['arm']}:{t['figure']} = "
                  f"{t['value']} (bound {t['kind']} {t['bound']}): met={t['met']} [{flag}]")
    if out:
        (Path(out) / "validation_slice.json").write_text(json.dumps(results, indent=1))
    return results


def test_every_subject_is_made_and_reports_every_arm(slice_results):
    assert len(slice_results) == len(SLICE)
    for res in slice_results:
        assert "error" not in res, f"{res['subject']}: the subject could not be made: " \
                                   f"{res.get('error')}"
        assert set(res["arms"]) == set(ARMS)
        for arm, a in res["arms"].items():
            assert a["stages"], f"{res['subject']} [{arm}]: no stage ran"
            if a["error"] is None:
                # a completed arm has a fitted modulus and an MHD for every position
                assert a["fitted"]["breast_E"] > 0
                positions = a["calibrate"] + a["held_out"]
                assert set(a["mhd_mm"]) == set(positions)
                assert all(v is not None and v >= 0 for v in a["mhd_mm"].values())
            else:
                # a stage that stopped is named, with the stages before it
                assert a["failed_stage"], f"{res['subject']} [{arm}]: {a['error']}"
                assert a["stages"][-1]["status"] == "failed"


def test_truth_labels_arm_completes(slice_results):
    """With the truth label maps given, the pipeline reaches every prediction."""
    bad = {r["subject"]: r["arms"]["truth_labels"]["error"] for r in slice_results
           if r["arms"]["truth_labels"]["error"] is not None}
    assert not bad, bad


def test_enforced_targets_are_met(slice_results):
    missed = [f"{r['subject']} issue {t['issue']} {t['arm']}:{t['figure']} = {t['value']} "
              f"(bound {t['kind']} {t['bound']})"
              for r in slice_results for t in r["targets"] if t["enforced"] and not t["met"]]
    assert not missed, "\n".join(missed)


def _rigid(v, t):
    """About 4 mm: 3, 1, -2.5 mm and 1.5 deg about the anterior axis (y)."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.radians(1.5) * np.array([0.0, 1.0, 0.0])).as_matrix()
    return v @ R.T + np.array([3.0, 1.0, -2.5])


def _offset(v, t):
    """1 mm outwards along the vertex normals."""
    from breastmodel.diagnosis.measurement import _vertex_normals

    return v + _vertex_normals(v, t)


#: The diagnosis' CI slice on FEBio truth: the torso subject (bulk truth, the control) as its
#: truth-labels run fitted it, and its problem with the prone or the tilted measured skin
#: moved rigidly by about 4 mm (a misregistration of that position) or every measured skin
#: offset 1 mm (a segmentation bias). label -> {position prefix ("*": every one): move}.
DIAGNOSIS_CASES = {"none": {}, "misregistration:prone": {"prone": _rigid},
                   "misregistration:supine_tilted": {"supine_tilted": _rigid},
                   "skin_offset": {"*": _offset}}


def _answer(run_dir: Path, work: Path) -> tuple[str, dict, dict]:
    """The diagnosis' answer (its first significant candidate, else "none"), that
    candidate's row and the whole diagnosis."""
    from breastmodel.diagnosis import answer, load_run, rank_candidates

    d = rank_candidates(load_run(run_dir), progress=False, verify_top=0, work_dir=work)
    best = answer(d["ranking"])
    return (best["name"] if best else "none", best or {}, d)


@pytest.mark.parametrize("label", list(DIAGNOSIS_CASES))
def test_the_diagnosis_names_the_cause_on_febio_truth(slice_results, slice_work, tmp_path,
                                                      label):
    from breastmodel.diagnosis import load_run
    from breastmodel.pipeline.problem import move_measured_skin
    from breastmodel.pipeline.run import run_problem

    base = load_run(slice_work / "runs" / "small-003" / "truth_labels")
    run_dir, expected = base.out, label
    moves = {p: m for q, m in DIAGNOSIS_CASES[label].items() for p in base.positions
             if q == "*" or p.startswith(q)}
    if moves:
        folder = tmp_path / "problem"
        shutil.copytree(base.problem_dir, folder)
        for pos, move in moves.items():
            move_measured_skin(folder, pos, move)
        run_dir = tmp_path / "run"
        run_problem(folder, base.config, run_dir, progress=False)
    if label.startswith("misregistration:"):  # named by the position it moved
        (moved,) = moves
        expected = f"misregistration:{moved}"
    answer, first, d = _answer(run_dir, tmp_path / "evaluations")
    print(f"{label}: {answer}; {d['verdict']}")
    assert answer == expected, d["verdict"]
    if label == "skin_offset":
        assert first["estimate"]["measured.offset_mm"] == pytest.approx(-1.0, abs=0.3)
    if label.startswith("misregistration:"):
        shift = float(np.linalg.norm([3.0, 1.0, -2.5]))
        assert first["transform"]["translation_mm"] == pytest.approx(shift, rel=0.3)


def test_the_diagnosis_names_a_hidden_asymmetry_on_febio_truth(slice_work, tmp_path):
    """A hidden physical effect on FEBio truth: the torso subject drawn again with its left
    breast 0.7x and its right 1.4x the modulus (the family's ``asymmetric`` truth physics),
    fitted with one modulus from its truth labels: the diagnosis names the asymmetry, its
    right/left ratio within 25 % of the truth's."""
    from breastmodel.pipeline.run import run_subject
    from breastmodel.validation import suite_config
    from breastmodel.validation.figures import truth_breast_E
    from imaging.subject import read_subject

    febio = _febio()
    cache = Path(os.environ.get("BREASTMODEL_TRUTH_CACHE") or slice_work / "truth_cache")
    make = family_maker(size="small", febio=febio, cache=cache, physics="asymmetric")
    subject, truth, _ = make("small-003", slice_work / "asymmetric" / "small-003")
    sub = read_subject(subject)
    run_dir = tmp_path / "run"
    # Its tilted registration moves the markers past their localisation error (1.08 mm) but
    # differs from the markers' fit on the chest wall by less than that fit's own expected
    # error (0.94 against 1.03 mm): kept, flagged (truth TRE 0.46/0.53 mm mean/max, the
    # markers' 1.29/1.68), and require_fiducials, the run's default, would stop there.
    run_subject(subject, suite_config("truth_labels", truth, list(sub.positions),
                                      sub.reference, register={"require_fiducials": False}),
                run_dir, progress=False)
    answer, first, d = _answer(run_dir, tmp_path / "evaluations")
    print(f"regions:asymmetry: {answer} {first.get('estimate')}; {d['verdict']}")
    assert answer == "regions:asymmetry", d["verdict"]
    est, true_E = first["estimate"], truth_breast_E(truth)
    ratio = est["effects.regions.E_right"] / est["effects.regions.E_left"]
    assert ratio == pytest.approx(true_E["right"] / true_E["left"], rel=0.25)


def test_the_diagnosis_names_a_coarse_mesh_on_febio_truth(slice_results, slice_work, tmp_path):
    """The mesh class (``FEBIO_MESH`` of bench/diagnosis_matrix.py): the torso subject's
    truth-labels run made again on a mesh of twice its "auto" edge. The diagnosis names the
    mesh (its probe, on a mesh of half that edge, moves the fitted modulus by 10 % or more;
    +12 % in the FEBio matrix) and says which size to rerun with."""
    import json

    from breastmodel.config import load_toml
    from breastmodel.diagnosis import load_run
    from breastmodel.pipeline.run import cache_of, run_subject

    base = load_run(slice_work / "runs" / "small-003" / "truth_labels")
    auto = json.loads((base.problem_dir / "problem.json").read_text())["mesh_size_mm"]
    cfg = json.loads(json.dumps(base.config))
    cfg["mesh"]["size_mm"] = 2.0 * float(auto)
    subject = load_toml(base.out / "config.toml", stage="run")["subject"]
    run_dir = tmp_path / "run"
    run_subject(subject, cfg, run_dir, progress=False, cache=cache_of(base.out))
    answer, first, d = _answer(run_dir, tmp_path / "evaluations")
    print(f"mesh_refinement at {2.0 * float(auto):g} mm: {answer}; {d['verdict']}")
    assert answer == "mesh_refinement", d["verdict"]
    assert f"size_mm = {float(auto):g}" in d["verdict"]


#: Hidden physical effects the skin alone cannot show on the torso subject (the fitted
#: modulus absorbs them), named by the landmark check (:mod:`breastmodel.diagnosis.landmarks`;
#: the FEBio matrix's small-003 rows): expected answer -> the family's truth physics.
WITNESSED = {"skin": "skin_layer", "regions:gland": "gland_10x"}


@pytest.mark.parametrize("expected", list(WITNESSED))
def test_the_landmarks_name_what_the_skin_cannot_show_on_febio_truth(slice_work, tmp_path,
                                                                     expected):
    """The torso subject drawn again with a skin layer 10x the breast's modulus, or glands
    10x, fitted with one modulus from its truth labels: no candidate is significant on the
    skin, and the landmark check names the right one (its re-fit brings the landmarks home
    by 40 % or more in the matrix, against 8 % at most for any candidate on the control)."""
    from breastmodel.pipeline.run import run_subject
    from breastmodel.validation import suite_config
    from imaging.subject import read_subject

    febio = _febio()
    cache = Path(os.environ.get("BREASTMODEL_TRUTH_CACHE") or slice_work / "truth_cache")
    physics = WITNESSED[expected]
    make = family_maker(size="small", febio=febio, cache=cache, physics=physics)
    subject, truth, _ = make("small-003", slice_work / physics / "small-003")
    sub = read_subject(subject)
    run_dir = tmp_path / "run"
    cfg = suite_config("truth_labels", truth, list(sub.positions), sub.reference,
                       register={"require_fiducials": False})
    # the gland as its own region of the mesh (default off), so that the gland candidate
    # exists: the matrix's gland rows are meshed so (bench/diagnosis_matrix.py)
    cfg["mesh"]["keep_gland"] = expected == "regions:gland"
    run_subject(subject, cfg, run_dir, progress=False)
    from breastmodel.diagnosis import answer, load_run, rank_candidates

    d = rank_candidates(load_run(run_dir), progress=False, work_dir=tmp_path / "evaluations")
    best = answer(d["ranking"])
    lc = d["landmark_check"]
    print(f"{physics}: {best and best['name']}; {d['verdict']}; landmarks {lc}")
    assert best is not None and best["name"] == expected, d["verdict"]
    assert lc["named"] == expected
    after = best["landmarks"]["rms_after_mm"]
    assert after <= 0.8 * lc["rms_before_mm"]
    assert "internal landmarks" in d["verdict"]
