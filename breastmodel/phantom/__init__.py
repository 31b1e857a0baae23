"""Synthetic MRI subjects (phantoms) with known truth.

``make_phantom(out, seed=0)`` writes a subject folder and ``<out>_truth``; see
:mod:`breastmodel.phantom.writer`. The anatomy is in :mod:`breastmodel.phantom.anatomy`.
A family of varied subjects whose truth deformation FEBio computes:
``make_subject(draw_spec(seed), out)`` (:mod:`breastmodel.phantom.family`).
"""

from breastmodel.phantom.anatomy import Anatomy, Breast, reference_volumes
from breastmodel.phantom.family import SubjectSpec, draw_spec, make_subject
from breastmodel.phantom.motion import RigidMotion, patient_gravity
from breastmodel.phantom.writer import displacement, make_phantom, truth_folder

__all__ = [
    "Anatomy", "Breast", "RigidMotion", "SubjectSpec", "displacement", "draw_spec",
    "make_phantom", "make_subject", "patient_gravity", "reference_volumes", "truth_folder",
]
