"""Local node relocation to remove the few flat tets fTetWild leaves (skewness near 1).

:func:`relocate_free_nodes` moves interior nodes only. Most of the flat tets that remain
hang on a badly shaped boundary triangle (circumradius several times the inradius), which
no interior move can mend: :func:`relocate_boundary_nodes` slides boundary nodes along
the input surface (every candidate is projected back onto it), so the boundary stays on
the surface the mesher was given.
"""

from __future__ import annotations

import numpy as np

from meshing.quality import _volume_skewness, volume_skewness
from meshing.sets import OUTWARD_FACES


def _skew(nodes, tets):
    return volume_skewness(nodes, tets)[1]


def _node_tets(tets: np.ndarray, n_nodes: int):
    flat = tets.ravel()
    order = np.argsort(flat, kind="stable")
    start = np.searchsorted(flat[order], np.arange(n_nodes + 1))
    return order // 4, start


def _try(x, v, local, cands, before):
    """Best candidate position of node v (or None): lowest worst skewness of the tets
    ``local`` around it, all of them positive; the first of equals (within 1e-6) in the
    order given. Every candidate is measured in one call (the tets' corners stacked)."""
    cands = np.asarray(cands, float).reshape(-1, 3)
    if len(cands) == 0:
        return None
    corners = np.broadcast_to(x[local], (len(cands), *local.shape, 3)).copy()
    corners[:, local == v] = cands[:, None, :]
    vol, skew, _ = _volume_skewness(corners.reshape(-1, 4, 3))
    ok = (vol.reshape(len(cands), -1) > 0).all(1)
    worst = skew.reshape(len(cands), -1).max(1)
    best, best_pos = before, None
    for c, good, w in zip(cands, ok, worst):
        if good and w < best - 1e-6:
            best, best_pos = w, c.copy()
    if best_pos is not None:
        x[v] = best_pos
    return best_pos


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
            moved += _try(x, v, local, cands, before) is not None
        if moved == 0:
            break
    return x


def relocate_boundary_nodes(
    nodes: np.ndarray,
    tets: np.ndarray,
    boundary_faces: np.ndarray,
    movable: np.ndarray,
    project,
    *,
    max_skew: float = 0.85,
    rounds: int = 4,
    crease_deg: float = 60.0,
    max_deviation: float = np.inf,
) -> np.ndarray:
    """Slide boundary nodes of flat tets along the surface so that the worst incident tet
    improves.

    Candidates for a boundary node are the centroid of its boundary neighbours, points a
    quarter and a half of the way there, and steps of 0.3 edge towards and away from each
    neighbour, all passed through ``project``. Nodes on a crease (incident boundary
    normals more than ``crease_deg`` from their mean, e.g. the edges of a field-of-view
    cut) stay, so that creases are not rounded off.

    Parameters
    ----------
    nodes : (N, 3) mm; tets : (M, 4), positively oriented
    boundary_faces : (B, 3) outward boundary faces of ``tets``
    movable : (N,) bool, nodes allowed to move (e.g. boundary nodes off the interface)
    project : callable, (k, 3) mm -> (k, 3) mm, closest points of the input surface

    Returns
    -------
    (N, 3) new node positions (the input is not modified)
    """
    from meshing.surface import triangle_normals

    x = np.array(nodes, dtype=float, copy=True)
    inc, start = _node_tets(tets, len(x))
    flat = np.asarray(boundary_faces).ravel()
    order = np.argsort(flat, kind="stable")
    bstart = np.searchsorted(flat[order], np.arange(len(x) + 1))
    binc = order // 3
    cos_crease = np.cos(np.radians(crease_deg))
    for _ in range(rounds):
        bad = np.flatnonzero(_skew(x, tets) > max_skew)
        moved = 0
        for v in np.unique(tets[bad]):
            fs = binc[bstart[v] : bstart[v + 1]]
            if not movable[v] or len(fs) == 0:
                continue
            n = triangle_normals(x, boundary_faces[fs])
            mean = n.mean(0)
            if (n @ mean).min() < cos_crease * np.linalg.norm(mean):
                continue
            local = tets[inc[start[v] : start[v + 1]]]
            nbrs = np.unique(boundary_faces[fs])
            nbrs = nbrs[nbrs != v]
            lap = x[nbrs].mean(0)
            cands = [lap, 0.5 * (x[v] + lap), 0.25 * (3 * x[v] + lap)]
            for u in nbrs:
                cands += [x[v] + 0.3 * (x[u] - x[v]), x[v] - 0.3 * (x[u] - x[v])]
            cands = project(np.array(cands))
            if np.isfinite(max_deviation):
                faces = boundary_faces[fs]
                old = x[v].copy()
                cent = []
                for c in cands:
                    x[v] = c
                    cent.append(x[faces].mean(1))
                x[v] = old
                cent = np.concatenate(cent)
                dev = np.linalg.norm(project(cent) - cent, axis=1).reshape(len(cands), -1)
                cands = cands[dev.max(1) <= max_deviation]
            moved += _try(x, v, local, cands, _skew(x, local).max()) is not None
        if moved == 0:
            break
    return x


