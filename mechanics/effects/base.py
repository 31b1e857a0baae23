"""The protocol every physical effect follows, and the registry that lists them by name.

The solver knows nothing of physics: its residual is the bulk material's internal force plus
the sum of each effect's :class:`Contribution`, and its Dirichlet set is the union of the
effects' :class:`Constraint` s. A new effect is one file with a subclass of :class:`Effect`
decorated with :func:`register_effect`; ``mechanics/effects/__init__.py`` imports every module of
the package. The class declares what callers need to know about it (:class:`Effect`), so the
problem builder, the truth model and the diagnosis never test an effect's name.

Sign convention: residual R(x) = f_int(x) - f_ext(x) in mN per node; an effect that pushes
node i in +z contributes a negative ``force[i, 2]``. The stiffness is dR/dx (mN/mm).
Degrees of freedom are numbered ``3 * node + component``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar

import numpy as np

from mechanics.mesh import Mesh


@dataclass(frozen=True)
class Param:
    """A scalar parameter of an effect or material, with its unit, default and bounds."""

    name: str
    unit: str
    default: float
    lower: float
    upper: float
    doc: str = ""
    #: A numerical setting (penalty, smoothing), not physics: never scored by the diagnosis.
    numerical: bool = False
    #: Why the diagnosis does not re-fit this parameter on its own ("" when it does).
    unscored: str = ""

    def check(self, value: float, owner: str) -> float:
        v = float(value)
        if not (self.lower <= v <= self.upper):
            raise ValueError(
                f"{owner}: parameter {self.name}={v} {self.unit} is outside "
                f"[{self.lower}, {self.upper}] {self.unit}"
            )
        return v


@dataclass(frozen=True)
class Option:
    """A setting of an effect that is not fitted (a direction, a law, a list of groups).

    ``default`` is what the effect uses when the option is not given; ``choices``, when not
    empty, are the only values accepted (checked by :class:`Effect`); ``types`` are the
    Python types a configuration value may have (checked by the config validation)."""

    name: str
    default: Any = None
    doc: str = ""
    choices: tuple = ()
    types: tuple[type, ...] = ()

    def check(self, value: Any, owner: str) -> Any:
        if self.choices and value not in self.choices:
            raise ValueError(f"effect {owner!r}: {self.name} must be one of {self.choices}, "
                             f"got {value!r}")
        return value


@dataclass(frozen=True)
class Variant:
    """A change of a model's effect tables that the diagnosis can score (plain data).

    name : "skin", "ligaments:medial", "strain_stiffening:fascia"
    doc : one line for people
    effects : {effect key: table, or None to remove}
    free : {parameter path: (lower, upper)} re-fitted with the change
    amplitude : bounds of the switch-on's linear amount ((1, 1) on/off, (0, 2) continuous)
    replaces : fitted parameter paths the change makes inert
    start : {parameter path: value} where the free parameters start
    kind : "effect" (an effect switched on) or "option" (an option of a used effect)
    skip : not "" when the change is deliberately not scored: the reason
    """

    name: str
    doc: str = ""
    effects: Mapping[str, Any] = field(default_factory=dict)
    free: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    amplitude: tuple[float, float] = (1.0, 1.0)
    replaces: tuple[str, ...] = ()
    start: Mapping[str, float] = field(default_factory=dict)
    kind: str = "effect"
    skip: str = ""


@dataclass(frozen=True)
class ModelView:
    """What an effect's diagnosis variants may read of a model (plain data).

    used : effect name -> table of the effects the model uses (first instance of each)
    keys : effect name -> its key in the model's effects table ("skin", "skin:2")
    materials : region name -> material table
    regions : region codes of the mesh (None: unknown)
    node_pairs : node-pair set names of the mesh (None: unknown)
    node_sets : names of the mesh's node sets that hold nodes (None: unknown)
    """

    used: Mapping[str, Mapping[str, Any]]
    keys: Mapping[str, str]
    materials: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    regions: frozenset[int] | None = None
    node_pairs: frozenset[str] | None = None
    node_sets: frozenset[str] | None = None


def bounds(param: Param) -> tuple[float, float]:
    """(lower, upper) of a parameter, as floats."""
    return (float(param.lower), float(param.upper))


@dataclass(frozen=True)
class Contribution:
    """An effect's share of the residual and of its derivative.

    force : (N, 3) mN, residual contribution (internal minus external)
    rows, cols, vals : COO triplets of d(force)/dx in dof numbering, mN/mm (may be empty;
        duplicates are summed)
    """

    force: np.ndarray
    rows: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    cols: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    vals: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @staticmethod
    def zero(n_nodes: int) -> Contribution:
        return Contribution(np.zeros((n_nodes, 3)))


@dataclass(frozen=True)
class Constraint:
    """Dirichlet condition: ``u[nodes, components] = values`` (mm), reached at full load.

    values : None for zero, else (k, len(components)) prescribed displacements in mm.
    """

    nodes: np.ndarray
    components: tuple[int, ...] = (0, 1, 2)
    values: np.ndarray | None = None


@dataclass(frozen=True)
class MaterialSpec:
    """Which registered material a region uses, with its parameter values."""

    name: str
    params: Mapping[str, float]


class Effect:
    """Base class of a physical effect: what it declares, and the hooks it overrides.

    Declarations (class attributes):

    - ``name``, ``doc``; ``params``: the fittable scalars (unit, default, bounds);
      ``option_specs``: every other keyword it accepts (:class:`Option`). Any other keyword is
      refused here, once for all effects. ``self.values`` holds the parameters and
      ``self.options`` every declared option (defaults filled in).
    - ``requires``: mesh sets it needs, as ``"face_sets:skin"``, ``"node_sets:fixed"`` or
      ``"node_pairs:ligament_medial"``.
    - ``split_interface``: it needs the breast-muscle interface split into two node layers
      (:func:`mechanics.effects._interface.split_interface`).
    - ``excludes``: effects that cannot be used with it (either side may declare it).
    - ``load_only``: it adds a load and no stiffness (the solver's rigid-mode check).
    - ``symmetric``: False when the tangent is unsymmetric (friction).
    - ``not_diagnosed``: why it is never a candidate missing effect ("" when it is);
      ``probe``: parameter values at which the diagnosis switches it on;
      ``sets_materials``: ``"region.param"`` material parameters it overrides;
      :meth:`variants`, :meth:`option_variants`, :meth:`inert_params`: its diagnosis changes.
    - :meth:`mesh_regions`: regions the mesh must keep apart for it; ``example``: options
      of a minimal instance (the registry's contract test builds every effect with them).
    """

    name: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()
    option_specs: ClassVar[tuple[Option, ...]] = ()
    requires: ClassVar[tuple[str, ...]] = ()
    doc: ClassVar[str] = ""
    split_interface: ClassVar[bool] = False
    excludes: ClassVar[tuple[str, ...]] = ()
    load_only: ClassVar[bool] = False
    #: False when the tangent is unsymmetric (friction): the solver then skips symmetric solvers.
    symmetric: ClassVar[bool] = True
    not_diagnosed: ClassVar[str] = ""
    probe: ClassVar[Mapping[str, float]] = MappingProxyType({})
    sets_materials: ClassVar[tuple[str, ...]] = ()
    #: Options of a minimal instance on a mesh with the standard sets (contract tests).
    example: ClassVar[Mapping[str, Any]] = MappingProxyType({})

    def __init__(self, mesh: Mesh, **values: Any):
        self.mesh = mesh
        params = {p.name: p for p in self.params}
        specs = {o.name: o for o in self.option_specs}
        unknown = sorted(set(values) - set(params) - set(specs))
        if unknown:
            raise ValueError(f"effect {self.name!r}: unknown option(s) {unknown}; known "
                             f"{sorted(params) + sorted(specs)}")
        self.values = {p.name: p.default for p in self.params}
        self.options: dict[str, Any] = {o.name: o.default for o in self.option_specs}
        for k, v in values.items():
            if k in params:
                self.values[k] = params[k].check(v, self.name)
            else:
                self.options[k] = specs[k].check(v, self.name)
        for req in self.requires:
            kind, key = req.split(":", 1)
            if key not in getattr(mesh, kind):
                raise ValueError(f"effect {self.name!r}: the mesh has no {kind} {key!r}")

    # -- declarations read by the problem builder, the truth model and the diagnosis -----
    @classmethod
    def excluded_by(cls, names) -> list[str]:
        """The effects among ``names`` that cannot be used with this one (either side may
        declare the exclusion)."""
        return [n for n in names if n != cls.name and (
            n in cls.excludes or cls.name in getattr(EFFECTS.get(n), "excludes", ()))]

    @classmethod
    def mesh_regions(cls, table: Mapping[str, Any]) -> frozenset[str]:
        """Region names (``mechanics.mesh.REGIONS``) that the mesh must keep apart for this
        effect with options ``table``."""
        return frozenset()

    @classmethod
    def material_values(cls, table: Mapping[str, Any]) -> dict[str, float]:
        """``"region.param"`` -> value of the bulk-material parameters this effect sets with
        options ``table`` (region names of ``mechanics.mesh.REGIONS``); see
        ``sets_materials``."""
        return {}

    @classmethod
    def inert_params(cls, table: Mapping[str, Any]) -> frozenset[str]:
        """Parameters that have no effect with options ``table`` (never scored)."""
        return frozenset()

    @classmethod
    def variants(cls, view: ModelView) -> list[Variant]:
        """Ways the diagnosis switches this effect on in a model that lacks it.

        The default: the effect at its ``probe`` values, its first physical parameter (the
        probed one if any) re-fitted in its bounds, switched on continuously (amplitude 0-2);
        with no physical parameter, an on/off change."""
        strength = {p.name: p for p in cls.params if not p.numerical}
        probe = dict(cls.probe)
        free, start = {}, {}
        if strength:
            pname = next(iter(probe), next(iter(strength)))
            path = f"effects.{cls.name}.{pname}"
            free = {path: bounds(strength[pname])}
            v = float(probe.get(pname, strength[pname].default))
            start = {path: v if v > 0 else strength[pname].upper / 100}  # log-scale re-fit
        return [Variant(cls.name, cls.doc or cls.name, {cls.name: probe}, free,
                        (0.0, 2.0) if free else (1.0, 1.0), start=start)]

    @classmethod
    def option_variants(cls, key: str, table: Mapping[str, Any],
                        view: ModelView) -> list[Variant]:
        """Changes of the options of this effect, used under ``key`` with ``table``, that
        the diagnosis scores (a law, a missing group)."""
        return []

    # -- hooks; override what the effect needs -------------------------------------------
    def constraints(self) -> list[Constraint]:
        """Dirichlet conditions this effect imposes (supports)."""
        return []

    def modify_materials(self, materials: dict[int, MaterialSpec]) -> dict[int, MaterialSpec]:
        """Return region -> material after this effect (e.g. Gent stiffening); never mutate."""
        return materials

    def begin_step(self, X: np.ndarray, x: np.ndarray, load: float | None = None) -> None:
        """Called at the start of each load step with the reference positions X and the last
        converged positions x (N, 3) mm, reached at load factor ``load`` (None: unknown):
        update contact pairings, stick anchors, etc."""

    def path_points(self) -> tuple[float, ...]:
        """Load factors in (0, 1) at which the solver must converge a step, for an effect
        whose state follows the loading path (friction): its history is updated there."""
        return ()

    def contribute(self, X: np.ndarray, x: np.ndarray, load: float) -> Contribution:
        """Residual and tangent at current positions x given reference positions X (N, 3) mm.
        ``load`` in [0, 1] is the load factor; body loads scale with it, structures do not."""
        return Contribution.zero(len(x))

    def regularization(self, X: np.ndarray, x: np.ndarray):
        """COO triplets (rows, cols, vals; dof numbering, mN/mm) of a stiffness the solver may
        add, scaled down, when the tangent is singular; never part of the residual. Empty by
        default."""
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)

    def to_febio(self, feb) -> None:
        """Add this effect to an FEBio file (``feb``: :class:`mechanics.febio.FebBuilder`).
        The default refuses: an effect says itself how FEBio expresses it."""
        from mechanics.febio import unsupported

        raise unsupported(f"effect {self.name!r}", "it does not say how (no to_febio hook)")


def constraints_to_febio(effect: Effect, feb) -> None:
    """Write an effect's :meth:`Effect.constraints` as FEBio boundary conditions."""
    for k, c in enumerate(effect.constraints()):
        feb.fix(f"{effect.name}_{k + 1}", c.nodes, c.components, c.values)


class MaterialModifier(Effect):
    """An effect that only changes the bulk materials (``modify_materials``): FEBio sees it
    through ``Model.materials``, so it adds nothing to the file."""

    def to_febio(self, feb) -> None:
        return None


EFFECTS: dict[str, type[Effect]] = {}


def effect_name(key: str) -> str:
    """The registered name of an effects-table key (``"skin:2"`` -> ``"skin"``)."""
    return str(key).split(":", 1)[0]


def needs_split_interface(keys) -> bool:
    """True when an effect among the effects-table ``keys`` declares ``split_interface``."""
    return any(getattr(EFFECTS.get(effect_name(k)), "split_interface", False) for k in keys)


def exclusions(keys) -> list[tuple[str, str]]:
    """Pairs of effects-table keys whose effects exclude each other."""
    keys = list(keys)
    out = []
    for i, a in enumerate(keys):
        cls = EFFECTS.get(effect_name(a))
        if cls is None:
            continue
        clash = set(cls.excluded_by([effect_name(b) for b in keys[i + 1:]]))
        out += [(a, b) for b in keys[i + 1:] if effect_name(b) in clash]
    return out


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator: make an effect available by its ``name``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    if cls.name in EFFECTS and EFFECTS[cls.name] is not cls:
        raise ValueError(f"effect name {cls.name!r} registered twice")
    EFFECTS[cls.name] = cls
    return cls
