"""The physics that deforms a simulated phantom ("truth model"), and presets with one hidden
effect changed, for testing the diagnosis of missing effects.

A :class:`TruthModel` is plain data: bulk materials per region code, effects by registered
name with their keyword arguments (``mechanics.effects.EFFECTS``; gravity is added per
position by the simulation), and the target tet size of the mesh. Presets are the default
model plus a small dict of overrides (an effect set to ``None`` is removed).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from mechanics.mesh import LAYER_REGIONS, REGIONS

__all__ = ["TruthModel", "default_truth_model", "from_toml", "preset", "PRESETS",
           "with_effects"]

#: Young's modulus of the breast (fat + gland) in the default truth, kPa. Measured with 1 kPa
#: (bench/phantom_sim.py, adult anatomy, 8 mm mesh): nipple displacement from the stress-free
#: state 23 mm prone and 28 mm supine (~50 mm prone to supine), above the paper's range;
#: sag scales ~ 1/E, so 2 kPa gives roughly 25 mm prone to supine.
E_BREAST = 2.0
#: Muscle / chest wall, kPa (paper).
E_MUSCLE = 10.0
NU = 0.49


def _frozen(d: dict) -> MappingProxyType:
    return MappingProxyType({k: (_frozen(v) if isinstance(v, dict) else v) for k, v in d.items()})


def _thaw(d) -> dict:
    return {k: (_thaw(v) if isinstance(v, MappingProxyType | dict) else v) for k, v in d.items()}


@dataclass(frozen=True)
class TruthModel:
    """Physics of a simulated phantom.

    Attributes
    ----------
    materials : {region code: {"name": "neo_hookean" | "gent", "E": kPa, "nu": -, ["Jm"]}}
        Codes of ``mechanics.mesh.REGIONS`` (1 breast_left, 2 muscle, 3 breast_right).
    effects : {effect name: keyword dict}
        Registered effects other than gravity (added per position). An effect that declares
        ``split_interface`` makes the simulation split the breast-muscle interface.
    mesh_size_mm : float
        Target tet edge of the truth mesh, mm (finer than a fitted model's 8-10 mm).
    name : str
        Label recorded in the truth folder (preset name).
    load_steps : int or None
        Load steps the truth solver starts from (None: its own default; soft tissue that
        sags far needs smaller first steps).
    """

    materials: MappingProxyType = field(default_factory=lambda: _frozen({}))
    effects: MappingProxyType = field(default_factory=lambda: _frozen({}))
    mesh_size_mm: float = 6.0
    name: str = "custom"
    load_steps: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "materials", _frozen(
            {int(k): dict(v) for k, v in dict(self.materials).items()}))
        object.__setattr__(self, "effects", _frozen(
            {str(k): dict(v or {}) for k, v in dict(self.effects).items()}))
        if not self.mesh_size_mm > 0:
            raise ValueError(f"truth model: mesh_size_mm must be > 0, got {self.mesh_size_mm}")
        if self.load_steps is not None and not (int(self.load_steps) == self.load_steps >= 1):
            raise ValueError(f"truth model: load_steps must be a positive integer, got "
                             f"{self.load_steps!r}")
        from mechanics.effects import exclusions
        from mechanics.effects.gravity import Gravity

        if Gravity.name in self.effects:
            raise ValueError(f"truth model: {Gravity.name} is set per position; remove it from "
                             "effects")
        for a, b in exclusions(self.effects):
            raise ValueError(f"truth model: {a!r} and {b!r} exclude each other")

    @property
    def has_gland(self) -> bool:
        """True when the truth gives glandular tissue its own modulus (mesh keeps gland):
        through an effect that needs the gland regions (``mesh_regions``) or a material for
        region gland_left or gland_right."""
        gland = ("gland_left", "gland_right")
        if any(REGIONS[k] in self.materials for k in gland):
            return True
        from mechanics.effects import EFFECTS, effect_name

        return any(set(gland) & EFFECTS[effect_name(k)].mesh_regions(dict(v))
                   for k, v in self.effects.items() if effect_name(k) in EFFECTS)

    @property
    def layers(self) -> tuple[str, ...]:
        """The face sets whose breast tets the truth gives their own law (a material for a
        code of ``mechanics.mesh.LAYER_REGIONS``): "skin" (the skin written as a solid layer),
        "interface" (the compliant tissue the breast slides on)."""
        return tuple(name for name, codes in LAYER_REGIONS.items()
                     if any(code in self.materials for code in codes))

    @property
    def split_interface(self) -> bool:
        """True when the interface nodes must be duplicated (an effect declares
        ``split_interface``)."""
        from mechanics.effects import needs_split_interface

        return needs_split_interface(self.effects)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (region codes as strings)."""
        return {
            "name": self.name,
            "mesh_size_mm": self.mesh_size_mm,
            "materials": {str(k): dict(v) for k, v in self.materials.items()},
            "effects": _thaw(self.effects),
            **({} if self.load_steps is None else {"load_steps": int(self.load_steps)}),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TruthModel:
        return cls(materials={int(k): v for k, v in d["materials"].items()},
                   effects=d["effects"], mesh_size_mm=float(d["mesh_size_mm"]),
                   name=str(d.get("name", "custom")), load_steps=d.get("load_steps"))

    def run_model(self, *, drop: tuple[str, ...] = ()) -> dict:
        """The truth as a run config's ``[model]`` table (materials by region name), without
        the effects named in ``drop`` (a fitted model that lacks them)."""
        names = {code: name for name, code in REGIONS.items()}
        return {"materials": {names[k]: dict(v) for k, v in self.materials.items()},
                "effects": {k: _thaw(v) for k, v in self.effects.items() if k not in drop}}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)


def default_truth_model(*, mesh_size_mm: float = 6.0) -> TruthModel:
    """The paper's model: Neo-Hookean breast (2 kPa) and muscle (10 kPa), nu 0.49, skin
    membrane 4 kPa 2 mm, fascia 120 kPa 0.1 mm, ligaments 100 kPa, the paper's supports and
    a tied breast-muscle interface (preset ``"sliding"``: the paper's friction 0.1)."""
    nh = {"name": "neo_hookean", "nu": NU}
    return TruthModel(
        materials={
            REGIONS["breast_left"]: {**nh, "E": E_BREAST},
            REGIONS["muscle"]: {**nh, "E": E_MUSCLE},
            REGIONS["breast_right"]: {**nh, "E": E_BREAST},
        },
        effects={
            "supports": {},
            "skin": {"E": 4.0, "thickness": 2.0},
            "fascia": {"E": 120.0, "thickness": 0.1},
            "ligaments": {"E": 100.0},
            # The paper slides with friction 0.1; sliding converges on most meshed phantoms
            # (about 17 s per position) but about 1 fTetWild mesh in 5 stalls at the first load
            # step, so the default stays tied and sliding is a preset.
            "tied": {},
        },
        mesh_size_mm=mesh_size_mm,
        name="default",
    )


#: Presets: overrides of the default effects ({effect: kwargs, or None to remove it}) and of
#: the materials ({region code: dict}). Each changes ONE physical effect. With the default
#: tied interface the fascia does not stretch and the ligaments stay slack in supine, so
#: "gent_fascia" and "no_ligaments" change nothing measurable until sliding converges.
PRESETS: dict[str, dict[str, dict]] = {
    "default": {},
    "sliding": {"effects": {"tied": None, "sliding": {"friction": 0.1}}},
    "frictionless": {"effects": {"tied": None, "sliding": {"friction": 0.0}}},
    "no_ligaments": {"effects": {"ligaments": None}},
    "no_skin": {"effects": {"skin": None}},
    "stiff_skin": {"effects": {"skin": {"E": 12.0, "thickness": 2.0}}},
    "gent_fascia": {"effects": {"fascia": {"E": 120.0, "thickness": 0.1, "law": "gent",
                                           "Jm": 0.3}}},
    # Jm 0.1: -19 % supine displacement on the half-size anatomy at 1 kPa (Jm 1: -3 %).
    "gent_breast": {"effects": {"strain_stiffening": {"Jm": 0.1}}},
    "asymmetric": {"effects": {"regions": {"E_left": 0.6, "E_right": 1.5, "gland": False}}},
    # glandular heterogeneity: gland 3x stiffer than fat (the default breast modulus)
    "gland": {"effects": {"regions": {"E_left": E_BREAST, "E_right": E_BREAST,
                                      "E_gland": 3 * E_BREAST, "gland": True}}},
}


def with_effects(model: TruthModel, effects: dict[str, dict | None], *,
                 materials: dict[int, dict] | None = None, name: str | None = None) -> TruthModel:
    """Copy of ``model`` with effects replaced/added (dict) or removed (None)."""
    eff = _thaw(model.effects)
    for k, v in effects.items():
        if v is None:
            eff.pop(k, None)
        else:
            eff[k] = dict(v)
    from mechanics.effects import exclusions

    added = {k for k, v in effects.items() if v is not None}
    for a, b in exclusions(list(eff)):  # an added effect replaces those it excludes
        if a in added:
            eff.pop(b, None)
        if b in added:
            eff.pop(a, None)
    mats = {k: dict(v) for k, v in model.materials.items()}
    mats.update({int(k): dict(v) for k, v in (materials or {}).items()})
    return replace(model, effects=eff, materials=mats, name=name or model.name)


def preset(name: str, *, base: TruthModel | None = None) -> TruthModel:
    """A named truth model: ``base`` (default :func:`default_truth_model`) with the preset's
    overrides; several names joined by ``+`` apply in order ("no_skin+gent_breast")."""
    model = base if base is not None else default_truth_model()
    for part in name.split("+"):
        if part not in PRESETS:
            raise ValueError(f"phantom: unknown truth preset {part!r}; known: {sorted(PRESETS)}")
        ov = PRESETS[part]
        model = with_effects(model, ov.get("effects", {}), materials=ov.get("materials"))
    return replace(model, name=name)


def from_toml(path) -> TruthModel:
    """A truth model from a TOML file: ``[materials.<region name or code>]`` tables (name, E,
    nu, ...), ``[effects.<registered effect>]`` keyword tables, optional ``mesh_size_mm`` and
    ``name``. Regions without a table keep the default truth's material.

    Raises
    ------
    ValueError
        Unknown region or effect, or a bad table (names the file).
    """
    from pathlib import Path

    from breastmodel.config import load_toml
    from mechanics.effects import EFFECTS

    path = Path(path)
    raw = load_toml(path, stage="phantom")
    extra = set(raw) - {"materials", "effects", "mesh_size_mm", "name"}
    if extra:
        raise ValueError(f"phantom: {path}: unknown key(s) {sorted(extra)}; expected "
                         "materials, effects, mesh_size_mm, name")
    base = default_truth_model()
    mats = {k: dict(v) for k, v in base.materials.items()}
    for region, table in dict(raw.get("materials", {})).items():
        code = REGIONS.get(region) if not str(region).isdigit() else int(region)
        if code is None:
            raise ValueError(f"phantom: {path}: unknown region {region!r}; known "
                             f"{sorted(REGIONS)}")
        mats[code] = dict(table)
    effects = dict(raw.get("effects", {}))
    for name in effects:
        if name.split(":", 1)[0] not in EFFECTS:
            raise ValueError(f"phantom: {path}: unknown effect {name!r}; known "
                             f"{sorted(EFFECTS)}")
    return TruthModel(materials=mats, effects=effects,
                      mesh_size_mm=float(raw.get("mesh_size_mm", base.mesh_size_mm)),
                      name=str(raw.get("name", path.stem)))
