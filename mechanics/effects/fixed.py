"""Dirichlet supports: fix or prescribe displacement components of a node set."""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from mechanics.effects.base import (
    Constraint,
    Effect,
    Option,
    constraints_to_febio,
    register_effect,
)


@register_effect
class Fixed(Effect):
    """u[nodes, components] = values (mm) at full load, reached in proportion to the load.

    Options: ``node_set`` (name in ``mesh.node_sets``) or ``nodes`` (indices);
    ``components`` subset of (0, 1, 2) (default all); ``values`` None (zero), a scalar, a
    (len(components),) vector for all nodes, or (k, len(components)) per node, mm.
    The stress-free algorithm passes ``nodes`` and per-node ``values``.
    """

    name = "fixed"
    doc = "Dirichlet support or prescribed displacement on a node set"
    not_diagnosed = "the chest-wall boundary condition every model has"
    example = MappingProxyType({"node_set": "fixed"})
    option_specs = (
        Option("node_set", None, "name of the node set", types=(str,)),
        Option("nodes", None, "node indices", types=(list, tuple)),
        Option("components", (0, 1, 2), "fixed components", types=(list, tuple)),
        Option("values", None, "prescribed displacements, mm", types=(int, float, list, tuple)),
    )

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        opts = self.options
        node_set, nodes, vals = opts["node_set"], opts["nodes"], opts["values"]
        comps = tuple(int(c) for c in opts["components"])
        if (node_set is None) == (nodes is None):
            raise ValueError("effect 'fixed': give exactly one of node_set or nodes")
        if node_set is not None:
            if node_set not in mesh.node_sets:
                raise ValueError(f"effect 'fixed': the mesh has no node set {node_set!r} "
                                 f"(has {sorted(mesh.node_sets)})")
            nodes = mesh.node_sets[node_set]
        nodes = np.asarray(nodes, np.int64).reshape(-1)
        if len(nodes) and (nodes.min() < 0 or nodes.max() >= mesh.n_nodes):
            raise ValueError("effect 'fixed': node index out of range")
        if not comps or any(c not in (0, 1, 2) for c in comps) or len(set(comps)) != len(comps):
            raise ValueError(f"effect 'fixed': components must be distinct in 0,1,2, got {comps}")
        if vals is not None:
            vals = np.broadcast_to(np.asarray(vals, float), (len(nodes), len(comps))).copy()
        self.nodes, self.components, self.prescribed = nodes, comps, vals

    def constraints(self):
        return [Constraint(self.nodes, self.components, self.prescribed)]

    to_febio = constraints_to_febio
