"""Where the reference scan's field of view cut the model's breast: its boundary faces on the
image's faces, which the body goes on past and the model does not.

A soft breast that falls out of view in the reference (laterally, in supine) comes back into
view in another position (prone), and the model, which lacks the tissue beyond and has a free
face where the body had more of it, is off there. On small-soft-000 of the validation suite
(the coil's field of view, x within +-60 mm; FEBio's supine truth put 5346 mm^3 of the right
breast outside it) the fitted model's prone skin, against FEBio's, was off by 2.6 mm on
average (9.1 mm at most) within 10 mm of the right cut and 0.2-0.8 mm in the middle
(README, "The soft band").
"""

from __future__ import annotations

import numpy as np

from mechanics.mesh import BREAST_SIDE, Mesh
from meshing.labels import Grid
from meshing.sets import tet_faces
from meshing.surface import fov_faces

__all__ = ["CUT_SHARE", "breast_cut", "cut_warning"]

#: Share of a breast's skin area above which the cut is said to matter (:func:`cut_warning`).
CUT_SHARE = 0.05


def _areas(nodes: np.ndarray, faces: np.ndarray) -> np.ndarray:
    a, b, c = (nodes[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def breast_cut(mesh: Mesh, grid: Grid) -> dict[str, dict[str, float]]:
    """Per breast side ("left", "right"): ``cut_mm2``, the area of the breast's boundary faces
    on a field-of-view plane of the label map it was meshed from (``grid``), ``skin_mm2``, the
    area of its other boundary faces (skin), and ``share``, cut over skin."""
    bf, owner, _, _ = tet_faces(mesh.tets)
    side = np.array([BREAST_SIDE.get(int(r), 0) for r in mesh.region])[owner]
    cut = fov_faces(mesh.nodes, bf, grid)
    area = _areas(mesh.nodes, bf)
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
            + "; the model ends there while the body goes on, so near the cut its predictions "
              "of the other positions can be off by millimetres (compare the MHD over the "
              "skin both surfaces show, mhd_overlap_mm); a wider field of view in the "
              "reference removes it")
