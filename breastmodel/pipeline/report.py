"""A single self-contained HTML report (pictures embedded as base64 PNG)."""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_report"]


def _png(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _error_figure(name: str, v: np.ndarray, f: np.ndarray, err: np.ndarray,
                  measured: tuple[np.ndarray, np.ndarray]):
    """Anterior (x-z) and lateral (y-z) views of the predicted skin coloured by the signed
    node-to-surface error, with the measured skin's vertices in grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    lim = float(np.nanpercentile(np.abs(err), 98)) if len(err) else 1.0
    lim = lim if lim > 0 else 1.0
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    mv = measured[0]
    for ax, (i, j, title) in zip(axes, [(0, 2, "anterior view (x: patient left, z: superior)"),
                                        (1, 2, "lateral view (y: posterior, z: superior)")]):
        ax.scatter(mv[:, i], mv[:, j], s=0.2, c="0.75", rasterized=True)
        tri = Triangulation(v[:, i], v[:, j], f)
        pc = ax.tripcolor(tri, err, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="gouraud")
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("mm")
    fig.colorbar(pc, ax=axes, shrink=0.85, label="signed error, mm (+ outside measured skin)")
    fig.suptitle(f"{name}: predicted skin vs measured (grey)")
    return fig


def _history_figure(fit_info: Mapping[str, Any] | None, sf: Mapping[str, Any]):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = 2 if fit_info else 1
    fig, axes = plt.subplots(1, n, figsize=(5 * n, 3.4), squeeze=False)
    ax = axes[0, 0]
    hist = sf.get("history") or []
    if hist:
        ax.semilogy([r["iteration"] for r in hist], [max(r["mean_error"], 1e-9) for r in hist],
                    "o-", label="mean")
        ax.semilogy([r["iteration"] for r in hist], [max(r["max_error"], 1e-9) for r in hist],
                    "s--", label="max")
        ax.legend()
    ax.set_xlabel("iteration")
    ax.set_ylabel("node mismatch, mm")
    ax.set_title(f"stress-free: {sf.get('method')}", fontsize=9)
    if fit_info:
        ax = axes[0, 1]
        h = fit_info.get("history", [])
        y = np.array([r["objective"] if r["objective"] is not None else math.nan for r in h],
                     float)
        ax.plot(np.arange(1, len(y) + 1), y, ".", label="evaluation")
        ok = np.where(np.isfinite(y), y, np.inf)
        ax.plot(np.arange(1, len(y) + 1), np.minimum.accumulate(ok), "-", label="best so far")
        ax.set_xlabel("simulation")
        ax.set_ylabel("mean MHD on calibration positions, mm")
        ax.set_title(f"fit: {fit_info.get('method')}", fontsize=9)
        ax.legend()
    fig.tight_layout()
    return fig


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.3f}"
    return html.escape(str(v))


def _table(header: list[str], rows: list[list]) -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_fmt(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def write_report(path: Path, metrics: Mapping[str, Any], params: Mapping[str, Any],
                 pictures: Mapping[str, tuple], fit_info: Mapping[str, Any] | None,
                 sf: Mapping[str, Any], *, subject_id: str) -> Path:
    """Write ``path`` (HTML): metrics table, per-region and landmark tables, error maps per
    position, the stress-free and fit histories, and the parameters."""
    from breastmodel.config import write_atomic

    pos = metrics["positions"]
    parts = [f"<h1>breastmodel run: {html.escape(subject_id)}</h1>",
             "<h2>Skin surface distances (mm)</h2>",
             _table(["position", "MHD", "Hausdorff", "RMSE", "p95", "converged"],
                    [[p, m.get("mhd_mm"), m.get("hausdorff_mm"), m.get("rmse_mm"),
                      m.get("p95_mm"), m.get("converged")] for p, m in pos.items()])]
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
    parts.append("<h2>Error maps</h2>")
    for name, (v, f, err, measured) in pictures.items():
        png = _png(_error_figure(name, v, f, err, measured))
        parts.append(f'<img alt="{html.escape(name)}" src="data:image/png;base64,{png}">')
    parts += ["<h2>Stress-free geometry and fit</h2>",
              f'<img alt="history" src="data:image/png;base64,'
              f'{_png(_history_figure(fit_info, sf))}">',
              "<h2>Parameters</h2>",
              _table(["parameter", "value"], [[k, v] for k, v in
                                              params.get("parameters", {}).items()])]
    if fit_info:
        best = fit_info.get("best", {})
        rows = [[k, v] for k, v in best.get("params", {}).items()]
        rows += [["mean MHD of the calibration positions, mm", best.get("objective")],
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
    style = ("body{font-family:sans-serif;max-width:1100px;margin:auto}"
             "table{border-collapse:collapse;margin:8px 0}"
             "td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}"
             "img{max-width:100%}")
    doc = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>breastmodel "
           f"{html.escape(subject_id)}</title><style>{style}</style></head><body>"
           + "\n".join(parts) + "</body></html>\n")
    write_atomic(path, doc)
    return path
