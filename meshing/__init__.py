"""meshing stage: label map -> repaired surfaces -> tagged tetrahedral mesh.

Public API: :func:`mesh_labels` (label map -> ``mechanics.mesh.Mesh``),
:func:`meshing.surface.skin_surface` (measured skin), :mod:`meshing.export` (VTU, FEBio,
PLY), :func:`meshing.quality.report`. pymeshlab, pytetwild and open3d live behind the
adapters ``_meshlab``, ``_tetwild`` and ``_occupancy``.
"""

from meshing.labels import MeshingWarning
from meshing.volume import mesh_labels

__all__ = ["mesh_labels", "MeshingWarning"]
