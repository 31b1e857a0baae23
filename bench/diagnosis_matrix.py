"""Benchmark: the diagnosis as a classifier, a confusion matrix over known causes.

Every case is a subject whose data carry one known cause of misfit that the fitted model
lacks: a hidden physical effect, a misregistered position, an offset of the measured skin,
the scan's field-of-view cut left free in the model (``cut_faces``, on the FEBio suite,
whose truths go on past the cut), a mesh twice as coarse as the "auto" size
(``mesh_refinement``, FEBio suite), or nothing ("none": noise only). The diagnosis runs on the
fitted model; its answer is the best significant candidate, or "none". The table gives, per
case, the truth, the answer, the truth's rank, its explained fraction and delta BIC, the
verified worst MHD against the run's, and the wall time of the diagnosis; then top-1 and
top-3 rates, false alarms on "none" and the confusion matrix. Results go to
``bench/results/diagnosis_matrix.json``.

Two suites:
- ``--suite mounds`` (default): two-mound problems (:mod:`breastmodel.phantom.mounds`,
  seconds each), whose truth our own solver makes (a unit check of the ranking, not a
  validation).
- ``--suite febio``: subjects of the validation family (half-size anatomies, seeds
  ``--seeds``) whose truth FEBio computed with one hidden effect (:data:`FEBIO_CASES`: the
  family's truth physics), MRI rendered from it; the fitted model is the suite's bulk model
  (one breast modulus, least squares on the reference and prone) built from the truth label
  maps (the "truth labels" arm, so that segmentation is out of the question), then
  diagnosed.

Run: ``.venv/bin/python bench/diagnosis_matrix.py [--suite mounds|febio] [--cells 8 6 3 2]
[--stress-free inverse] [--cases skin,none] [--seeds 3,8] [--workers 2] [--out /tmp/matrix]
[--results FILE.json]``. ``--cells 26 16 6 2`` is a 20k-tet mound subject (the diagnosis'
time target: <= 10 minutes on 2 cores). The febio suite needs FEBio (``$FEBIO`` or
``../shared/febio/febio4``) and caches its truths in ``--truth-cache``.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from breastmodel.config import write_json  # noqa: E402
from breastmodel.diagnosis import answer, load_run, rank_candidates  # noqa: E402
from breastmodel.diagnosis.missing import RIM_MM  # noqa: E402
from breastmodel.phantom.mounds import mound_problem  # noqa: E402
from breastmodel.pipeline.config import resolve_config  # noqa: E402
from breastmodel.pipeline.problem import move_measured_skin  # noqa: E402
from breastmodel.pipeline.run import run_problem  # noqa: E402

NH = {"name": "neo_hookean", "nu": 0.49}
BASE = {"materials": {"breast_left": {**NH, "E": 1.0}, "breast_right": {**NH, "E": 1.0},
                      "muscle": {**NH, "E": 10.0}},
        "effects": {"fixed": {"node_set": "fixed"}}}
TIED = "materials.breast_left.E|materials.breast_right.E"


@dataclass(frozen=True)
class Case:
    """One subject of the matrix: its label (the candidate name the diagnosis should give, or
    "none"), its problem folder and the run config of the fitted model."""

    label: str
    problem: Path | None
    config: dict
    subject: Path | None = None  # a subject folder to run from its images instead
    tag: str = ""  # the case's folder name (default: the label)
    # measured skins moved after the subject's problem is built ({position: move}), and the
    # folder name of the run that builds it (the control's, whose stages it then shares)
    moves: dict | None = None
    base_tag: str = ""
    weak: bool = False  # the effect near the noise floor: "none" is also a right answer


def _with(**effects) -> dict:
    out = copy.deepcopy(BASE)
    out["effects"].update(effects)
    return out


def _rigid(v, t):
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(np.radians(1.5) * np.array([0.0, 1.0, 0.0])).as_matrix()
    return v @ R.T + np.array([3.0, 1.0, -2.5])


def _offset(v, t):
    from breastmodel.diagnosis.measurement import _vertex_normals

    return v + 1.0 * _vertex_normals(v, t)


#: label -> (truth model, change of the measured skins or None, noise mm)
MOUND_CASES = {
    "skin": (_with(skin={"E": 4.0}), None, 0.0),
    "regions:asymmetry": (_with(regions={"E_left": 0.6, "E_right": 1.5, "gland": False}),
                          None, 0.0),
    "strain_stiffening": (_with(strain_stiffening={"Jm": 0.1}), None, 0.0),
    "ligaments:lateral": (_with(ligaments={"groups": ["lateral"], "E": 800.0}), None, 0.0),
    "misregistration:supine_tilted": (BASE, {"supine_tilted": _rigid}, 0.0),
    "misregistration:prone": (BASE, {"prone": _rigid}, 0.0),
    "skin_offset": (BASE, {p: _offset for p in ("prone", "supine", "supine_tilted")}, 0.0),
    "none": (BASE, None, 0.1),
}


def mound_suite(root: Path, names: list[str], *, cells: tuple[int, ...],
                stress_free: str) -> Iterator[Case]:
    """Two-mound subjects, one per name of :data:`MOUND_CASES`."""
    for name in names:
        truth, moves, noise = MOUND_CASES[name]
        folder = root / name.replace(":", "_") / "problem"
        mound_problem(folder, truth, cells=tuple(cells), stress_free=stress_free,
                      noise_mm=noise, seed=3)
        for pos, move in (moves or {}).items():
            move_measured_skin(folder, pos, move)
        cfg = resolve_config({
            "model": copy.deepcopy(BASE), "stress_free": {"method": stress_free},
            "fit": {"enabled": True, "budget": 20, "sensitivity": False,
                    "method": "least_squares", "calibrate": ["prone", "supine"],
                    "parameters": {TIED: {"min": 0.2, "max": 5.0}}}})
        yield Case(name, folder, cfg)


#: case -> (label: the candidate the diagnosis should name, "ligaments" for any group; the
#: family's truth physics, :data:`breastmodel.phantom.subject_spec.PHYSICS`). A ``_weak``
#: case holds the same effect near the noise floor.
FEBIO_CASES = {
    "regions:asymmetry": ("regions:asymmetry", "asymmetric"),
    "strain_stiffening": ("strain_stiffening", "gent_breast"),
    "strain_stiffening_weak": ("strain_stiffening", "gent_breast_weak"),
    "regions:gland": ("regions:gland", "gland_10x"),
    "regions:gland_weak": ("regions:gland", "gland"),
    # no strength is visible on the family's bonded interface: on small-003's prone truth
    # mesh (our solver) cables 30x the default stiffness moved the skin by 0.22 mm at most
    "ligaments_weak": ("ligaments", "ligaments"),
    "fascia": ("fascia", "fascia"),
    # the skin written as a solid layer one element thick (FEBio's shells fail on these
    # subjects, ``PHYSICS`` in breastmodel/phantom/subject_spec.py)
    "skin": ("skin", "skin_layer"),
    "skin_weak": ("skin", "skin_layer_weak"),
    # the sliding interface as the loose tissue the breast slides on: the breast tets with a
    # node on the breast-muscle interface twice (visible) or 1.25 times (weak) as soft as
    # the breast; FEBio's sliding-elastic fails on these subjects. The candidates that
    # answer it: compliant_interface (a shearing interface) or sliding (contact)
    "sliding": ("sliding", "sliding_layer"),
    "sliding_weak": ("sliding", "sliding_layer_weak"),
    "none": ("none", "bulk"),
}
#: The measurement classes on the FEBio suite: the control subject (bulk truth) with one
#: position's measured skin moved rigidly by about 4 mm (``_rigid``: a misregistration) or
#: every measured skin offset 1 mm along its normal (``_offset``: a segmentation bias), moved
#: in the problem the pipeline built from its images. label -> (position prefix, move).
FEBIO_MEASUREMENT = {
    "misregistration:prone": ("prone", _rigid),
    "misregistration:supine_tilted": ("supine_tilted", _rigid),
    "skin_offset": ("", _offset),
}


#: The model's classes on the FEBio suite: the control subject (bulk truth, its body going on
#: past the scan's cut) fitted with the suite's model changed so that it lacks what the
#: label names. label -> the change of the model's effects (``suite_config(effects=...)``).
FEBIO_MODEL = {
    "cut_faces": {"cut_faces": None},  # the field-of-view cut left free
}
#: The mesh class: the control subject fitted on a mesh of this many times its "auto" edge
#: length (a user's coarse ``[mesh] size_mm``); the diagnosis should name ``mesh_refinement``.
FEBIO_MESH = {"mesh_refinement": 2.0}


def febio_suite(root: Path, names: list[str], *, seeds: list[int], cache: Path | None
                ) -> Iterator[Case]:
    """Family subjects with FEBio truth, one per name of :data:`FEBIO_CASES`,
    :data:`FEBIO_MEASUREMENT`, :data:`FEBIO_MODEL` or :data:`FEBIO_MESH` and seed."""
    from breastmodel.validation.suite import family_maker, suite_config
    from imaging.subject import read_subject

    for name in names:
        for seed in seeds:
            control = name in FEBIO_MEASUREMENT or name in FEBIO_MODEL or name in FEBIO_MESH
            label, physics = (name, "bulk") if control else FEBIO_CASES[name]
            make = family_maker(size="small", cache=cache, physics=physics)
            tag = f"{name.replace(':', '_')}-{seed}"
            base_tag = f"none-{seed}" if control else tag
            subject, truth, _ = make(f"small-{seed}", root / base_tag / "subject")
            sub = read_subject(subject)
            # a registration its checks flag is kept, with its warning, and recorded in the
            # row (``registration_flagged``): the matrix scores the diagnosis, and the
            # asymmetric truth of seed 3 (2026-12-07) flagged its tilted position by 0.01 mm
            # (a marker 1.09 mm off the fiducials' solution, against its 1.08 mm allowance)
            cfg = suite_config("truth_labels", truth, list(sub.positions), sub.reference,
                               effects=FEBIO_MODEL.get(name),
                               register={"require_fiducials": False})
            if label == "regions:gland":
                cfg["mesh"]["keep_gland"] = True
            if name in FEBIO_MESH:
                cfg["mesh"]["size_mm"] = FEBIO_MESH[name] * _auto_size(truth, sub.reference)
            if name not in FEBIO_MEASUREMENT:
                yield Case(label, None, cfg, subject=subject, tag=tag,
                           weak=name.endswith("_weak"))
                continue
            prefix, move = FEBIO_MEASUREMENT[name]
            moved = [p for p in sub.positions if p.startswith(prefix)]
            label = f"misregistration:{moved[0]}" if prefix else name
            yield Case(label, None, cfg, subject=subject, tag=tag,
                       moves={p: move for p in moved}, base_tag=base_tag)


def _auto_size(truth: Path, reference: str) -> float:
    """The "auto" element size of the reference's truth label map, mm."""
    import SimpleITK as sitk

    from meshing.sizing import mesh_size

    return mesh_size("auto", sitk.ReadImage(str(truth / f"{reference}_labels.nii.gz")))[0]


