"""Slices of a volume with the patient's directions on the axes (radiological display).

Every view is taken from the volume reoriented to LPS index axes (i -> patient left,
j -> posterior, k -> superior), so the labels hold whatever the file's direction matrix:

- axial (fixed k): patient right on the screen's left, anterior on top;
- coronal (fixed j): right on the left, superior on top;
- sagittal (fixed i): anterior on the left, superior on top.

Axes are in physical mm; :func:`draw_slice` draws one view (image, label contours, marks)
into a matplotlib axes, for reports and the QA notebook.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import SimpleITK as sitk

from imaging.labels import LABEL_COLOURS

__all__ = ["ORIENTATIONS", "LABEL_COLOURS", "lps", "slice_count", "centre_index",
           "oriented_slice", "slice_position_mm", "draw_slice", "views_figure", "slice_browser"]

#: view -> (fixed array axis in (z, y, x), (screen-left, screen-right), (bottom, top))
ORIENTATIONS = {"axial": (0, ("R", "L"), ("P", "A")),
                "coronal": (1, ("R", "L"), ("I", "S")),
                "sagittal": (2, ("A", "P"), ("I", "S"))}


def lps(img: sitk.Image) -> sitk.Image:
    """The volume with its index axes along L, P, S (a copy when it has to be flipped)."""
    d = np.asarray(img.GetDirection()).reshape(3, 3)
    if np.allclose(d, np.eye(3)):
        return img
    return sitk.DICOMOrient(img, "LPS")


def slice_count(img: sitk.Image, view: str) -> int:
    """Number of slices of ``view`` in the LPS-oriented volume."""
    axis = ORIENTATIONS[view][0]
    return int(lps(img).GetSize()[::-1][axis])


def centre_index(img: sitk.Image, view: str, labels: sitk.Image | None = None) -> int:
    """Slice index of ``view`` that cuts the most breast tissue (labels 1 and 3; else any
    label) of ``labels``, or the volume's middle slice without labels."""
    axis = ORIENTATIONS[view][0]
    if labels is None:
        return int(lps(img).GetSize()[::-1][axis] // 2)
    a = sitk.GetArrayFromImage(lps(labels))  # a copy: a view would outlive the temporary image
    other = tuple(i for i in range(3) if i != axis)
    for mask in (np.isin(a, (1, 3)), a > 0):
        count = mask.sum(axis=other)
        if count.any():
            return int(np.argmax(count))
    return a.shape[axis] // 2


def oriented_slice(img: sitk.Image, view: str, index: int) -> tuple[np.ndarray, list[float]]:
    """One slice of the LPS-oriented volume and its extent.

    Returns
    -------
    plane : (rows, cols) array, row 0 at the bottom of the screen (``origin="lower"``)
    extent : [left, right, bottom, top] in mm, for ``imshow(extent=...)``
    """
    o = lps(img)
    a = sitk.GetArrayViewFromImage(o)
    axis = ORIENTATIONS[view][0]
    index = int(np.clip(index, 0, a.shape[axis] - 1))
    sp, org = np.asarray(o.GetSpacing()), np.asarray(o.GetOrigin())
    n = np.asarray(o.GetSize())
    lo, hi = org - 0.5 * sp, org + (n - 0.5) * sp  # voxel edges, mm (LPS axes)
    if view == "axial":  # cols x (R -> L), rows y; anterior (small y) on top
        plane = a[index][::-1]
        return np.asarray(plane), [lo[0], hi[0], hi[1], lo[1]]
    if view == "coronal":  # cols x, rows z (I -> S)
        return np.asarray(a[:, index, :]), [lo[0], hi[0], lo[2], hi[2]]
    # sagittal: cols y (A -> P), rows z
    return np.asarray(a[:, :, index]), [lo[1], hi[1], lo[2], hi[2]]


def slice_position_mm(img: sitk.Image, view: str, index: int) -> float:
    """Physical coordinate (mm, LPS) of a slice along its fixed axis."""
    o = lps(img)
    axis_xyz = 2 - ORIENTATIONS[view][0]
    return float(o.GetOrigin()[axis_xyz] + index * o.GetSpacing()[axis_xyz])


def draw_slice(ax, img: sitk.Image, view: str, index: int, *,
               labels: sitk.Image | None = None, overlay: sitk.Image | None = None,
               points: Mapping[str, np.ndarray] | None = None, window=None,
               title: str | None = None) -> None:
    """Draw one view into ``ax``: grey image, label contours, an optional second image in
    magenta over the first in green, and points within half a slice.

    Parameters
    ----------
    ax : matplotlib Axes
    img : the volume
    view : ``"axial"``, ``"coronal"`` or ``"sagittal"``
    index : slice index along the view's fixed axis (LPS-oriented volume)
    labels : label map on the same grid (contours coloured by :data:`LABEL_COLOURS`)
    overlay : a second volume on the same grid (registration check: green = ``img``,
        magenta = ``overlay``, grey where they agree)
    points : name -> (3,) LPS mm, marked with a cross and the name
    window : (low, high) grey window (default: 1st and 99.5th percentiles of the slice)
    title : axes title (default: the view and the slice position in mm)
    """
    plane, ext = oriented_slice(img, view, index)
    plane = plane.astype(float)
    lo, hi = window if window is not None else np.percentile(plane, [1, 99.5])
    scale = max(hi - lo, 1e-12)
    if overlay is not None:
        other = oriented_slice(overlay, view, index)[0].astype(float)
        olo, ohi = np.percentile(other, [1, 99.5])
        g = np.clip((plane - lo) / scale, 0, 1)
        m = np.clip((other - olo) / max(ohi - olo, 1e-12), 0, 1)
        ax.imshow(np.dstack([m, g, m]), extent=ext, origin="lower", interpolation="nearest")
    else:
        ax.imshow(plane, cmap="gray", vmin=lo, vmax=hi, extent=ext, origin="lower",
                  interpolation="nearest")
    if labels is not None:
        lab = oriented_slice(labels, view, index)[0]
        ny, nx = lab.shape
        xs = np.linspace(ext[0], ext[1], nx + 1)
        ys = np.linspace(ext[2], ext[3], ny + 1)
        xc, yc = 0.5 * (xs[1:] + xs[:-1]), 0.5 * (ys[1:] + ys[:-1])
        for code, col in LABEL_COLOURS.items():
            m = lab == code
            if m.any() and not m.all():
                ax.contour(xc, yc, m.astype(float), levels=[0.5], colors=col, linewidths=0.8)
    pos = slice_position_mm(img, view, index)
    axis_xyz = 2 - ORIENTATIONS[view][0]
    half = 0.5 * lps(img).GetSpacing()[axis_xyz]
    cols = {"axial": (0, 1), "coronal": (0, 2), "sagittal": (1, 2)}[view]
    for name, p in (points or {}).items():
        p = np.asarray(p, float)
        if abs(p[axis_xyz] - pos) <= half:
            ax.plot(p[cols[0]], p[cols[1]], "c+", ms=10)
            ax.annotate(name, (p[cols[0]], p[cols[1]]), color="c", fontsize=7)
    _, (left, right), (bottom, top) = ORIENTATIONS[view]
    names = "xyz"
    ax.set_xlabel(f"{left}  <-  {names[cols[0]]} (mm)  ->  {right}", fontsize=8)
    ax.set_ylabel(f"{bottom}  <-  {names[cols[1]]} (mm)  ->  {top}", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_aspect("equal")
    ax.set_title(title if title is not None
                 else f"{view} {names[axis_xyz]} = {pos:.1f} mm", fontsize=9)


def views_figure(img: sitk.Image, labels: sitk.Image | None = None, *,
                 indices: Mapping[str, int] | None = None, title: str = ""):
    """Axial, coronal and sagittal views side by side (:func:`draw_slice`), at ``indices``
    (view -> slice index; default :func:`centre_index`). Returns a matplotlib Figure."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 4.5))
    for ax, view in zip(fig.subplots(1, 3), ORIENTATIONS):
        i = (indices or {}).get(view, centre_index(img, view, labels))
        draw_slice(ax, img, view, i, labels=labels)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def slice_browser(img: sitk.Image, labels: sitk.Image | None = None):
    """A Jupyter widget that scrolls through the volume in all three orientations: one slider
    per view (slice index; the title gives its position in mm) above the three views with
    label contours and patient directions on the axes.

    Returns
    -------
    ipywidgets.VBox
        ``.sliders`` (view -> IntSlider) and ``.figure`` (the matplotlib Figure drawn) are
        attached for scripted use.
    """
    import ipywidgets as w
    from IPython.display import display

    sliders = {view: w.IntSlider(value=centre_index(img, view, labels), min=0,
                                 max=slice_count(img, view) - 1, description=view,
                                 continuous_update=False,
                                 layout=w.Layout(width="32%"))
               for view in ORIENTATIONS}
    out = w.Output()
    box = w.VBox([w.HBox(list(sliders.values())), out])

    def redraw(_=None):
        box.figure = views_figure(img, labels, indices={k: s.value for k, s in sliders.items()})
        out.clear_output(wait=True)
        with out:
            display(box.figure)

    for s in sliders.values():
        s.observe(redraw, names="value")
    box.sliders = sliders
    redraw()
    return box
