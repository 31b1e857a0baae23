"""``diagnose``: where a finished run fails and which physical effect is missing.

Writes ``DIR/diagnosis.json`` (``where``: the error tables of
:func:`~breastmodel.diagnosis.maps.failure_tables`; ``missing``: the ranking of
:func:`~breastmodel.diagnosis.missing.rank_candidates`) and ``DIR/diagnosis.html`` (verdict,
error maps of every position from three views on one colour scale, region tables, error
against strain, the ranking with its evidence, and the command that adds the best candidate).
"""

from __future__ import annotations

import html
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.diagnosis.scoring import HELD_OUT_MIN_CHANGE_MM, answer

__all__ = ["diagnose", "write_diagnosis_html"]


def diagnose(run_dir: str | Path, *, n_workers: int = 0, scheduler: str | None = None,
             verify_top: int = 1, rim_mm: float | None = None, max_solves: int | None = None,
             max_seconds: float | None = None, refine: bool = True,
             progress: bool = True) -> dict:
    """Diagnose the run in ``run_dir``; returns what ``diagnosis.json`` holds.

    The options are those of :func:`~breastmodel.diagnosis.missing.rank_candidates`.

    Raises
    ------
    StageError
        ``run_dir`` is not a finished run folder.
    """
    from breastmodel.config import write_json
    from breastmodel.diagnosis.maps import failure_map, failure_tables, skin_regions
    from breastmodel.diagnosis.missing import rank_candidates
    from breastmodel.diagnosis.rundata import load_run

    run = load_run(run_dir)
    regions = skin_regions(run.problem.mesh, run.X[:run.problem.mesh.n_nodes])
    maps = {p: failure_map(run, p, regions=regions) for p in run.positions}
    where = failure_tables(run, maps=maps, regions=regions)
    kw = {} if rim_mm is None else {"rim_mm": rim_mm}
    missing = rank_candidates(run, n_workers=n_workers, scheduler=scheduler,
                              verify_top=verify_top, progress=progress,
                              max_solves=max_solves, max_seconds=max_seconds,
                              refine=refine, **kw)
    out = {"subject": run.subject, "run": str(run.out), "where": where, "missing": missing}
    write_json(run.out / "diagnosis.json", out)
    write_diagnosis_html(run.out / "diagnosis.html", out, maps)
    return out


