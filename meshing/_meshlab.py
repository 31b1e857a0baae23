"""Adapter around pymeshlab: surface repair, Taubin smoothing and isotropic remeshing.

The rest of the package sees plain arrays; only this module imports pymeshlab.
"""

from __future__ import annotations

import numpy as np


def _abs(value: float):
    import pymeshlab as ml

    cls = getattr(ml, "AbsoluteValue", None) or ml.PureValue
    return cls(float(value))


def topology(vertices: np.ndarray, faces: np.ndarray) -> dict:
    """Topological measures of a triangle mesh (boundary and non-manifold edge counts...)."""
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(np.asarray(vertices, float), np.asarray(faces, np.int32)))
    return dict(ms.get_topological_measures())


def repair_and_remesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    target_edge_mm: float,
    taubin_steps: int = 10,
    remesh_iterations: int = 6,
    max_hole_edges: int = 1000,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Clean a raw marching-cubes surface and remesh it isotropically.

    Order matters: Taubin smoothing first removes the voxel staircase (so remeshing does not
    reproject onto it), remeshing then gives near-equilateral triangles of the target edge,
    and a short final Taubin pass removes remeshing ripples. Taubin (lambda 0.5,
    mu -0.53) is low-pass and does not shrink the surface like plain Laplacian smoothing.

    Parameters
    ----------
    vertices : (n, 3) float, mm
    faces : (m, 3) int
    target_edge_mm : float
        Target edge length of the remeshed surface, mm.

    Returns
    -------
    vertices : (n', 3) float64, mm
    faces : (m', 3) int64
    repairs : list of str
        What was repaired (empty when the input was clean).
    """
    import pymeshlab as ml

    ms = ml.MeshSet()
    ms.add_mesh(ml.Mesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int32)))
    repairs: list[str] = []

    def count(what: str, before: int, after: int) -> None:
        if before != after:
            repairs.append(f"{what}: {before - after}")

    n_v, n_f = ms.current_mesh().vertex_number(), ms.current_mesh().face_number()
    ms.meshing_remove_duplicate_vertices()
    count("duplicate vertices merged", n_v, ms.current_mesh().vertex_number())
    n_f = ms.current_mesh().face_number()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    count("duplicate or null faces removed", n_f, ms.current_mesh().face_number())
    topo = ms.get_topological_measures()
    if topo["non_two_manifold_edges"] or topo["non_two_manifold_vertices"]:
        n_f = ms.current_mesh().face_number()
        ms.meshing_repair_non_manifold_edges(method=0)
        ms.meshing_repair_non_manifold_vertices()
        count("faces removed at non-manifold edges/vertices", n_f, ms.current_mesh().face_number())
    ms.meshing_remove_unreferenced_vertices()
    if ms.get_topological_measures()["boundary_edges"]:
        n_f = ms.current_mesh().face_number()
        ms.meshing_close_holes(maxholesize=max_hole_edges, newfaceselected=False)
        count("faces added to close holes", ms.current_mesh().face_number(), n_f)

    if taubin_steps:
        ms.apply_coord_taubin_smoothing(lambda_=0.5, mu=-0.53, stepsmoothnum=int(taubin_steps))
    ms.meshing_isotropic_explicit_remeshing(
        targetlen=_abs(target_edge_mm), iterations=int(remesh_iterations)
    )
    ms.apply_coord_taubin_smoothing(lambda_=0.5, mu=-0.53, stepsmoothnum=3)
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    return (
        np.array(m.vertex_matrix(), dtype=np.float64),
        np.array(m.face_matrix(), dtype=np.int64),
        repairs,
    )
