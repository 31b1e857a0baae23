"""Gravity: a uniform body force rho * g along a unit direction, scaled by the load factor."""

from __future__ import annotations

import numpy as np

from mechanics.effects.base import Contribution, Effect, Option, Param, register_effect
from mechanics.kernels import tet_volumes


@register_effect
class Gravity(Effect):
    """Body force of the tissue's weight (consistent nodal loads of linear tets).

    Options: ``direction`` (3,) unit vector in the mesh frame (normalised; default -z),
    ``regions``: list of region codes that carry weight (default all),
    ``density_by_region``: {region: kg/m^3} overriding ``density``.
    """

    name = "gravity"
    params = (
        Param("density", "kg/m^3", 1000.0, 0.0, 1e5, "mass density"),
        Param("g", "m/s^2", 9.81, 0.0, 1e3, "gravitational acceleration"),
    )
    doc = "weight of the tissue along a gravity direction"
    load_only = True  # adds no stiffness (dead load)
    not_diagnosed = "set per position from the registration"
    option_specs = (
        Option("direction", (0.0, 0.0, -1.0), "gravity direction in the mesh frame",
               types=(list, tuple)),
        Option("regions", None, "region codes that carry weight (default all)",
               types=(list, tuple)),
        Option("density_by_region", None, "{region code: kg/m^3} overriding density",
               types=(dict,)),
    )

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        d = np.asarray(self.options["direction"], float).reshape(-1)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
            raise ValueError(f"effect 'gravity': direction must be a non-zero 3-vector, got {d}")
        self.direction = d / np.linalg.norm(d)
        self.regions = self.options["regions"]
        self.density_by_region = {int(k): float(v) for k, v in
                                  dict(self.options["density_by_region"] or {}).items()}
        self._cache = None

    def nodal_weight(self, X: np.ndarray) -> np.ndarray:
        """(N, 3) external force at full load, mN (rho g in mN/mm^3 = kg/m^3 * m/s^2 * 1e-6)."""
        # The solver may hand over a fresh copy of the same X each call: compare values
        # (O(N)), which is far cheaper than recomputing the tet volumes.
        if self._cache is not None and (self._cache[0] is X or np.array_equal(self._cache[0], X)):
            return self._cache[1]
        mesh = self.mesh
        V0 = tet_volumes(X, mesh.tets)
        rho = np.full(mesh.n_tets, self.values["density"])
        for code, value in self.density_by_region.items():
            rho[mesh.region == code] = value
        if self.regions is not None:
            rho[~np.isin(mesh.region, np.asarray(list(self.regions)))] = 0.0
        w = rho * self.values["g"] * 1e-6 * V0 / 4.0  # mN per node of each tet
        per_node = np.bincount(mesh.tets.ravel(), weights=np.repeat(w, 4),
                               minlength=mesh.n_nodes)
        f = per_node[:, None] * self.direction[None, :]
        self._cache = (np.array(X, copy=True), f)
        return f

    def contribute(self, X, x, load):
        return Contribution(-load * self.nodal_weight(X))

    def to_febio(self, feb):
        """FEBio ``body force`` (acceleration g, mm/s^2) on the materials' density (kg/mm^3).
        FEBio integrates it with each element's own quadrature (UT4, tet10 included)."""
        from mechanics.febio import KG_M3_TO_KG_MM3, M_TO_MM

        codes = [int(c) for c in np.unique(self.mesh.region)]
        rho = {c: self.density_by_region.get(c, self.values["density"]) for c in codes}
        if self.regions is not None:
            rho = {c: (v if c in set(int(r) for r in self.regions) else 0.0)
                   for c, v in rho.items()}
        # FEBio's body force b enters the residual as -rho b: b is minus the acceleration
        feb.set_body_force(-self.values["g"] * M_TO_MM * self.direction,
                           {c: v * KG_M3_TO_KG_MM3 for c, v in rho.items()}, owner=self.name)
