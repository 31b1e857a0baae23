"""No-equilibrium verdicts: a model whose supports leave a rigid-body mode free (found before
the solve), a solve that fails at a limit point of its load path (the body gives way; with
the force budget of what carries the load), and a mesh whose hinged tets rotate freely."""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from mechanics.effects.base import Effect
from mechanics.model import Model
from mechanics.newton.options import NoEquilibrium
from mechanics.newton.residual import _effects

if TYPE_CHECKING:
    from mechanics.newton.workspace import _Newton

log = logging.getLogger("mechanics.solver")

#: Names of the rigid-body modes of :func:`_check_rigid_modes`, in its order.
_MODES = ("translation along x", "translation along y", "translation along z",
          "rotation about x", "rotation about y", "rotation about z")


def _check_rigid_modes(X: np.ndarray, fixed: np.ndarray, used: np.ndarray,
                       model: Model) -> None:
    """Fail before the solve, with a plain verdict, when the supports leave a rigid-body
    mode free and no effect can hold the body: no support at all (effects that act between
    parts of the body, such as membranes, cables and contact, cannot hold it), or supports
    that leave a mode free and effects that only load the body."""
    orphans = np.repeat(~used, 3)
    held = fixed & ~orphans
    if held.any() and any(type(e).contribute is not _base_contribute for e in model.effects
                          if not _is_load_only(e)):
        return  # an effect may hold the body (springs, contact): rely on the solve check
    Xc = X[used].mean(axis=0)
    d = X - Xc
    scale = np.abs(d[used]).max() or 1.0
    n = len(X)
    modes = np.zeros((6, n, 3))
    for k in range(3):
        modes[k, :, k] = 1.0
        axis = np.eye(3)[k]
        modes[3 + k] = np.cross(axis, d) / scale
    Rc = modes.reshape(6, -1)[:, held]
    G = Rc @ Rc.T if Rc.size else np.zeros((6, 6))
    w, V = np.linalg.eigh(G)
    free = w <= 1e-10 * max(w.max(), 1.0)
    if not free.any():
        return
    # name the free modes: the basis modes that the free eigenvectors span
    span = np.abs(V[:, free]).sum(axis=1)
    names = [_MODES[i] for i in range(6) if span[i] > 1e-6]
    supports = {e.name: int(sum(len(np.asarray(c.nodes).reshape(-1)) for c in e.constraints()))
                for e in model.effects if e.constraints()}
    where = (", ".join(f"'{k}' holds {v} node(s)" for k, v in supports.items())
             if supports else "no effect sets a support")
    held_set = model.mesh.node_sets.get("fixed")  # the meshing stage's chest-wall node set
    empty = held_set is not None and len(held_set) == 0
    hint = (" The mesh's 'fixed' node set is empty: the meshing stage takes it from the "
            "chest-wall muscle, and a segmentation without muscle leaves none; segment the "
            "muscle, or support the body another way." if empty else "")
    verdict = {"kind": "no equilibrium", "reason": "unsupported",
               "free_modes": int(free.sum()), "modes": names, "supports": supports}
    raise NoEquilibrium(
        f"mechanics: no equilibrium: nothing holds the body against {int(free.sum())} "
        f"rigid-body mode(s) ({', '.join(names)}): {where}.{hint} Add supports (e.g. a "
        "'fixed' effect on a node set) before solving.", verdict=verdict)


_base_contribute = Effect.contribute


def _is_load_only(eff) -> bool:
    return bool(getattr(eff, "load_only", False))

#: A solve that fails after its last cut-back is at a limit point (no equilibrium along the
#: load path) when its last converged step moved the body this many times more per unit
#: load than its first step did (the structure has lost its stiffness against the load), or
#: when, at the last step's rate, the body would move more than LIMIT_REACH times its size
#: by full load (it was never held: a breast sliding off a flat slab in the tilted position,
#: 236 mm per unit load at the last step and 308 at the first, on a 200 mm slab).
#: Either way, the motion must be one of the whole part (its mean over its nodes at least
#: LIMIT_COHERENCE of their mean magnitude): a part that gives way moves away as a body,
#: one that sags or spreads in place under a stalled Newton does not.
LIMIT_SOFTENING = 10.0
LIMIT_REACH = 0.5
LIMIT_COHERENCE = 0.5


