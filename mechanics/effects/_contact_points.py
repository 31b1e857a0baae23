"""Contact points on the breast side of a split interface (see
:mod:`mechanics.effects.sliding`): the slave (breast-side) and master (muscle-side) face sets,
the quadrature rules on the slave triangles, and the points' positions, reference areas
(mm^2) and normals."""

from __future__ import annotations

import numpy as np

from mechanics.effects._contact import GAP_EDGES, nodal_areas
from mechanics.effects.base import Effect

#: Quadrature rules on the slave triangles: barycentric points and weights (sum 1).
_A1, _B1 = 0.0597158717897698, 0.4701420641051151
_A2, _B2 = 0.7974269853530873, 0.1012865073234563
RULES = {
    1: (np.full((1, 3), 1 / 3), np.ones(1)),
    3: (np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]]),
        np.full(3, 1 / 3)),
    7: (np.array([[1 / 3, 1 / 3, 1 / 3], [_A1, _B1, _B1], [_B1, _A1, _B1], [_B1, _B1, _A1],
                  [_A2, _B2, _B2], [_B2, _A2, _B2], [_B2, _B2, _A2]]),
        np.array([0.225] + [0.1323941527885062] * 3 + [0.1259391805448271] * 3)),
}


class _InterfaceContact(Effect):
    """Shared set-up of the split-interface effects: slave faces, master faces, and the
    contact points on the slave faces (:meth:`_setup_points`)."""

    requires = ("face_sets:interface", "face_sets:interface_muscle")

    def _setup(self):
        mesh = self.mesh
        self.slave_faces = np.asarray(mesh.face_sets["interface"], np.int64)
        self.master = np.asarray(mesh.face_sets["interface_muscle"], np.int64)
        self.slaves = np.unique(self.slave_faces)
        if np.intersect1d(self.slaves, np.unique(self.master)).size:
            raise ValueError(
                f"effect {self.name!r}: the 'interface' and 'interface_muscle' face sets share "
                "nodes; split the interface first (mechanics.effects._interface."
                "split_interface)")

    def _setup_points(self):
        """Contact points of ``self.points`` (0: one per slave node; 1, 3, 7: quadrature
        points per slave triangle): their slave nodes ``sconn`` (P, m) and weights ``sN``
        (P, m), and ``_C`` (P, 12, 3 m + 9), which maps the local dofs (m slave nodes, 3
        master nodes) to (x_p, x1, x2, x3)."""
        if self.points == 0:
            self.sconn = self.slaves[:, None]
            self.sN = np.ones((len(self.slaves), 1))
        else:
            eta, _ = RULES[self.points]
            self.sconn = np.repeat(self.slave_faces, len(eta), axis=0)
            self.sN = np.tile(eta, (len(self.slave_faces), 1))
        P, m = self.sN.shape
        C = np.zeros((P, 12, 3 * m + 9))
        for b in range(m):
            C[:, 0:3, 3 * b:3 * b + 3] = self.sN[:, b, None, None] * np.eye(3)
        C[:, 3:, 3 * m:] = np.eye(9)
        self._C = C
        self._C9 = GAP_EDGES @ C  # (P, 9, 3 m + 9): local dofs -> (d, e1, e2) of the gap
        self._w = None

    def weights(self, X: np.ndarray) -> np.ndarray:
        """(P,) reference area of each contact point, mm^2."""
        if self._w is None or self._w[0] is not X:
            if self.points == 0:
                w = nodal_areas(X, self.slave_faces, self.slaves)
            else:
                Xt = X[self.slave_faces]
                A = 0.5 * np.linalg.norm(np.cross(Xt[:, 1] - Xt[:, 0], Xt[:, 2] - Xt[:, 0]),
                                         axis=1)
                w = np.outer(A, RULES[self.points][1]).ravel()
            self._w = (X, w)
        return self._w[1]

    def contact_points(self, x: np.ndarray) -> np.ndarray:
        """(P, 3) current positions of the contact points on the breast side, mm."""
        return np.einsum("pm,pmi->pi", self.sN, x[self.sconn])

    def point_normals(self, x: np.ndarray) -> np.ndarray | None:
        """(P, 3) unit normals of the breast-side triangles the contact points lie on (the
        pairing ignores muscle triangles facing away from them); None for node points."""
        if self.points == 0:
            return None
        xt = x[self.sconn]
        n = np.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
