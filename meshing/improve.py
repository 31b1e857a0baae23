"""Local node relocation to remove the few flat tets fTetWild leaves (skewness near 1).

Only nodes that lie on no boundary and no interface face move, so the surfaces and the
breast-muscle interface stay exactly where the mesher put them.
"""

from __future__ import annotations

import numpy as np

from meshing.quality import element_quality
from meshing.sets import OUTWARD_FACES


def _skew(nodes, tets):
    return element_quality(nodes, tets)["skewness"]


def _node_tets(tets: np.ndarray, n_nodes: int):
    flat = tets.ravel()
    order = np.argsort(flat, kind="stable")
    start = np.searchsorted(flat[order], np.arange(n_nodes + 1))
    return order // 4, start


def relocate_free_nodes(
    nodes: np.ndarray,
    tets: np.ndarray,
    movable: np.ndarray,
    *,
    max_skew: float = 0.85,
    rounds: int = 4,
) -> np.ndarray:
    """Move free nodes of flat tets so that the worst incident tet improves.

    For every node of a tet with skewness above ``max_skew`` that ``movable`` allows, try
    the centroid of its neighbours, the ideal apex over the opposite face of each incident
    bad tet, and halfway points; keep the candidate that most lowers the worst skewness of
    the incident tets while keeping all of them positive.

    Parameters
    ----------
    nodes : (N, 3) mm; tets : (M, 4), positively oriented; movable : (N,) bool

    Returns
    -------
    (N, 3) new node positions (the input is not modified)
    """
    x = np.array(nodes, dtype=float, copy=True)
    inc, start = _node_tets(tets, len(x))
    for _ in range(rounds):
        skew = _skew(x, tets)
        bad = np.flatnonzero(skew > max_skew)
        if len(bad) == 0:
            break
        moved = 0
        for v in np.unique(tets[bad]):
            if not movable[v]:
                continue
            around = inc[start[v] : start[v + 1]]
            local = tets[around]
            before = _skew(x, local).max()
            nbrs = np.unique(local)
            cands = [x[nbrs[nbrs != v]].mean(0)]
            for t in local[_skew(x, local) > max_skew]:
                k = int(np.flatnonzero(t == v)[0])
                face = x[t[OUTWARD_FACES[k]]]
                n = np.cross(face[1] - face[0], face[2] - face[0])
                n = -n / np.linalg.norm(n)  # the outward face normal points away from v
                edge = np.mean(np.linalg.norm(face - np.roll(face, 1, axis=0), axis=1))
                cands.append(face.mean(0) + n * edge * np.sqrt(2.0 / 3.0))
            cands += [0.5 * (x[v] + c) for c in cands]
            best, best_pos = before, None
            old = x[v].copy()
            for c in cands:
                x[v] = c
                q = element_quality(x, local)
                if (q["volume"] > 0).all() and q["skewness"].max() < best - 1e-6:
                    best, best_pos = q["skewness"].max(), c.copy()
            x[v] = old if best_pos is None else best_pos
            moved += best_pos is not None
        if moved == 0:
            break
    return x
