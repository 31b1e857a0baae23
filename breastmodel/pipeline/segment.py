"""Segmentation of a subject's positions, the library side of ``breastmodel segment``
(:mod:`breastmodel.commands.segment` documents the files and the config): per position the
label map, QA picture, tissue volumes and the segmentation's own confidence, each written
atomically, ``segmentation.json`` merged per position."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

log = logging.getLogger("breastmodel.segment")

PREPROCESS_KEYS = {"n4", "n4_shrink", "isotropic_mm", "denoise_iterations", "denoise_method"}
SEGMENT_KEYS = {"gland", "skin_level", "levelset_iterations", "curvature",
                "marker_diameter_mm", "min_region_mm3", "positions", "contrast",
                "stop_below_agreement"}
#: ``[segment]`` keys of the stage itself, not of :func:`imaging.segment.segment_volume`.
_STAGE_KEYS = {"positions", "stop_below_agreement"}
#: Agreement (Dice) of a region's two estimates below which the segmentation stops. On the
#: validation suite's 33 scans (bench/segment_suite.py) the agreements of scans that met
#: the Dice targets were 0.94-1.00; the muscles of the 2 mm, SNR 13 coil subject's three
#: scans (muscle Dice 0.24-0.40) agreed to 0.23-0.37, and its pipeline went on to fail in
#: the fit.
STOP_BELOW_AGREEMENT = 0.5


def read_config(path: Path | None) -> dict[str, dict[str, Any]]:
    """Read and check the [preprocess] and [segment] tables (missing file section: {})."""
    from breastmodel.config import check_keys, load_toml

    if path is None:
        return {"preprocess": {}, "segment": {}}
    raw = load_toml(path, stage="segment")
    pre = dict(raw.get("preprocess", {}))
    seg = dict(raw.get("segment", {}))
    check_keys(pre, PREPROCESS_KEYS, where=f"segment: {path} [preprocess]")
    check_keys(seg, SEGMENT_KEYS, where=f"segment: {path} [segment]")
    return {"preprocess": pre, "segment": seg}


def read_seeds(path: Path) -> dict[str, list]:
    """Seeds CSV -> {position: [Seed, ...]}; one clear error for a malformed row."""
    import csv

    from imaging.segment import Seed

    if not path.is_file():
        raise FileNotFoundError(f"segment: seeds file {path} does not exist")
    out: dict[str, list] = {}
    with path.open(newline="") as f:
        for i, row in enumerate(csv.DictReader(f), start=2):
            try:
                seed = Seed(int(row["label"]), (float(row["x"]), float(row["y"]),
                                                float(row["z"])))
                out.setdefault(row["position"].strip(), []).append(seed)
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"segment: {path} line {i}: expected columns "
                                 "position,label,x,y,z with numbers") from None
    return out


def segment_position(
    subject,
    position: str,
    out: Path,
    *,
    seeds: Sequence = (),
    preprocess_options: Mapping[str, Any] | None = None,
    segment_options: Mapping[str, Any] | None = None,
    truth: Path | None = None,
) -> dict[str, Any]:
    """Segment one position and write its label map and QA picture; return its summary.

    Parameters
    ----------
    subject : imaging.subject.Subject
        The subject (from :func:`imaging.subject.read_subject`).
    position : str
        Position name.
    out : Path
        Output folder.
    seeds : sequence of imaging.segment.Seed
        User seeds for this position.
    preprocess_options, segment_options : mapping
        Keyword options of :func:`imaging.segment.segment_volume`.
    truth : Path, optional
        Folder with ``<position>_labels.nii.gz`` for Dice.

    Returns
    -------
    dict
        volumes_ml, breast volumes by side, levels, notes, and dice when truth is given.
    """
    from imaging.io import read_volume, write_volume
    from imaging.qa import dice, qa_figure, save_figure, tissue_volumes_ml
    from imaging.segment import breast_volumes_by_side, segment_volume

    opts = dict(preprocess_options or {})
    opts.update({k: v for k, v in (segment_options or {}).items() if k not in _STAGE_KEYS})
    stop = float((segment_options or {}).get("stop_below_agreement", STOP_BELOW_AGREEMENT))
    img = subject.load(position)
    res = segment_volume(img, seeds=list(seeds), name=str(subject.positions[position].volume_path),
                         **opts)
    out.mkdir(parents=True, exist_ok=True)
    write_volume(res.labels, out / f"{position}_labels.nii.gz")
    pts = [s.point for s in seeds]
    fig = qa_figure(img, res.labels, seeds=pts or None, title=f"{subject.id} {position}")
    save_figure(fig, out / f"{position}_qa.png")
    summary: dict[str, Any] = {
        "labels": f"{position}_labels.nii.gz",
        "qa": f"{position}_qa.png",
        "volumes_ml": tissue_volumes_ml(res.labels),
        "breast_by_side_ml": breast_volumes_by_side(res.labels, res.midline_x_mm),
        "midline_x_mm": res.midline_x_mm,
        "levels": res.levels,
        "markers_removed": len(res.markers_mm),
        "seeds": [{"label": s.label, "point_mm": list(s.point)} for s in seeds],
        "notes": list(res.notes),
        "confidence": res.confidence,
        "contrast": res.contrast,
    }
    _stop_if_it_does_not_hold(res, summary, out, stop, img_path=subject.positions[position]
                              .volume_path)
    if truth is not None:
        tpath = Path(truth) / f"{position}_labels.nii.gz"
        if tpath.is_file():
            summary["dice"] = dice(res.labels, read_volume(tpath))
        else:
            log.warning("segment: no truth label map %s; Dice skipped", tpath)
    return summary


def _stop_if_it_does_not_hold(res, summary, out: Path, stop: float, *, img_path) -> None:
    """Stop (after the label map and QA picture are written, for a look) when a region's
    two estimates agree below ``stop`` (0: never), the breast volume is implausible or the
    breast tissue lies behind the chest wall (a contrast read wrong)."""
    from breastmodel.errors import StageError

    conf = res.confidence
    low = {k: v for k, v in conf.get("agreement", {}).items() if v < stop}
    bad = [f"the {k}'s active contour and its threshold start agree only to Dice {v:.2f} "
           f"(< {stop:g})" for k, v in low.items()]
    if stop > 0 and not conf.get("breast_ml_plausible", True):
        bad.append(f"{conf['breast_ml']:.1f} ml of breast tissue is not plausible")
    if stop > 0 and not conf.get("breast_in_front", True):
        bad.append(f"the breast tissue lies {conf['breast_behind_wall_mm']:.1f} mm behind the "
                   "chest wall")
    if bad:
        raise StageError(
            "segment", "the segmentation does not hold up: " + "; ".join(bad)
            + f" (contrast {res.contrast}; look at {out / summary['qa']}). Give seeds "
            "(--seeds), declare [segment] contrast, or set [segment] stop_below_agreement "
            "= 0 to go on with it", img_path)


def read_confidence(out: Path, position: str) -> dict[str, Any]:
    """A position's confidence from ``out/segmentation.json`` (:func:`update_summary`): its
    regions' agreement, the warnings, ``confident``; {} where none was written (a label map
    given, not segmented)."""
    return dict(_entry(out, position).get("confidence") or {})


def _entry(out: Path, position: str) -> dict[str, Any]:
    """A position's summary in ``out/segmentation.json``; {} where none was written."""
    path = Path(out) / "segmentation.json"
    if not path.is_file():
        return {}
    return json.loads(path.read_text()).get("positions", {}).get(position) or {}


