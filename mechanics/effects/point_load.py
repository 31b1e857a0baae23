"""Point loads: a fixed force on nodes (dead load), scaled by the load factor."""

from __future__ import annotations

import numpy as np

from mechanics.effects.base import Contribution, Effect, register_effect


@register_effect
class PointLoad(Effect):
    """External force on nodes, mN (dead load: fixed direction and magnitude).

    Options: ``node_set`` or ``nodes``; ``force``: (3,) applied to every node, or (k, 3).
    """

    name = "point_load"
    doc = "external nodal forces"
    load_only = True

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        opts = dict(self.options)
        node_set, nodes = opts.pop("node_set", None), opts.pop("nodes", None)
        force = opts.pop("force", None)
        if opts:
            raise ValueError(f"effect 'point_load': unknown option(s) {sorted(opts)}")
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
