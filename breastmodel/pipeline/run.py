"""``run_subject``: the cached subject pipeline.

segment (per position) -> register -> measured skins, and the reference's mesh -> the
*problem* (mesh, skins, gravity, landmarks) -> [fit] -> stress-free geometry -> predict +
score (per position) -> outputs (metrics.json, ``<position>_predicted.ply``, params.json,
report.html). The mesh needs only the reference's segmentation: on an adult volume it runs
in a worker process beside the other positions' segmentation and the registration.

Every stage is a :class:`breastmodel.cache.Cache` stage under ``OUT/cache/`` keyed by the
hash of its own settings and its inputs (files by content, upstream stages by key): a rerun
skips what is done, a killed run resumes at the stage it was in, and a changed model
parameter recomputes only the stress-free geometry, the predictions and the outputs.

The stage log is :class:`breastmodel.pipeline.runner.Runner`; the bodies of the subject
stages (segment, register, skins, mesh, problem) are in
:mod:`breastmodel.pipeline.subject_stages`, those of the model stages in
:mod:`breastmodel.pipeline.model_stages`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from breastmodel.errors import StageError
from breastmodel.pipeline.config import given_labels
from breastmodel.pipeline.model_stages import (
    check_landmarks,
    fit_stage,
    fit_start,
    predict_stage,
    stress_free_stage,
)
from breastmodel.pipeline.refinement import refinement_check
from breastmodel.pipeline.runner import Prepared, Runner, RunResult
from breastmodel.pipeline.subject_stages import (
    mesh_key,
    mesh_options,
    mesh_stage,
    problem_stage,
    reference_labels,
    register_stage,
    segment_stage,
    skins_stage,
)

log = logging.getLogger("breastmodel.pipeline")

__all__ = ["Prepared", "RunResult", "cache_of", "prepare_subject", "run_problem", "run_subject"]



def cache_of(run_dir: str | Path) -> Path:
    """The stage cache a finished run used (its own ``cache/`` unless it shared another)."""
    run_dir = Path(run_dir)
    stages = run_dir / "stages.json"
    if stages.is_file():
        c = json.loads(stages.read_text()).get("cache")
        if c:
            return Path(c)
    return run_dir / "cache"


# ---------------------------------------------------------------- the pipeline


def _check_subject(subject, cfg: Mapping[str, Any]) -> list[str]:
    positions = list(subject.positions)
    if len(positions) < 2:
        raise StageError("subject", f"the subject has only the position(s) {positions}; the "
                         "pipeline needs the reference and at least one other", subject.root)
    ev = cfg["evaluate"]["positions"]
    for p in ev or ():
        if p not in positions:
            raise StageError("subject", f"[evaluate] position {p!r} is missing from the "
                             f"subject (it has {positions})", subject.root / "subject.toml")
    for p in cfg["segment"].get("labels_positions") or ():
        if p not in positions:
            raise StageError("subject", f"[segment] labels_positions: position {p!r} is "
                             f"missing from the subject (it has {positions})",
                             subject.root / "subject.toml")
    for p in positions:
        src = given_labels(cfg["segment"], p)
        if src is not None and not src.is_file():
            raise StageError("segment", f"[segment] labels = {str(src.parent)!r} has no "
                             f"label map for position {p!r}", src)
    if cfg["register"].get("require_fiducials", True) and not subject.fiducials:
        raise StageError("register", "no fiducials.csv (or fiducials.mrk.json): rigid "
                         "registration is initialised from the fiducials; add them or set "
                         "[register] require_fiducials = false to initialise from image "
                         "moments", subject.root)
    return positions


def prepare_subject(subject_dir: str | Path, cfg: Mapping[str, Any], out: str | Path, *,
                    progress: bool = True, command: str = "run",
                    cache: str | Path | None = None) -> Prepared:
    """Run (or reuse) the stages up to the problem folder: segment every position, register,
    mesh the reference and extract every measured skin in the reference frame.

    Raises
    ------
    StageError
        The first stage that meets bad input (missing position volume, no fiducials, no
        breast in a segmentation...), naming the file and the problem.
    """
    from breastmodel.config import write_provenance
    from breastmodel.pipeline.register import with_threads
    from breastmodel.pipeline.segment import contrast_doubt
    from imaging.markups import markups_files
    from imaging.subject import SubjectError, read_subject
    from meshing.background import mesh_in_background

    out = Path(out)
    try:
        subject = read_subject(subject_dir)
    except SubjectError as exc:
        raise StageError("subject", str(exc)) from None
    positions = _check_subject(subject, cfg)
    out.mkdir(parents=True, exist_ok=True)
    write_provenance(out, {"subject": str(subject_dir), **cfg}, command=command)
    R = Runner(out, progress, cache)

    seg_cfg = {"preprocess": cfg["preprocess"], "segment": cfg["segment"]}
    ref, mesh_cfg = subject.reference, mesh_key(cfg["mesh"])
    seg_dirs, seg_keys, job = {}, {}, None
    with contextlib.ExitStack() as background:
        # the reference first: its mesh runs beside the other positions' segmentation and
        # the registration (a worker process on an adult volume)
        for pos in [ref, *(p for p in positions if p != ref)]:
            seg_dirs[pos], seg_keys[pos] = R.stage(
                "segment", {**seg_cfg, "position": pos}, _segment_inputs(subject, pos, cfg),
                segment_stage(subject, pos, seg_cfg), label=f"segment {pos}")
            _say_doubts(seg_dirs[pos], pos)
            if pos == ref and not R.done("mesh", mesh_cfg, [seg_keys[ref]]):
                job = background.enter_context(mesh_in_background(
                    reference_labels(seg_dirs, ref), **mesh_options(cfg)))
        if said := contrast_doubt(seg_dirs):
            log.warning("segment: %s", said)
        sub_files = [subject.root / "subject.toml"] + [
            subject.positions[p].volume_path for p in positions]
        if (subject.root / "fiducials.csv").is_file():
            sub_files.append(subject.root / "fiducials.csv")
        sub_files += markups_files(subject.root, positions)
        reg_dir, reg_key = R.stage("register", {"register": with_threads(cfg["register"])},
                                   [*(seg_keys[p] for p in positions), *sub_files],
                                   register_stage(subject, seg_dirs, cfg))
        skins_dir, skins_key = R.stage("skins", {"surface": cfg["surface"]}, [reg_key],
                                       skins_stage(subject, reg_dir, cfg), label="measured skins")
        mesh_dir, m_key = R.stage("mesh", mesh_cfg, [seg_keys[ref]],
                                     mesh_stage(reference_labels(seg_dirs, ref), mesh_options(cfg),
                                                job),
                                     label=f"mesh {ref}")
    lm = [subject.root / "landmarks.csv"] if (subject.root / "landmarks.csv").is_file() else []
    inputs = (reg_key, skins_key, *lm)
    prob_dir, prob_key = R.stage("problem", {}, [m_key, *inputs],
                                 problem_stage(subject, reg_dir, mesh_dir, skins_dir))
    return Prepared(subject, positions, R, prob_dir, prob_key, reg_dir, seg_dirs, inputs,
                    seg_keys)


def _say_doubts(seg_dir: Path, position: str) -> None:
    """Warn, on every run that uses it, where a position's segmentation doubted itself."""
    from breastmodel.pipeline.segment import read_confidence

    warnings = read_confidence(seg_dir, position).get("warnings") or []
    if warnings:
        log.warning("segment %s: %s (look at %s)", position, "; ".join(warnings),
                    Path(seg_dir) / f"{position}_qa.png")


