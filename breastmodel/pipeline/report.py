"""A single self-contained HTML report (pictures embedded as base64 PNG).

The pictures are drawn by :mod:`breastmodel.pipeline.report_figures`; a PNG of the page by
:func:`screenshot` (:mod:`breastmodel.pipeline.screenshot`, importable from here).
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.pipeline.report_figures import (
    error_figure,
    history_figure,
    img_tag,
    registration_figure,
    segmentation_figure,
)
from breastmodel.pipeline.report_fit import identifiability_notes, offset_notes
from breastmodel.pipeline.screenshot import find_chromium, screenshot

__all__ = ["common_error_limit", "find_chromium", "parameter_units", "screenshot", "write_report"]


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.3f}"
    return html.escape(str(v))


def _percent(v) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{100.0 * v:.1f}"


def _table(header: list[str], rows: list[list]) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def common_error_limit(errors) -> float:
    """One colour limit (mm) for every position's error map: the 98th percentile of |signed
    error| over all positions together (1 mm when there is no error)."""
    allerr = np.concatenate([np.abs(np.asarray(e, float)).ravel() for e in errors] or [[]])
    lim = float(np.nanpercentile(allerr, 98)) if allerr.size else 1.0
    return lim if lim > 0 and math.isfinite(lim) else 1.0


def parameter_units(model: Mapping[str, Any], path: str) -> str:
    """The unit of a parameter path (``materials.<region>.<p>`` or ``effects.<name>.<p>``),
    from the registered material or effect; ``"?"`` when the registry does not know it."""
    from mechanics.effects import EFFECTS
    from mechanics.materials import MATERIALS

    parts = str(path).split("|")[0].split(".")
    if len(parts) != 3:
        return "?"
    kind, owner, name = parts
    if kind == "materials":
        law = (model.get("materials", {}).get(owner) or {}).get("name")
        cls = MATERIALS.get(law)
    else:
        cls = EFFECTS.get(owner.split(":", 1)[0])
    for p in getattr(cls, "params", ()) if cls is not None else ():
        if p.name == name:
            return p.unit
    return "?"


def _qa_sections(images: Mapping[str, Any], segment: Mapping[str, Any]) -> list[str]:
    """Segmentation and registration QA: figures and tables (``segment``: the run's
    ``[segment]`` table, which says which label maps were given rather than segmented)."""
    import SimpleITK as sitk

    from breastmodel.pipeline.config import given_labels
    from breastmodel.pipeline.segment import read_confidences
    from imaging.io import read_volume
    from imaging.qa import tissue_volumes_ml

    parts = ["<h2 id='segmentation'>Segmentation QA</h2>",
             "<p>Each position's label map on its own image (central slices through the "
             "labelled tissue; radiological display, axes in mm).</p>"]
    rows = []
    seg_dirs, vols = images.get("segment_dirs") or {}, images.get("input_volumes") or {}
    confs = read_confidences({p: Path(f) for p, f in seg_dirs.items()})
    for pos in images["labels"]:
        lab_path = Path(seg_dirs[pos]) / f"{pos}_labels.nii.gz" if pos in seg_dirs else None
        if lab_path is None or not lab_path.is_file() or pos not in vols:
            continue
        labels = sitk.ReadImage(str(lab_path))
        img = read_volume(vols[pos])  # a file or a DICOM series folder
        v = tissue_volumes_ml(labels)
        given = given_labels(segment, pos)
        conf = confs.get(pos) or {}
        rows.append([pos, "segmented" if given is None else f"given: {given}",
                     *(v.get(k) for k in ("breast", "muscle", "gland")),
                     " / ".join(f"{conf['agreement'][k]:.3f}" for k in ("body", "muscle")
                                if k in conf.get("agreement", {})) or "-",
                     "; ".join(conf.get("warnings") or []) or "-"])
        parts.append(img_tag(segmentation_figure(pos, img, labels, "segmentation"),
                          f"segmentation {pos}"))
    if rows:
        parts.insert(2, _table(["position", "label map", "breast (ml)", "muscle (ml)",
                                "gland (ml)", "agreement body / muscle (Dice)", "warnings"],
                               rows))
    reg = images.get("registration") or {}
    ref = images["reference"]
    parts += ["<h2 id='registration'>Registration QA</h2>",
              f"<p>Rigid transforms of every position into the reference frame ({html.escape(ref)}"
              "); <code>&lt;position&gt;.tfm</code> maps reference points into the position's "
              "image.</p>"]
    rrows = []
    for pos, e in (reg.get("positions") or {}).items():
        res, tre, sp = (e.get(k) or {} for k in ("fiducial_residuals_mm", "tre_mm",
                                                 "seed_spread_mm"))
        rrows.append([pos, e.get("initialisation"), len(e.get("fiducials_used") or []),
                      max(res.values()) if res else None, e.get("correlation"),
                      sp.get("standard_error"), tre.get("mean"), e.get("rotation_error_deg"),
                      "; ".join(e.get("warnings") or []) or "-"])
    parts.append(_table(["position", "initialisation", "fiducials used",
                         "max fiducial residual (mm)", "correlation", "repeats' standard error "
                         "(mm)", "TRE mean (mm)", "rotation error (deg)", "warnings"], rrows))
    out = Path(images.get("out", "."))
    reference = sitk.ReadImage(str(out / images["volumes"][ref]))
    ref_labels = sitk.ReadImage(str(out / images["labels"][ref]))
    for pos in (reg.get("positions") or {}):
        moved = sitk.ReadImage(str(out / images["volumes"][pos]))
        pts = {f"{k}": v for k, v in (images.get("fiducials", {}).get(pos) or {}).items()}
        parts.append(img_tag(registration_figure(pos, reference, moved, ref_labels, pts),
                          f"registration {pos}"))
    return parts


def _refinement_section(ref: Mapping[str, Any] | None) -> list[str]:
    """The mesh-refinement check (``[evaluate] refinement = true``)."""
    if not ref:
        return []
    if "skipped" in ref:
        return ["<h2 id='refinement'>Mesh refinement check</h2>",
                f"<p>Not run: {html.escape(str(ref['skipped']))}.</p>"]
    h, hf = ref["size_mm"], ref["fine_size_mm"]
    worst = max((abs(r["change_mm"]) for r in ref["positions"].values()), default=0.0)
    return ["<h2 id='refinement'>Mesh refinement check</h2>",
            f"<p>The prediction at the same parameters on a mesh of half the edge length "
            f"({h:g} mm, {ref['n_tets']} tets, against {hf:g} mm, {ref['fine_n_tets']} tets): "
            f"the MHD changes by up to {worst:.2f} mm, what the default mesh size costs.</p>",
            _table(["position", f"MHD at {h:g} mm", f"MHD at {hf:g} mm", "change (mm)"],
                   [[p, r["mhd_mm"], r["fine_mhd_mm"], r["change_mm"]]
                    for p, r in ref["positions"].items()])]


def _repair_rows(mesh: Mapping[str, Any]) -> list[list]:
    """Status rows of the label maps' repairs before meshing and skin measurement (none when
    the run's stages predate their record)."""
    rows = []
    if "repairs" in mesh:
        rows.append(["mesh", f"{mesh.get('n_tets')} tets, {mesh.get('mesh_size_mm')} mm",
                     f"{len(mesh['repairs'])} repair(s) of the label map",
                     "; ".join(mesh["repairs"]) or "-"])
    for pos, rep in (mesh.get("skin_repairs") or {}).items():
        rows.append([f"measured skin {pos}", "label map surface",
                     f"{len(rep)} repair(s) of the label map", "; ".join(rep) or "-"])
    fov = mesh.get("field_of_view")
    if fov:
        rows.append(["field of view", "the reference's breasts on its cut planes",
                     ", ".join(f"{side} {100 * c['share']:.0f} % of the skin area"
                               for side, c in fov["cut"].items()) or "-",
                     fov.get("warning") or "-"])
    return rows


