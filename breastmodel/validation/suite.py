"""Running the suite: each subject made, each arm run, results written and resumed."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from breastmodel.validation.figures import (
    arm_figures,
    dice_per_position,
    read_json,
    registration_figures,
    truth_breast_E,
)
from breastmodel.validation.targets import ARMS, EXTRA_ARMS, FIT_PARAMETER, check_targets

log = logging.getLogger("breastmodel.validation")


def split_positions(positions: Sequence[str], reference: str) -> tuple[list[str], list[str]]:
    """(calibrated, held out): the reference and prone (else the first other position) are
    fitted, the rest is held out."""
    others = [p for p in positions if p != reference]
    first = "prone" if "prone" in others else (others[0] if others else None)
    calibrate = [reference] + ([first] if first else [])
    return calibrate, [p for p in positions if p not in calibrate]


def suite_config(arm: str, truth_dir: str | Path, positions: Sequence[str], reference: str,
                 *, mesh_size_mm: float | str = "auto", E_start: float = 1.0,
                 E_muscle: float = 10.0,
                 effects: Mapping[str, Mapping[str, Any] | None] | None = None,
                 register: Mapping[str, Any] | None = None) -> dict:
    """The resolved run config of one arm: the bulk model (Neo-Hookean breast and muscle,
    posterior chest wall fixed, and where the scan cut it: ``cut_faces``), least-squares fit
    of one breast modulus on the calibration positions, every position predicted.

    Parameters
    ----------
    arm : one of :data:`ARMS` or :data:`EXTRA_ARMS`
    truth_dir : the subject's truth folder (``<position>_labels.nii.gz``)
    positions, reference : the subject's positions and its reference
    mesh_size_mm : tet edge of the fitted model, mm, or "auto" (the pipeline's default)
    E_start : starting breast modulus of the fit, kPa
    E_muscle : muscle modulus, kPa (held fixed)
    effects : effect key -> table replacing the bulk model's, or None leaving it out (a
        study's variant of the model, e.g. ``bench/cut_faces.py``)
    register : ``[register]`` keys over the run's defaults (e.g. ``require_fiducials``)
    """
    from breastmodel.pipeline.config import resolve_config

    if arm not in ARMS + EXTRA_ARMS:
        raise ValueError(f"validation: unknown arm {arm!r}; known {ARMS + EXTRA_ARMS}")
    calibrate, held_out = split_positions(positions, reference)
    nh = {"name": "neo_hookean", "nu": 0.49}
    raw: dict[str, Any] = {
        "mesh": {"size_mm": mesh_size_mm if mesh_size_mm == "auto" else float(mesh_size_mm)},
        "model": {"materials": {"breast_left": {**nh, "E": E_start},
                                "breast_right": {**nh, "E": E_start},
                                "muscle": {**nh, "E": E_muscle}},
                  "effects": {"fixed": {"node_set": "fixed"}, "cut_faces": {}}},
        "fit": {"enabled": True, "method": "least_squares", "calibrate": calibrate,
                "evaluate": held_out or None, "sensitivity": False,
                "parameters": {FIT_PARAMETER: {"min": 0.05, "max": 5.0}}},
    }
    for key, table in (effects or {}).items():
        if table is None:
            raw["model"]["effects"].pop(key, None)
        else:
            raw["model"]["effects"][key] = dict(table)
    if register:
        raw["register"] = dict(register)
    if arm == "truth_labels":
        raw["segment"] = {"labels": str(Path(truth_dir).resolve())}
    elif arm == "reference_truth":
        raw["segment"] = {"labels": str(Path(truth_dir).resolve()),
                          "labels_positions": [reference]}
    return resolve_config(raw, where=f"validation ({arm})")


def run_arm(subject_dir: str | Path, truth_dir: str | Path, out: str | Path, arm: str, *,
            mesh_size_mm: float | str = "auto", progress: bool = False,
            effects: Mapping[str, Mapping[str, Any] | None] | None = None,
            register: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Run one arm of one subject and collect its figures; a failing stage is recorded.
    ``effects`` changes the bulk model, ``register`` the registration's keys (see
    :func:`suite_config`).

    Returns
    -------
    dict with ``arm``, ``error`` (None or the stage's message), ``failed_stage``,
    ``stages`` (name, label, status, wall_s), ``dice`` {position: {tissue: Dice}},
    ``registration`` {position: TRE, rotation error, fiducial residual, warnings},
    ``fitted`` {breast_E kPa, n_simulations}, ``truth_E`` {side: kPa}, ``mhd_mm``
    {position: MHD}, ``field_of_view`` (the reference's breasts on its cut planes,
    :func:`meshing.field_of_view.breast_cut`, and the warning), ``calibrate``,
    ``held_out``, ``figures`` (flat, see :data:`TARGETS`) and ``wall_s``.
    """
    from breastmodel.errors import StageError
    from breastmodel.pipeline.run import run_subject
    from imaging.subject import read_subject

    subject_dir, truth_dir, out = Path(subject_dir), Path(truth_dir), Path(out)
    subject = read_subject(subject_dir)
    positions, reference = list(subject.positions), subject.reference
    calibrate, held_out = split_positions(positions, reference)
    cfg = suite_config(arm, truth_dir, positions, reference, mesh_size_mm=mesh_size_mm,
                       effects=effects, register=register)
    t0 = time.perf_counter()
    error = failed = None
    try:
        res = run_subject(subject_dir, cfg, out, progress=progress)
        stages = res["stages"]
    except (StageError, RuntimeError, ValueError, OSError) as exc:
        stages = getattr(exc, "stages", [])
        error = f"{type(exc).__name__}: {exc}"
        failed = getattr(exc, "stage", None) or next(
            (s["name"] for s in stages if s["status"] == "failed"), None)
        log.warning("validation: %s [%s] stopped: %s", subject_dir.name, arm, error)
    result: dict[str, Any] = {
        "arm": arm, "error": error, "failed_stage": failed,
        "stages": stages, "calibrate": calibrate, "held_out": held_out,
        "truth_E": truth_breast_E(truth_dir),
    }
    if arm == "pipeline":
        result["dice"] = dice_per_position(stages, out, truth_dir)
    result["registration"] = registration_figures(stages, out, truth_dir, reference)
    params = read_json(out / "params.json") if error is None else None
    if params:
        E = params["parameters"].get("materials.breast_left.E")
        fit = params.get("fit") or {}
        result["fitted"] = {"breast_E": E, "n_simulations": fit.get("n_simulations")}
    metrics = read_json(out / "metrics.json") if error is None else None
    if metrics:
        result["mhd_mm"] = {p: m.get("mhd_mm") for p, m in metrics["positions"].items()}
        result["p95_mm"] = {p: m.get("p95_mm") for p, m in metrics["positions"].items()}
        result["mhd_overlap_mm"] = {p: m.get("mhd_overlap_mm")
                                    for p, m in metrics["positions"].items()}
        result["field_of_view"] = (metrics.get("mesh") or {}).get("field_of_view")
    result["wall_s"] = round(time.perf_counter() - t0, 2)
    result["figures"] = arm_figures(arm, result, calibrate, held_out)
    return result


def evaluate_subject(subject_dir: str | Path, truth_dir: str | Path, work_dir: str | Path, *,
                     arms: Iterable[str] = ARMS, mesh_size_mm: float | str = "auto",
                     progress: bool = False,
                     register: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Every arm of one subject (see :func:`run_arm`), keyed by arm, with the targets."""
    work_dir = Path(work_dir)
    out = {"subject": Path(subject_dir).name, "arms": {}}
    for arm in arms:
        out["arms"][arm] = run_arm(subject_dir, truth_dir, work_dir / arm, arm,
                                   mesh_size_mm=mesh_size_mm, progress=progress,
                                   register=register)
    out["targets"] = check_targets(out)
    return out


def run_suite(names: Sequence[str], make: Callable[[str, Path], tuple[Path, Path, dict]],
              work: str | Path, *, arms: Iterable[str] = ARMS, mesh_size_mm: float | str = "auto",
              force: bool = False, progress: bool = False,
              on_result: Callable[[dict], None] | None = None,
              register: Mapping[str, Any] | None = None) -> list[dict[str, Any]]:
    """Make and evaluate each subject; each result is written atomically to
    ``work/results/<name>.json`` and a rerun skips the finished ones (``force``: redo).

    Parameters
    ----------
    names : subject names (folder names under ``work/subjects``)
    make : ``make(name, folder) -> (subject_dir, truth_dir, info)``: writes (or finds) the
        subject; ``info`` (its description and the time it took) goes into the result. An
        exception is recorded as the subject's error.
    work : the suite's folder
    register : ``[register]`` keys over the run's defaults, every subject and arm
    """
    from breastmodel.config import write_json

    work = Path(work)
    (work / "results").mkdir(parents=True, exist_ok=True)
    results = []
    for name in names:
        path = work / "results" / f"{name}.json"
        if path.is_file() and not force:
            results.append(json.loads(path.read_text()))
            log.info("validation: %s done already", name)
            continue
        t0 = time.perf_counter()
        try:
            subject_dir, truth_dir, info = make(name, work / "subjects" / name)
        except Exception as exc:  # a subject that cannot be made is a row, not a crash
            res = {"subject": name, "error": f"make: {type(exc).__name__}: {exc}", "arms": {},
                   "targets": [], "make_s": round(time.perf_counter() - t0, 2)}
        else:
            make_s = round(time.perf_counter() - t0, 2)
            res = evaluate_subject(subject_dir, truth_dir, work / "runs" / name, arms=arms,
                                   mesh_size_mm=mesh_size_mm, progress=progress,
                                   register=register)
            res.update(subject=name, info=info, make_s=make_s)
        write_json(path, res)
        results.append(res)
        if on_result is not None:
            on_result(res)
    return results


def spec_label(spec) -> str:
    """A short description of a family subject for tables: field of view, cup, voxels,
    contrast, SNR, tilt and hidden physics (``slab C 0.5x0.5x0.6 t1-fs snr22 t30 bulk``)."""
    vox = "x".join(f"{v:g}" for v in spec.voxel_size)
    tilt = next((p.rsplit("_", 1)[-1] for p in spec.positions if "tilted" in p), "-")
    return (f"{spec.fov} {spec.cup} {vox} {spec.contrast}{'-fs' if spec.fat_suppressed else ''}"
            f" snr{spec.snr:.0f} t{tilt} {spec.physics}")


def family_maker(*, size: str = "small", febio: str | None = None,
                 cache: str | Path | None = None, **overrides):
    """``make(name, folder)`` for :func:`run_suite`: the subject of seed
    ``int(name.rsplit('-', 1)[-1])`` drawn from the phantom family
    (:func:`breastmodel.phantom.family.draw_spec` with ``overrides``), its truth computed by
    FEBio. A subject made before is reused only when its marker ``folder/.made`` holds the
    same spec (a changed family draws another subject, which is made anew)."""
    from breastmodel.phantom.family import draw_spec, make_subject
    from breastmodel.phantom.writer import truth_folder

    def make(name: str, folder: Path):
        seed = int(name.rsplit("-", 1)[-1])
        spec = draw_spec(seed, size=size, **overrides)
        done = Path(folder) / ".made"
        t0 = time.perf_counter()
        made = read_json(done) if done.is_file() else None
        if made != spec.to_dict():
            done.unlink(missing_ok=True)
            make_subject(spec, folder, truth_solver="febio", febio=febio, cache_dir=cache,
                         progress=False)
            done.write_text(json.dumps(spec.to_dict()))
        return Path(folder), truth_folder(folder), {
            "seed": seed, "label": spec_label(spec), "spec": spec.to_dict(),
            "make_s": round(time.perf_counter() - t0, 2)}

    return make
