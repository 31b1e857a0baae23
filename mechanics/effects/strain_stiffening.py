"""Strain stiffening: switch the bulk law of chosen regions from Neo-Hookean to Gent."""

from __future__ import annotations

from types import MappingProxyType

from mechanics.effects.base import (
    MaterialModifier,
    MaterialSpec,
    Option,
    Param,
    register_effect,
)
from mechanics.mesh import REGIONS


def region_codes(regions, owner: str) -> list[int]:
    """Region names (``REGIONS`` keys) or codes -> codes."""
    out = []
    for r in regions:
        if isinstance(r, str):
            if r not in REGIONS:
                raise ValueError(f"effect {owner!r}: unknown region {r!r}; known {list(REGIONS)}")
            out.append(REGIONS[r])
        else:
            out.append(int(r))
    return out


@register_effect
class StrainStiffening(MaterialModifier):
    """Gent law W = -mu Jm/2 ln(1 - (I1bar - 3)/Jm) on the chosen regions, keeping E and nu.

    Options: ``regions`` names or codes (default: every breast and gland region),
    ``Jm_by_region`` {region: Jm} overriding ``Jm``. Neo-Hookean is the limit Jm -> inf.
    """

    name = "strain_stiffening"
    doc = "Gent strain stiffening (limit Jm) of the bulk tissue, per region"
    params = (Param("Jm", "-", 10.0, 0.05, 1e4, "Gent limit of I1bar - 3"),)
    option_specs = (
        Option("regions", ("breast_left", "breast_right", "gland_left", "gland_right"),
               "region names or codes that stiffen", types=(list, tuple)),
        Option("Jm_by_region", None, "{region: Jm} overriding Jm", types=(dict,)),
    )
    #: The default Jm = 10 is the "barely on" end (nearly Neo-Hookean at breast strains).
    probe = MappingProxyType({"Jm": 0.3})

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        regions = self.options["regions"]
        jm_by = dict(self.options["Jm_by_region"] or {})
        self.regions = region_codes(regions, self.name)
        self.jm = {r: self.values["Jm"] for r in self.regions}
        for k, v in jm_by.items():
            (code,) = region_codes([k], self.name)
            self.jm[code] = self.params[0].check(v, f"strain_stiffening (region {k})")

    def modify_materials(self, materials):
        out = dict(materials)
        for code, jm in self.jm.items():
            spec = out.get(code)
            if spec is None:
                continue
            if spec.name not in ("neo_hookean", "gent"):
                raise ValueError(f"effect 'strain_stiffening': region {code} uses "
                                 f"{spec.name!r}; only neo_hookean or gent can stiffen")
            params = {k: v for k, v in spec.params.items() if k in ("E", "nu")}
            params["Jm"] = jm
            out[code] = MaterialSpec("gent", MappingProxyType(params))
        return out
