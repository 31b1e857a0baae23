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

__all__ = ["diagnose", "write_diagnosis_html"]


def diagnose(run_dir: str | Path, *, n_workers: int = 0, scheduler: str | None = None,
             verify_top: int = 1, rim_mm: float | None = None, progress: bool = True) -> dict:
    """Diagnose the run in ``run_dir``; returns what ``diagnosis.json`` holds.

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
                              verify_top=verify_top, progress=progress, **kw)
    out = {"subject": run.subject, "run": str(run.out), "where": where, "missing": missing}
    write_json(run.out / "diagnosis.json", out)
    write_diagnosis_html(run.out / "diagnosis.html", out, maps)
    return out


def _table(header, rows) -> str:
    def cell(v):
        if isinstance(v, float):
            return f"{v:.3f}"
        return html.escape(str(v))
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def write_diagnosis_html(path: Path, diag: Mapping[str, Any],
                         maps: Mapping[str, Mapping[str, Any]]) -> None:
    """A self-contained HTML page of a diagnosis (pictures embedded)."""
    from breastmodel.config import write_atomic
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
    parts.append("<h2>2. Which effect is missing</h2>")
    pos = miss["objective_positions"]
    rows = []
    for i, r in enumerate(miss["ranking"], 1):
        est = ", ".join(f"{k.split('.', 1)[1]}={v:.3g}" for k, v in r["estimate"].items())
        ev = "; ".join(f"{e['where']} {e['rms_before_mm']:.2f}->{e['rms_after_mm']:.2f}"
                       for e in r["evidence"][:3])
        ver = r.get("verified", {})
        vtxt = ("" if not ver else ver.get("error") or
                ", ".join(f"{p} {v:.2f}" for p, v in ver["mhd_mm"].items()))
        rows.append([i, r["name"], r["kind"], "yes" if r["significant"] else "no",
                     f"{100 * r['explained']:.0f} %", r["predicted_rms_mm"],
                     *[r["predicted"][p]["rms_mm"] for p in pos], est, ev, vtxt])
    parts.append(_table(["#", "candidate", "kind", "explains more than noise", "explained",
                         "predicted RMS", *[f"RMS {p}" for p in pos], "estimate",
                         "evidence (region RMS before->after)",
                         "MHD after a real re-fit with it (mm)"], rows))
    if miss["failed"]:
        parts += ["<h3>Candidates whose evaluation failed</h3>",
                  _table(["candidate", "error"], [[f["name"], f["error"]]
                                                  for f in miss["failed"]])]
    parts += ["<h3>Not scored</h3>",
              _table(["name", "reason"], [[s["name"], s["reason"]] for s in miss["skipped"]])]
    sig = [r for r in miss["ranking"] if r["significant"]]
    if sig:
        parts.append("<h2>3. Add it and watch the error fall</h2><pre>breastmodel run SUBJECT "
                     f"--config RUN.toml --out DIR2 --add-effect {html.escape(sig[0]['name'])}\n"
                     f"breastmodel compare {html.escape(str(diag['run']))} DIR2 --out "
                     "COMPARE</pre>")
    style = ("<style>body{font-family:sans-serif;max-width:1300px;margin:auto}"
             "table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #bbb;"
             "padding:2px 6px}.verdict{font-size:16px}img{max-width:100%}</style>")
    write_atomic(Path(path), "<!doctype html><html><head><meta charset='utf-8'>"
                 f"<title>diagnosis</title>{style}</head><body>{''.join(parts)}</body></html>")