def _status_rows(metrics: Mapping[str, Any], fit_info: Mapping[str, Any] | None,
                 sf: Mapping[str, Any]) -> list[list]:
    rows = _repair_rows(metrics.get("mesh") or {})
    rows += [["stress-free geometry", sf.get("method"),
             "converged" if sf.get("converged") else "NOT converged",
             f"{sf.get('forward_solves', 0)} forward solves"]]
    for p, m in metrics["positions"].items():
        ok = m.get("converged")
        rows.append([f"predict {p}", "forward solve",
                     "converged" if ok else f"NOT converged (load {m.get('load_reached')})",
                     m.get("error") or "-"])
    if fit_info:
        rows.append(["fit", fit_info.get("method"),
                     fit_info.get("termination") or "best of the evaluations",
                     f"{fit_info.get('n_simulations')} simulations, "
                     f"{fit_info.get('n_failed', 0)} failed"])
    else:
        rows.append(["fit", "none", "parameters as configured", "-"])
    return rows


def write_report(path: Path, metrics: Mapping[str, Any], params: Mapping[str, Any],
                 pictures: Mapping[str, tuple], fit_info: Mapping[str, Any] | None,
                 sf: Mapping[str, Any], *, subject_id: str,
                 images: Mapping[str, Any] | None = None,
                 config: Mapping[str, Any] | None = None,
                 provenance_path: Path | None = None) -> Path:
    """Write ``path`` (one self-contained HTML page, pictures embedded as PNG).

    Sections: run status (stress-free, every prediction, the fit), parameters with units,
    bounds and uncertainty, skin distances, per-region and landmark tables, error maps on one
    colour scale, segmentation and registration QA (when ``images`` is given, from
    :func:`breastmodel.pipeline.outputs.export_images`), the stress-free and fit histories,
    the configuration and the package versions with the date.

    Parameters
    ----------
    path : output file
    metrics : the run's metrics (``metrics.json``)
    params : the parameters used (``params.json``)
    pictures : position -> (predicted skin vertices (n, 3) mm, triangles, signed error (n,)
        mm, measured skin (vertices, triangles))
    fit_info : the fit result or None
    sf : the stress-free stage's info (with its history)
    subject_id : the subject's name
    images : exported images, transforms, registration report and stage folders
    config : the resolved run config
    provenance_path : ``provenance.json`` (command and package versions)
    """
    import datetime
    import json

    from breastmodel.config import package_versions, write_atomic

    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    prov = {}
    if provenance_path is not None and Path(provenance_path).is_file():
        prov = json.loads(Path(provenance_path).read_text())
    versions = prov.get("versions") or package_versions()
    parts = [f"<h1>breastmodel run: {html.escape(subject_id)}</h1>",
             f"<p>{html.escape(now)}; breastmodel {html.escape(versions.get('breastmodel', '?'))}"
             f"; reference frame: {html.escape(str(metrics.get('reference')))} (LPS, mm)</p>",
             "<h2 id='status'>Run status</h2>",
             _table(["step", "method", "status", "details"],
                    _status_rows(metrics, fit_info, sf))]
    parts += _parameter_section(params, fit_info, config)
    parts += _distance_sections(metrics)
    parts += _error_map_section(pictures)
    if images:
        parts += _qa_sections(images, (config or {}).get("segment") or {})
    parts += ["<h2 id='history'>Stress-free geometry and fit</h2>",
              img_tag(history_figure(fit_info, sf), "history")]
    parts += _fit_sections(fit_info)
    parts += _file_sections(metrics, images)
    cfg_file = Path(provenance_path).with_name("config.toml") if provenance_path else None
    if cfg_file is not None and cfg_file.is_file():
        parts += ["<h2 id='config'>Configuration (config.toml)</h2>",
                  f"<pre>{html.escape(cfg_file.read_text())}</pre>"]
    parts += ["<h2 id='versions'>Versions</h2>",
              _table(["package", "version"],
                     [["command", prov.get("command", "-")], *versions.items()])]
    style = ("body{font-family:sans-serif;max-width:1100px;margin:auto}"
             "table{border-collapse:collapse;margin:8px 0}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
             "pre{background:#f4f4f4;padding:6px;font-size:11px}"
             "img{max-width:100%}")
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>breastmodel "
           f"{html.escape(subject_id)}</title><style>{style}</style></head><body>"
           + "\n".join(parts) + "</body></html>\n")
    write_atomic(path, doc)
    return path


