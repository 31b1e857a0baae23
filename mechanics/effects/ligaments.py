"""Suspensory ligaments: tension-only cables between (breast node, muscle node) anchor pairs.

A cable of reference length L (from the stress-free positions X), current length l and
stretch lambda = l / L carries the axial force (mN)

    linear:      N = E A (lambda - 1)                 (engineering strain)
    neo_hookean: N = E A / 3 (lambda - 1 / lambda^2)  (incompressible rod, mu = E / 3)

for lambda > 1 and N = 0 in compression (slack). The energy is L * int N dlambda, so the
tangent is exact and symmetric; it has a kink at lambda = 1 (a slack cable adds nothing).
"""

from __future__ import annotations

import numpy as np

from mechanics.effects.base import (
    Contribution,
    Effect,
    Option,
    Param,
    Variant,
    bounds,
    register_effect,
)
from mechanics.effects.membrane import scatter

GROUPS = ("inframammary", "medial", "lateral")
LAWS = ("linear", "neo_hookean")


def cable_terms(x: np.ndarray, pairs: np.ndarray, L: np.ndarray, EA: np.ndarray, *,
                law: str = "linear"):
    """Axial force and end forces/stiffness of tension-only cables.

    Parameters
    ----------
    x : (N, 3) current positions, mm
    pairs : (P, 2) node indices
    L : (P,) reference lengths, mm
    EA : (P,) axial rigidity E * A, mN (kPa * mm^2)
    law : "linear" or "neo_hookean"

    Returns
    -------
    N : (P,) axial force, mN (>= 0)
    fe : (P, 2, 3) internal forces on the two ends, mN
    Ke : (P, 6, 6) stiffness, mN/mm
    """
    d = x[pairs[:, 1]] - x[pairs[:, 0]]
    ell = np.linalg.norm(d, axis=1)
    lam = ell / L
    taut = lam > 1.0
    if law == "linear":
        N = EA * (lam - 1.0)
        dN = EA.copy()  # dN/dlambda
    else:
        N = EA / 3.0 * (lam - lam**-2)
        dN = EA / 3.0 * (1.0 + 2.0 * lam**-3)
    N = np.where(taut, N, 0.0)
    dN = np.where(taut, dN, 0.0)
    safe = np.where(ell > 0.0, ell, 1.0)
    t = d / safe[:, None]
    f1 = N[:, None] * t  # force on end 1 (internal: pulls end 1 back towards end 0)
    fe = np.stack([-f1, f1], axis=1)
    # d f1 / d x1 = dN/dl t t^T + N / l (I - t t^T)
    tt = np.einsum("pi,pj->pij", t, t)
    k = (dN / L)[:, None, None] * tt + (N / safe)[:, None, None] * (np.eye(3) - tt)
    Ke = np.zeros((len(pairs), 6, 6))
    Ke[:, :3, :3] = k
    Ke[:, 3:, 3:] = k
    Ke[:, :3, 3:] = -k
    Ke[:, 3:, :3] = -k
    return N, fe, Ke


