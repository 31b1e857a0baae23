"""Linear (small-strain) isotropic elasticity, for small-strain checks.

W = mu |dev eps|^2 + K/2 (tr eps)^2 with eps = sym(F - I); the volumetric half uses the
linearised volume ratio 1 + tr(eps), so the whole residual is linear in the displacement.
"""

from __future__ import annotations

import numpy as np

from mechanics.materials.base import Material, register_material

_I = np.eye(3)
# d(dev sym(F)) / dF as a (3,3,3,3) tensor: sym minus trace part.
_DEV = 0.5 * (np.einsum("ik,JL->iJkL", _I, _I) + np.einsum("iL,Jk->iJkL", _I, _I)) - np.einsum(
    "iJ,kL->iJkL", _I, _I
) / 3.0


@register_material
class Linear(Material):
    """Hooke's law with E [kPa] and nu (geometrically linear)."""

    name = "linear"
    geometrically_linear = True

    def deviatoric(self, F: np.ndarray, *, tangent: bool = True):
        eps = 0.5 * (F + F.transpose(0, 2, 1)) - _I
        dev = eps - np.trace(eps, axis1=1, axis2=2)[:, None, None] * _I / 3.0
        W = self.mu * np.einsum("mij,mij->m", dev, dev)
        P = 2.0 * self.mu * dev
        A = np.broadcast_to(2.0 * self.mu * _DEV, (len(F), 3, 3, 3, 3)) if tangent else None
        return W, P, A

    def to_febio(self):
        from mechanics.febio import unsupported

        raise unsupported("material 'linear'", "it is geometrically linear (small strain); "
                          "FEBio's 'isotropic elastic' is St Venant-Kirchhoff (large strain) "
                          "and would solve a different problem")