def _table(header, rows, *, raw_header: bool = False) -> str:
    def cell(v):
        if isinstance(v, float):
            return f"{v:.3f}"
        return html.escape(str(v))
    head = "".join(f"<th>{h if raw_header else html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def correction_rows(miss: Mapping[str, Any]) -> dict[str, dict[str, np.ndarray]]:
    """Rows of the correction maps: the residual after re-fitting alone, then what each
    mapped candidate explains (minus its predicted change of the residual), per position as
    a value per skin node in canonical order (NaN on the unscored rim), mm."""
    cm = miss.get("correction_maps")
    if not cm:
        return {}
    idx, n = np.asarray(cm["index"], int), int(cm["n_skin_nodes"])
    k = len(idx)

    def split(v):
        out = {}
        for i, p in enumerate(cm["positions"]):
            full = np.full(n, np.nan)
            full[idx] = np.asarray(v[i * k:(i + 1) * k], float)
            out[p] = full
        return out

    rows = {"residual": split(cm["residual"])}
    for name, v in cm["corrections"].items():
        rows[f"explained by {name}"] = split(-np.asarray(v, float))
    return rows


def _correction_maps(miss: Mapping[str, Any], maps: Mapping[str, Any]) -> list[str]:
    from breastmodel.diagnosis.views import img_tag, value_maps_figure

    rows = correction_rows(miss)
    if not rows:
        return []
    return ["<h3>Where each candidate acts</h3>",
            "<p>First row: the residual after re-fitting the fitted parameters alone (anterior "
            "view; the unscored rim is blank). Below, for each of the best candidates, the "
            "part of that residual it explains (minus its predicted change of the residual), "
            "on the same colour scale: a candidate that explains the residual looks like the "
            "first row.</p>",
            img_tag(value_maps_figure({p: maps[p] for p in miss["objective_positions"]
                                       if p in maps}, rows), "correction maps")]


def write_diagnosis_html(path: Path, diag: Mapping[str, Any],
                         maps: Mapping[str, Mapping[str, Any]]) -> None:
    """A self-contained HTML page of a diagnosis (pictures embedded)."""
    from breastmodel.config import write_atomic

    miss = diag["missing"]
    parts = _where_section(diag, maps)
    parts += _missing_section(miss)
    parts += _landmark_section(miss)
    parts += _failed_section(miss)
    parts += _correction_maps(miss, maps)
    parts += ["<h3>Not scored</h3>",
              _table(["name", "reason"], [[s["name"], s["reason"]] for s in miss["skipped"]])]
    parts += _next_step(diag)
    style = ("<style>body{font-family:sans-serif;max-width:1300px;margin:auto}"
             "table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #bbb;"
             "padding:2px 6px}.verdict{font-size:16px}img{max-width:100%}</style>")
    write_atomic(Path(path), "<!doctype html><html><head><meta charset='utf-8'>"
                 f"<title>diagnosis</title>{style}</head><body>{''.join(parts)}</body></html>")


def _where_section(diag: Mapping[str, Any], maps: Mapping[str, Mapping[str, Any]]) -> list:
    """The page's title and verdict, then where the model fails: the error maps, each
    position's region table and the error against local strain."""
    from breastmodel.diagnosis.views import (
        error_limit,
        error_maps_figure,
        error_vs_strain_figure,
        img_tag,
    )

    where, miss = diag["where"], diag["missing"]
    limit = error_limit(maps.values())
    parts = [f"<h1>Diagnosis: {html.escape(str(diag['subject']))}</h1>",
             f"<p class='verdict'><b>{html.escape(miss['verdict'])}</b></p>",
             f"<p>Noise floor {miss['noise_floor_mm']:.3f} mm, from the "
             f"{html.escape(miss['noise_floor_from'])}. Residual RMS now "
             f"{miss['baseline']['rms_mm']:.3f} mm, after re-fitting the fitted parameters "
             f"alone {miss['baseline']['rms_after_refit_mm']:.3f} mm (positions "
             f"{', '.join(miss['objective_positions'])}).</p>",
             "<h2>1. Where the model fails</h2>",
             f"<p>Signed node-to-surface error of the predicted skin (+ outside the measured "
             f"skin), one colour scale for every position (&plusmn;{limit:.2f} mm).</p>",
             img_tag(error_maps_figure(maps, limit=limit), "error maps")]
    for pos, t in where["positions"].items():
        rows = [[name, r["n"], r["mean_signed_mm"], r["rmse_mm"], r["p95_mm"], r["max_mm"],
                 r["normal_rms_mm"], r["tangential_rms_mm"], r["mean_strain"]]
                for name, r in t["regions"].items() if r.get("n")]
        parts += [f"<h3>{html.escape(pos)}</h3>",
                  _table(["region", "nodes", "mean signed", "RMSE", "p95", "max",
                          "normal RMS", "tangential RMS", "mean strain"], rows)]
    parts += ["<h3>Error against local strain</h3>",
              img_tag(error_vs_strain_figure(
                  maps, tables={p: t["error_vs_strain"] for p, t in where["positions"].items()}),
                  "error vs strain")]
    return parts


def _missing_section(miss: Mapping[str, Any]) -> list:
    """What is missing: how candidates are scored, and the ranking table."""
    parts = ["<h2>2. What is missing</h2>"]
    parts.append(
        "<p>Physical effects the model does not use, parameters it holds fixed, and errors of "
        "the measurement itself (a rigid misregistration of one position: 6 parameters; an "
        "offset of the measured skin: 1) and of the mesh (mesh_refinement: the fitted model "
        "on a mesh of half the edge length, its amount fixed), each scored by the residual "
        "left after a linear re-fit with it. &Delta;BIC = n<sub>eff</sub> "
        "ln(SS/SS<sub>0</sub>) + k ln(n<sub>eff</sub>) charges every added parameter "
        "(n<sub>eff</sub> = "
        f"{miss.get('n_effective', float('nan')):.0f} independent residuals of "
        f"{miss['n_scored_nodes'] * len(miss['objective_positions'])}); a candidate explains "
        "more than the noise when &Delta;BIC &lt; -6, it removes at least 20 % of the squared "
        "residual and a quarter of the noise floor. Held out: the RMS of a position the run "
        "did not calibrate on, re-fitted on the calibration positions only, without -> with "
        "the candidate (a real effect improves it too), and how far the candidate moves it: "
        f"a position moved by less than {HELD_OUT_MIN_CHANGE_MM:g} mm RMS cannot test it.</p>")
    pos = miss["objective_positions"]
    rows = []
    for i, r in enumerate(miss["ranking"], 1):
        est = ", ".join(f"{k.split('.', 1)[-1]}={v:.3g}" for k, v in r["estimate"].items())
        ev = "; ".join(f"{e['where']} {e['rms_before_mm']:.2f}->{e['rms_after_mm']:.2f}"
                       for e in r["evidence"][:3])
        ver = r.get("verified", {})
        vtxt = ("" if not ver else ver.get("error") or
                ", ".join(f"{p} {v:.2f}" for p, v in ver["mhd_mm"].items()))
        if r.get("unconfirmed"):
            vtxt += (f" (not confirmed: worst {r['unconfirmed']['worst_mhd_before_mm']:.2f}"
                     f" -> {r['unconfirmed']['worst_mhd_after_mm']:.2f})")
        ho = "; ".join(f"{p} {v['rms_before_mm']:.2f}->{v['rms_after_mm']:.2f}"
                       + f" (moved {v['change_rms_mm']:.2f})"
                       for p, v in (r.get("held_out") or {}).items()) or "n/a"
        rows.append([i, r["name"], r["kind"], r.get("n_parameters", ""),
                     "yes" if r["significant"] else "no", f"{100 * r['explained']:.0f} %",
                     r.get("delta_bic", float("nan")), r["predicted_rms_mm"],
                     *[r["predicted"][p]["rms_mm"] for p in pos], ho, est, ev, vtxt])
    parts.append(_table(["#", "candidate", "kind", "k", "explains more than noise",
                         "explained", "&Delta;BIC", "predicted RMS",
                         *[f"RMS {p}" for p in pos], "held out (RMS; how far it moves it)",
                         "estimate",
                         "evidence (region RMS before->after)",
                         "MHD after a real re-fit with it (mm)"], rows, raw_header=True))
    return parts


def _landmark_section(miss: Mapping[str, Any]) -> list:
    """The landmark check (:mod:`breastmodel.diagnosis.landmarks`; not run: nothing)."""
    lc = miss.get("landmark_check")
    if not lc:
        return []
    named = lc.get("named")
    if not lc["refits"]:
        return ["<h3>The internal landmarks as a witness</h3>",
                f"<p>No candidate explained more than the noise on the skin, and the skin "
                f"favoured no physical one (&Delta;BIC &lt; 0), so none was re-fitted for the "
                f"internal landmarks (RMS error {lc['rms_before_mm']:.2f} mm with the fitted "
                f"model).</p>"]
    return ["<h3>The internal landmarks as a witness</h3>",
            f"<p>No candidate explained more than the noise on the skin, so the best physical "
            f"ones the skin favours (and the best misregistration) were re-fitted on the skin "
            f"and the internal landmarks of "
            f"{', '.join(map(html.escape, lc['positions']))}, which no fit saw, were compared "
            f"with their measured places: RMS error {lc['rms_before_mm']:.2f} mm with the "
            f"fitted model. A candidate is named when it lowers that by "
            f"{100 * lc['drop']:.0f} % and {lc['min_drop_mm']:g} mm at least, more than any "
            f"other, without taking any position's farther or raising the worst skin MHD: "
            + (f"<b>{html.escape(named)}</b>." if named else "none did.") + "</p>",
            _table(["candidate", "landmark RMS after its re-fit (mm)", "worst MHD before",
                    "worst MHD after", "error"],
                   [[x["name"], x["rms_after_mm"] if x["rms_after_mm"] is not None
                     else float("nan"), x["worst_mhd_before_mm"] or float("nan"),
                     x["worst_mhd_after_mm"] or float("nan"), x["error"] or ""]
                    for x in lc["refits"]])]


def _failed_section(miss: Mapping[str, Any]) -> list:
    """The candidates whose evaluation failed, with the budget they had (none: nothing)."""
    if not miss["failed"]:
        return []
    b = miss.get("budget", {})
    return ["<h3>Candidates whose evaluation failed</h3>",
            f"<p>Each evaluation may spend {b.get('max_solves', '?')} forward solves and "
            f"{b.get('max_seconds', float('nan')):.0f} s (the fitted model's own took "
            f"{b.get('base_solves', '?')} and {b.get('base_seconds', float('nan')):.1f} "
            "s).</p>",
            _table(["candidate", "kind", "evaluation", "seconds", "reason"],
                   [[f["name"], f.get("kind", ""), f.get("evaluation", ""),
                     f.get("seconds") or float("nan"), f["error"]]
                    for f in miss["failed"]])]


def _next_step(diag: Mapping[str, Any]) -> list:
    """What to do about the best significant candidate: correct the measurement, or add the
    effect and compare (none significant: nothing)."""
    miss = diag["missing"]
    best = answer(miss["ranking"])
    if best is not None and best.get("measurement") == "refinement":
        return [f"<h2>3. Refine the mesh</h2><p>{html.escape(miss['verdict'])}.</p>"]
    if best is not None and best.get("measurement"):
        return ["<h2>3. Correct the measurement</h2><p>"
                f"{html.escape(miss['verdict'])}. The estimate: "
                + html.escape(", ".join(f"{k.split('.', 1)[-1]} = {v:.2f}" for k, v in
                                        best["estimate"].items())) + "</p>"]
    if best is not None:
        return ["<h2>3. Add it and watch the error fall</h2><pre>breastmodel run SUBJECT "
                f"--config RUN.toml --out DIR2 --add-effect {html.escape(best['name'])}\n"
                f"breastmodel compare {html.escape(str(diag['run']))} DIR2 --out "
                "COMPARE</pre>"]
    return []
