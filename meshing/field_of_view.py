"""Where the reference scan's field of view cut the model's breast: its boundary faces on the
image's faces, which the body goes on past and the model does not.

Near such a cut the model is less sure than elsewhere: its free face stands where the body went
on, and tissue that lay out of view in the reference (laterally, in supine) comes into view in
another position (prone) without the model having it. The pipeline's default model holds the
muscle's cut (``mechanics.effects.cut_faces``: the chest wall goes on to the thorax) and leaves
the breast's free. Measured on the validation suite, whose truths go on past the cuts since
2026-12-02 (truth labels; the fitted model's skin against FEBio's, so neither registration nor
measured skin enters; ``bench/fov_cut.py``, ``bench/results/fov_cut_2026-12-02b.json``): within
15 mm of the cut faces the skin is off by 0.56-0.97 mm on average (the coil small-000 in prone
0.82 mm, 1.26 mm with the muscle's cut free), elsewhere 0.16-0.31 mm. The cut share of
:func:`breast_cut` says where this applies; what it costs depends on how much tissue crosses
the cut, which the reference alone cannot show.
"""

from __future__ import annotations

import numpy as np

from mechanics.mesh import BREAST_SIDE, Mesh
from meshing.labels import Grid
from meshing.sets import tet_faces
from meshing.surface import fov_faces, triangle_areas

__all__ = ["CUT_SHARE", "breast_cut", "cut_warning"]

#: Share of a breast's skin area above which the cut is said to matter (:func:`cut_warning`).
CUT_SHARE = 0.05


def breast_cut(mesh: Mesh, grid: Grid) -> dict[str, dict[str, float]]:
    """Per breast side ("left", "right"): ``cut_mm2``, the area of the breast's boundary faces
    on a field-of-view plane of the label map it was meshed from (``grid``), ``skin_mm2``, the
    area of its other boundary faces (skin), and ``share``, cut over skin."""
    bf, owner, _, _ = tet_faces(mesh.tets)
    side = np.array([BREAST_SIDE.get(int(r), 0) for r in mesh.region])[owner]
    cut = fov_faces(mesh.nodes, bf, grid)
    area = triangle_areas(mesh.nodes, bf)
    out = {}
    for name, code in (("left", 1), ("right", 3)):
        on = side == code
        c, s = float(area[on & cut].sum()), float(area[on & ~cut].sum())
        if s > 0:
            out[name] = {"cut_mm2": round(c, 1), "skin_mm2": round(s, 1),
                         "share": round(c / s, 4)}
    return out


def cut_warning(cut: dict[str, dict[str, float]], reference: str) -> str | None:
    """The warning for a reference scan whose field of view cut a breast over more than
    :data:`CUT_SHARE` of its skin area (``cut``: :func:`breast_cut`); None otherwise."""
    over = {s: c for s, c in cut.items() if c["share"] > CUT_SHARE}
    if not over:
        return None
    parts = [f"the {s} breast over {c['cut_mm2']:.0f} mm^2 ({100 * c['share']:.0f} % of its "
             "skin area)" for s, c in over.items()]
    return (f"field of view: the reference scan ({reference}) cuts " + " and ".join(parts)
            + "; the model ends there while the body goes on (a model with the effect "
              "cut_faces holds the muscle's cut there, as the default one does), so within "
              "about 15 mm of the cut its predicted skin "
              "is less sure than elsewhere (on the validation suite 0.6-1.0 mm from the truth "
              "on average against 0.2-0.3 mm): judge the fit by the MHD over the skin both "
              "surfaces show (mhd_overlap_mm), or scan the reference with a wider field of "
              "view")
