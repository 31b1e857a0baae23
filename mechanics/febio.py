"""FEBio 4.0 input files from a :class:`mechanics.model.Model`: one writer for every use.

FEBio (febio.org) is an independent finite-element code; a ``.feb`` file written here lets it
solve the same problem as :func:`mechanics.solver.solve` (a validation truth) or carries a
fitted model to other users. Units are the project's: mm, kPa, mN, with mass in kg and time
in s (density 1000 kg/m^3 = 1e-6 kg/mm^3, g = 9810 mm/s^2).

The knowledge of how a physical unit reads in FEBio lives with that unit: every material
implements ``to_febio(self)`` (FEBio type and parameters) and every effect
``to_febio(self, feb)``, which adds what it needs to the :class:`FebBuilder` ``feb`` (node
sets, surfaces, shells, springs, contact, loads, boundary conditions). A unit without the
hook, or whose options FEBio cannot express, raises :class:`FebioUnsupported` naming itself
and why, before any file is written. Hooks that can only approximate (e.g. a membrane's
tension-field wrinkling) call :meth:`FebBuilder.approximate`, which refuses unless the caller
passed ``approximate=True`` and otherwise records the approximation as a comment in the file.

Element technology (``element``):

- ``"tet4"``: FEBio's standard displacement tet; the same discrete problem as our
  ``formulation="standard"`` (and it locks volumetrically as that does at nu near 1/2).
- ``"ut4"``: FEBio's nodally integrated UT4 tet (locking-free). It integrates the whole
  energy at the nodes (plus a small element share, ``alpha``), whereas our "anp" averages only
  the volume ratio, so UT4 is somewhat softer than "anp" on the same mesh; its stiffness is
  costly to evaluate (minutes on a 20k-tet mesh).
- ``"tet10"``: quadratic tets; a mid-edge node is added on every edge (appended after the
  mesh nodes, straight edges). The displacements of the mesh nodes are the first N rows of
  FEBio's output. Effects on surfaces (shells, contact) are refused with tet10.

Output: FEBio writes the displacement of every node to the plain-text logfile
``displacement.txt`` (``id,ux,uy,uz`` per node after every converged time step), read by
:func:`read_node_data`.

The writer's parts: its vocabulary and XML formatting in :mod:`mechanics.febio_xml`, the
collector the hooks add to in :mod:`mechanics.febio_builder`, the rendering of the file in
:mod:`mechanics.febio_document`; this module holds the entry points and names what callers
import.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mechanics.febio_builder import FebBuilder
from mechanics.febio_xml import (
    DISPLACEMENT_FILE,
    ELEMENTS,
    KG_M3_TO_KG_MM3,
    M_TO_MM,
    SOLVERS,
    TET10_EDGES,
    FebioUnsupported,
    tet10_nodes,
    unsupported,
)

if TYPE_CHECKING:
    from mechanics.model import Model

__all__ = ["DISPLACEMENT_FILE", "ELEMENTS", "KG_M3_TO_KG_MM3", "M_TO_MM", "SOLVERS",
           "TET10_EDGES", "TOLERANCES", "FebBuilder", "FebioUnsupported", "feb_comments",
           "feb_text", "read_node_data", "tet10_nodes", "unsupported"]


#: Default solver tolerances and limits (FEBio's names; ``dtmin_fraction`` of a step).
TOLERANCES = {"dtol": 1e-6, "etol": 1e-8, "rtol": 0.0, "lstol": 0.9, "max_refs": 25,
              "max_ups": 10, "max_retries": 8, "opt_iter": 10, "dtmin_fraction": 1e-3}


def feb_text(model: Model, *, X: np.ndarray | None = None, element: str = "ut4",
             steps: int = 10, solver: str = "newton", approximate: bool = False,
             export_sets: bool = False, **tolerances: float) -> str:
    """FEBio 4.0 input text for ``model``.

    Parameters
    ----------
    model : Model (mesh, materials per region, effects)
    X : (N, 3) reference positions, mm (default the mesh nodes)
    element : "ut4" (locking-free, default), "tet4" or "tet10" (see the module docstring)
    steps : number of equal load steps (time 0 -> 1); FEBio's auto time stepper may cut them
    solver : "newton" (full Newton) or "bfgs" (FEBio's quasi-Newton)
    approximate : allow hooks to write approximations (listed as comments in the file)
    export_sets : also write every named set of the mesh under its own name (node sets,
        face sets as surfaces, node pairs as discrete sets)
    **tolerances : FEBio solver settings overriding ``TOLERANCES``: ``dtol`` (displacement),
        ``etol`` (energy), ``rtol`` (residual), ``lstol``, ``max_refs``, ``max_ups`` (BFGS),
        ``max_retries``, ``opt_iter``, ``dtmin_fraction``

    Returns
    -------
    str : the ``.feb`` file; node i of the mesh is FEBio node i + 1

    Raises
    ------
    FebioUnsupported
        A material or effect that FEBio cannot express (named in the message).
    """
    unknown = sorted(set(tolerances) - set(TOLERANCES))
    if unknown:
        raise ValueError(f"FEBio export: unknown solver setting(s) {unknown}; "
                         f"known: {sorted(TOLERANCES)}")
    tol = {**TOLERANCES, **tolerances}
    feb = FebBuilder(model, model.mesh.nodes if X is None else X, element=element,
                     approximate=approximate)
    if export_sets:
        feb.export_sets()
    for eff in model.effects:
        eff.to_febio(feb)
    return feb.text(steps=steps, solver=solver, tol=tol)


def feb_comments(text: str, kind: str) -> list[str]:
    """The ``<!-- approximation: ... -->`` (``kind="approximation"``) or ``<!-- note: ... -->``
    (``kind="note"``) comments of a ``.feb`` text that :func:`feb_text` wrote, in order."""
    head = f"<!-- {kind}:"
    return [ln.strip()[len(head):].removesuffix("-->").strip()
            for ln in text.splitlines() if ln.strip().startswith(head)]


def read_node_data(text: str, n_nodes: int, *, source: str = "FEBio logfile"
                   ) -> tuple[np.ndarray, float]:
    """The last record of an FEBio logfile ``node_data`` file (``id,ux,uy,uz`` lines).

    Parameters
    ----------
    text : the file's content
    n_nodes : how many nodes to return (rows 0..n_nodes-1 = FEBio ids 1..n_nodes)
    source : name used in error messages

    Returns
    -------
    u : (n_nodes, 3) displacement, mm
    time : the record's time (1.0 at full load)
    """
    blocks = text.split("*Step")
    if len(blocks) < 2:
        raise ValueError(f"{source}: no data record (FEBio converged no time step)")
    last = blocks[-1].splitlines()
    time = float("nan")
    rows = []
    for line in last:
        s = line.strip()
        if s.startswith("*Time"):
            time = float(s.split("=", 1)[1])
        elif s and not s.startswith("*") and not s.startswith("="):
            rows.append([float(v) for v in s.split(",")])
    a = np.asarray(rows, float).reshape(-1, 4)
    ids = a[:, 0].astype(np.int64)
    u = np.full((int(ids.max()) if len(ids) else 0, 3), np.nan)
    u[ids - 1] = a[:, 1:]
    if len(u) < n_nodes or np.isnan(u[:n_nodes]).any():
        raise ValueError(f"{source}: the last record lacks nodes (has {len(ids)}, "
                         f"needs {n_nodes})")
    return u[:n_nodes], time