def _parameter_section(params: Mapping[str, Any], fit_info: Mapping[str, Any] | None,
                       config: Mapping[str, Any] | None) -> list[str]:
    """Every parameter with its unit, whether it was fitted, its search range and
    uncertainty; then what the data cannot determine."""
    model = params.get("model", {})
    bounds = (config or {}).get("fit", {}).get("parameters") or {}
    unc = (fit_info or {}).get("uncertainty") or {}
    prow = []
    for k, v in params.get("parameters", {}).items():
        b = bounds.get(k) or {}
        rng = (f"[{b['min']:g}, {b['max']:g}]" if "min" in b and "max" in b
               else ", ".join(f"{x:g}" for x in b["values"]) if "values" in b else "-")
        u = unc.get(k)
        prow.append([k, v, parameter_units(model, k), "fitted" if k in bounds and fit_info
                     else "fixed", rng,
                     u if u is not None else ("not estimated" if k in bounds and fit_info
                                              else "-")])
    parts = ["<h2 id='parameters'>Parameters</h2>",
             _table(["parameter", "value", "unit", "fitted or fixed", "search range",
                     "uncertainty (1 sd)"], prow)]
    values = params.get("parameters", {})
    units = {k: parameter_units(model, k) for k in values}
    return parts + [f"<p class='ident'>{n}</p>" for n in (
        offset_notes(values, units, (fit_info or {}).get("skin_offset_sensitivity"))
        + identifiability_notes((fit_info or {}).get("identifiability")))]


