"""Where the reference scan's field of view cut the body: the model's faces on the label map's
cut planes (node sets ``cut_muscle`` and ``cut_breast``, :func:`meshing.sets.named_sets`),
past which the body goes on and the model does not.

A model meshed from a scan ends at the scan's edge with a free face; the body does not. This
effect holds those faces as the tissue beyond them would: the chest wall's cut faces fixed
(the wall goes on to the thorax), and the breast's left free by default, or held along their
plane's normal (``breast = "normal"``: they slide along the cut) or fixed (``"fixed"``).
On the validation suite's coil subject small-000, whose FEBio truth goes on past the cut,
the fitted breast modulus is +41 % of the truth with the cut free, +1.9 % with the muscle's
held and -11 % with the breast's held along the normal too (fixed: -16 %, against a first
truth extended at the sides only): README, "The body goes on past the scan's cut";
``bench/cut_faces.py``.

A diagnosis candidate (the field-of-view truncation, a cause that is not the tissue's) where
the mesh has cut nodes: the effect switched on where a model lacks it, and what a model using
it leaves free at the cut, held.
"""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from mechanics.effects.base import (
    Constraint,
    Effect,
    Option,
    Variant,
    constraints_to_febio,
    register_effect,
)

_HOLDS = ("free", "normal", "fixed")


def _boundary(tets: np.ndarray) -> np.ndarray:
    """(F, 3) the mesh's boundary faces, node-sorted (orientation does not matter here)."""
    from mechanics.mesh import sorted_tet_faces

    faces, count = np.unique(sorted_tet_faces(tets), axis=0, return_counts=True)
    return faces[count == 1]


def _normal_axis(nodes: np.ndarray, boundary: np.ndarray, cut: np.ndarray) -> np.ndarray:
    """(len(cut),) the axis (0, 1, 2) of each cut node's plane: the largest component of the
    summed normals of the boundary faces (:func:`_boundary`) whose three nodes are cut nodes."""
    on = np.zeros(len(nodes), bool)
    on[cut] = True
    faces = boundary[on[boundary].all(1)]
    p = nodes[faces]
    n = np.abs(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    summed = np.zeros((len(nodes), 3))
    for k in range(3):
        np.add.at(summed, faces[:, k], n)
    return np.argmax(summed[cut], axis=1)


#: The candidate that holds the muscle's cut, as a model lacking it or leaving it loose gets it.
_MUSCLE_HELD = "the field-of-view cut: the muscle's cut faces fixed as the chest wall beyond them"


@register_effect
class CutFaces(Effect):
    """The model's faces on the reference scan's field-of-view planes held as the body beyond
    them would hold them.

    Options ``muscle`` (default ``"fixed"``) and ``breast`` (default ``"free"``), each
    ``"fixed"`` (the cut nodes held in x, y and z), ``"normal"`` (held along their cut
    plane's normal, free to slide along it) or ``"free"``. Nodes of node set ``fixed`` are
    left to the effect that fixes them, and a node on both cuts to the muscle's where that is
    fixed. A mesh without these node sets (made by another tool, or a two-mound mesh) knows no
    cut: nothing is held.
    """

    name = "cut_faces"
    doc = "the faces on the reference's field-of-view cut held as the body beyond them would"
    example = MappingProxyType({})
    option_specs = (
        Option("muscle", "fixed", "the muscle's cut nodes: fixed, normal or free",
               types=(str,), choices=_HOLDS),
        Option("breast", "free", "the breast's cut nodes: free, normal or fixed",
               types=(str,), choices=_HOLDS),
    )

    @staticmethod
    def _cut(view, which: str) -> bool:
        """Whether the mesh may have cut nodes of ``which`` (True where it is unknown)."""
        return view.node_sets is None or f"cut_{which}" in view.node_sets

    @classmethod
    def variants(cls, view):
        """The cut held as by default (an on/off change), where the mesh has one."""
        if not (cls._cut(view, "muscle") or cls._cut(view, "breast")):
            return [Variant(cls.name, skip="the mesh has no field-of-view cut")]
        return [Variant(cls.name, _MUSCLE_HELD, {cls.name: {}})]

    @classmethod
    def option_variants(cls, key, table, view):
        """What the model leaves loose at the cut, held: the muscle's faces (fixed), the
        breast's (along their plane's normal, the tissue beyond sliding along the cut)."""
        out = []
        if table.get("muscle", "fixed") != "fixed" and cls._cut(view, "muscle"):
            out.append(Variant(f"{cls.name}:muscle", _MUSCLE_HELD,
                               {key: {**table, "muscle": "fixed"}}, kind="option"))
        if table.get("breast", "free") == "free" and cls._cut(view, "breast"):
            out.append(Variant(f"{cls.name}:breast_normal", "the field-of-view cut: the "
                               "breast's cut faces held along their normal as the tissue "
                               "beyond them", {key: {**table, "breast": "normal"}},
                               kind="option"))
        return out

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        held = np.asarray(mesh.node_sets.get("fixed", ()), np.int64)
        cut = {k: np.setdiff1d(np.asarray(mesh.node_sets.get(f"cut_{k}", ()), np.int64), held)
               for k in ("muscle", "breast")}
        if self.options["muscle"] == "fixed":
            cut["breast"] = np.setdiff1d(cut["breast"], cut["muscle"])
        self._constraints = []
        boundary = None  # made once, only where a cut is held along its normal
        for k, nodes in cut.items():
            how = self.options[k]
            if how == "fixed" and len(nodes):
                self._constraints.append(Constraint(nodes, (0, 1, 2)))
            elif how == "normal" and len(nodes):
                if boundary is None:
                    boundary = _boundary(np.asarray(mesh.tets))
                axis = _normal_axis(np.asarray(mesh.nodes, float), boundary, nodes)
                self._constraints += [Constraint(nodes[axis == i], (i,)) for i in range(3)
                                      if (axis == i).any()]

    def constraints(self):
        return list(self._constraints)

    to_febio = constraints_to_febio
