"""The mesh as a candidate: is the run's mesh too coarse?

``mesh_refinement`` is the run's fitted model again on a mesh of half the edge length, or of
about :data:`MAX_PROBE_TETS` tets where halving would make more
(:func:`breastmodel.pipeline.refinement.refine_run`: cached stages of the run, the very ones
``[evaluate] refinement = true`` makes at half the edge). Its column is the change of each
scored skin node's signed error when the node moves as the fine mesh predicts: the node's
displacement from the measured reference configuration is replaced by the fine mesh's,
interpolated on the fine skin at the node's closest point there (reference configuration),
and the node's signed distance to the measured skin is taken again. The shape of the skin
itself, which the finer mesh follows more closely, is left out: that is the reference
position's residual, the noise floor. The column's amount is fixed at 1 (the finer mesh, no
parameter); the fitted parameters are re-fitted with it as with every candidate. A coarse
mesh is mostly too stiff, which the fitted modulus absorbs: the candidate is then also a
convergence check (:mod:`breastmodel.diagnosis.scoring`: a finer mesh that moves a fitted
parameter by 10 % or more makes it significant, whatever it explains).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.diagnosis.candidates import Candidate

__all__ = ["MAX_PROBE_TETS", "MESH_CANDIDATE", "add_mesh_candidate", "mesh_candidate",
           "probe_factor", "probe_mesh", "refined_column", "refined_columns"]

MESH_CANDIDATE = "mesh_refinement"
#: The probe halves the mesh's edge, unless that would make more than about this many tets
#: (as the edge's inverse cube: halving 6 mm gave 7.0x on small-003's mesh, 10926 -> 76803);
#: then its edge is the one that would make this many by that rule. Graded meshes grow less:
#: full-000's 45.6k tets at 6 mm became 111.7k at 4.02 mm (the probe 169 s, peak 1.6 GB).
MAX_PROBE_TETS = 150_000


def probe_factor(n_tets: int) -> float:
    """The probe's edge as a fraction of the run's: 1/2, or more for a mesh whose half-edge
    copy would exceed :data:`MAX_PROBE_TETS`."""
    return max(0.5, (n_tets / MAX_PROBE_TETS) ** (1.0 / 3.0))


def mesh_candidate(probe: Mapping[str, Any], positions: Sequence[str]) -> Candidate:
    """The ``mesh_refinement`` candidate of a probe (:func:`probe_mesh`) whose scored
    positions are ``positions``."""
    return Candidate(MESH_CANDIDATE, "numerical",
                     f"the same model on a mesh of {probe['fine_size_mm']:g} mm edges "
                     f"({probe['fine_n_tets']} tets) instead of {probe['size_mm']:g} mm "
                     f"({probe['n_tets']}): a refinement probe, no parameter",
                     amplitude=(1.0, 1.0), measurement="refinement", acts_on=tuple(positions))


def probe_mesh(run, *, progress: bool = True) -> tuple[dict | None, str]:
    """The run's refinement probe (its edge :func:`probe_factor` times the run's):
    ``(probe, "")`` with the folders of :func:`~breastmodel.pipeline.refinement.refine_run`,
    or ``(None, reason)`` where the run cannot be remeshed (a given problem folder), its mesh
    is too large to refine, or a stage fails."""
    from breastmodel.errors import StageError
    from breastmodel.pipeline.refinement import refine_run

    factor = probe_factor(run.problem.mesh.n_tets)
    if factor > 0.8:
        return None, (f"the mesh has {run.problem.mesh.n_tets} tets: a probe of at most "
                      f"{MAX_PROBE_TETS} tets would refine its edge by less than a fifth")
    try:
        return refine_run(run.out, factor=round(factor, 2), progress=progress), ""
    except StageError as exc:
        return None, str(exc)
    except Exception as exc:  # noqa: BLE001 - a failed probe is one candidate, not the diagnosis
        return None, f"the probe failed: {type(exc).__name__}: {exc}"


def _barycentric(q: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(n, 3) barycentric coordinates of points ``q`` on triangles (a, b, c)."""
    v0, v1, v2 = b - a, c - a, q - a
    d00, d01, d11 = (np.einsum("ij,ij->i", x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    den = np.where(np.abs(d00 * d11 - d01 ** 2) > 1e-300, d00 * d11 - d01 ** 2, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.column_stack([1.0 - v - w, v, w])


def _fine_skin_motion(probe: Mapping[str, Any], positions: Sequence[str]):
    """The fine mesh's skin: its triangles, reference node positions and each position's
    displacement from them (canonical, conforming node numbering)."""
    from breastmodel.pipeline.problem import load_problem, skin_nodes

    prob = load_problem(Path(probe["problem_dir"]))
    mesh = prob.mesh
    tri = np.asarray(mesh.face_sets["skin"])
    conf = np.unique(tri)
    u = {}
    for p in positions:
        with np.load(Path(probe["predict_dirs"][p]) / "predicted.npz") as z:
            x = z["x"]
        full = np.zeros((mesh.n_nodes, 3))
        full[conf] = x[skin_nodes(prob, len(x))] - mesh.nodes[conf]
        u[p] = full
    return tri, mesh.nodes, u


def refined_columns(problem, state: Mapping[str, Any], nodes: np.ndarray, keep: np.ndarray,
                    positions: Sequence[str], probe: Mapping[str, Any]) -> dict:
    """Per position, the change of the scored skin nodes' signed errors on the probe's finer
    mesh, mm (``{position: (n,)}``, the order of the residual).

    ``state`` is the fitted model's solution on the run's mesh (``X``, ``u`` {position}),
    ``nodes`` / ``keep`` the skin nodes and the scored ones (as in
    :func:`breastmodel.diagnosis.residual.measured_geometry`).
    """
    from breastmodel.evaluation.distances import TriangleSurface

    tri, ref_f, u_f = _fine_skin_motion(probe, positions)
    R = np.asarray(problem.mesh.nodes)[nodes[keep]]  # the measured reference configuration
    q, t = TriangleSurface(ref_f, tri).closest(R)
    w = _barycentric(q, *(ref_f[tri[t, k]] for k in range(3)))
    X = np.asarray(state["X"])
    out = {}
    for p in positions:
        x = (X + np.asarray(state["u"][p]))[nodes[keep]]
        fine_u = np.einsum("ik,ikj->ij", w, u_f[p][tri[t]])
        moved = R + fine_u
        skin = TriangleSurface(*problem.skins[p])  # one BVH for both queries
        out[p] = skin.distance(moved, signed=True)[0] - skin.distance(x, signed=True)[0]
    return out


def refined_column(geometry: Mapping[str, Mapping[str, np.ndarray]],
                   order: Sequence[str]) -> tuple[list, list, list, list]:
    """The candidate's column over the stacked residual (``geometry[p]["refined"]`` of
    every position in ``order``), its amount fixed at 1."""
    return ([np.concatenate([geometry[p]["refined"] for p in order])], [1.0], [1.0],
            ["refinement"])


def add_mesh_candidate(run, state: Mapping[str, Any], nodes: np.ndarray, keep: np.ndarray,
                       positions: Sequence[str], geometry: dict, *, refine: bool,
                       progress: bool) -> tuple[Candidate | None, dict]:
    """Probe the run's mesh and put the candidate's column in ``geometry`` (``"refined"`` of
    every position). Returns ``(candidate, probe)`` (the probe's sizes, tet counts, folder and
    seconds, for the ranking entry), or ``(None, {"name", "reason"})``, what ``skipped``
    lists, where it is not asked for or the run cannot be remeshed."""
    import time

    if not refine:
        return None, {"name": MESH_CANDIDATE, "reason": "not asked for (--no-refinement)"}
    t0 = time.perf_counter()
    if progress:
        print(f"diagnose: {MESH_CANDIDATE}: the fitted model on a finer mesh (cached stages "
              "of the run)", flush=True)
    probe, why = probe_mesh(run, progress=progress)
    if probe is None:
        return None, {"name": MESH_CANDIDATE, "reason": why}
    cols = refined_columns(run.problem, state, nodes, keep, positions, probe)
    for p in positions:
        geometry[p]["refined"] = cols[p]
    info = {k: probe[k] for k in ("size_mm", "fine_size_mm", "n_tets", "fine_n_tets")}
    info.update(problem_dir=str(probe["problem_dir"]), seconds=time.perf_counter() - t0)
    return mesh_candidate(probe, positions), info
