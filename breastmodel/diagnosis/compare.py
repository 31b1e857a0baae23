"""Compare runs of one subject (model revisions, e.g. before and after adding an effect).

:func:`compare_runs` reads the runs' metrics and models into a JSON-ready summary;
:func:`write_compare` also writes ``compare.json`` and a self-contained ``compare.html``
(per-position MHD table, MHD against model revision, error maps side by side on one shared
colour scale, per-region RMSE). Runs must share the subject and the mesh, so that the same
skin node and the same region mean the same tissue in every run.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.errors import StageError

__all__ = ["METRICS", "compare_runs", "format_table", "model_changes", "write_compare"]

#: metrics.json keys compared per position (mm)
METRICS = ("mhd_mm", "rmse_mm", "p95_mm")


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, Mapping):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def _fmt_value(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def model_changes(before: Mapping[str, Any], after: Mapping[str, Any]) -> list[str]:
    """What changed from one ``[model]`` table to the next, in words.

    Returns
    -------
    list of str
        ``"+ effect"`` / ``"- effect"`` for effects switched on / off, ``"path: a -> b"``
        for changed values (effect parameters, materials, formulation, density, g).
    """
    eb, ea = dict(before.get("effects") or {}), dict(after.get("effects") or {})
    out = [f"+ {k}" for k in ea if k not in eb] + [f"- {k}" for k in eb if k not in ea]
    rest_b = {k: v for k, v in before.items() if k != "effects"}
    rest_a = {k: v for k, v in after.items() if k != "effects"}
    rest_b["effects"] = {k: v for k, v in eb.items() if k in ea}
    rest_a["effects"] = {k: v for k, v in ea.items() if k in eb}
    fb, fa = _flat(rest_b), _flat(rest_a)
    for k in sorted(set(fb) | set(fa)):
        a, b = fb.get(k, "-"), fa.get(k, "-")
        if a != b:
            out.append(f"{k}: {_fmt_value(a)} -> {_fmt_value(b)}")
    return out


def _check_same(runs: Sequence[Any]) -> None:
    first = runs[0]
    mesh0 = first.problem.mesh
    for r in runs[1:]:
        if r.subject != first.subject:
            raise StageError("compare", f"the runs are of different subjects: "
                             f"{first.subject!r} ({first.out}) and {r.subject!r}", r.out)
        mesh = r.problem.mesh
        if (mesh.n_nodes != mesh0.n_nodes or mesh.n_tets != mesh0.n_tets
                or not np.array_equal(mesh.tets, mesh0.tets)
                or not np.allclose(mesh.nodes, mesh0.nodes, atol=1e-9)):
            raise StageError("compare", f"the runs use different meshes ({mesh0.n_nodes} "
                             f"nodes in {first.out}, {mesh.n_nodes} here); compare runs "
                             "that share the mesh stage", r.out)


def _delta(vals: list, ref: list) -> list:
    return [None if v is None or r is None else v - r for v, r in zip(vals, ref)]


def _get(m: Mapping[str, Any], key: str) -> float | None:
    v = m.get(key)
    return None if v is None or not math.isfinite(float(v)) else float(v)


def compare_runs(dirs: Sequence[str | Path], *, labels: Sequence[str] | None = None,
                 runs: Sequence[Any] | None = None) -> dict:
    """JSON-ready comparison of runs of one subject, in the given order.

    Parameters
    ----------
    dirs : run folders (``breastmodel run --out``), oldest model revision first
    labels : one x-axis label per run; default: the first run's folder name, then what
        changed in the model from the previous run (:func:`model_changes`)
    runs : the loaded runs (:func:`breastmodel.diagnosis.load_run`), when already at hand

    Returns
    -------
    dict
        ``subject``; ``runs``: [{``dir``, ``label``, ``changes``, ``effects`` (name ->
        parameters), ``materials``, ``parameters``, ``fitted``}]; ``positions``: the
        positions every run predicted, each ``{metric: {"values", "delta_previous",
        "delta_first"}}`` for ``mhd_mm``, ``rmse_mm``, ``p95_mm`` (mm; deltas are run minus
        previous run / minus the first run, None where undefined); ``mean``: the same for
        the mean over those positions; ``missing``: positions some run lacks.

    Raises
    ------
    StageError
        A folder is not a finished run, or the runs differ in subject or mesh.
    """
    from breastmodel.diagnosis.rundata import load_run

    if len(dirs) < 2 and runs is None:
        raise StageError("compare", "give at least two run folders")
    runs = list(runs) if runs is not None else [load_run(d) for d in dirs]
    _check_same(runs)
    positions = [p for p in runs[0].metrics["positions"]
                 if all(p in r.metrics["positions"] for r in runs)]
    if not positions:
        raise StageError("compare", "the runs have no predicted position in common")
    allpos = {p for r in runs for p in r.metrics["positions"]}
    if labels is not None and len(labels) != len(runs):
        raise StageError("compare", f"{len(labels)} labels for {len(runs)} runs")
    rows = []
    for i, r in enumerate(runs):
        params = _params(r)
        changes = [] if i == 0 else model_changes(runs[i - 1].model, r.model)
        label = (labels[i] if labels is not None else
                 Path(r.out).name if i == 0 else
                 ", ".join(changes) if changes else "no model change")
        rows.append({"dir": str(r.out), "label": label, "changes": changes,
                     "effects": dict(r.model.get("effects") or {}),
                     "materials": dict(r.model.get("materials") or {}),
                     "parameters": params.get("parameters", {}),
                     "fitted": bool(params.get("fitted", False))})
    table: dict[str, Any] = {}
    for p in positions:
        table[p] = {}
        for k in METRICS:
            vals = [_get(r.metrics["positions"][p], k) for r in runs]
            table[p][k] = {"values": vals, "delta_previous": [None, *_delta(vals[1:], vals)],
                           "delta_first": _delta(vals, [vals[0]] * len(vals))}
    mean = {}
    for k in METRICS:
        vals = [None if any(table[p][k]["values"][i] is None for p in positions)
                else float(np.mean([table[p][k]["values"][i] for p in positions]))
                for i in range(len(runs))]
        mean[k] = {"values": vals, "delta_previous": [None, *_delta(vals[1:], vals)],
                   "delta_first": _delta(vals, [vals[0]] * len(vals))}
    return {"subject": runs[0].subject, "units": "mm", "runs": rows, "positions": table,
            "mean": mean, "missing": sorted(allpos - set(positions))}


def _params(run) -> dict:
    import json

    path = Path(run.out) / "params.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def format_table(summary: Mapping[str, Any]) -> str:
    """A short plain-text table of MHD per position and run (mm) with the change from the
    first run."""
    runs = summary["runs"]
    head = f"{'position':>14} " + " ".join(f"{'run ' + str(i + 1):>9}" for i in range(len(runs)))
    head += f" {'last-first':>10}"
    lines = [head]
    rows = {**summary["positions"], "mean": summary["mean"]}
    for p, t in rows.items():
        v = t["mhd_mm"]["values"]
        d = t["mhd_mm"]["delta_first"][-1]
        lines.append(f"{p:>14} " + " ".join(f"{x:9.3f}" if x is not None else f"{'-':>9}"
                                            for x in v)
                     + (f" {d:+10.3f}" if d is not None else f" {'-':>10}"))
    lines.append("MHD, mm. Runs:")
    lines += [f"  run {i + 1}: {r['label']}  ({r['dir']})" for i, r in enumerate(runs)]
    return "\n".join(lines)


def _cell(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3f}" if math.isfinite(v) else "nan"
    return html.escape(str(v))


def _html_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def write_compare(dirs: Sequence[str | Path], out: str | Path, *,
                  labels: Sequence[str] | None = None,
                  views: Sequence[str] = ("anterior", "lateral", "inferior")) -> dict:
    """Compare runs and write ``out/compare.json`` and ``out/compare.html``.

    The error maps of every run and position share one symmetric colour scale; the skin
    regions of the per-region table are those of the first run's stress-free geometry,
    applied to every run. Returns the :func:`compare_runs` summary plus ``regions``
    (position -> region -> ``{"rmse_mm", "mean_signed_mm"}``: one value per run, mm) and
    ``colour_limit_mm``.
    """
    from breastmodel.config import write_atomic, write_json
    from breastmodel.diagnosis.maps import failure_map, region_stats, skin_regions
    from breastmodel.diagnosis.rundata import load_run
    from breastmodel.diagnosis.views import (
        error_limit,
        error_maps_figure,
        img_tag,
        revision_figure,
    )

    if len(dirs) < 2:
        raise StageError("compare", "give at least two run folders")
    runs = [load_run(d) for d in dirs]
    summary = compare_runs(dirs, labels=labels, runs=runs)
    positions = list(summary["positions"])
    regions = skin_regions(runs[0].problem.mesh, runs[0].X[:runs[0].problem.mesh.n_nodes])
    maps = [{p: failure_map(r, p, regions=regions) for p in positions} for r in runs]
    masks = {"all": np.ones(len(next(iter(regions.values()))), bool), **regions}
    summary["regions"] = {
        p: {k: {stat: [region_stats(m[p], mask)[stat] for m in maps]
                for stat in ("rmse_mm", "mean_signed_mm")}
            for k, mask in masks.items()} for p in positions}
    limit = error_limit(fm for m in maps for fm in m.values())
    summary["colour_limit_mm"] = limit
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "compare.json", summary)

    tags = [f"run {i + 1}" for i in range(len(runs))]
    rl = summary["runs"]
    parts = [f"<h1>breastmodel compare: {html.escape(str(summary['subject']))}</h1>",
             "<h2>Runs</h2>",
             _html_table(["run", "folder", "what changed", "effects", "fitted"],
                         [[t, r["dir"], r["label"] if i else "(baseline) " + r["label"],
                           ", ".join(r["effects"]) or "-", r["fitted"]]
                          for i, (t, r) in enumerate(zip(tags, rl))])]
    for k, name in (("mhd_mm", "MHD"), ("rmse_mm", "RMSE"), ("p95_mm", "p95")):
        rows = [[p, *t[k]["values"], t[k]["delta_first"][-1]]
                for p, t in {**summary["positions"], "mean": summary["mean"]}.items()]
        parts += [f"<h2>{name} per position (mm)</h2>",
                  _html_table(["position", *tags, f"{tags[-1]} - {tags[0]}"], rows)]
    xl = [f"{t}: {r['label'][:40]}" for t, r in zip(tags, rl)]
    parts += ["<h2>MHD against model revision</h2>",
              img_tag(revision_figure({p: summary["positions"][p]["mhd_mm"]["values"]
                                       for p in positions}, xl), "MHD per revision")]
    parts.append(f"<h2>Error maps (one colour scale: +-{limit:.2f} mm; grey: measured "
                 "skin)</h2>")
    for p in positions:
        fig = error_maps_figure({t: m[p] for t, m in zip(tags, maps)}, views=views,
                                limit=limit, title=p)
        parts.append(img_tag(fig, f"error maps {p}"))
    parts.append("<h2>RMSE per skin region (mm)</h2>")
    for p in positions:
        rows = [[k, *v["rmse_mm"]] for k, v in summary["regions"][p].items()]
        parts += [f"<h3>{html.escape(p)}</h3>", _html_table(["region", *tags], rows)]
    style = ("body{font-family:sans-serif;max-width:1200px;margin:auto}"
             "table{border-collapse:collapse;margin:8px 0}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
             "img{max-width:100%}")
    doc = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>breastmodel compare"
           f"</title><style>{style}</style></head><body>" + "\n".join(parts)
           + "</body></html>\n")
    write_atomic(out / "compare.html", doc)
    return summary
