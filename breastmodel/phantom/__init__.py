"""Synthetic MRI subjects (phantoms) with known truth.

``make_phantom(out, seed=0)`` writes a subject folder and ``<out>_truth``; see
:mod:`breastmodel.phantom.writer`. The anatomy is in :mod:`breastmodel.phantom.anatomy`.
A family of varied subjects whose truth deformation FEBio computes:
``make_subject(draw_spec(seed), out)`` (:mod:`breastmodel.phantom.family`).
"""

import importlib

#: public name -> the module that defines it; imported on first use, so that a light module
#: of the package (``mounds``: the two-mound mesh, numpy only) loads without the imaging
#: stack that the writer needs (the mechanics tests use it with numpy and scipy alone)
_WHERE = {
    "Anatomy": "anatomy", "Breast": "anatomy", "reference_volumes": "anatomy",
    "SubjectSpec": "family", "draw_spec": "family", "make_subject": "family",
    "RigidMotion": "motion", "patient_gravity": "motion",
    "displacement": "writer", "make_phantom": "writer", "truth_folder": "writer",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
