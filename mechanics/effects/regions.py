"""Tissue regions: separate moduli for the left and right breast and for glandular tissue."""

from __future__ import annotations

from types import MappingProxyType

from mechanics.effects.base import (
    MaterialModifier,
    MaterialSpec,
    Option,
    Param,
    Variant,
    bounds,
    register_effect,
)
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
    _scored = "scored through its E parameters"
    params = (
        Param("E_left", "kPa", 0.2, 0.1, 4.0, "Young's modulus of the left breast",
              unscored=_scored),
        Param("E_right", "kPa", 0.3, 0.1, 4.0, "Young's modulus of the right breast",
              unscored=_scored),
        Param("E_gland", "kPa", 1.0, 0.1, 20.0, "Young's modulus of glandular tissue",
              unscored=_scored),
    )
    option_specs = (Option("gland", True, "glandular regions get E_gland", types=(bool,)),)
    sets_materials = ("breast_left.E", "breast_right.E", "gland_left.E", "gland_right.E")

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        self.gland = bool(self.options["gland"])

    @classmethod
    def mesh_regions(cls, table):
        """The gland regions when glandular tissue gets its own modulus."""
        return frozenset({"gland_left", "gland_right"} if table.get("gland", True) else ())

    @classmethod
    def material_values(cls, table):
        v = {p.name: float(table.get(p.name, p.default)) for p in cls.params}
        gland = bool(table.get("gland", True))
        return {"breast_left.E": v["E_left"], "breast_right.E": v["E_right"],
                "gland_left.E": v["E_gland"] if gland else v["E_left"],
                "gland_right.E": v["E_gland"] if gland else v["E_right"]}

    @classmethod
    def variants(cls, view):
        """Left-right asymmetry, and glandular tissue with its own modulus (when the mesh
        keeps gland), starting from the model's breast moduli."""
        p = {q.name: q for q in cls.params}
        lo, hi = bounds(p["E_left"])
        E = [min(max(float(view.materials.get(f"breast_{s}", {}).get("E", 1.0)), lo), hi)
             for s in ("left", "right")]
        replaces = tuple(f"materials.breast_{s}.E" for s in ("left", "right"))
        out = [Variant(
            f"{cls.name}:asymmetry", "different moduli of the left and right breast",
            {cls.name: {"E_left": E[0], "E_right": E[1], "gland": False}},
            {f"effects.{cls.name}.E_left": (lo, hi), f"effects.{cls.name}.E_right": (lo, hi)},
            (0.0, 0.0), replaces,
            {f"effects.{cls.name}.E_left": E[0], f"effects.{cls.name}.E_right": E[1]})]
        if view.regions is None or {REGIONS["gland_left"], REGIONS["gland_right"]} & set(
                view.regions):
            out.append(Variant(
                f"{cls.name}:gland", "glandular tissue with its own modulus",
                {cls.name: {"E_left": E[0], "E_right": E[1], "E_gland": float(E[0]),
                            "gland": True}},
                {f"effects.{cls.name}.E_gland": bounds(p["E_gland"])}, (0.0, 0.0), replaces,
                {f"effects.{cls.name}.E_gland": float(E[0])}))
        else:
            out.append(Variant(f"{cls.name}:gland", skip="the mesh has no gland regions "
                               "([mesh] keep_gland = true)"))
        return out

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
