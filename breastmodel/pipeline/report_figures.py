"""The report's pictures: error maps of the predicted skin, the stress-free and fit
histories, and the segmentation and registration QA slices, each as a matplotlib figure, and
:func:`img_tag`, a figure as an embedded PNG ``<img>``."""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Mapping
from typing import Any

import numpy as np


def png_base64(fig) -> str:
    """``fig`` as a base64 PNG (90 dpi), the figure closed."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def error_figure(name: str, v: np.ndarray, f: np.ndarray, err: np.ndarray,
                  measured: tuple[np.ndarray, np.ndarray], lim: float):
    """Anterior (x-z) and lateral (y-z) views of the predicted skin coloured by the signed
    node-to-surface error on the colour scale [-lim, lim] mm (one for every position), with
    the measured skin's vertices in grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.tri import Triangulation

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    mv = measured[0]
    for ax, (i, j, title) in zip(axes, [(0, 2, "anterior view: R <- x -> L, z up = S"),
                                        (1, 2, "lateral view: A <- y -> P, z up = S")]):
        ax.scatter(mv[:, i], mv[:, j], s=0.2, c="0.75", rasterized=True)
        tri = Triangulation(v[:, i], v[:, j], f)
        pc = ax.tripcolor(tri, err, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="gouraud")
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(("x" if i == 0 else "y") + " (mm)")
        ax.set_ylabel("z (mm)")
    fig.colorbar(pc, ax=axes, shrink=0.85, label="signed error, mm (+ outside measured skin)")
    fig.suptitle(f"{name}: predicted skin vs measured (grey)")
    return fig


def history_figure(fit_info: Mapping[str, Any] | None, sf: Mapping[str, Any]):
    """The stress-free iterations' node mismatch (mean, max) and, with a fit, every
    evaluation's objective with the best so far."""
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


def _figure(n: int, width: float = 4.2, height: float = 4.0):
    """A figure of ``n`` axes side by side (inches each)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, n, figsize=(width * n, height), squeeze=False)
    return fig, list(axes[0])


def segmentation_figure(name: str, img, labels, title: str):
    """Axial, coronal and sagittal slices of ``img`` through the labelled tissue, the
    labels drawn over it."""
    from imaging.views import centre_index, draw_slice

    fig, axes = _figure(3)
    for ax, view in zip(axes, ("axial", "coronal", "sagittal")):
        draw_slice(ax, img, view, centre_index(img, view, labels), labels=labels)
    fig.suptitle(f"{name}: {title} (orange breast, red muscle, green gland)", fontsize=10)
    fig.tight_layout()
    return fig


def registration_figure(name: str, reference, moved, ref_labels, points):
    """Axial, coronal and sagittal slices of ``reference`` with ``moved`` overlaid (a
    registered position) and its fiducial ``points``."""
    from imaging.views import centre_index, draw_slice

    fig, axes = _figure(3)
    for ax, view in zip(axes, ("axial", "coronal", "sagittal")):
        draw_slice(ax, reference, view, centre_index(reference, view, ref_labels),
                   overlay=moved, points=points)
    fig.suptitle(f"{name} registered onto the reference: reference green, {name} magenta, "
                 "grey where they agree; cyan: fiducials", fontsize=10)
    fig.tight_layout()
    return fig


def img_tag(fig, alt: str) -> str:
    """``fig`` as an ``<img>`` tag with the PNG embedded."""
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{png_base64(fig)}">'
