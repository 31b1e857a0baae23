"""The validation suite: subjects whose truth another FE code computed, run through the whole
pipeline as a user would, with every stage's figure per subject.

Each subject is run in two *arms*:

``pipeline``
    everything as a user would run it: the project's segmentation, registration, meshing,
    fit of one breast modulus on the calibration positions, prediction of every position;
``truth_labels``
    the same with the truth label maps given (``[segment] labels``), which takes the
    segmentation out of the question and separates the stages.

A stage that stops is recorded with its error (the figures of the stages before it are
kept); it never stops the suite. :data:`TARGETS` lists the figures the open issues target:
each is checked and recorded; the enforced ones fail a test when missed.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("breastmodel.validation")

__all__ = ["ARMS", "TARGETS", "Target", "suite_config", "evaluate_subject", "check_targets",
           "summary_rows", "format_table", "run_suite", "family_maker"]

#: The arms each subject runs in.
ARMS = ("pipeline", "truth_labels")

#: The fitted parameter: one breast modulus for both breasts (the paper's single tissue).
FIT_PARAMETER = "materials.breast_left.E|materials.breast_right.E"


@dataclass(frozen=True)
class Target:
    """A figure an issue targets.

    figure : key of a subject's ``figures`` (``dice_breast_min``, ``tre_max_mm``, ...)
    bound : the bound, in the figure's unit
    kind : "max" (figure <= bound) or "min" (figure >= bound)
    arm : the arm whose figure is checked
    issue : the issue that targets it
    enforced : True once that issue has landed: a miss then fails the CI slice
    """

    figure: str
    bound: float
    kind: str
    arm: str
    issue: int
    enforced: bool = False

    def met(self, value: float | None) -> bool | None:
        if value is None or not np.isfinite(value):
            return None
        return bool(value <= self.bound) if self.kind == "max" else bool(value >= self.bound)


TARGETS: tuple[Target, ...] = (
    Target("completed", 1.0, "min", "pipeline", 14),
    Target("dice_breast_min", 0.95, "min", "pipeline", 14),
    Target("dice_muscle_min", 0.90, "min", "pipeline", 14),
    Target("tre_max_mm", 0.5, "max", "pipeline", 14),
    Target("rotation_error_max_deg", 0.3, "max", "pipeline", 14),
    Target("completed", 1.0, "min", "truth_labels", 15),
    Target("breast_E_rel_error", 0.10, "max", "truth_labels", 15),
    Target("mhd_calibrated_max_mm", 1.0, "max", "truth_labels", 15),
    Target("mhd_held_out_max_mm", 1.5, "max", "truth_labels", 15),
    Target("breast_E_rel_error", 0.10, "max", "pipeline", 15),
    Target("mhd_calibrated_max_mm", 1.0, "max", "pipeline", 15),
    Target("mhd_held_out_max_mm", 1.5, "max", "pipeline", 15),
)


# ------------------------------------------------------------------------------ config

def split_positions(positions: Sequence[str], reference: str) -> tuple[list[str], list[str]]:
    """(calibrated, held out): the reference and prone (else the first other position) are
    fitted, the rest is held out."""
    others = [p for p in positions if p != reference]
    first = "prone" if "prone" in others else (others[0] if others else None)
    calibrate = [reference] + ([first] if first else [])
    return calibrate, [p for p in positions if p not in calibrate]


def suite_config(arm: str, truth_dir: str | Path, positions: Sequence[str], reference: str,
                 *, mesh_size_mm: float = 8.0, E_start: float = 1.0,
                 E_muscle: float = 10.0) -> dict:
    """The resolved run config of one arm: the bulk model (Neo-Hookean breast and muscle,
    posterior chest wall fixed), least-squares fit of one breast modulus on the calibration
    positions, every position predicted.

    Parameters
    ----------
    arm : one of :data:`ARMS`
    truth_dir : the subject's truth folder (``<position>_labels.nii.gz``)
    positions, reference : the subject's positions and its reference
    mesh_size_mm : tet edge of the fitted model, mm
    E_start : starting breast modulus of the fit, kPa
    E_muscle : muscle modulus, kPa (held fixed)
    """
    from breastmodel.pipeline.config import resolve_config

    if arm not in ARMS:
        raise ValueError(f"validation: unknown arm {arm!r}; known {ARMS}")
    calibrate, held_out = split_positions(positions, reference)
    nh = {"name": "neo_hookean", "nu": 0.49}
    raw: dict[str, Any] = {
        "mesh": {"size_mm": float(mesh_size_mm)},
        "model": {"materials": {"breast_left": {**nh, "E": E_start},
                                "breast_right": {**nh, "E": E_start},
                                "muscle": {**nh, "E": E_muscle}},
                  "effects": {"fixed": {"node_set": "fixed"}}},
        "fit": {"enabled": True, "method": "least_squares", "calibrate": calibrate,
                "evaluate": held_out or None, "sensitivity": False,
                "parameters": {FIT_PARAMETER: {"min": 0.05, "max": 5.0}}},
    }
    if arm == "truth_labels":
        raw["segment"] = {"labels": str(Path(truth_dir).resolve())}
    return resolve_config(raw, where=f"validation ({arm})")


# ------------------------------------------------------------------------------ figures

def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def _stage_dir(out: Path, stage: Mapping[str, Any]) -> Path:
    return out / "cache" / stage["name"] / stage["key"]


def _dice(stages, out: Path, truth_dir: Path) -> dict[str, dict[str, float]]:
    from imaging.io import read_volume
    from imaging.qa import dice

    res = {}
    for st in stages:
        if st["name"] != "segment" or st["status"] == "failed":
            continue
        pos = st["label"].split(" ", 1)[1]
        mine = _stage_dir(out, st) / f"{pos}_labels.nii.gz"
        truth = truth_dir / f"{pos}_labels.nii.gz"
        if mine.is_file() and truth.is_file():
            res[pos] = {k: round(v, 4) for k, v in dice(read_volume(mine),
                                                        read_volume(truth)).items()}
    return res


def chest_wall_points(truth_dir: Path, reference: str, *, every: int = 97) -> np.ndarray:
    """(n, 3) physical points (mm) of the truth chest wall (label 2) in the reference image."""
    import SimpleITK as sitk

    from imaging.io import read_volume

    tl = read_volume(truth_dir / f"{reference}_labels.nii.gz")
    idx = np.argwhere(sitk.GetArrayViewFromImage(tl) == 2)[::every][:, ::-1]
    return np.asarray([tl.TransformContinuousIndexToPhysicalPoint(tuple(map(float, i)))
                       for i in idx]).reshape(-1, 3)


def _registration(stages, out: Path, truth_dir: Path, reference: str) -> dict[str, dict]:
    import SimpleITK as sitk

    from registration.transforms import read_transform, rigid_matrix, transform_points

    reg = next((s for s in stages if s["name"] == "register" and s["status"] != "failed"),
               None)
    if reg is None:
        return {}
    d = _stage_dir(out, reg)
    report = _read_json(d / "registration.json") or {}
    pts = chest_wall_points(truth_dir, reference)
    m_ref = sitk.ReadTransform(str(truth_dir / f"{reference}_motion.tfm"))
    res = {}
    for pos, entry in (report.get("positions") or {}).items():
        est = read_transform(d / f"{pos}.tfm")
        m_pos = sitk.ReadTransform(str(truth_dir / f"{pos}_motion.tfm"))
        truth_pts = transform_points(m_pos, transform_points(m_ref.GetInverse(), pts))
        tre = np.linalg.norm(transform_points(est, pts) - truth_pts, axis=1)
        r_est, _ = rigid_matrix(est)
        r_true = rigid_matrix(m_pos)[0] @ rigid_matrix(m_ref)[0].T
        c = (np.trace(r_true.T @ r_est) - 1.0) / 2.0
        fid = entry.get("fiducial_residuals_mm") or {}
        res[pos] = {"tre_mean_mm": round(float(tre.mean()), 4),
                    "tre_max_mm": round(float(tre.max()), 4),
                    "rotation_error_deg": round(float(np.degrees(np.arccos(np.clip(c, -1, 1)))),
                                                4),
                    "fiducial_residual_max_mm": (round(max(fid.values()), 3) if fid else None),
                    "warnings": list(entry.get("warnings") or [])}
    return res


def _truth_breast_E(truth_dir: Path) -> dict[str, float]:
    tm = _read_json(truth_dir / "truth_model.json") or {}
    mats = tm.get("materials") or {}
    out = {}
    for code, side in (("1", "left"), ("3", "right")):
        if code in mats and "E" in mats[code]:
            out[side] = float(mats[code]["E"])
    eff = (tm.get("effects") or {}).get("regions")
    if eff:  # the truth's regions effect sets each side's modulus
        out["left"] = float(eff.get("E_left", out.get("left", np.nan)))
        out["right"] = float(eff.get("E_right", out.get("right", np.nan)))
    return out


def _figures(arm: str, result: Mapping[str, Any], calibrate, held_out) -> dict[str, float]:
    """Flat figures of one arm (None where a stage did not get that far)."""
    f: dict[str, Any] = {"completed": 1.0 if result.get("error") is None else 0.0}
    dice = result.get("dice") or {}
    if dice:
        f["dice_breast_min"] = min(v.get("breast", np.nan) for v in dice.values())
        f["dice_muscle_min"] = min(v.get("muscle", np.nan) for v in dice.values())
    reg = result.get("registration") or {}
    if reg:
        f["tre_max_mm"] = max(v["tre_max_mm"] for v in reg.values())
        f["rotation_error_max_deg"] = max(v["rotation_error_deg"] for v in reg.values())
    fit = result.get("fitted") or {}
    truth = result.get("truth_E") or {}
    if fit.get("breast_E") is not None and truth:
        t = np.mean(list(truth.values()))
        f["breast_E_rel_error"] = abs(fit["breast_E"] - t) / t
    mhd = result.get("mhd_mm") or {}
    cal = [mhd[p] for p in calibrate if p in mhd]
    held = [mhd[p] for p in held_out if p in mhd]
    if cal:
        f["mhd_calibrated_max_mm"] = max(cal)
    if held:
        f["mhd_held_out_max_mm"] = max(held)
    return {k: (None if v is None or not np.isfinite(v) else round(float(v), 4))
            for k, v in f.items()}


def run_arm(subject_dir: str | Path, truth_dir: str | Path, out: str | Path, arm: str, *,
            mesh_size_mm: float = 8.0, progress: bool = False) -> dict[str, Any]:
    """Run one arm of one subject and collect its figures; a failing stage is recorded.

    Returns
    -------
    dict with ``arm``, ``error`` (None or the stage's message), ``failed_stage``,
    ``stages`` (name, label, status, wall_s), ``dice`` {position: {tissue: Dice}},
    ``registration`` {position: TRE, rotation error, fiducial residual, warnings},
    ``fitted`` {breast_E kPa, n_simulations}, ``truth_E`` {side: kPa}, ``mhd_mm``
    {position: MHD}, ``calibrate``, ``held_out``, ``figures`` (flat, see :data:`TARGETS`)
    and ``wall_s``.
    """
    from breastmodel.errors import StageError
    from breastmodel.pipeline.run import run_subject
    from imaging.subject import read_subject

    subject_dir, truth_dir, out = Path(subject_dir), Path(truth_dir), Path(out)
    subject = read_subject(subject_dir)
    positions, reference = list(subject.positions), subject.reference
    calibrate, held_out = split_positions(positions, reference)
    cfg = suite_config(arm, truth_dir, positions, reference, mesh_size_mm=mesh_size_mm)
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
        "truth_E": _truth_breast_E(truth_dir),
    }
    if arm == "pipeline":
        result["dice"] = _dice(stages, out, truth_dir)
    result["registration"] = _registration(stages, out, truth_dir, reference)
    params = _read_json(out / "params.json") if error is None else None
    if params:
        E = params["parameters"].get("materials.breast_left.E")
        fit = params.get("fit") or {}
        result["fitted"] = {"breast_E": E, "n_simulations": fit.get("n_simulations")}
    metrics = _read_json(out / "metrics.json") if error is None else None
    if metrics:
        result["mhd_mm"] = {p: m.get("mhd_mm") for p, m in metrics["positions"].items()}
        result["p95_mm"] = {p: m.get("p95_mm") for p, m in metrics["positions"].items()}
    result["wall_s"] = round(time.perf_counter() - t0, 2)
    result["figures"] = _figures(arm, result, calibrate, held_out)
    return result


def evaluate_subject(subject_dir: str | Path, truth_dir: str | Path, work_dir: str | Path, *,
                     arms: Iterable[str] = ARMS, mesh_size_mm: float = 8.0,
                     progress: bool = False) -> dict[str, Any]:
    """Every arm of one subject (see :func:`run_arm`), keyed by arm, with the targets."""
    work_dir = Path(work_dir)
    out = {"subject": Path(subject_dir).name, "arms": {}}
    for arm in arms:
        out["arms"][arm] = run_arm(subject_dir, truth_dir, work_dir / arm, arm,
                                   mesh_size_mm=mesh_size_mm, progress=progress)
    out["targets"] = check_targets(out)
    return out


def check_targets(result: Mapping[str, Any],
                  targets: Sequence[Target] = TARGETS) -> list[dict[str, Any]]:
    """Each target's value and verdict on one subject's result (``met`` None: no figure)."""
    rows = []
    for t in targets:
        arm = (result.get("arms") or {}).get(t.arm)
        if arm is None:
            continue
        v = arm["figures"].get(t.figure)
        rows.append({"figure": t.figure, "arm": t.arm, "bound": t.bound, "kind": t.kind,
                     "issue": t.issue, "enforced": t.enforced, "value": v, "met": t.met(v)})
    return rows


# ------------------------------------------------------------------------------ the suite

def run_suite(names: Sequence[str], make: Callable[[str, Path], tuple[Path, Path, dict]],
              work: str | Path, *, arms: Iterable[str] = ARMS, mesh_size_mm: float = 8.0,
              force: bool = False, progress: bool = False,
              on_result: Callable[[dict], None] | None = None) -> list[dict[str, Any]]:
    """Make and evaluate each subject; each result is written atomically to
    ``work/results/<name>.json`` and a rerun skips the finished ones (``force``: redo).

    Parameters
    ----------
    names : subject names (folder names under ``work/subjects``)
    make : ``make(name, folder) -> (subject_dir, truth_dir, info)``: writes (or finds) the
        subject; ``info`` (its description and the time it took) goes into the result. An
        exception is recorded as the subject's error.
    work : the suite's folder
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
                                   mesh_size_mm=mesh_size_mm, progress=progress)
            res.update(subject=name, info=info, make_s=make_s)
        write_json(path, res)
        results.append(res)
        if on_result is not None:
            on_result(res)
    return results


