"""Tied interface: the breast is bonded to the muscle (no sliding, no separation).

On a split interface (see :mod:`mechanics.effects.sliding`) every breast-side node is tied by
a stiff penalty spring, w_s eps |x_s - x_m|^2 / 2, to the material point x_m of the muscle
surface that it touched in the stress-free configuration (fixed facet and barycentric
coordinates: exact, symmetric tangent). This is the over-constrained "Dirichlet chest wall"
case of the literature. On a conforming mesh the interface is bonded already and the effect
adds nothing.
"""

from __future__ import annotations

import numpy as np

from mechanics.effects._contact import closest_facets, coo_blocks, nodal_areas, node_dofs
from mechanics.effects.base import Contribution, Effect, Param, Variant, register_effect


@register_effect
class Tied(Effect):
    """Bonded breast-muscle interface (alternative to ``sliding``)."""

    name = "tied"
    doc = "breast bonded to the muscle at the interface (no sliding)"
    requires = ("face_sets:interface",)
    params = (Param("penalty", "kPa/mm", 1000.0, 1e-3, 1e7, "tie stiffness per area",
                    numerical=True),)
    split_interface = True
    excludes = ("sliding",)
    # the springs stretch by the gap in the deformed configuration (False), or by its change
    # from the reference (True: the nodes' relative displacement)
    relative = False

    @classmethod
    def variants(cls, view):
        """The interface bonded instead of the effect it excludes; nothing to score when the
        model has none (its conforming interface is bonded already)."""
        other = cls.excluded_by(view.used)
        if not other:
            return [Variant(cls.name, skip="the model's interface is already bonded "
                            "(conforming mesh)")]
        change = {view.keys[n]: None for n in other}
        return [Variant(cls.name, "bonded breast-muscle interface instead of "
                        + " and ".join(other), {**change, cls.name: {}})]

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        self.split = "interface_muscle" in mesh.face_sets
        if self.split:
            self.slave_faces = np.asarray(mesh.face_sets["interface"], np.int64)
            self.master = np.asarray(mesh.face_sets["interface_muscle"], np.int64)
            self.slaves = np.unique(self.slave_faces)
        self._ref = None

    def _pairing(self, X):
        """(muscle nodes, barycentric coordinates, tributary areas, springs) of the slave
        nodes in the reference ``X``, made once per reference."""
        if self._ref is None or self._ref[0] is not X:
            facet, bary, _ = closest_facets(X[self.slaves], X, self.master)
            w = nodal_areas(X, self.slave_faces, self.slaves)
            self._ref = (X, self.master[facet], bary, w, self.springs(X, w))
        return self._ref[1:]

    def contribute(self, X, x, load):
        if not self.split:
            return Contribution.zero(len(x))
        mnodes, bary, _, P = self._pairing(X)
        S = len(self.slaves)
        B = np.zeros((S, 3, 12))
        B[:, :, 0:3] = np.eye(3)
        for a in range(3):
            B[:, :, 3 + 3 * a:6 + 3 * a] = -bary[:, a, None, None] * np.eye(3)
        nodes = np.concatenate([self.slaves[:, None], mnodes], axis=1)
        dofs = node_dofs(nodes)
        q = (x - X if self.relative else x)[nodes].reshape(S, 12)
        t = np.einsum("sij,sj->si", P, np.einsum("sij,sj->si", B, q))  # on the slave, mN
        force = np.zeros(3 * len(x))
        np.add.at(force, dofs.ravel(), np.einsum("sij,si->sj", B, t).ravel())
        K = B.transpose(0, 2, 1) @ P @ B
        return Contribution(force.reshape(-1, 3), *coo_blocks(dofs, dofs, K))

    def springs(self, X, w):
        """(S, 3, 3) stiffness of each slave node's spring, mN/mm: the penalty times its
        tributary area, the same in every direction."""
        return (self.values["penalty"] * w)[:, None, None] * np.eye(3)

    def to_febio(self, feb):
        """Split interface: FEBio ``tied-elastic`` contact (penalty per area, kPa/mm, no
        automatic scaling) between the breast side (primary, faces flipped so that the normal
        points out of the breast) and the muscle side. Conforming mesh: nothing to add."""
        if not self.split:
            return
        owner = f"effect {self.name!r}"
        primary = feb.surface(f"{self.name}_breast", self.slave_faces[:, ::-1], owner=owner)
        secondary = feb.surface(f"{self.name}_muscle", self.master, owner=owner)
        pair = feb.surface_pair(self.name, primary, secondary)
        feb.contact("tied-elastic", pair, {"penalty": self.values["penalty"],
                                           "auto_penalty": "0", "laugon": "PENALTY",
                                           "symmetric_stiffness": "1", "tolerance": 0.01,
                                           "search_tol": 0.01})