@register_effect
class Ligaments(Effect):
    """Tension-only link elements between the mesh's ligament anchor pairs.

    Options: ``groups`` subset of ("inframammary", "medial", "lateral") (default: every group
    the mesh has; each reads node pairs ``ligament_<group>``), ``law`` "linear" (default) or
    "neo_hookean", ``E_by_group`` {group: kPa} overriding ``E`` (the paper fixes the lateral
    ligaments at 100 kPa while fitting the others).
    """

    name = "ligaments"
    doc = "tension-only suspensory ligaments (inframammary, medial, lateral) as cables"
    params = (
        Param("E", "kPa", 100.0, 1.0, 1000.0, "Young's modulus of the ligaments"),
        Param("area", "mm^2", 1.0, 0.01, 100.0, "cross-section of one ligament cable",
              unscored="covered by E"),
    )
    option_specs = (
        Option("groups", None, f"subset of {GROUPS} (default: every group the mesh has)",
               types=(list, tuple)),
        Option("law", "linear", "cable law", LAWS, (str,)),
        Option("E_by_group", None, "{group: kPa} overriding E", types=(dict,)),
    )

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        opts = self.options
        present = tuple(g for g in GROUPS if f"ligament_{g}" in mesh.node_pairs)
        groups = tuple(present if opts["groups"] is None else opts["groups"])
        self.law = str(opts["law"])
        e_by = {str(k): float(v) for k, v in dict(opts["E_by_group"] or {}).items()}
        bad = [g for g in list(groups) + list(e_by) if g not in GROUPS]
        if bad:
            raise ValueError(f"effect 'ligaments': unknown group(s) {bad}; known {GROUPS}")
        missing = [g for g in groups if f"ligament_{g}" not in mesh.node_pairs]
        if missing:
            raise ValueError(f"effect 'ligaments': the mesh has no node pairs "
                             f"{['ligament_' + g for g in missing]}")
        pe = self.params[0]
        for g, v in e_by.items():
            pe.check(v, f"ligaments ({g})")
        pairs, E = [], []
        for g in groups:
            p = np.asarray(mesh.node_pairs[f"ligament_{g}"], np.int64).reshape(-1, 2)
            pairs.append(p)
            E.append(np.full(len(p), e_by.get(g, self.values["E"])))
        self.groups = groups
        self.pairs = np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64)
        self.E = np.concatenate(E) if E else np.zeros(0)
        if len(self.pairs) and (self.pairs.min() < 0 or self.pairs.max() >= mesh.n_nodes):
            raise ValueError("effect 'ligaments': anchor node index out of range")

    @classmethod
    def _variant(cls, group: str, kind: str, effects, free=None, start=None) -> Variant:
        return Variant(f"{cls.name}:{group}", f"{group} suspensory ligaments (tension-only)",
                       effects, free or {}, (0.0, 2.0) if free else (1.0, 1.0),
                       start=start or {}, kind=kind)

    @classmethod
    def variants(cls, view):
        """Each group the mesh has anchors for, alone, its E re-fitted."""
        have = (sorted(view.node_pairs) if view.node_pairs is not None
                else [f"ligament_{g}" for g in GROUPS])
        E = cls.params[0]
        path = f"effects.{cls.name}.E"
        return [cls._variant(g, "effect", {cls.name: {"groups": [g]}}, {path: bounds(E)},
                             {path: E.default})
                for g in GROUPS if f"ligament_{g}" in have]

    @classmethod
    def option_variants(cls, key, table, view):
        """Each group the mesh has anchors for that the model leaves out, added."""
        if view.node_pairs is None:
            return []
        have = set(table.get("groups") or [
            g for g in GROUPS if f"ligament_{g}" in view.node_pairs])
        return [cls._variant(g, "option", {key: {**table, "groups": sorted(have | {g})}})
                for g in GROUPS if g not in have and f"ligament_{g}" in view.node_pairs]

    def lengths(self, X: np.ndarray) -> np.ndarray:
        """(P,) reference lengths, mm; zero-length anchors are an error."""
        L = np.linalg.norm(X[self.pairs[:, 1]] - X[self.pairs[:, 0]], axis=1)
        if np.any(L <= 1e-9):
            raise ValueError("effect 'ligaments': an anchor pair has zero reference length")
        return L

    def forces(self, X: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(P,) axial cable forces, mN (zero when slack)."""
        N, _, _ = cable_terms(x, self.pairs, self.lengths(X), self.E * self.values["area"],
                              law=self.law)
        return N

    def contribute(self, X, x, load):
        if len(self.pairs) == 0:
            return Contribution.zero(len(x))
        _, fe, Ke = cable_terms(x, self.pairs, self.lengths(X), self.E * self.values["area"],
                                law=self.law)
        return scatter(len(x), self.pairs, fe, Ke)

    def to_febio(self, feb):
        """One FEBio discrete set per modulus, ``nonlinear spring`` with the force as a function
        of the engineering strain (l - L) / L: EA max(strain, 0) (tension-only, exact for the
        linear law). The neo_hookean law is a sampled curve in the stretch (an
        approximation, refused unless allowed)."""
        if len(self.pairs) == 0:
            return
        if self.law == "linear":
            measure, pts = "strain", [(-1.0, 0.0), (0.0, 0.0), (1.0, 1.0)]
        else:
            feb.approximate(f"effect {self.name!r}", "the neo_hookean cable law is written "
                            "as a piecewise-linear curve of the stretch (step 0.01)")
            lam = np.round(np.arange(0.0, 301.0) * 0.01 + 0.5, 2)
            measure = "stretch"
            pts = [(float(s), float(np.where(s > 1.0, (s - s**-2) / 3.0, 0.0))) for s in lam]
        for E in np.unique(self.E):
            pairs = self.pairs[self.E == E]
            curve = ["<interpolate>linear</interpolate>", "<extend>extrapolate</extend>",
                     "<points>", *[f"\t<pt>{a!r},{b!r}</pt>" for a, b in pts], "</points>"]
            feb.discrete(f"{self.name}_E{E:g}", pairs, "nonlinear spring",
                         {"scale": float(E * self.values["area"]), "measure": measure,
                          'force type="point"': curve})
