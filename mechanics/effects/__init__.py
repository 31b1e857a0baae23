"""Physical effects, each one module that registers itself with ``@register_effect``.

Importing this package imports every module in it, so dropping a new file here is all the
registration an effect needs. ``EFFECTS`` maps name -> class.
"""

import importlib
import pkgutil

from mechanics.effects.base import (
    EFFECTS,
    Constraint,
    Contribution,
    Effect,
    MaterialModifier,
    MaterialSpec,
    ModelView,
    Option,
    Param,
    Variant,
    effect_name,
    exclusions,
    needs_split_interface,
    register_effect,
)

for _m in pkgutil.iter_modules(__path__):
    if _m.name != "base" and not _m.name.startswith("_"):
        importlib.import_module(f"{__name__}.{_m.name}")

__all__ = [
    "EFFECTS", "Constraint", "Contribution", "Effect", "MaterialModifier", "MaterialSpec",
    "ModelView", "Option", "Param", "Variant", "effect_name", "exclusions",
    "needs_split_interface", "register_effect",
]
