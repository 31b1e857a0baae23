"""A small structured breast-like test mesh (two breast mounds on a muscle slab) and the
paper-like model on it, shared by the effects tests and benchmarks.

Not a phantom of the project's subjects (the meshing stage makes those): a deterministic,
numpy-only mesh with every set the effects read, for tests and benchmarks of mechanics.
"""

from __future__ import annotations

import numpy as np

from breastmodel.phantom.mounds import boundary_faces  # noqa: F401 - re-exported for tests
from breastmodel.phantom.mounds import mound_mesh as breastlike_mesh  # noqa: F401
from mechanics.model import build_model

GRAVITY = {"prone": (0.0, -1.0, 0.0), "supine": (0.0, 1.0, 0.0),
           "tilted": (np.sqrt(0.5), np.sqrt(0.5), 0.0)}


def paper_model(mesh, E_breast, E_skin, E_fascia, position, **changes):
    """The paper's model (all effects) on ``mesh``; ``changes`` replace effect tables, None
    drops one. Moduli in kPa; ``position`` a key of ``GRAVITY``."""
    mats = {r: {"name": "neo_hookean", "E": E_breast, "nu": 0.49} for r in (1, 3, 4, 5)}
    mats[2] = {"name": "neo_hookean", "E": 10.0, "nu": 0.49}
    effects = {
        "gravity": {"direction": GRAVITY[position]},
        "supports": {},
        "skin": {"E": E_skin},
        "fascia": {"E": E_fascia},
        "ligaments": {"E": 100.0},
        "sliding": {"friction": 0.1},
        "regions": {"E_left": E_breast, "E_right": E_breast, "gland": False},
    }
    for k, v in changes.items():
        if v is None:
            effects.pop(k)
        else:
            effects[k] = v
    return build_model(mesh, mats, effects)


def add_mesh_arguments(ap, *, phantom_size: float) -> None:
    """The benchmarks' ``--phantom-mesh`` and ``--phantom-size`` options (see
    :func:`bench_mesh`)."""
    from pathlib import Path

    ap.add_argument("--phantom-mesh", type=Path, default=None,
                    help="run on an fTetWild mesh of the half-size phantom anatomy (curved "
                         "chest wall) instead of the flat slab: a saved Mesh .npz, meshed at "
                         "--phantom-size and written there first when missing")
    ap.add_argument("--phantom-size", type=float, default=phantom_size,
                    help=f"element size when meshing the phantom, mm (default {phantom_size})")


def bench_mesh(cells, phantom_mesh=None, phantom_size: float = 4.3):
    """The split mesh a benchmark runs on, and a dict that says which: the two-mound mesh of
    ``cells``, or with ``phantom_mesh`` (a .npz path) the half-size phantom anatomy meshed
    at ``phantom_size`` mm by the meshing stage (read from that file, written there first)."""
    from mechanics.effects._interface import split_interface

    if phantom_mesh is None:
        return split_interface(breastlike_mesh(cells=cells)), {"cells": list(cells)}
    from breastmodel.phantom import Anatomy
    from breastmodel.phantom.simulated import anatomy_mesh

    mesh = anatomy_mesh(Anatomy.small(), size_mm=phantom_size, path=phantom_mesh)
    return split_interface(mesh), {"phantom_mesh": str(phantom_mesh)}
