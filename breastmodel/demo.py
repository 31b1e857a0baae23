"""The demo's story, the library side of ``breastmodel demo`` (:mod:`breastmodel.commands.demo`
tells it): fit the bulk model, diagnose, refit with the named effect, compare, and one
page that links it all."""

from __future__ import annotations

import html
import json
import logging
import os
import resource
import time
from pathlib import Path
from typing import Any

log = logging.getLogger("breastmodel.demo")
#: Rim of the skin left out of the diagnosis, mm (``diagnose``'s default of 15 mm leaves too
#: few skin nodes of the half-size demo phantom, whose skin the slab's sides cut).
RIM_MM = 5.0
#: Registration settings of the demo (the rest: the pipeline's defaults). The fiducial check
#: is a warning here, not an error: the phantom's soft breast carries its inframammary-fold
#: markers about 2 mm between prone and supine, so the check flags prone although the refined
#: transform is right (chest-wall TRE against the truth: mean 0.18 mm, max 0.32 mm).
REGISTER = {"require_fiducials": False}


def cpu_seconds() -> float:
    """CPU seconds of this process and its finished children."""
    r, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime


def run_story(data: str | Path, out: str | Path, *, mesh_size_mm: float = 8.0,
              rim_mm: float = RIM_MM, n_workers: int = 0, progress: bool = True) -> dict[str, Any]:
    """Fit the bulk model, diagnose, refit with the best candidate, compare; write the page.

    Parameters
    ----------
    data
        Folder with ``subject/`` (the pipeline's input), ``subject_truth/`` (truth label maps
        and physics) and ``demo.json`` (the hidden effect's candidate name).
    out
        Output folder: ``run0/`` (bulk model, with ``diagnosis.html``), ``run1/`` (with the
        diagnosed effect), ``compare/`` and ``index.html``. A rerun reuses finished stages.
    mesh_size_mm
        Tet edge of the fitted model, mm.
    rim_mm
        Skin nodes closer than this to the skin's open edge stay out of the diagnosis, mm.
    n_workers
        Local dask workers of the diagnosis (0: in this process).
    progress
        Print the stages.

    Returns
    -------
    dict
        ``hidden_effect``, ``named`` (the diagnosis' best significant candidate or None),
        ``rank`` (the hidden effect's rank, 1-based, or None), ``verdict``, ``mhd_mm``
        (position -> [before, after], mm), ``page`` (path of ``index.html``), ``steps``
        (step -> wall and CPU seconds) and ``compare`` (the comparison summary).
    """
    from breastmodel.commands.run import add_effect, from_run_config
    from breastmodel.config import write_json
    from breastmodel.diagnosis import write_compare
    from breastmodel.diagnosis.diagnose import diagnose
    from breastmodel.pipeline.run import cache_of, run_subject
    from breastmodel.validation.suite import suite_config
    from imaging.subject import read_subject

    data, out = Path(data), Path(out)
    subject_dir, truth_dir = data / "subject", data / "subject_truth"
    meta = json.loads((data / "demo.json").read_text())
    subject = read_subject(subject_dir)
    timed = _Steps(progress)

    # run 1: the bulk model, one breast modulus fitted on supine and prone, tilted held out
    cfg0 = suite_config("truth_labels", truth_dir, list(subject.positions), subject.reference,
                        mesh_size_mm=mesh_size_mm, E_start=0.5)
    cfg0["register"].update(REGISTER)
    run0, run1 = out / "run0", out / "run1"
    timed("fit the bulk model (run 1)",
          lambda: run_subject(subject_dir, cfg0, run0, progress=progress))
    diag = timed("diagnose run 1",
                 lambda: diagnose(run0, n_workers=n_workers, rim_mm=rim_mm,
                                  progress=progress))["missing"]
    hidden = meta["hidden_effect"]
    names, named, rank = _named(diag, hidden, run0)
    # run 2: what `breastmodel run SUBJECT --from run0 --add-effect NAMED` does
    cfg1 = add_effect(from_run_config(run0), named, run0)
    timed(f"refit with {named} (run 2)",
          lambda: run_subject(subject_dir, cfg1, run1, progress=progress, cache=cache_of(run0)))
    cmp = timed("compare", lambda: write_compare([run0, run1], out / "compare",
                                                 labels=["bulk model", f"+ {named}"]))
    mhd = {p: t["mhd_mm"]["values"] for p, t in cmp["positions"].items()}
    page = out / "index.html"
    result = {"hidden_effect": hidden, "named": named, "rank": rank,
              "verdict": diag["verdict"], "top": names[:5], "mhd_mm": mhd,
              "page": str(page), "steps": timed.steps, "compare": cmp,
              "truth": json.loads((truth_dir / "truth_model.json").read_text()),
              "spec": meta.get("spec"), "mesh_size_mm": mesh_size_mm,
              "load": list(os.getloadavg())}
    write_story_page(page, result)
    write_json(out / "demo.json", {k: v for k, v in result.items() if k != "compare"})
    return result