#: Candidates that also name a class: a sliding interface is a shearing one or a contact.
SAME_CLASS = {"sliding": ("compliant_interface",)}


def matches(answer: str, label: str) -> bool:
    """The answer names the truth ("ligaments": any group of them)."""
    return (answer == label or answer in SAME_CLASS.get(label, ())
            or (label == "ligaments" and answer.startswith("ligaments:")))


def diagnose_case(case: Case, out: Path, *, workers: int, rim_mm: float = RIM_MM) -> dict:
    run_dir = out / (case.tag or case.label.replace(":", "_")) / "run"
    t0 = time.perf_counter()
    from breastmodel.pipeline.run import run_subject

    if case.moves:
        # the control's run builds the problem from the images; its measured skins move here
        base_dir = out / case.base_tag / "run"
        run_subject(case.subject, case.config, base_dir, progress=False)
        folder = out / case.tag / "problem"
        shutil.copytree(load_run(base_dir).problem_dir, folder, dirs_exist_ok=True)
        for pos, move in case.moves.items():
            move_measured_skin(folder, pos, move)
        run_problem(folder, case.config, run_dir, progress=False)
    elif case.subject is not None:
        run_subject(case.subject, case.config, run_dir, progress=False)
    else:
        run_problem(case.problem, case.config, run_dir, progress=False)
    t_run = time.perf_counter() - t0
    t0 = time.perf_counter()
    cpu0 = os.times()
    d = rank_candidates(load_run(run_dir), progress=False, n_workers=workers,
                        work_dir=run_dir / "diagnosis" / "evaluations", rim_mm=rim_mm)
    cpu1 = os.times()
    wall = time.perf_counter() - t0
    names = [r["name"] for r in d["ranking"]]
    flagged = _flagged(run_dir if not case.moves else out / case.base_tag / "run")
    best = answer(d["ranking"])
    named = best["name"] if best else "none"
    truth = next((r for r in d["ranking"] if matches(r["name"], case.label)), None)
    # the worst MHD over the scored positions (since 2026-12-07; the reference, which the
    # stress-free inverse reproduces whatever the model, counted before)
    scored = d["objective_positions"]
    worst = max(v for p, v in d["baseline"]["mhd_mm"].items() if p in scored)
    # the answer's real re-fit: its check, or the landmark check's (which named it)
    ver = (best.get("verified") or best.get("landmark_refit") or {}) if best else {}
    # held-out check: the truth against the best wrong candidate of the same parameter count
    wrong = next((r for r in d["ranking"] if truth and not matches(r["name"], case.label)
                  and r["n_parameters"] == truth["n_parameters"] and r.get("held_out")), None)
    return {
        "label": case.label, "tag": case.tag, "answer": named, "rim_mm": d["rim_mm"],
        "strength": "weak" if case.weak else "visible",
        "correct": matches(named, case.label) or (case.weak and named == "none"),
        "rank": names.index(truth["name"]) + 1 if truth else None,
        "top3": names[:3], "explained": truth["explained"] if truth else None,
        "delta_bic": truth["delta_bic"] if truth else None,
        "worst_mhd_mm": worst,
        "verified_worst_mhd_mm": max(v for p, v in ver["mhd_mm"].items() if p in scored)
        if ver.get("mhd_mm") else None,
        "held_out_truth": truth.get("held_out") if truth else None,
        "held_out_wrong": {"name": wrong["name"], **wrong["held_out"]} if wrong else None,
        "registration_flagged": flagged,
        "failed": [f["name"] for f in d["failed"]], "n_evaluations": d["n_evaluations"],
        "budget": d["budget"],
        "run_s": t_run, "diagnose_s": wall,
        "diagnose_cpu_s": (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system),
        "verdict": d["verdict"],
        "confounders": [{"name": c["name"], "change": c["change"]} for c in d["confounders"]],
        "mesh_probe": _mesh_probe(d),
        "landmark_check": _landmarks(d.get("landmark_check")),
    }