def _distance_sections(metrics: Mapping[str, Any]) -> list[str]:
    """Skin surface distances per position, the mesh-refinement check, the per-region table
    and the internal landmarks' errors."""
    pos = metrics["positions"]
    parts = ["<h2 id='distances'>Skin surface distances (mm)</h2>",
             _table(["position", "MHD", "Hausdorff", "RMSE", "p95", "MHD over the skin both show",
                     "model skin past the measured edge (%)",
                     "measured skin past the model's edge (%)", "converged"],
                    [[p, m.get("mhd_mm"), m.get("hausdorff_mm"), m.get("rmse_mm"),
                      m.get("p95_mm"), m.get("mhd_overlap_mm"),
                      _percent(m.get("uncovered_pred_fraction")),
                      _percent(m.get("uncovered_meas_fraction")), m.get("converged")]
                     for p, m in pos.items()]),
             "<p>The MHD counts every vertex of both skins; the next column leaves out the "
             "skin one surface shows past the other's edge (a position's field of view cuts the "
             "body elsewhere than the reference's), with the share left out of each beside "
             "it.</p>"]
    parts += _refinement_section(metrics.get("refinement"))
    rows = [[p, r, s.get("n"), s.get("mean_mm"), s.get("mean_signed_mm"), s.get("rmse_mm"),
             s.get("p95_mm"), s.get("max_mm")]
            for p, m in pos.items() for r, s in m.get("regions", {}).items()]
    if rows:
        parts += ["<h2>Per skin region (predicted nodes to measured skin, mm)</h2>",
                  _table(["position", "region", "nodes", "mean", "mean signed", "RMSE", "p95",
                          "max"], rows)]
    lrows = [[p, k, v["error_mm"]] for p, m in pos.items()
             for k, v in (m.get("landmarks") or {}).get("per_landmark", {}).items()]
    lsum = [[p, m["landmarks"].get("mean_mm"), m["landmarks"].get("max_mm")]
            for p, m in pos.items() if m.get("landmarks")]
    if lsum:
        parts += ["<h2>Internal landmarks (mm)</h2>",
                  _table(["position", "mean error", "max error"], lsum)]
        if lrows:
            parts.append(_table(["position", "landmark", "error"], lrows))
    return parts