class _Steps:
    """Runs the story's steps, printing each name with ``progress``; ``steps`` holds each
    one's wall and CPU seconds."""

    def __init__(self, progress: bool):
        self.progress = progress
        self.steps: dict[str, dict[str, float]] = {}

    def __call__(self, name: str, fn):
        """``fn()``, timed under ``name``."""
        w0, c0 = time.perf_counter(), cpu_seconds()
        if self.progress:
            print(f"\n== {name}", flush=True)
        res = fn()
        self.steps[name] = {"wall_s": round(time.perf_counter() - w0, 1),
                            "cpu_s": round(cpu_seconds() - c0, 1)}
        return res


def _named(diag: dict[str, Any], hidden: str, run0: Path) -> tuple[list[str], str, int | None]:
    """The ranked candidates' names, the best significant one and the hidden effect's rank
    (1-based; None when unranked). Raises when no candidate is significant."""
    names = [r["name"] for r in diag["ranking"]]
    from breastmodel.diagnosis import answer

    best = answer(diag["ranking"])
    named = best["name"] if best else None
    rank = names.index(hidden) + 1 if hidden in names else None
    if named is None:
        raise RuntimeError(f"demo: the diagnosis found no significant missing effect "
                           f"({diag['verdict']}); see {run0 / 'diagnosis.html'}")
    return names, named, rank


def _truth_rows(truth: dict) -> str:
    names = {"1": "breast, left", "2": "muscle", "3": "breast, right"}
    rows = "".join(f"<tr><td>{html.escape(names.get(k, 'region ' + k))}</td>"
                   f"<td>{html.escape(m.get('name', ''))}</td><td>{float(m['E']):.3f}</td></tr>"
                   for k, m in sorted(truth.get("materials", {}).items()))
    return f"<table><tr><th>region</th><th>law</th><th>E, kPa</th></tr>{rows}</table>"