def family_maker(*, size: str = "small", febio: str | None = None,
                 cache: str | Path | None = None, **overrides):
    """``make(name, folder)`` for :func:`run_suite`: the subject of seed
    ``int(name.rsplit('-', 1)[-1])`` drawn from the phantom family
    (:func:`breastmodel.phantom.family.draw_spec` with ``overrides``), its truth computed by
    FEBio; a subject made before (marker ``folder/.made``) is reused."""
    from breastmodel.phantom.family import draw_spec, make_subject, spec_label
    from breastmodel.phantom.writer import truth_folder

    def make(name: str, folder: Path):
        seed = int(name.rsplit("-", 1)[-1])
        spec = draw_spec(seed, size=size, **overrides)
        done = Path(folder) / ".made"
        t0 = time.perf_counter()
        if not done.is_file():
            make_subject(spec, folder, truth_solver="febio", febio=febio, cache_dir=cache,
                         progress=False)
            done.write_text(json.dumps({"seed": seed}))
        return Path(folder), truth_folder(folder), {
            "seed": seed, "label": spec_label(spec), "spec": spec.to_dict(),
            "make_s": round(time.perf_counter() - t0, 2)}

    return make


# ------------------------------------------------------------------------------ tables

def _fmt(v, digits=2) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def _abbr(position: str) -> str:
    """Short position name for tables: initials of its words plus any number
    (``supine_tilted_30`` -> ``st30``, ``prone`` -> ``p``)."""
    parts = position.split("_")
    return "".join(p if p.isdigit() else p[0] for p in parts if p)