def _error_map_section(pictures: Mapping[str, tuple]) -> list[str]:
    """Every position's error map on one colour scale."""
    lim = common_error_limit([p[2] for p in pictures.values()])
    parts = ["<h2 id='maps'>Error maps</h2>",
             f"<p>Signed distance of the predicted skin to the measured skin (+ outside), on "
             f"one colour scale for every position: &plusmn;{lim:.2f} mm.</p>"]
    for name, (v, f, err, measured) in pictures.items():
        parts.append(img_tag(error_figure(name, v, f, err, measured, lim), name))
    return parts


def _fit_sections(fit_info: Mapping[str, Any] | None) -> list[str]:
    """The fit's best parameters and objective, and the sensitivity at the optimum (no fit:
    nothing)."""
    parts = []
    if fit_info:
        best = fit_info.get("best", {})
        rows = [[k, v] for k, v in best.get("params", {}).items()]
        sees = fit_info.get("sees", ["skin"])
        what = ("mean MHD of the calibration positions, mm" if sees == ["skin"] else
                f"objective: mean of {' and '.join(sees)} errors over the calibration "
                "positions, mm")
        rows += [[what, best.get("objective")],
                 ["simulations", fit_info.get("n_simulations")],
                 ["failed simulations", fit_info.get("n_failed")],
                 ["calibration positions", ", ".join(fit_info.get("calibrate", []))],
                 ["held-out positions", ", ".join(fit_info.get("evaluate", []))]]
        parts += [f"<h2>Fit ({html.escape(str(fit_info.get('method')))})</h2>",
                  _table(["", "value"], rows)]
    if fit_info and fit_info.get("sensitivity"):
        srows = [[k, s.get("value"), s.get("objective_low"), s.get("objective_high"),
                  s.get("elasticity")] for k, s in fit_info["sensitivity"].items()]
        parts += ["<h2>Sensitivity at the optimum</h2>",
                  _table(["parameter", "value", "MHD at -10%", "MHD at +10%",
                          "d ln MHD / d ln p"], srows)]
    return parts


def _file_sections(metrics: Mapping[str, Any], images: Mapping[str, Any] | None) -> list[str]:
    """The files the run wrote, and its FEBio models."""
    parts = []
    blocks = (metrics.get("files") or {}).get("positions") or {}
    files = ["run.vtm (ParaView)", *(f for b in blocks.values() for f in b.values()),
             *(e["file"] for e in ((metrics.get("files") or {}).get("febio") or {}).values()
               if e.get("file"))]
    if images:
        files += [*images["volumes"].values(), *images["labels"].values(),
                  *(images.get("segmentations") or {}).values(),
                  *images["transforms"].values(), *images.get("colour_tables", []),
                  *(f"{p}_fiducials.mrk.json" for p, v in images["fiducials"].items() if v)]
    if blocks:
        parts += ["<h2 id='files'>Files</h2>",
                  "<p>" + ", ".join(html.escape(f) for f in files) + "</p>"]
    feb = (metrics.get("files") or {}).get("febio") or {}
    if feb:
        parts += ["<h2 id='febio'>FEBio models</h2>",
                  "<p>One FEBio 4 file per position on the stress-free geometry; open it in "
                  "FEBio Studio or run <code>febio4 -i FILE</code>.</p>",
                  _table(["position", "file", "element", "approximations or why not written",
                          "notes"],
                         [[p, e.get("file") or "not written", e.get("element", "-"),
                           "; ".join(e.get("approximations") or []) or e.get("why") or "none",
                           "; ".join(e.get("notes") or []) or "-"]
                          for p, e in feb.items()])]
    return parts