def write_story_page(path: Path, res: dict[str, Any]) -> None:
    """``index.html``: the story on one page, with the run reports, the diagnosis and the
    comparison linked and embedded (relative paths: the folder can be moved)."""
    from breastmodel.config import write_atomic

    e = html.escape
    ok = res["named"] == res["hidden_effect"]
    rows = "".join(
        f"<tr><td>{e(p)}</td><td>{b:.2f}</td><td>{a:.2f}</td><td>{a - b:+.2f}</td></tr>"
        for p, (b, a) in res["mhd_mm"].items())
    where = ""
    for p, reg in (res["compare"].get("regions") or {}).items():
        sub = {k: v["rmse_mm"] for k, v in reg.items() if "." in k}
        worst = max(sub, key=lambda k: sub[k][0]) if sub else None
        where += (f"<tr><td>{e(p)}</td>"
                  + "".join(f"<td>{reg[k]['rmse_mm'][0]:.2f} &rarr; {reg[k]['rmse_mm'][1]:.2f}"
                            f"</td>" if k in reg else "<td>-</td>" for k in ("left", "right"))
                  + (f"<td>{e(worst)}: {sub[worst][0]:.2f} &rarr; {sub[worst][1]:.2f}</td>"
                     if worst else "<td>-</td>") + "</tr>")
    fitted = res["compare"]["runs"]
    par = "".join(  # a tied pair "a|b" repeats a and b
        f"<tr><td>{e(r['label'])}</td><td>"
        + e(", ".join(f"{k} = {v:.3g}" for k, v in sorted(r["parameters"].items())
                      if isinstance(v, float) and "|" not in k)) + "</td></tr>" for r in fitted)
    steps = "".join(f"<tr><td>{e(k)}</td><td>{v['wall_s']:.0f}</td><td>{v['cpu_s']:.0f}</td>"
                    f"</tr>" for k, v in res["steps"].items())
    pages = [("1. The bulk model's report: where it fails", "run0/report.html"),
             ("2. The diagnosis of run 1: which effect is missing", "run0/diagnosis.html"),
             ("3. The comparison: the error falls", "compare/compare.html"),
             ("4. The refitted model's report", "run1/report.html")]
    frames = "".join(
        f"<h2>{e(t)}</h2><p><a href='{e(u)}'>{e(u)}</a> (open in its own tab)</p>"
        f"<iframe src='{e(u)}' loading='lazy'></iframe>" for t, u in pages)
    regions_note = ("<p>With the <code>regions</code> effect on, "
                    "<code>effects.regions.E_left</code> "
                    "and <code>E_right</code> are the moduli of the left and the right breast, "
                    "and <code>materials.breast_*.E</code> are no longer used.</p>"
                    if str(res["named"]).startswith("regions") else "")
    style = ("<style>body{font-family:sans-serif;max-width:1200px;margin:auto;padding:1em}"
             "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #bbb;"
             "padding:3px 8px;text-align:right}td:first-child{text-align:left}"
             "iframe{width:100%;height:900px;border:1px solid #999}"
             ".ok{color:#060}.bad{color:#a00}</style>")
    body = f"""<h1>breastmodel demo: a model that misses an effect, and finds it</h1>
<p>A phantom subject (three positions: prone, supine, supine tilted) whose deformation under
gravity FEBio computed on its own 5 mm mesh with a <b>hidden effect</b>: the left and the right
breast have different moduli. The bulk model fitted here ({res['mesh_size_mm']:g} mm mesh of the
registered label maps) ties one modulus across both breasts.</p>
<h2>Truth (FEBio)</h2>{_truth_rows(res['truth'])}
<h2>The story in numbers</h2>
<ol><li>Fit the bulk model (run 1) on supine and prone; the tilted position is held out.</li>
<li>The diagnosis ranks the effects the model lacks: <b>{e(res['verdict'])}</b></li>
<li>Hidden effect: <code>{e(res['hidden_effect'])}</code>; the diagnosis names
<code>{e(str(res['named']))}</code> <span class='{'ok' if ok else 'bad'}'>
({'correct' if ok else 'wrong'}; the hidden effect ranks #{res['rank']})</span>.</li>
<li>Refit with it (run 2) and compare.</li></ol>
<table><tr><th>position</th><th>MHD before, mm</th><th>MHD after, mm</th><th>change</th></tr>
{rows}</table>
<p>MHD: modified Hausdorff distance between the predicted and the measured skin.</p>
<h3>Where the bulk model fails: skin RMSE per breast, before &rarr; after (mm)</h3>
<table><tr><th>position</th><th>left breast</th><th>right breast</th>
<th>worst region before</th></tr>{where}</table>
<h3>Fitted parameters (kPa)</h3><table>{par}</table>{regions_note}
<h3>Time per step (s)</h3><table><tr><th>step</th><th>wall</th><th>CPU</th></tr>{steps}</table>
{frames}"""
    write_atomic(Path(path), "<!doctype html><html><head><meta charset='utf-8'>"
                 f"<title>breastmodel demo</title>{style}</head><body>{body}</body></html>")
