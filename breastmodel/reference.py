"""The hanging-hemisphere reference problem (``../shared/febio/hemisphere``) as a model.

A hemisphere of radius 60 mm hangs under its own weight from its flat face (node set
``base``, fixed); E = 1 kPa, nu = 0.49, density 1000 kg/m^3, g = 9.81 m/s^2 along -z. Its
continuum tip displacement and FEBio's figures are in that folder's README.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: The laws of the reference: Neo-Hookean, and Gent with Jm = 5.
LAWS = {"neo_hookean": {"name": "neo_hookean", "E": 1.0, "nu": 0.49},
        "gent": {"name": "gent", "E": 1.0, "nu": 0.49, "Jm": 5.0}}


def hemisphere_model(mesh_path: str | Path, law: str = "neo_hookean", *,
                     formulation: str = "anp", skin: dict | None = None):
    """The reference on a stored mesh (``hemi_20k.npz``, ``hemi_150k.npz``).

    Parameters
    ----------
    mesh_path : .npz with ``nodes`` (N, 3) mm, ``tets`` (M, 4), ``base``, ``tip``
    law : "neo_hookean" or "gent"
    formulation : "anp" or "standard"
    skin : keyword table of a ``skin`` effect on the curved face (face set ``skin``); None:
        no skin

    Returns
    -------
    model : mechanics.model.Model
    tip : int, the node at (0, 0, -60)
    """
    from mechanics.mesh import Mesh
    from mechanics.model import build_model

    if law not in LAWS:
        raise ValueError(f"hemisphere reference: law must be one of {sorted(LAWS)}, got {law!r}")
    z = np.load(mesh_path)
    faces = {}
    if skin is not None:
        from meshing.sets import tet_faces

        boundary = tet_faces(z["tets"])[0]
        faces["skin"] = boundary[~np.all(np.isclose(z["nodes"][boundary, 2], 0.0), axis=1)]
    mesh = Mesh(z["nodes"], z["tets"], np.ones(len(z["tets"])), node_sets={"base": z["base"]},
                face_sets=faces)
    gravity = {"direction": (0, 0, -1), "g": 9.81, "density": 1000.0}
    effects = {"gravity": gravity, "fixed": {"node_set": "base"}}
    if skin is not None:
        effects["skin"] = dict(skin)
    model = build_model(mesh, {1: dict(LAWS[law])}, effects, formulation=formulation)
    return model, int(z["tip"])