def contrast_doubt(seg_dirs: Mapping[str, Path]) -> str:
    """:func:`imaging.segment_contrast.contrast_disagreement` of the positions segmented in
    ``seg_dirs`` (``{position: its folder}``): "" where their scans read alike."""
    return _contrast_doubt({pos: _entry(folder, pos) for pos, folder in seg_dirs.items()})


def _contrast_doubt(entries: Mapping[str, Mapping[str, Any]]) -> str:
    """:func:`contrast_doubt` of the positions' summaries ``entries``."""
    from imaging.segment_contrast import contrast_disagreement

    return contrast_disagreement({pos: e["contrast"] for pos, e in entries.items()
                                  if e.get("contrast")})


def _doubted(conf: Mapping[str, Any], said: str) -> dict[str, Any]:
    """A segmented position's confidence ``conf`` not confident and saying ``said`` (once);
    as it is where nothing is said or nothing was segmented."""
    warnings = list(conf.get("warnings") or [])
    if not said or not conf or said in warnings:
        return dict(conf)
    return {**conf, "confident": False, "warnings": [*warnings, said]}


def read_confidences(seg_dirs: Mapping[str, Path]) -> dict[str, dict[str, Any]]:
    """Each position's :func:`read_confidence` from its folder in ``seg_dirs``; where the
    segmented positions' scans read different contrasts (:func:`contrast_doubt`), each of
    them is not confident and says so."""
    entries = {pos: _entry(folder, pos) for pos, folder in seg_dirs.items()}
    said = _contrast_doubt(entries)
    return {pos: _doubted(e.get("confidence") or {}, said) for pos, e in entries.items()}


def update_summary(out: Path, position: str, summary: Mapping[str, Any]) -> None:
    """Merge one position's summary into ``out/segmentation.json`` (atomic)."""
    from breastmodel.config import write_json

    path = out / "segmentation.json"
    data = {}
    if path.is_file():
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError:
            log.warning("segment: %s was unreadable; starting it afresh", path)
    data.setdefault("positions", {})[position] = dict(summary)
    write_json(path, data)


def segment_subject(
    subject_dir: Path,
    out: Path,
    *,
    truth: Path | None = None,
    config: Path | None = None,
    positions: Sequence[str] | None = None,
    seeds: Mapping[str, Sequence] | None = None,
    gland: bool | None = None,
) -> dict[str, Any]:
    """Segment the positions of a subject folder into ``out``; return the summaries."""
    from breastmodel.config import write_provenance
    from imaging.subject import read_subject

    cfg = read_config(config)
    if gland is not None:
        cfg["segment"]["gland"] = gland
    subject = read_subject(subject_dir)
    names = list(positions or cfg["segment"].get("positions") or subject.positions)
    unknown = sorted(set(names) - set(subject.positions))
    if unknown:
        raise ValueError(f"segment: {subject_dir}: unknown position(s) {unknown}; "
                         f"the subject has {sorted(subject.positions)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_provenance(out, {**cfg, "subject": str(subject_dir),
                           "truth": str(truth) if truth else None}, command="segment")
    results = {}
    for name in names:
        log.info("segment: %s", name)
        summary = segment_position(
            subject, name, out, seeds=(seeds or {}).get(name, ()),
            preprocess_options=cfg["preprocess"], segment_options=cfg["segment"], truth=truth,
        )
        update_summary(out, name, summary)
        results[name] = summary
        if "dice" in summary:
            log.info("segment: %s Dice %s", name,
                     {k: round(v, 4) for k, v in summary["dice"].items()})
    said = _contrast_doubt(results)
    if said:  # every position's confidence says so, in segmentation.json too
        log.warning("segment: %s", said)
        for name, summary in results.items():
            summary["confidence"] = _doubted(summary["confidence"], said)
            update_summary(out, name, summary)
    return results
