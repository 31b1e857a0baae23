"""Fascia: a 0.1 mm hyperelastic membrane on the breast-muscle interface (face set
``interface``, breast side when the interface is split)."""

from __future__ import annotations

from mechanics.effects.base import Param, register_effect
from mechanics.effects.membrane import (
    JM_MEMBRANE,
    THICKNESS_UNSCORED,
    MembraneEffect,
    membrane_options,
)


@register_effect
class Fascia(MembraneEffect):
    """Neo-Hookean (or Gent, option ``law="gent"``) membrane triangles on face set
    ``interface``: the deep layer of the superficial fascia (0.1 mm, E fitted in 80-250 kPa,
    best 120 kPa). On a split interface it lies on the breast side and slides with it.
    Held between the breast and the muscle it cannot wrinkle, so by default it keeps the
    plain law in compression (option ``wrinkling``, see ``membrane``)."""

    name = "fascia"
    face_set = "interface"
    option_specs = membrane_options("none")
    requires = ("face_sets:interface",)
    doc = "hyperelastic fascia membrane (0.1 mm) between breast and pectoral muscle"
    params = (
        Param("E", "kPa", 120.0, 80.0, 250.0, "Young's modulus of the fascia"),
        Param("thickness", "mm", 0.1, 0.01, 2.0, "fascia thickness", unscored=THICKNESS_UNSCORED),
        JM_MEMBRANE,
    )
