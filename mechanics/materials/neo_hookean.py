"""Neo-Hookean: W = mu/2 (I1bar - 3) + (1/d)(J - 1)^2, mu = E/(2(1+nu)), d = 6(1-2nu)/E."""

from __future__ import annotations

import numpy as np

from mechanics.materials.base import IsochoricI1Material, register_material


@register_material
class NeoHookean(IsochoricI1Material):
    """The paper's compressible Neo-Hookean law (parameters E [kPa], nu)."""

    name = "neo_hookean"

    def psi(self, I1bar: np.ndarray):
        half_mu = 0.5 * self.mu
        return half_mu * (I1bar - 3.0), np.full_like(I1bar, half_mu), np.zeros_like(I1bar)

    def to_febio(self):
        """FEBio's uncoupled Mooney-Rivlin with c1 = mu/2, c2 = 0 and the bulk term
        k/2 (J - 1)^2 (``pressure_model`` Abaqus), k = K = 2/d: the same energy."""
        return "Mooney-Rivlin", {"c1": 0.5 * self.mu, "c2": 0.0, "k": self.bulk,
                                 "pressure_model": "Abaqus"}
