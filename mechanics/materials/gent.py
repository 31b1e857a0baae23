"""Gent: W = -mu Jm/2 ln(1 - (I1bar - 3)/Jm) + (1/d)(J - 1)^2 (Gent 1996).

Stiffens without bound as I1bar - 3 approaches Jm; beyond it the energy is undefined and the
kernel returns NaN, which the solver treats like an inverted element (it cuts the step back).
"""

from __future__ import annotations

import numpy as np

from mechanics.effects.base import Param
from mechanics.materials.base import POISSON, YOUNG, IsochoricI1Material, register_material


@register_material
class Gent(IsochoricI1Material):
    """Gent law with locking parameter Jm (dimensionless); Neo-Hookean as Jm -> infinity."""

    name = "gent"
    params = (YOUNG, POISSON, Param("Jm", "-", 1.0, 0.01, 1e4, "limit of I1bar - 3"))

    def psi(self, I1bar: np.ndarray):
        mu, Jm = self.mu, self.values["Jm"]
        s = 1.0 - (I1bar - 3.0) / Jm
        s = np.where(s > 0.0, s, np.nan)  # beyond the limit stretch: undefined
        return -0.5 * mu * Jm * np.log(s), 0.5 * mu / s, 0.5 * mu / (Jm * s * s)

    def to_febio(self):
        """FEBio's uncoupled Gent, W = -G Jm/2 ln(1 - (I1bar - 3)/Jm), with G = mu and the
        bulk term k/2 (J - 1)^2 (``pressure_model`` Abaqus), k = K = 2/d: the same energy."""
        return "Gent", {"G": self.mu, "Jm": self.values["Jm"], "k": self.bulk,
                        "pressure_model": "Abaqus"}
