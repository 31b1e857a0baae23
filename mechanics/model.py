"""A model: mesh + materials per region + physical effects, built from plain dicts."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from mechanics.effects import EFFECTS, Effect, MaterialSpec
from mechanics.materials import MATERIALS
from mechanics.mesh import Mesh


@dataclass(frozen=True, eq=False)
class Model:
    """Everything a solve needs besides the reference positions.

    mesh : the tet mesh (its nodes are the default reference positions)
    materials : region code -> MaterialSpec (after every effect's ``modify_materials``)
    effects : instantiated effects, in the order given
    formulation : "anp" (averaged nodal pressure, locking-free) or "standard"
    """

    mesh: Mesh
    materials: Mapping[int, MaterialSpec]
    effects: tuple[Effect, ...] = ()
    formulation: str = "anp"


def _material_spec(region: int, m: MaterialSpec | Mapping[str, Any]) -> MaterialSpec:
    if isinstance(m, MaterialSpec):
        spec = m
    else:
        m = dict(m)
        name = m.pop("name", m.pop("model", None))
        if name is None:
            raise ValueError(f"mechanics: material of region {region} has no 'name'")
        spec = MaterialSpec(str(name), MappingProxyType({k: float(v) for k, v in m.items()}))
    if spec.name not in MATERIALS:
        raise ValueError(f"mechanics: unknown material {spec.name!r} for region {region}; "
                         f"known: {sorted(MATERIALS)}")
    MATERIALS[spec.name].from_params(spec.params)  # validates names and bounds now
    return spec


def build_model(mesh: Mesh, materials: Mapping[int, MaterialSpec] | Mapping[int, dict],
                effects: Mapping[str, dict | list[dict]] | None = None, *,
                formulation: str = "anp") -> Model:
    """Instantiate materials and effects by name.

    Parameters
    ----------
    mesh : Mesh
    materials : region code -> MaterialSpec or dict ``{"name": "neo_hookean", "E": 1.0,
        "nu": 0.49}`` (E in kPa)
    effects : effect name -> keyword dict, e.g. ``{"gravity": {"direction": (0, 1, 0),
        "density": 1000.0, "g": 9.81}, "fixed": {"node_set": "fixed"}}``. Several instances of
        one effect: a list of dicts, or keys ``"name:label"`` (``"fixed:chest"``).
    formulation : "anp" (default) or "standard"

    Each effect's ``modify_materials`` is applied in order to the material map.
    """
    mats: dict[int, MaterialSpec] = {
        int(k): _material_spec(int(k), v) for k, v in dict(materials).items()
    }
    missing = sorted({int(r) for r in set(mesh.region.tolist())} - set(mats))
    if missing:
        raise ValueError(f"mechanics: regions {missing} of the mesh have no material")
    built: list[Effect] = []
    for key, kwargs in dict(effects or {}).items():
        name = str(key).split(":", 1)[0]
        if name not in EFFECTS:
            raise ValueError(f"mechanics: unknown effect {name!r}; known: {sorted(EFFECTS)}")
        for kw in kwargs if isinstance(kwargs, list | tuple) else [kwargs]:
            built.append(EFFECTS[name](mesh, **dict(kw or {})))
    for eff in built:
        mats = dict(eff.modify_materials(dict(mats)))
    return Model(mesh, MappingProxyType(mats), tuple(built), formulation)
