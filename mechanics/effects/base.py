"""The protocol every physical effect follows, and the registry that lists them by name.

The solver knows nothing of physics: its residual is the bulk material's internal force plus
the sum of each effect's :class:`Contribution`, and its Dirichlet set is the union of the
effects' :class:`Constraint` s. A new effect is one file with a subclass of :class:`Effect`
decorated with :func:`register_effect`, plus one import line in ``mechanics/effects/__init__.py``.

Sign convention: residual R(x) = f_int(x) - f_ext(x) in mN per node; an effect that pushes
node i in +z contributes a negative ``force[i, 2]``. The stiffness is dR/dx (mN/mm).
Degrees of freedom are numbered ``3 * node + component``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
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

    def check(self, value: float, owner: str) -> float:
        v = float(value)
        if not (self.lower <= v <= self.upper):
            raise ValueError(
                f"{owner}: parameter {self.name}={v} {self.unit} is outside "
                f"[{self.lower}, {self.upper}] {self.unit}"
            )
        return v


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
    """Base class of a physical effect. Subclasses set ``name``, ``params``, ``requires``.

    ``params`` are the fittable scalars (unit, default, bounds); any other keyword is an
    option (e.g. a gravity direction or a list of regions) that the subclass validates.
    ``requires`` names the mesh sets the effect needs, as ``"face_sets:skin"``,
    ``"node_sets:fixed"`` or ``"node_pairs:ligament_medial"``.
    """

    name: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()
    requires: ClassVar[tuple[str, ...]] = ()
    doc: ClassVar[str] = ""
    #: False when the tangent is unsymmetric (friction): the solver then skips symmetric solvers.
    symmetric: ClassVar[bool] = True

    def __init__(self, mesh: Mesh, **values: Any):
        self.mesh = mesh
        known = {p.name for p in self.params}
        self.values = {p.name: p.default for p in self.params}
        self.options: dict[str, Any] = {}
        for k, v in values.items():
            if k in known:
                self.values[k] = next(p for p in self.params if p.name == k).check(v, self.name)
            else:
                self.options[k] = v
        for req in self.requires:
            kind, key = req.split(":", 1)
            if key not in getattr(mesh, kind):
                raise ValueError(f"effect {self.name!r}: the mesh has no {kind} {key!r}")

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


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator: make an effect available by its ``name``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    if cls.name in EFFECTS and EFFECTS[cls.name] is not cls:
        raise ValueError(f"effect name {cls.name!r} registered twice")
    EFFECTS[cls.name] = cls
    return cls