def _defects(tets: np.ndarray) -> int:
    """Count of topological defects: faces used by more than two tets, boundary edges not
    on exactly two boundary faces, tets that repeat a node."""
    st = np.sort(tets, axis=1)
    n = int((st[:, 1:] == st[:, :-1]).any(1).sum())
    faces = np.sort(tets[:, OUTWARD_FACES].reshape(-1, 3), axis=1)
    uf, cnt = _unique_rows(faces)
    n += int((cnt > 2).sum())
    edges = np.sort(uf[cnt == 1][:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    _, ecnt = _unique_rows(edges)
    return n + int((ecnt != 2).sum())


def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(rows, axis=0, return_counts=True)`` for rows of 2 or 3 node indices,
    through one int64 key per row (a tenth of the time: the collapse loop asks for it on
    every face of the mesh, 90 times on full-000's)."""
    rows = np.asarray(rows, np.int64)
    bits = 63 // rows.shape[1]
    if rows.size == 0 or int(rows.max()) >= 1 << bits:
        return np.unique(rows, axis=0, return_counts=True)
    key = np.zeros(len(rows), np.int64)
    for j in range(rows.shape[1]):
        key = (key << bits) | rows[:, j]
    _, first, cnt = np.unique(key, return_index=True, return_counts=True)
    return rows[first], cnt


def collapse_short_edges(
    nodes: np.ndarray,
    tets: np.ndarray,
    keep_on: list[np.ndarray],
    *,
    max_skew: float = 0.9,
    max_collapses: int = 50,
) -> np.ndarray:
    """Collapse an edge of each tet flatter than ``max_skew`` when that helps.

    A flat tet whose nodes cannot move far enough (its short edge lies on the boundary or
    on the interface) disappears with one of its edges (the shortest admissible one): one
    end node takes the place of the other (no new positions, so surfaces stay where they
    are). A node on a surface
    of ``keep_on`` only merges into a node on the same surface along an edge of it; the
    collapse is kept only if every changed tet stays positive with skewness below that of
    the worst tet it touched and it adds no topological defect (a face of three tets, a
    non-manifold boundary edge).

    Parameters
    ----------
    nodes : (N, 3) mm; tets : (M, 4), positively oriented
    keep_on : list of (F, 3) face arrays (e.g. boundary faces, interface faces)

    Returns
    -------
    tets : (M', 4) (node indices unchanged; some nodes may end up unused)
    kept : (M',) int, the input row of each output tet
    """
    t = np.array(tets, copy=True)
    kept = np.arange(len(t))
    on = [np.zeros(len(nodes), bool) for _ in keep_on]
    surf_edges = []
    for mask, faces in zip(on, keep_on):
        mask[np.asarray(faces).ravel()] = True
        e = np.sort(np.asarray(faces)[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
        surf_edges.append({tuple(x) for x in e.tolist()})
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]

    def collapse_one(t, tet, defects):
        """Rows of t kept and t after the first admissible collapse of one of tet's edges
        (shortest first), or None."""
        lens = [np.linalg.norm(nodes[tet[a]] - nodes[tet[b]]) for a, b in pairs]
        for k in np.argsort(lens):
            a, b = int(tet[pairs[k][0]]), int(tet[pairs[k][1]])
            for keep, gone in ((a, b), (b, a)):
                if any(m[gone] and not (m[keep] and (min(a, b), max(a, b)) in e)
                       for m, e in zip(on, surf_edges)):
                    continue
                touch = (t == gone).any(1)
                both = touch & (t == keep).any(1)
                worst = _skew(nodes, t[touch]).max()
                new = t.copy()
                new[new == gone] = keep
                changed = new[touch & ~both]
                # No changed tet (every tet at `gone` holds the edge, e.g. a cap node of the
                # flat tet alone): the collapse just removes them. The max over nothing
                # raised here, the error CI's pipeline test met on one fTetWild mesh.
                vol, skew = volume_skewness(nodes, changed)
                if len(changed) and not ((vol > 0).all() and skew.max() < worst - 1e-6):
                    continue
                if _defects(new[~both]) <= defects:
                    return ~both, new[~both]
        return None

    for _ in range(max_collapses):
        skew = _skew(nodes, t)
        bad = np.flatnonzero(skew > max_skew)
        defects = _defects(t)
        for i in bad[np.argsort(-skew[bad])]:
            res = collapse_one(t, t[i], defects)
            if res is not None:
                kept, t = kept[res[0]], res[1]
                break
        else:
            break
    return t, kept
