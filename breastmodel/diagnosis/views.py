"""Pictures of where the model fails (matplotlib, Agg): drawing only, no computation.

The inputs are :func:`breastmodel.diagnosis.maps.failure_map` dicts. Every error map of one
figure, or of one report, uses ONE symmetric colour scale (:func:`error_limit` over every map
shown), so that colours compare across positions and across model revisions.

Views (LPS mm; projections, not mirror images: horizontal x vertical points at the viewer;
the painter's algorithm draws the farthest triangles first):

* ``anterior``: from the front; horizontal x (the patient's left on the right), vertical z.
* ``lateral``: from the patient's left; horizontal y (anterior on the left), vertical z; the
  left breast hides most of the right one. ``right_lateral``: from the patient's right;
  horizontal -y (anterior on the right).
* ``inferior``: from the feet; horizontal x, vertical -y (anterior up).
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "VIEWS", "error_limit", "error_maps_figure", "error_vs_strain_figure", "img_tag",
    "png_base64", "png_bytes", "revision_figure", "value_maps_figure",
]

#: name -> (direction towards the viewer, horizontal axis, vertical axis), unit vectors, LPS.
VIEWS: dict[str, tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]] = {
    "anterior": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    "lateral": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "right_lateral": ((-1, 0, 0), (0, -1, 0), (0, 0, 1)),
    "inferior": ((0, 0, -1), (1, 0, 0), (0, -1, 0)),
}
_AXIS_NAMES = {(1, 0, 0): "x (patient left), mm", (0, -1, 0): "-y (anterior), mm",
               (0, 1, 0): "y (posterior), mm", (0, 0, 1): "z (superior), mm"}
CMAP = "RdBu_r"
CBAR_LABEL = "signed error, mm (+ = predicted outside measured skin)"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def error_limit(maps: Iterable[Mapping[str, Any]], *, percentile: float = 98.0) -> float:
    """Shared symmetric colour limit (mm): the ``percentile`` of |signed error| over all maps
    (robust to a few outliers); 1 mm when there is no error at all."""
    errs = [np.abs(np.asarray(m["signed_error"], float)) for m in maps]
    errs = np.concatenate(errs) if errs else np.zeros(0)
    errs = errs[np.isfinite(errs)]
    lim = float(np.percentile(errs, percentile)) if len(errs) else 0.0
    return lim if lim > 0 else 1.0


def draw_error_map(ax, fm: Mapping[str, Any], view: str, *, limit: float,
                   measured: bool = True):
    """Draw one map on ``ax``: the measured skin in light grey below, the predicted skin
    coloured by the signed error (per triangle: the mean of its nodes). Returns the
    collection (for a colour bar)."""
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import Normalize

    if view not in VIEWS:
        raise ValueError(f"diagnose: unknown view {view!r}; known: {sorted(VIEWS)}")
    toward, h, v = (np.asarray(a, float) for a in VIEWS[view])
    basis = np.stack([h, v])
    if measured and fm.get("measured") is not None:
        mv, mf = fm["measured"]
        mv2 = np.asarray(mv) @ basis.T
        ax.add_collection(PolyCollection(mv2[np.asarray(mf)], facecolors="0.82",
                                         edgecolors="none", rasterized=True))
    pts, faces = np.asarray(fm["points"]), np.asarray(fm["faces"])
    order = np.argsort(pts[faces].mean(axis=1) @ toward)  # farthest first
    faces = faces[order]
    err = np.asarray(fm["signed_error"], float)[faces].mean(axis=1)
    pc = PolyCollection((pts @ basis.T)[faces], array=err, cmap=CMAP,
                        norm=Normalize(-limit, limit), edgecolors="face", linewidths=0.2,
                        rasterized=True)
    ax.add_collection(pc)
    allp = pts @ basis.T
    if measured and fm.get("measured") is not None:
        allp = np.vstack([allp, mv2])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    pad = 0.03 * float(np.max(hi - lo) or 1.0)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel(_AXIS_NAMES.get(tuple(int(c) for c in h), "mm"), fontsize=7)
    ax.set_ylabel(_AXIS_NAMES.get(tuple(int(c) for c in v), "mm"), fontsize=7)
    ax.tick_params(labelsize=6)
    return pc


def error_maps_figure(rows: Mapping[str, Mapping[str, Any]], *,
                      views: Sequence[str] = ("anterior", "lateral", "inferior"),
                      limit: float | None = None, title: str | None = None):
    """One row per map (e.g. per position, or per run of one position), one column per view,
    with one shared symmetric colour scale.

    Parameters
    ----------
    rows : row label -> :func:`~breastmodel.diagnosis.maps.failure_map` dict
    views : names of :data:`VIEWS`
    limit : colour limit, mm (default :func:`error_limit` of the rows; pass the same value
        to every figure of a report)
    title : figure title

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _plt()
    if not rows:
        raise ValueError("diagnose: no error map to draw")
    limit = error_limit(rows.values()) if limit is None else float(limit)
    fig, axes = plt.subplots(len(rows), len(views), squeeze=False, layout="constrained",
                             figsize=(3.6 * len(views) + 1.0, 3.2 * len(rows)))
    pc = None
    for i, (label, fm) in enumerate(rows.items()):
        for j, view in enumerate(views):
            pc = draw_error_map(axes[i, j], fm, view, limit=limit)
            axes[i, j].set_title(f"{label}: {view}", fontsize=8)
    fig.colorbar(pc, ax=axes, shrink=0.8, label=CBAR_LABEL)
    if title:
        fig.suptitle(title)
    return fig


