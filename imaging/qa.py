"""Segmentation quality: Dice per tissue, tissue volumes, and a contour overlay figure.

Compute functions return numbers; :func:`qa_figure` is the only plotting function and is
called by the command and the notebook, never by compute code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from imaging.atomic import write_atomic_with
from imaging.labels import BREAST, BREAST_TISSUE, GLAND, LABEL_COLOURS, TISSUES


def _same_grid(a: sitk.Image, b: sitk.Image) -> bool:
    return (a.GetSize() == b.GetSize()
            and np.allclose(a.GetSpacing(), b.GetSpacing(), atol=1e-4)
            and np.allclose(a.GetOrigin(), b.GetOrigin(), atol=1e-3)
            and np.allclose(a.GetDirection(), b.GetDirection(), atol=1e-5))


def dice(labels: sitk.Image, truth: sitk.Image, *, merge_gland: bool = True) -> dict[str, float]:
    """Dice coefficient per tissue, ``2|A n B| / (|A| + |B|)``.

    Parameters
    ----------
    labels, truth : SimpleITK.Image
        Label maps (0/1/2/3) on the same grid.
    merge_gland : bool
        Count gland (3) as breast (1) for the ``breast`` score, as the breast label of the
        convention includes gland; ``gland`` is then scored separately when either has it.

    Returns
    -------
    dict tissue name -> Dice in [0, 1] (NaN when both maps lack the tissue)
    """
    if not _same_grid(labels, truth):
        raise ValueError("segmentation QA: label map and truth are on different grids")
    a = sitk.GetArrayViewFromImage(labels)
    b = sitk.GetArrayViewFromImage(truth)
    out = {}
    for code, name in TISSUES.items():
        if code == BREAST and merge_gland:
            ma, mb = np.isin(a, BREAST_TISSUE), np.isin(b, BREAST_TISSUE)
        else:
            ma, mb = a == code, b == code
        if code == GLAND and not (ma.any() and mb.any()):
            continue
        denom = int(ma.sum()) + int(mb.sum())
        out[name] = float(2 * np.count_nonzero(ma & mb) / denom) if denom else float("nan")
    return out


def tissue_volumes_ml(labels: sitk.Image) -> dict[str, float]:
    """Volume of each tissue in millilitres (1 ml = 1000 mm^3)."""
    a = sitk.GetArrayViewFromImage(labels)
    vox = float(np.prod(labels.GetSpacing())) / 1000.0
    counts = np.bincount(a.ravel().astype(np.int64), minlength=max(TISSUES) + 1)
    return {name: float(counts[code] * vox) for code, name in TISSUES.items()}


def slice_centre(labels: sitk.Image) -> tuple[int, int, int]:
    """(z, y, x) array index of the centroid of the labelled voxels (volume centre if none)."""
    a = sitk.GetArrayViewFromImage(labels)
    idx = np.argwhere(a > 0)
    if len(idx) == 0:
        return tuple(int(n // 2) for n in a.shape)
    return tuple(int(v) for v in np.round(idx.mean(axis=0)))


_LETTERS = (("R", "L"), ("A", "P"), ("I", "S"))  # (negative, positive) of LPS x, y, z


def _letter(vec) -> str:
    """Anatomical letter of the LPS axis a direction vector mostly follows."""
    v = np.asarray(vec, float)
    k = int(np.argmax(np.abs(v)))
    return _LETTERS[k][int(v[k] > 0)]


#: The three views of :func:`qa_figure`: (name, horizontal index axis, vertical index axis,
#: row 0 at the top).
VIEWS = (("axial", 0, 1, True), ("coronal", 0, 2, False), ("sagittal", 1, 2, False))


def view_orientation(img: sitk.Image) -> dict[str, dict[str, str]]:
    """Anatomical letters (L/R, A/P, S/I) at the four edges of each view of :func:`qa_figure`.

    Parameters
    ----------
    img : SimpleITK.Image
        The volume (its direction matrix decides).

    Returns
    -------
    dict view name -> {"left", "right", "top", "bottom"} -> letter
    """
    d = np.asarray(img.GetDirection(), float).reshape(3, 3)
    out = {}
    for name, h, v, top_first in VIEWS:
        first_v, last_v = _letter(-d[:, v]), _letter(d[:, v])
        out[name] = {"left": _letter(-d[:, h]), "right": _letter(d[:, h]),
                     "top": first_v if top_first else last_v,
                     "bottom": last_v if top_first else first_v}
    return out


def qa_figure(img: sitk.Image, labels: sitk.Image, *, seeds=None, centre=None, title=""):
    """Axial, sagittal and coronal slices of ``img`` with label contours and the anatomical
    letters (L/R, A/P, S/I, from the image's direction matrix) at the edges of each view.

    Parameters
    ----------
    img, labels : SimpleITK.Image
        Volume and label map on the same grid.
    seeds : (K, 3) mm, optional
        Seed points to mark (drawn on the slice nearest to each).
    centre : (z, y, x) index, optional
        Slice position (default: centroid of the labels).
    title : str
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    a = sitk.GetArrayFromImage(img).astype(float)
    lab = sitk.GetArrayViewFromImage(labels)
    sx, sy, sz = img.GetSpacing()
    cz, cy, cx = slice_centre(labels) if centre is None else centre
    views = [
        ("axial", a[cz], lab[cz], sy / sx),
        ("coronal", a[:, cy, :], lab[:, cy, :], sz / sx),
        ("sagittal", a[:, :, cx], lab[:, :, cx], sz / sy),
    ]
    lo, hi = np.percentile(np.concatenate([v[1].ravel() for v in views]), [1, 99.5])
    orient = view_orientation(img)
    fig = Figure(figsize=(13, 4.5))
    for ax, (name, im, lb, aspect) in zip(fig.subplots(1, 3), views):
        origin = "upper" if name == "axial" else "lower"
        ax.imshow(im, cmap="gray", vmin=lo, vmax=hi, aspect=aspect, origin=origin)
        for code, col in LABEL_COLOURS.items():
            m = lb == code
            if m.any() and not m.all():
                # contour follows the axes that imshow set up (row 0 on top for axial)
                ax.contour(m.astype(float), levels=[0.5], colors=col, linewidths=0.8)
        ax.set_title(name)
        ax.set_axis_off()
        for edge, (x, y, ha, va) in {"left": (0.01, 0.5, "left", "center"),
                                     "right": (0.99, 0.5, "right", "center"),
                                     "top": (0.5, 0.99, "center", "top"),
                                     "bottom": (0.5, 0.01, "center", "bottom")}.items():
            ax.text(x, y, orient[name][edge], transform=ax.transAxes, ha=ha, va=va,
                    color="yellow", fontsize=11, fontweight="bold")
    if seeds is not None and len(seeds):
        idx = np.asarray([img.TransformPhysicalPointToContinuousIndex(tuple(map(float, p)))
                          for p in np.asarray(seeds, float)])
        axes = fig.axes
        axes[0].plot(idx[:, 0], idx[:, 1], "c+", ms=10)
        axes[1].plot(idx[:, 0], idx[:, 2], "c+", ms=10)
        axes[2].plot(idx[:, 1], idx[:, 2], "c+", ms=10)
    fig.suptitle(f"{title}  (orange breast, red muscle, green gland)".strip())
    fig.tight_layout()
    return fig


def save_figure(fig, path: str | Path, *, dpi: int = 90) -> None:
    """Save a figure as PNG atomically."""
    write_atomic_with(path, lambda tmp: fig.savefig(tmp, dpi=dpi), suffix=".png")
