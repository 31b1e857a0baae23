"""Bulk material laws, one module each, registered by name in ``MATERIALS``.

Adding a law is one new module here that subclasses :class:`Material` and decorates it with
:func:`register_material`; importing this package imports every module in the folder.
"""

import importlib
import pkgutil

from mechanics.materials.base import MATERIALS, Material, register_material

for _m in pkgutil.iter_modules(__path__):
    if _m.name != "base" and not _m.name.startswith("_"):
        importlib.import_module(f"{__name__}.{_m.name}")

__all__ = ["MATERIALS", "Material", "register_material"]
