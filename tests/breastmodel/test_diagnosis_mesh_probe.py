"""The mesh as a diagnosis candidate (``mesh_refinement``): its column, and where it cannot be
made. The probe itself (the refinement stages of a subject run) is tested with the pipeline's
refinement check (tests/breastmodel/test_pipeline.py)."""

from __future__ import annotations

import numpy as np
import pytest

from breastmodel.diagnosis.mesh_probe import (
    MESH_CANDIDATE,
    add_mesh_candidate,
    mesh_candidate,
    probe_mesh,
    refined_columns,
)
from breastmodel.diagnosis.residual import measured_geometry
from breastmodel.phantom.mounds import mound_problem
from breastmodel.pipeline.config import resolve_config
from breastmodel.pipeline.problem import load_problem, skin_nodes
from breastmodel.pipeline.run import run_problem

POSITIONS = ("prone", "supine", "supine_tilted")
NH = {"name": "neo_hookean", "nu": 0.49}
BASE = {"materials": {"breast_left": {**NH, "E": 1.0}, "breast_right": {**NH, "E": 1.0},
                      "muscle": {**NH, "E": 10.0}},
        "effects": {"fixed": {"node_set": "fixed"}}}


@pytest.fixture(scope="module")
def mounds(tmp_path_factory):
    root = tmp_path_factory.mktemp("mesh_probe")
    prob = mound_problem(root / "problem", BASE)
    problem = load_problem(prob)
    nodes = skin_nodes(problem, problem.mesh.n_nodes)
    return root, prob, problem, nodes


def _probe(root, prob, problem, move) -> dict:
    """A probe whose "fine" mesh is the run's own, each position predicted at ``move(nodes)``."""
    dirs = {}
    for p in POSITIONS:
        d = root / f"fine_{p}"
        d.mkdir(exist_ok=True)
        np.savez(d / "predicted.npz", x=move(np.asarray(problem.mesh.nodes)))
        dirs[p] = d
    return {"problem_dir": prob, "predict_dirs": dirs}


def test_the_column_is_the_change_of_each_scored_nodes_signed_error(mounds):
    root, prob, problem, nodes = mounds
    keep = np.ones(len(nodes), bool)
    keep[::3] = False  # the scored nodes only, in their order
    # the run's state: each position at a distance from its measured skin
    state = {"X": np.asarray(problem.mesh.nodes),
             "u": {p: np.zeros_like(problem.mesh.nodes) for p in POSITIONS}}
    same = refined_columns(problem, state, nodes, keep, POSITIONS,
                           _probe(root, prob, problem, lambda x: x))
    for p in POSITIONS:
        assert same[p].shape == (keep.sum(),)
        assert np.max(np.abs(same[p])) < 1e-9  # the same prediction changes nothing
    t = np.array([0.02, -0.03, 0.05])  # the fine mesh moves every skin node by t, mm
    moved = refined_columns(problem, state, nodes, keep, POSITIONS,
                            _probe(root, prob, problem, lambda x: x + t))
    geometry = measured_geometry(problem, state, nodes, keep, POSITIONS)
    for p in POSITIONS:
        expected = geometry[p]["g"] @ t  # d(signed distance) = g . (change of the node)
        err = np.abs(moved[p] - expected)
        assert np.percentile(err, 95) < 2e-3 and np.median(err) < 5e-4
        assert np.max(np.abs(expected)) > 0.03  # the shift is seen, not a zero column


def test_a_run_from_a_given_problem_folder_lists_the_probe_as_skipped(mounds, tmp_path):
    root, prob, problem, nodes = mounds
    cfg = resolve_config({"model": BASE, "stress_free": {"method": "none"}})
    run_problem(prob, cfg, tmp_path / "run", progress=False)
    from breastmodel.diagnosis import load_run

    run = load_run(tmp_path / "run")
    probe, why = probe_mesh(run, progress=False)
    assert probe is None and "given problem folder" in why
    keep = np.ones(len(nodes), bool)
    cand, skipped = add_mesh_candidate(run, {}, nodes, keep, POSITIONS, {}, refine=True,
                                       progress=False)
    assert cand is None and skipped["name"] == MESH_CANDIDATE
    assert "given problem folder" in skipped["reason"]
    cand, skipped = add_mesh_candidate(run, {}, nodes, keep, POSITIONS, {}, refine=False,
                                       progress=False)
    assert cand is None and "--no-refinement" in skipped["reason"]


def test_a_modulus_that_moves_with_the_finer_mesh_names_the_mesh_to_check():
    from breastmodel.diagnosis.scoring import confounders, confounding_sentence

    E = "materials.breast_left.E|materials.breast_right.E"
    probe = {"size_mm": 12.0, "fine_size_mm": 6.0, "n_tets": 900, "fine_n_tets": 7000}
    ranking = [{"name": MESH_CANDIDATE, "significant": False, "explained": 0.19,
                "measurement": "refinement", "probe": probe, "estimate": {E: 1.125}},
               {"name": "misregistration:prone", "significant": False, "explained": 0.16,
                "measurement": "rigid", "estimate": {E: 1.0}}]
    said = confounding_sentence(confounders(ranking, {E: 1.0}))
    assert f"+12 % with {MESH_CANDIDATE}" in said
    assert "a finer mesh (`[mesh] size_mm = 6`)" in said and "--add-effect" not in said