def _limit_point(nw: _Newton, first, prev, lam: float, u: np.ndarray) -> dict | None:
    """Verdict of a failed solve whose load-displacement path flattens (see
    :data:`LIMIT_SOFTENING`), with the force budget of the breast (the body where the mesh
    has no breast region) at the last converged load: its load along the load direction,
    and what the solid, each effect and the supports carry of it (mN; they sum to the
    load). None when the path does not flatten (a numerical failure, not a verdict)."""
    if first is None or prev is None or lam <= prev[0] or first[0] <= 0.0:
        return None
    from mechanics.mesh import BREAST_REGIONS

    model, X = nw.model, nw.X
    tets = model.mesh.tets
    in_breast = np.isin(model.mesh.region, np.asarray(BREAST_REGIONS))
    part = "breast" if in_breast.any() else "body"
    nodes = np.unique(tets[in_breast] if in_breast.any() else tets)
    U, U0 = u.reshape(-1, 3)[nodes], prev[1].reshape(-1, 3)[nodes]
    rate = np.linalg.norm(U - U0, axis=1).max() / (lam - prev[0])  # mm per unit load
    softening = rate / max(np.linalg.norm(first[1].reshape(-1, 3)[nodes], axis=1).max()
                           / first[0], 1e-300)
    # the displacement at full load if the last step's rate held, against the part's size
    extent = float(np.linalg.norm(np.ptp(X[nodes], axis=0)))
    reach = (np.linalg.norm(U, axis=1).max() + (1.0 - lam) * rate) / extent
    # how much of the last step's motion is one motion of the whole part (1: a rigid
    # translation, sliding away; near 0: sagging or spreading in place)
    dU = U - U0
    coherence = float(np.linalg.norm(dU.mean(0)) / max(np.linalg.norm(dU, axis=1).mean(),
                                                      1e-300))
    log.debug("limit point check: softening %.3g, reach %.3g, coherence %.3g", softening,
              reach, coherence)
    if not ((softening >= LIMIT_SOFTENING or reach >= LIMIT_REACH)
            and coherence >= LIMIT_COHERENCE):
        return None
    x = X + u.reshape(-1, 3)
    load = np.zeros(3)
    carried: dict[str, np.ndarray] = {}
    for eff in model.effects:
        f = np.asarray(eff.contribute(X, x, lam).force, float).reshape(-1, 3)[nodes].sum(0)
        if _is_load_only(eff):
            load -= f  # the force the load applies (residual = internal - external)
        else:
            carried[eff.name] = f
    if not np.any(load):
        return None
    ev = nw.solid.evaluate(x, tangent=False)
    carried["solid"] = ev.force.reshape(-1, 3)[nodes].sum(0)
    R = ev.force.reshape(-1) + _effects(model, X, x, lam)[0]
    fixed = nw.fixed.reshape(-1, 3)[nodes]
    carried["supports"] = -np.where(fixed, R.reshape(-1, 3)[nodes], 0.0).sum(0)
    # the budget along the way the part gives way (its mean motion over the last step),
    # where the load pushes that way; else along the load
    move = (U - U0).mean(0)
    move = move / max(np.linalg.norm(move), 1e-300)
    d = move if load @ move > 0.05 * np.linalg.norm(load) else load / np.linalg.norm(load)
    shares = {k: float(v @ d) for k, v in carried.items() if abs(float(v @ d)) > 1e-9}
    along = float(load @ d)
    budget = ", ".join(f"{k} {v:.0f}" for k, v in sorted(shares.items(), key=lambda kv: -kv[1]))
    message = (
        f"the {part} gives way along ({', '.join(f'{c:.2f}' for c in move)}): over the last "
        f"converged step it moved {rate:.0f} mm per unit load ({softening:.1f}x the first "
        f"step's rate; {reach:.1f}x its size by full load). At load {lam:.3g} the load pushes "
        f"it {along:.0f} mN along ({', '.join(f'{c:.2f}' for c in d)}) (at full load "
        f"{along / lam:.0f} mN), carried by: {budget} mN; the supports hold "
        f"{int(np.any(nw.fixed.reshape(-1, 3)[nw.solid.used_nodes], axis=1).sum())} of "
        f"{int(nw.solid.used_nodes.sum())} nodes. Nothing in the model holds the "
        f"rest in this position: add support along that direction (e.g. hold the skin's "
        "lateral cut), or stiffen what carries it (ligaments, skin, fascia, friction)")
    return {"kind": "no equilibrium", "reason": "limit point", "load": float(lam),
            "softening": float(softening), "mm_per_unit_load": float(rate),
            "reach": float(reach), "coherence": coherence, "part": part,
            "part_size_mm": extent,
            "budget_direction": d.tolist(), "load_mN": along, "load_at_full_mN": along / lam,
            "carried_mN": shares, "motion_direction": move.tolist(),
            "message": message}


