"""Synthetic MRI subjects (phantoms) with known truth.

``make_phantom(out, seed=0)`` writes a subject folder and ``<out>_truth``; see
:mod:`breastmodel.phantom.writer`. The anatomy is in :mod:`breastmodel.phantom.anatomy`.
"""

from breastmodel.phantom.anatomy import Anatomy, Breast, reference_volumes
from breastmodel.phantom.motion import RigidMotion, patient_gravity
from breastmodel.phantom.writer import displacement, make_phantom, truth_folder

__all__ = [
    "Anatomy", "Breast", "RigidMotion", "displacement", "make_phantom", "patient_gravity",
    "reference_volumes", "truth_folder",
]