def summary_rows(res: Mapping[str, Any]) -> dict[str, str]:
    """One table row per subject and arm: the figures, per position where they differ."""
    rows = []
    info = res.get("info") or {}
    for arm, a in (res.get("arms") or {}).items():
        dice = a.get("dice") or {}
        reg = a.get("registration") or {}
        mhd = a.get("mhd_mm") or {}
        times = {}
        for st in a.get("stages") or []:
            times[st["name"]] = times.get(st["name"], 0.0) + float(st["wall_s"])
        E = (a.get("fitted") or {}).get("breast_E")
        truth = a.get("truth_E") or {}
        rows.append({
            "subject": res["subject"], "kind": str(info.get("label", "")), "arm": arm,
            "dice b/m": " ".join(f"{v.get('breast', np.nan):.3f}/{v.get('muscle', np.nan):.3f}"
                                 for v in dice.values()) or "-",
            "TRE mm": " ".join(f"{_abbr(p)} {v['tre_max_mm']:.2f}" for p, v in reg.items()) or "-",
            "rot deg": " ".join(f"{v['rotation_error_deg']:.2f}" for v in reg.values()) or "-",
            "E fit/truth kPa": (f"{E:.3f}/" if E is not None else "-/")
                               + "/".join(f"{v:.2f}" for v in truth.values()),
            "MHD cal mm": " ".join(f"{_abbr(p)} {mhd[p]:.2f}" for p in a.get("calibrate", [])
                                   if mhd.get(p) is not None) or "-",
            "MHD held mm": " ".join(f"{_abbr(p)} {mhd[p]:.2f}" for p in a.get("held_out", [])
                                    if mhd.get(p) is not None) or "-",
            "time s": " ".join(f"{k[:4]} {v:.0f}" for k, v in times.items()),
            "error": (a.get("error") or "")[:90],
        })
    if res.get("error"):
        rows.append({"subject": res["subject"], "kind": "", "arm": "-",
                     "error": res["error"][:90]})
    return rows


def format_table(results: Sequence[Mapping[str, Any]], *, markdown: bool = False) -> str:
    """The suite's table: one row per subject and arm."""
    rows = [r for res in results for r in summary_rows(res)]
    if not rows:
        return "(no results)"
    cols = ["subject", "kind", "arm", "dice b/m", "TRE mm", "rot deg", "E fit/truth kPa",
            "MHD cal mm", "MHD held mm", "time s", "error"]
    cells = [[_fmt(r.get(c, "")) for c in cols] for r in rows]
    if markdown:
        lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        lines += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in cells]
        return "\n".join(lines)
    width = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
    fmt = "  ".join(f"{{:<{w}}}" for w in width)
    return "\n".join([fmt.format(*cols)] + [fmt.format(*row) for row in cells])