def _mesh_entry(shift: float) -> dict:
    """A synthetic linearisation: one fitted log-modulus whose column J the probe's column
    follows (``-shift * J`` plus a little of its own), on a residual of noise; the entry of
    the mesh candidate."""
    from breastmodel.diagnosis.missing import Plan
    from breastmodel.diagnosis.residual import Baseline, Linearisation, rms
    from breastmodel.diagnosis.scoring import score_candidates

    n, rng = 300, np.random.default_rng(5)
    J = rng.normal(size=2 * n)
    r0 = 0.3 * rng.normal(size=2 * n)
    col = -shift * J + 0.01 * rng.normal(size=2 * n)
    slices = {"prone": slice(0, n), "supine_tilted": slice(n, 2 * n)}
    lin = Linearisation({}, np.ones(n, bool), list(slices), slices, {}, r0, [J],
                        [np.log(0.2)], [np.log(5.0)], ["E"])
    r_base, z_base, _ = lin.solve([], [], [])
    base = Baseline(0.2, "given", [], [], np.zeros(2 * n, bool), r_base, z_base,
                    float(r_base @ r_base), rms(r0), rms(r_base), float(2 * n), None, {})
    geometry = {p: {"refined": col[s]} for p, s in slices.items()}
    cand = mesh_candidate({"size_mm": 12.0, "fine_size_mm": 6.0, "n_tets": 900,
                           "fine_n_tets": 7000}, list(slices))
    (entry,), failed, _ = score_candidates([cand], lin, base, Plan({}, {}, {"E": 1.0}),
                                           geometry)
    assert not failed
    return entry


@pytest.mark.parametrize("shift", [0.05, 0.15])
def test_a_finer_mesh_that_moves_the_fitted_modulus_by_a_tenth_says_the_mesh_is_too_coarse(
        shift):
    """The probe's column is nearly that of the modulus: the re-fit absorbs it (it explains
    almost nothing), but the modulus moves by exp(shift) - 1: at 5 % the mesh is fine, at
    16 % it is too coarse for the fitted value (a convergence check, not a hypothesis)."""
    from breastmodel.diagnosis.scoring import CONFOUNDING_CHANGE

    e = _mesh_entry(shift)
    assert abs(e["explained"]) < 0.05 and e["amount"] == 1.0
    ch = e["parameter_change"]
    assert ch["parameter"] == "E"
    assert ch["change"] == pytest.approx(np.expm1(shift), abs=0.01)
    assert e["significant"] is (ch["change"] >= CONFOUNDING_CHANGE)
    if e["significant"]:
        from breastmodel.diagnosis.scoring import mesh_sentence, verdict_sentence

        e["probe"] = {"size_mm": 12.0, "fine_size_mm": 6.0, "n_tets": 900, "fine_n_tets": 7000}
        said = verdict_sentence(e, 0.3)
        assert said.startswith("the mesh looks too coarse: on a mesh of 6 mm edges")
        assert "the fitted E would move by +16 %" in said and "`[mesh] size_mm = 6`" in said
        # after another answer (the demo's asymmetry on its 8 mm mesh): the mesh is named too
        beside = mesh_sentence(e)
        assert beside.startswith("the mesh looks too coarse") and "residual RMS" not in beside


def test_the_probe_halves_the_edge_unless_that_makes_too_many_tets():
    from breastmodel.diagnosis.mesh_probe import MAX_PROBE_TETS, probe_factor

    # the half-size subjects (11-17k tets): about 8x the tets, the refinement check's mesh
    assert probe_factor(11_000) == probe_factor(17_000) == 0.5
    f = probe_factor(45_600)  # the full-size validation subject
    assert 0.5 < f < 0.8 and 45_600 / f ** 3 == pytest.approx(MAX_PROBE_TETS)


def test_a_probe_that_fails_is_listed_with_its_reason_and_the_diagnosis_goes_on(monkeypatch):
    """A fine mesh the solver refuses (a skin-layer truth's probe, 2026-12-07: 2 of 76696
    tets of zero volume) costs the candidate, not the diagnosis."""
    import breastmodel.pipeline.refinement as refinement

    def refuse(*args, **kw):
        raise ValueError("mechanics: inverted or degenerate mesh: 2 of 76696 tets")

    monkeypatch.setattr(refinement, "refine_run", refuse)

    class Run:
        out = "RUN"
        problem = type("P", (), {"mesh": type("M", (), {"n_tets": 11_000})()})()

    probe, why = probe_mesh(Run(), progress=False)
    assert probe is None
    assert why == ("the probe failed: ValueError: mechanics: inverted or degenerate mesh: 2 of "
                   "76696 tets")
