"""Point loads: a fixed force on nodes (dead load), scaled by the load factor."""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from mechanics.effects.base import Contribution, Effect, Option, register_effect


@register_effect
class PointLoad(Effect):
    """External force on nodes, mN (dead load: fixed direction and magnitude).

    Options: ``node_set`` or ``nodes``; ``force``: (3,) applied to every node, or (k, 3).
    """

    name = "point_load"
    doc = "external nodal forces"
    load_only = True
    not_diagnosed = "an external load, not a property of the subject"
    example = MappingProxyType({"node_set": "fixed", "force": (0.0, 0.0, 1.0)})
    option_specs = (
        Option("node_set", None, "name of the node set", types=(str,)),
        Option("nodes", None, "node indices", types=(list, tuple)),
        Option("force", None, "(3,) or (k, 3) force, mN", types=(list, tuple)),
    )

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        node_set, nodes = self.options["node_set"], self.options["nodes"]
        force = self.options["force"]
        if (node_set is None) == (nodes is None) or force is None:
            raise ValueError("effect 'point_load': give force and exactly one of node_set, nodes")
        if node_set is not None:
            if node_set not in mesh.node_sets:
                raise ValueError(f"effect 'point_load': the mesh has no node set {node_set!r}")
            nodes = mesh.node_sets[node_set]
        nodes = np.asarray(nodes, np.int64).reshape(-1)
        f = np.broadcast_to(np.asarray(force, float), (len(nodes), 3))
        self.f = np.zeros((mesh.n_nodes, 3))
        np.add.at(self.f, nodes, f)

    def contribute(self, X, x, load):
        return Contribution(-load * self.f)

    def to_febio(self, feb):
        """Dead nodal forces (FEBio ``nodal_force``), ramped with the load."""
        nodes = np.flatnonzero(np.any(self.f != 0.0, axis=1))
        feb.nodal_force(self.name, nodes, self.f[nodes])