def _segment_inputs(subject, pos: str, cfg: Mapping[str, Any]) -> list:
    """What a position's segmentation is keyed on: its volume, or its given label map."""
    src = given_labels(cfg["segment"], pos)
    return [src] if src is not None and src.is_file() else [subject.positions[pos].volume_path]


def run_subject(subject_dir: str | Path, cfg: Mapping[str, Any], out: str | Path, *,
                progress: bool = True, cache: str | Path | None = None) -> RunResult:
    """Run the cached pipeline of one subject.

    Parameters
    ----------
    subject_dir : subject folder (``subject.toml``, volumes, fiducials.csv, landmarks.csv)
    cfg : resolved run config (:func:`breastmodel.pipeline.config.resolve_config`)
    out : output folder; the stage cache lives in ``out/cache``
    progress : print one line per stage
    cache : another stage cache to use (model revisions of one subject share their
        segmentation, registration and mesh: ``breastmodel run --from``)

    Returns
    -------
    RunResult
        The stages with their status, the metrics and the parameters used.

    Raises
    ------
    StageError
        The first stage that meets bad input, naming the file and the problem.
    """
    t0 = time.perf_counter()
    prep = prepare_subject(subject_dir, cfg, out, progress=progress, cache=cache)
    return _model_stages(prep, cfg, Path(out), t0)


