"""The residual and tangent that the Newton solver works on: the solid's forces and stiffness
plus every effect's contribution (mN per dof, 3 * node + component), the effects' Dirichlet
constraints, and the reduced saddle-point pattern, cached per topology and free dofs."""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from mechanics.model import Model
from mechanics.solid import Solid
from mechanics.system import ReducedSystem


def _solid(model: Model, X: np.ndarray) -> Solid:
    return Solid(model.mesh.tets, model.mesh.region, model.materials, X,
                 formulation=model.formulation)


def _effects(model: Model, X, x, load, cpu: dict | None = None):
    """Sum of the effects' forces, and the list of each effect's tangent triplets (rows,
    cols, vals), those with entries; ``cpu`` (effect name -> s) gathers each effect's CPU
    time."""
    force = np.zeros(3 * len(X))
    parts = []
    for eff in model.effects:
        c0 = time.process_time()
        c = eff.contribute(X, x, load)
        if cpu is not None:
            cpu[eff.name] = cpu.get(eff.name, 0.0) + time.process_time() - c0
        force += np.asarray(c.force, float).reshape(-1)
        if len(c.vals):
            parts.append((np.asarray(c.rows), np.asarray(c.cols), np.asarray(c.vals, float)))
    return force, parts


def residual_and_tangent(model: Model, X: np.ndarray, x: np.ndarray,
                         load: float) -> tuple[np.ndarray, sp.csr_matrix]:
    """Full residual R (3N,) mN and tangent dR/dx (3N, 3N) mN/mm, no constraints applied.

    The pressure of the "anp" formulation is eliminated (condensed tangent).
    """
    X = np.asarray(X, float)
    x = np.asarray(x, float)
    solid = _solid(model, X)
    ev = solid.evaluate(x)
    f, parts = _effects(model, X, x, load)
    R = ev.force.reshape(-1) + f
    K = solid.condensed_tangent(ev)
    if parts:
        r, c, v = (np.concatenate(a) for a in zip(*parts, strict=True))
        n = 3 * len(X)
        K = (K + sp.coo_matrix((v, (r, c)), shape=(n, n))).tocsr()
    return R, K


_PATTERN_CACHE: dict = {}


def _system(model: Model, solid: Solid, free: np.ndarray) -> ReducedSystem:
    """Pattern per (topology, free dofs, formulation); reused across solves of one model."""
    key = (id(model.mesh.tets), model.formulation, hash(free.tobytes()))
    hit = _PATTERN_CACHE.get(key)
    if hit is not None and hit[0] is model.mesh.tets:
        return hit[1]
    sysm = ReducedSystem(model.mesh.tets, solid.n_nodes, free,
                         solid.used_nodes if model.formulation == "anp" else None)
    if len(_PATTERN_CACHE) > 8:
        _PATTERN_CACHE.clear()
    _PATTERN_CACHE[key] = (model.mesh.tets, sysm)
    return sysm


def _constraints(model: Model, n_nodes: int, used: np.ndarray):
    fixed = np.zeros(3 * n_nodes, bool)
    target = np.zeros(3 * n_nodes)
    for eff in model.effects:
        for c in eff.constraints():
            nodes = np.asarray(c.nodes, np.int64).reshape(-1)
            comps = tuple(int(k) for k in c.components)
            dofs = (3 * nodes[:, None] + np.asarray(comps)[None, :])
            fixed[dofs.ravel()] = True
            if c.values is not None:
                vals = np.broadcast_to(np.asarray(c.values, float), dofs.shape)
                target[dofs.ravel()] = vals.ravel()
            else:
                target[dofs.ravel()] = 0.0
    # Nodes outside every tet carry no stiffness: hold them where they are.
    orphan = np.repeat(~used, 3)
    fixed |= orphan
    return fixed, target
