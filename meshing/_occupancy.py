"""Adapter around open3d ray casting: inside/outside and distance queries on closed surfaces.

Only this module imports open3d.
"""

from __future__ import annotations

import numpy as np


def _scene(vertices: np.ndarray, faces: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(vertices, np.float32)),
        o3d.core.Tensor(np.asarray(faces, np.uint32)),
    )
    return scene


def inside(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n,) bool: which points lie inside the closed surface (ray-parity vote)."""
    import open3d as o3d

    scene = _scene(vertices, faces)
    q = o3d.core.Tensor(np.asarray(points, np.float32))
    return scene.compute_occupancy(q, nsamples=3).numpy() > 0.5


def distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n,) float: unsigned distance of each point to the surface, mm."""
    import open3d as o3d

    scene = _scene(vertices, faces)
    q = o3d.core.Tensor(np.asarray(points, np.float32))
    return scene.compute_distance(q).numpy().astype(np.float64)


def projector(vertices: np.ndarray, faces: np.ndarray):
    """Function (n, 3) mm -> (n, 3) mm giving the closest point of the surface (the
    acceleration structure is built once, for many small queries)."""
    import open3d as o3d

    scene = _scene(vertices, faces)

    def project(points: np.ndarray) -> np.ndarray:
        q = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        return scene.compute_closest_points(q)["points"].numpy().astype(np.float64)

    return project