def run_problem(problem_dir: str | Path, cfg: Mapping[str, Any], out: str | Path, *,
                subject_id: str = "problem", progress: bool = True,
                cache: str | Path | None = None) -> RunResult:
    """The model half of the pipeline on a ready problem folder (mesh, gravity, measured
    skins: see :mod:`breastmodel.pipeline.problem`): [fit] -> stress-free -> predict ->
    outputs, cached like :func:`run_subject`. For synthetic measurements and tests."""
    from breastmodel.config import write_provenance

    t0 = time.perf_counter()
    out, problem_dir = Path(out), Path(problem_dir)
    meta = json.loads((problem_dir / "problem.json").read_text())
    out.mkdir(parents=True, exist_ok=True)
    write_provenance(out, {"subject": subject_id, **cfg}, command="run")
    R = Runner(out, progress, cache)

    def copy(d: Path) -> None:
        shutil.copytree(problem_dir, d, dirs_exist_ok=True)
    prob_dir, prob_key = R.stage("problem", {"copy_of": subject_id}, [problem_dir], copy,
                                 label="problem (given)")
    subject = _ProblemSubject(subject_id, meta["reference"])
    prep = Prepared(subject, list(meta["gravity"]), R, prob_dir, prob_key)
    return _model_stages(prep, cfg, out, t0)


@dataclass(frozen=True)
class _ProblemSubject:
    id: str
    reference: str


def _model_stages(prep: Prepared, cfg: Mapping[str, Any], out: Path, t0: float) -> RunResult:
    from breastmodel.config import write_json
    from breastmodel.pipeline.config import get_param, set_params
    from breastmodel.pipeline.outputs import write_outputs
    from breastmodel.pipeline.problem import fit_settings

    subject, positions, R = prep.subject, prep.positions, prep.runner
    prob_dir, prob_key = prep.problem_dir, prep.problem_key

    model = cfg["model"]
    fit_info = start = None
    starts_from = []  # the fit's key where its solution starts the stages below
    if cfg["fit"]["enabled"]:
        settings = fit_settings(cfg, positions, subject.reference)
        check_landmarks(prob_dir, settings)
        fit_dir, fit_key = R.stage("fit", {"settings": settings, "fit": {
            k: v for k, v in cfg["fit"].items() if k not in ("n_workers", "scheduler")}},
            [prob_key], fit_stage(prob_dir, cfg, settings, out, R.progress))
        fit_info = json.loads((fit_dir / "fit.json").read_text())
        model = set_params(model, fit_info["best"]["params"])
        start = fit_start(fit_dir)
        starts_from = [fit_key] if start is not None else []

    sf_cfg = {"model": model, "stress_free": cfg["stress_free"], "solver": cfg["solver"]}
    sf_dir, sf_key = R.stage("stress_free", sf_cfg, [prob_key, *starts_from],
                             stress_free_stage(prob_dir, cfg, model, R.progress, start),
                             label=f"stress-free ({cfg['stress_free']['method']})")
    pred_dirs = {}
    for pos in cfg["evaluate"]["positions"] or positions:
        pred_dirs[pos], _ = R.stage("predict", {"position": pos, "model": model,
                                                "solver": cfg["solver"]},
                                    [prob_key, sf_key, *starts_from],
                                    predict_stage(prob_dir, sf_dir, pos, cfg, model, start),
                                    label=f"predict {pos}")

    refinement = None
    if cfg["evaluate"]["refinement"]:
        refinement = refinement_check(prep, cfg, model, pred_dirs)

    paths = sorted({p for p in (cfg["fit"]["parameters"] or {})} | {
        f"materials.{r}.E" for r in model["materials"]})
    params = {"parameters": {p: get_param(model, p) for p in paths},
              "model": model, "fitted": fit_info is not None}
    if fit_info is not None:
        params["fit"] = {k: fit_info[k] for k in ("method", "best", "n_simulations",
                                                  "calibrate", "evaluate", "termination",
                                                  "uncertainty", "identifiability", "sees",
                                                  "optimum", "skin_offset_sensitivity")
                         if k in fit_info}
    result = write_outputs(out, prob_dir, sf_dir, pred_dirs, params, fit_info,
                           subject_id=subject.id, register_dir=prep.register_dir,
                           segment_dirs=prep.segment_dirs,
                           volumes={p: subject.positions[p].volume_path for p in positions}
                           if prep.register_dir is not None else None,
                           config=cfg, refinement=refinement)
    res = RunResult(stages=R.stages, metrics=result, params=params, out=str(out),
                    wall_s=time.perf_counter() - t0)
    write_json(out / "stages.json", {"stages": R.stages, "wall_s": res["wall_s"],
                                     "cache": str(R.cache_root)})
    return res
