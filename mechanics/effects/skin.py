"""Skin: a 2 mm hyperelastic membrane on the breast's outer surface (face set ``skin``)."""

from __future__ import annotations

from mechanics.effects.base import Param, register_effect
from mechanics.effects.membrane import (
    JM_MEMBRANE,
    THICKNESS_UNSCORED,
    MembraneEffect,
    membrane_options,
)


@register_effect
class Skin(MembraneEffect):
    """Neo-Hookean (or Gent, option ``law="gent"``) membrane triangles on face set ``skin``,
    sharing nodes with the solid. The paper's skin layer includes the superficial layer of
    the superficial fascia (2 mm thick, E fitted in 1-20 kPa, best 4 kPa). Under
    compression it wrinkles (tension-field theory: no compressive stress; option
    ``wrinkling="none"`` keeps the plain law, see ``mechanics/effects/membrane.py``)."""

    name = "skin"
    face_set = "skin"
    requires = ("face_sets:skin",)
    option_specs = membrane_options("tension_field")
    doc = "hyperelastic skin membrane (2 mm) on the breast surface"
    params = (
        Param("E", "kPa", 4.0, 1.0, 20.0, "Young's modulus of the skin"),
        Param("thickness", "mm", 2.0, 0.1, 10.0, "skin thickness", unscored=THICKNESS_UNSCORED),
        JM_MEMBRANE,
    )
