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
                     formulation: str = "anp"):
    """The reference on a stored mesh (``hemi_20k.npz``, ``hemi_150k.npz``).

    Parameters
    ----------
    mesh_path : .npz with ``nodes`` (N, 3) mm, ``tets`` (M, 4), ``base``, ``tip``
    law : "neo_hookean" or "gent"
    formulation : "anp" or "standard"

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
    mesh = Mesh(z["nodes"], z["tets"], np.ones(len(z["tets"])), node_sets={"base": z["base"]})
    gravity = {"direction": (0, 0, -1), "g": 9.81, "density": 1000.0}
    model = build_model(mesh, {1: dict(LAWS[law])},
                        {"gravity": gravity, "fixed": {"node_set": "base"}},
                        formulation=formulation)
    return model, int(z["tip"])