def value_maps_figure(maps: Mapping[str, Mapping[str, Any]],
                      rows: Mapping[str, Mapping[str, np.ndarray]], *,
                      view: str = "anterior", limit: float | None = None):
    """One row per label, one column per position: a value per skin node (NaN: not drawn)
    on the predicted skin of that position, one symmetric colour scale for all.

    Parameters
    ----------
    maps : position -> :func:`~breastmodel.diagnosis.maps.failure_map` dict (the skin)
    rows : label -> {position: (n,) value per skin node of that map, mm}
    view : a name of :data:`VIEWS`
    limit : colour limit, mm (default: the 98th percentile of |value| over every row)

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = _plt()
    positions = [p for p in maps if any(p in r for r in rows.values())]
    if not rows or not positions:
        raise ValueError("diagnose: no map to draw")
    if limit is None:
        limit = error_limit({"signed_error": v} for r in rows.values() for v in r.values())
    fig, axes = plt.subplots(len(rows), len(positions), squeeze=False, layout="constrained",
                             figsize=(3.4 * len(positions) + 1.0, 2.6 * len(rows)))
    pc = None
    for i, (label, vals) in enumerate(rows.items()):
        for j, pos in enumerate(positions):
            ax = axes[i, j]
            if pos not in vals:
                ax.set_axis_off()
                continue
            fm = {**maps[pos], "signed_error": np.asarray(vals[pos], float)}
            pc = draw_error_map(ax, fm, view, limit=limit)
            ax.set_title(f"{label}: {pos}", fontsize=8)
    if pc is not None:
        fig.colorbar(pc, ax=axes, shrink=0.8, label="mm (+ = predicted outside measured skin)")
    return fig


def error_vs_strain_figure(maps: Mapping[str, Mapping[str, Any]], *,
                           tables: Mapping[str, Mapping[str, Any]] | None = None):
    """Signed skin error against the local strain, one panel per position: the nodes as
    dots and, when ``tables`` (position -> ``error_vs_strain`` dict of
    :func:`~breastmodel.diagnosis.maps.failure_tables`) is given, the binned mean |error|
    and the Spearman correlation in the title."""
    plt = _plt()
    n = max(len(maps), 1)
    fig, axes = plt.subplots(1, n, figsize=(3.8 * n, 3.2), squeeze=False)
    for ax, (pos, fm) in zip(axes[0], maps.items()):
        s, d = np.asarray(fm["strain"], float), np.asarray(fm["signed_error"], float)
        ax.scatter(s, d, s=3, alpha=0.4, c="0.3", rasterized=True, label="skin nodes")
        ax.axhline(0.0, color="0.6", lw=0.8)
        t = (tables or {}).get(pos)
        title = pos
        if t:
            b = t.get("bins") or []
            if b:
                mid = [0.5 * (r["strain_lo"] + r["strain_hi"]) for r in b]
                ax.plot(mid, [r["mean_abs_mm"] for r in b], "o-", color="C3",
                        label="binned mean |error|")
            if t.get("spearman_abs") is not None:
                title += f"  (Spearman |e|: {t['spearman_abs']:.2f})"
        ax.set_title(title, fontsize=8)
        ax.set_xlabel("max principal Green-Lagrange strain", fontsize=7)
        ax.set_ylabel("signed error, mm", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.legend(fontsize=6)
    fig.tight_layout()
    return fig


def revision_figure(values: Mapping[str, Sequence[float]], labels: Sequence[str], *,
                    ylabel: str = "MHD, mm"):
    """A metric per position (one line each) against model revision.

    Parameters
    ----------
    values : position -> one value per run, in run order (mm)
    labels : one x tick label per run (e.g. ``"+ sliding"``)
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(max(4.0, 1.6 * len(labels) + 2.0), 3.4))
    xs = np.arange(len(labels))
    for pos, ys in values.items():
        ax.plot(xs, np.asarray(ys, float), "o-", label=pos)
    ax.set_xticks(xs)
    ax.set_xticklabels(labels, fontsize=7, rotation=20, ha="right")
    ax.set_xlabel("model revision")
    ax.set_ylabel(ylabel)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def png_bytes(fig, *, dpi: int = 90) -> bytes:
    """The figure as PNG bytes; closes the figure."""
    plt = _plt()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def png_base64(fig, *, dpi: int = 90) -> str:
    """The figure as a base64 PNG string (for ``data:image/png;base64,...``); closes it."""
    return base64.b64encode(png_bytes(fig, dpi=dpi)).decode("ascii")


def img_tag(fig, alt: str, *, dpi: int = 90) -> str:
    """A self-contained ``<img>`` element embedding the figure; closes it."""
    return (f'<img alt="{html.escape(alt)}" '
            f'src="data:image/png;base64,{png_base64(fig, dpi=dpi)}">')
