"""Evaluation of predictions against measurements: surface distances, MHD, landmark errors.

Imports open3d lazily (only when a surface is built).
"""

from .distances import TriangleSurface, closest_point_on_triangles, is_closed, point_to_surface
from .metrics import (
    landmark_errors,
    normal_tangential,
    per_region_metrics,
    surface_metrics,
    vertex_normals,
)

__all__ = [
    "TriangleSurface",
    "closest_point_on_triangles",
    "is_closed",
    "landmark_errors",
    "normal_tangential",
    "per_region_metrics",
    "point_to_surface",
    "surface_metrics",
    "vertex_normals",
]
