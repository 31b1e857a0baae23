"""The vocabulary of the FEBio 4.0 writer (:mod:`mechanics.febio`): element technologies and
solvers, the displacement logfile, unit conversions, the error of what FEBio cannot express,
the XML formatting of numbers, ids, connectivity rows and parameter blocks, and the mid-edge
nodes of quadratic tets."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

ELEMENTS = ("tet4", "ut4", "tet10")
SOLVERS = ("newton", "bfgs")
#: File (relative to FEBio's working folder) that receives the node displacements.
DISPLACEMENT_FILE = "displacement.txt"
#: Density 1000 kg/m^3 in kg/mm^3, the unit FEBio sees in a mm-kg-s model.
KG_M3_TO_KG_MM3 = 1e-9
#: m/s^2 -> mm/s^2.
M_TO_MM = 1e3
#: FEBio solid-domain type of each element technology.
_DOMAIN_TYPE = {"tet4": "elastic-solid", "ut4": "ut4-solid", "tet10": "elastic-solid"}
#: Edges of a tet in FEBio's tet10 node order (nodes 5..10).
TET10_EDGES = np.array([[0, 1], [1, 2], [2, 0], [0, 3], [1, 3], [2, 3]])


class FebioUnsupported(ValueError):
    """A material, effect or option that FEBio cannot express (the message names it and why)."""


def unsupported(owner: str, why: str) -> FebioUnsupported:
    """The error a unit raises when FEBio cannot express it."""
    return FebioUnsupported(f"FEBio export: {owner} cannot be expressed in FEBio: {why}")


def _num(v: float) -> str:
    return repr(float(v))


def _ids(a) -> str:
    return ",".join(map(str, (np.asarray(a, np.int64).ravel() + 1).tolist()))


def _rows(tag: str, conn: np.ndarray, first_id: int, indent: str = "\t\t\t") -> list[str]:
    """``<tag id="k">a,b,c</tag>`` lines of 0-based connectivity rows, ids from first_id."""
    conn = (np.asarray(conn, np.int64) + 1).tolist()
    return [f'{indent}<{tag} id="{first_id + i}">{",".join(map(str, row))}</{tag}>'
            for i, row in enumerate(conn)]


def _param_lines(params: Mapping[str, Any], indent: str) -> list[str]:
    """XML lines of parameters: a key may carry attributes (``'force type="point"'``); a value
    is a number, a string, or a list of pre-formatted child lines."""
    out = []
    for k, v in params.items():
        tag = k.split()[0]
        if isinstance(v, str):
            out.append(f"{indent}<{k}>{v}</{tag}>")
        elif isinstance(v, list | tuple):
            out.append(f"{indent}<{k}>")
            out += [f"{indent}\t{line}" for line in v]
            out.append(f"{indent}</{tag}>")
        else:
            out.append(f"{indent}<{k}>{_num(v)}</{tag}>")
    return out


def tet10_nodes(X: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mid-edge nodes for quadratic tets.

    Parameters
    ----------
    X : (N, 3) node positions, mm
    tets : (M, 4) node indices

    Returns
    -------
    X10 : (N + E, 3) positions, mm: the N corner nodes, then one node at the middle of each
        of the E distinct edges
    tets10 : (M, 10) node indices in FEBio's tet10 order (corners, then edges 01 12 20 03 13
        23)
    edges : (E, 2) corner nodes of each mid-edge node (sorted pair)
    """
    tets = np.asarray(tets, np.int64)
    n = len(X)
    e = np.sort(tets[:, TET10_EDGES].reshape(-1, 2), axis=1)
    keys, inv = np.unique(e[:, 0] * n + e[:, 1], return_inverse=True)
    edges = np.stack([keys // n, keys % n], axis=1)
    X10 = np.concatenate([X, 0.5 * (X[edges[:, 0]] + X[edges[:, 1]])])
    tets10 = np.concatenate([tets, n + inv.reshape(-1, 6)], axis=1)
    return X10, tets10, edges
