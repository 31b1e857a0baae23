"""Tissue regions: separate moduli for the left and right breast and for glandular tissue."""

from __future__ import annotations

from types import MappingProxyType

from mechanics.effects.base import MaterialModifier, MaterialSpec, Param, register_effect
from mechanics.mesh import REGIONS


@register_effect
class Regions(MaterialModifier):
    """Sets E of each breast region, keeping its law and other parameters.

    ``E_left`` applies to ``breast_left``, ``E_right`` to ``breast_right``; glandular
    regions get ``E_gland`` (option ``gland=True``, default) or their side's breast modulus
    (``gland=False``, the paper's single breast tissue).
    """

    name = "regions"
    doc = "separate Young's moduli for left breast, right breast and glandular tissue"
    params = (
        Param("E_left", "kPa", 0.2, 0.1, 4.0, "Young's modulus of the left breast"),
        Param("E_right", "kPa", 0.3, 0.1, 4.0, "Young's modulus of the right breast"),
        Param("E_gland", "kPa", 1.0, 0.1, 20.0, "Young's modulus of glandular tissue"),
    )

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        opts = dict(self.options)
        self.gland = bool(opts.pop("gland", True))
        if opts:
            raise ValueError(f"effect 'regions': unknown option(s) {sorted(opts)}")

    def moduli(self) -> dict[int, float]:
        """Region code -> E (kPa) this effect sets."""
        v = self.values
        return {
            REGIONS["breast_left"]: v["E_left"],
            REGIONS["breast_right"]: v["E_right"],
            REGIONS["gland_left"]: v["E_gland"] if self.gland else v["E_left"],
            REGIONS["gland_right"]: v["E_gland"] if self.gland else v["E_right"],
        }

    def modify_materials(self, materials):
        out = dict(materials)
        for code, E in self.moduli().items():
            spec = out.get(code)
            if spec is None:
                continue
            params = dict(spec.params)
            params["E"] = E
            out[code] = MaterialSpec(spec.name, MappingProxyType(params))
        return out