#: A tet whose volume ratio J is below this in a converged state has lost most of its
#: volume, which none of the model's tissues (nu about 0.49) does: the averaged nodal
#: pressure holds the volume of each node's patch, not of each tet, which lets neighbouring
#: tets collapse and swell side by side. Measured on the 20k-tet phantom in supine without
#: its skin: at the last converged load (0.947; Newton then stalled through 18 cut-backs)
#: 22 tets below 0.2 (min 0.04) and 113 above 1.5, at the left breast's lateral base; with
#: every effect, converged, the lowest is 0.54, and 0.83 on the 20k-tet hemisphere.
CRUSHED_J = 0.2


def _crush_hint(nw: _Newton, J: np.ndarray) -> str:
    """Where the last converged state's tets (``J`` their volume ratios) have collapsed (see
    :data:`CRUSHED_J`; geometrically linear ones never count), as a clause of the failure's
    message; empty where none has."""
    model, X = nw.model, nw.X
    bad = np.flatnonzero((np.asarray(J) < CRUSHED_J) & ~nw.solid.linear_mask)
    if len(bad) == 0:
        return ""
    from mechanics.mesh import REGIONS

    names = {code: name for name, code in REGIONS.items()}
    k = bad[np.argmin(J[bad])]
    at = ", ".join(f"{c:.1f}" for c in X[model.mesh.tets[k]].mean(axis=0))
    regions = ", ".join(names.get(int(c), str(int(c))) for c in np.unique(model.mesh.region[bad]))
    return (f"; in the last converged state {len(bad)} of {len(J)} tets have lost more than "
            f"{1 - CRUSHED_J:.0%} of their volume (J down to {J[k]:.2f}, the lowest at ({at}) "
            f"mm in the reference mesh; {regions}): no tissue of the model does that, so the "
            "mesh no longer represents the deformation there; what holds that tissue in the "
            "body (skin, supports) or smaller tets there may let the solve through")


def _mesh_hint(mesh) -> str:
    """Why a solve may fail from its very first load step, when the mesh shows it: tets that
    hang on the rest by an edge or a vertex (a free rotation). Computed only on failure."""
    from mechanics.mesh import hinged_tets

    bad = hinged_tets(mesh.tets)
    if len(bad) == 0:
        return ""
    shown = ", ".join(str(int(t)) for t in bad[:5]) + (", ..." if len(bad) > 5 else "")
    return (f"; the mesh has {len(bad)} tet(s) that meet the rest only at an edge or a vertex "
            f"(tets {shown}): they rotate freely; remove them or re-mesh (the meshing stage "
            "keeps only the face-connected body)")
