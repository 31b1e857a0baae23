"""Fields of a solved state for viewer files (written by ``meshing.export.write_vtu``).

Point data: ``displacement`` (N, 3) mm, ``pressure`` (N,) kPa ("anp"); cell data:
``stress`` (M, 9) Cauchy kPa (row-major), ``von_mises`` kPa, ``J``, ``stretch`` (M, 3)
principal stretches (descending). Points are the reference positions ("warp by vector" with
``displacement`` shows the deformed shape), or the deformed positions with ``deformed=True``
(points minus ``displacement`` give the reference).
"""

from __future__ import annotations

import numpy as np

from mechanics.kernels import deformation_gradient, reference_geometry
from mechanics.mesh import Mesh


def principal_stretches(X: np.ndarray, x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M, 3) principal stretches per element, descending (sqrt of eigenvalues of C)."""
    dN, _ = reference_geometry(X, tets)
    F = deformation_gradient(x, tets, dN)
    C = np.einsum("mki,mkj->mij", F, F)
    return np.sqrt(np.clip(np.linalg.eigvalsh(C), 0.0, None))[:, ::-1]


def von_mises(stress: np.ndarray) -> np.ndarray:
    """(M,) von Mises equivalent of Cauchy stresses (M, 3, 3), kPa."""
    dev = stress - np.trace(stress, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("mij,mij->m", dev, dev))


def result_fields(mesh: Mesh, state, *, X: np.ndarray | None = None,
                  deformed: bool = False):
    """The fields of a solved state for a viewer file.

    Parameters
    ----------
    mesh : Mesh
    state : State (``u``, ``stress``, ``J``, optional ``pressure``)
    X : (N, 3) reference positions, mm (default ``state.X`` or ``mesh.nodes``)
    deformed : points are the deformed positions X + u (else the reference positions)

    Returns
    -------
    points : (N, 3) mm
    point_data : ``displacement`` (N, 3) mm, ``pressure`` (N,) kPa ("anp")
    cell_data : ``stress`` (M, 9) Cauchy kPa, ``von_mises`` (M,) kPa, ``J`` (M,),
        ``stretch`` (M, 3) principal stretches, descending
    """
    if X is None:
        X = state.X if getattr(state, "X", None) is not None else mesh.nodes
    X = np.asarray(X, float)
    u = np.asarray(state.u, float)
    point_data = {"displacement": u}
    if state.pressure is not None and len(state.pressure) == mesh.n_nodes:
        point_data["pressure"] = np.asarray(state.pressure, float)
    stress = np.asarray(state.stress, float)
    cell_data = {"stress": stress.reshape(-1, 9), "von_mises": von_mises(stress),
                 "J": np.asarray(state.J, float),
                 "stretch": principal_stretches(X, X + u, mesh.tets)}
    return (X + u if deformed else X), point_data, cell_data