def _landmarks(lc: dict | None) -> dict | None:
    """The landmark check of a diagnosis (what it named, the landmarks' RMS before and after
    each re-fit, mm); None where it did not run."""
    if lc is None:
        return None
    return {"named": lc.get("named"), "rms_before_mm": lc["rms_before_mm"],
            "after_mm": {x["name"]: x["rms_after_mm"] for x in lc["refits"]}}


def _mesh_probe(d: dict) -> dict | None:
    """The mesh candidate of a diagnosis: its rank, explained fraction, the change of the
    fitted parameter it moves most, and the probe (sizes, tets, seconds); None without it."""
    names = [r["name"] for r in d["ranking"]]
    r = next((r for r in d["ranking"] if r["measurement"] == "refinement"), None)
    if r is None:
        return None
    return {"rank": names.index(r["name"]) + 1, "explained": r["explained"],
            "significant": r["significant"], "parameter_change": r.get("parameter_change"),
            **{k: r["probe"][k] for k in ("size_mm", "fine_size_mm", "n_tets", "fine_n_tets",
                                          "seconds")}}


def _flagged(run_dir: Path) -> list[str]:
    """The positions whose registration the run's checks flagged (none for a run made
    from a problem folder)."""
    stages = json.loads((run_dir / "stages.json").read_text())["stages"]
    key = next((s["key"] for s in stages if s["name"] == "register"), None)
    if key is None:
        return []
    reg = json.loads((run_dir / "cache" / "register" / key / "registration.json").read_text())
    return [p for p, e in reg["positions"].items() if e.get("status") == "flagged"]


