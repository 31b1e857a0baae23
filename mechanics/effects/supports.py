"""The paper's Dirichlet supports: posterior muscle fixed, fascia ends in z, skin ends in y;
optionally the lateral ends of the skin, where a model cut at the field of view ends but the
skin goes on around the torso."""

from __future__ import annotations

import numpy as np

from mechanics.effects.base import (
    Constraint,
    Effect,
    Option,
    constraints_to_febio,
    register_effect,
)


@register_effect
class Supports(Effect):
    """Posterior muscle nodes (node set ``fixed``) fixed in x, y, z; the superior and inferior
    ends of the fascia (``fascia_superior``, ``fascia_inferior``) fixed in one component
    (default 2, z: superior-inferior); those of the skin (``skin_superior``,
    ``skin_inferior``) in another (default 1, y: anterior-posterior).

    Options: ``muscle``, ``fascia_ends``, ``skin_ends`` (bool, default True) switch each
    group; ``fascia_component``, ``skin_component`` (0, 1 or 2).

    ``skin_lateral`` (bool, default False: not in the paper) also fixes the lateral ends of
    the skin (node set ``skin_lateral``) in ``lateral_component`` (default 0, x). On a
    model whose chest wall is a flat slab nothing else holds the breast sideways in a tilted
    position but the ligament cables and friction; the paper's 1 mm^2 cables cannot (see
    ``bench/effects_box.py``). In a body the skin is a closed sleeve around the torso, and
    its tension is what this support stands for.
    """

    name = "supports"
    doc = "paper's Dirichlet supports: posterior muscle fixed, fascia ends in z, skin ends in y"
    requires = ()
    option_specs = (
        Option("muscle", True, "fix the posterior muscle nodes", types=(bool,)),
        Option("fascia_ends", True, "fix the fascia ends in one component", types=(bool,)),
        Option("skin_ends", True, "fix the skin ends in one component", types=(bool,)),
        Option("skin_lateral", False, "fix the lateral skin ends", types=(bool,)),
        Option("fascia_component", 2, "component of the fascia ends", types=(int,)),
        Option("skin_component", 1, "component of the skin ends", types=(int,)),
        Option("lateral_component", 0, "component of the lateral skin ends", types=(int,)),
    )

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        opts = self.options
        use = {k: bool(opts[k]) for k in ("muscle", "fascia_ends", "skin_ends", "skin_lateral")}
        comp = {k: int(opts[k]) for k in ("fascia_component", "skin_component",
                                          "lateral_component")}
        if any(c not in (0, 1, 2) for c in comp.values()):
            raise ValueError(f"effect 'supports': components must be 0, 1 or 2, got {comp}")
        wanted = []
        if use["muscle"]:
            wanted.append((("fixed",), (0, 1, 2)))
        if use["fascia_ends"]:
            wanted.append((("fascia_superior", "fascia_inferior"), (comp["fascia_component"],)))
        if use["skin_ends"]:
            wanted.append((("skin_superior", "skin_inferior"), (comp["skin_component"],)))
        if use["skin_lateral"]:
            wanted.append((("skin_lateral",), (comp["lateral_component"],)))
        self._constraints = []
        for names, comps in wanted:
            missing = [n for n in names if n not in mesh.node_sets]
            if missing:
                raise ValueError(f"effect 'supports': the mesh has no node set(s) {missing} "
                                 f"(has {sorted(mesh.node_sets)})")
            nodes = np.unique(np.concatenate([mesh.node_sets[n] for n in names]))
            self._constraints.append(Constraint(nodes, comps))

    def constraints(self):
        return list(self._constraints)

    to_febio = constraints_to_febio