def summarise(rows: list[dict]) -> dict:
    labels = sorted({r["label"] for r in rows} | {r["answer"] for r in rows})
    confusion = {t: {a: 0 for a in labels} for t in labels}
    for r in rows:
        confusion[r["label"]][r["answer"]] += 1
    real = [r for r in rows if r["label"] != "none" and r.get("strength") != "weak"]
    weak = [r for r in rows if r.get("strength") == "weak"]
    nones = [r for r in rows if r["label"] == "none"]
    return {
        "top1": sum(matches(r["answer"], r["label"]) for r in real) / max(len(real), 1),
        "top3": sum(r["rank"] is not None and r["rank"] <= 3 for r in real) / max(len(real), 1),
        # at the weak strength "none" is right and another effect is an error
        "weak_errors": sum(not r["correct"] for r in weak) if weak else None,
        "false_alarms_on_none": sum(r["answer"] != "none" for r in nones) / max(len(nones), 1)
        if nones else None,
        "halved": [r["label"] for r in real if r["verified_worst_mhd_mm"] is not None
                   and r["verified_worst_mhd_mm"] <= 0.5 * r["worst_mhd_mm"]],
        "confusion": confusion,
    }


def _fmt(v, spec: str) -> str:
    return format(v, spec) if v is not None else "-"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", default="mounds", choices=("mounds", "febio"))
    ap.add_argument("--cells", type=int, nargs=4, default=(8, 6, 3, 2))
    ap.add_argument("--stress-free", default="none", choices=("none", "inverse"))
    ap.add_argument("--cases", default=None, help="comma list (default: the suite's all)")
    ap.add_argument("--seeds", default="3", help="febio suite: family seeds, comma list")
    ap.add_argument("--truth-cache", type=Path, default=None, help="febio suite: truth cache")
    ap.add_argument("--workers", type=int, default=0)
    ap.add_argument("--rim-mm", type=float, default=RIM_MM,
                    help="skin left out near its open edge, mm (default: diagnose's)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/diagnosis_matrix"))
    ap.add_argument("--results", type=Path, default=None,
                    help="default bench/results/diagnosis_matrix[_febio].json")
    ap.add_argument("--merge", action="store_true",
                    help="keep the results file's other rows (and its notes); rows of the "
                         "same case and seed are replaced")
    args = ap.parse_args(argv)
    known = (MOUND_CASES if args.suite == "mounds"
             else {**FEBIO_CASES, **FEBIO_MEASUREMENT, **FEBIO_MODEL, **FEBIO_MESH})
    names = [n for n in (args.cases or ",".join(known)).split(",") if n]
    unknown = sorted(set(names) - set(known))
    if unknown:
        ap.error(f"unknown case(s) {unknown}; known: {sorted(known)}")
    if args.suite == "mounds":
        cases = mound_suite(args.out, names, cells=args.cells, stress_free=args.stress_free)
    else:
        cases = febio_suite(args.out, names, seeds=[int(x) for x in args.seeds.split(",")],
                            cache=args.truth_cache)
    results = args.results or _HERE / "results" / (
        "diagnosis_matrix.json" if args.suite == "mounds" else "diagnosis_matrix_febio.json")
    rows = []
    print(f"{'truth':<32} {'answer':<32} {'rank':>4} {'expl':>5} {'dBIC':>7} {'MHD':>6} "
          f"{'->':>6} {'diag s':>7}")
    for case in cases:
        r = diagnose_case(case, args.out, workers=args.workers, rim_mm=args.rim_mm)
        rows.append(r)
        print(f"{case.tag or r['label']:<32} {r['answer']:<32} {_fmt(r['rank'], '4d'):>4} "
              f"{_fmt(r['explained'], '5.2f'):>5} {_fmt(r['delta_bic'], '7.1f'):>7} "
              f"{r['worst_mhd_mm']:6.2f} {_fmt(r['verified_worst_mhd_mm'], '6.2f'):>6} "
              f"{r['diagnose_s']:7.1f}", flush=True)
        write_json(args.out / "rows.partial.json", {"suite": args.suite, "rows": rows})
    kept = {}
    if args.merge and results.exists():
        kept = json.loads(results.read_text())
        tags = {r["tag"] for r in rows}
        rows = [r for r in kept.get("rows", []) if r.get("tag") not in tags] + rows
    summary = summarise(rows)
    print(f"top-1 {summary['top1']:.2f}, top-3 {summary['top3']:.2f}, false alarms on none "
          f"{summary['false_alarms_on_none']}, verified re-fit halves the worst MHD: "
          f"{summary['halved']}")
    n_tets = 6 * args.cells[0] * args.cells[1] * (args.cells[2] + args.cells[3]) \
        if args.suite == "mounds" else None
    write_json(results, {
        "suite": args.suite, "cells": list(args.cells), "n_tets": n_tets,
        "stress_free": args.stress_free, "workers": args.workers, "rows": rows,
        "summary": summary, "machine": platform.node(), "cpus": os.cpu_count(),
        "seeds": sorted({r["tag"].rsplit("-", 1)[-1] for r in rows if r.get("tag")})
        if args.merge else (args.seeds if args.suite == "febio" else None),
        **{k: v for k, v in kept.items() if k in ("note", "not_run", "extra_rows")}})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
