"""Adapter around pytetwild (fTetWild): tetrahedralise a triangle soup.

Only this module imports pytetwild. fTetWild keeps every input triangle inside an envelope
of half-width ``epsilon`` and returns its whole background mesh when filtering is disabled,
so that the caller decides which tets are inside which region.

fTetWild is not deterministic, even on one thread: it inserts the input triangles in an order
shuffled by a generator seeded from ``std::random_device`` (``sort_input_faces`` in its
``TriangleInsertion.cpp``; the ``not_sort_input`` switch is not exposed by pytetwild 0.4.2).
Two meshings of one input differ in their tets; callers cache a mesh by its inputs so that a
subject is meshed once, and tests bound properties, never exact counts.
"""

from __future__ import annotations

import contextlib
import os
import tempfile

import numpy as np


@contextlib.contextmanager
def _scratch_cwd():
    """Run inside a temporary working directory: fTetWild's inside filter writes a debug
    file ``__tracked_surface.stl`` into the current directory (its winding-number filter
    calls ``get_tracked_surface``, which saves the surface it extracts)."""
    old = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="ftetwild_") as tmp:
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(old)


def tetrahedralize(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    edge_mm: float,
    epsilon_mm: float,
    keep_background: bool = True,
    threads: int = 0,
    optimize_iterations: int = 30,
    stop_energy: float = 20.0,
    sizing: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedral mesh that conforms to all input triangles (within ``epsilon_mm``).

    Parameters
    ----------
    vertices : (n, 3) float, mm
    faces : (m, 3) int; may be non-manifold (several closed or open surfaces)
    edge_mm : float
        Ideal tet edge length, mm.
    epsilon_mm : float
        Envelope half-width: how far the tet faces may deviate from the input, mm.
    keep_background : bool
        Return every tet of the bounding box (True) instead of fTetWild's inside filter
        (False; that filter runs in a temporary working directory, see ``_scratch_cwd``).
    optimize_iterations, stop_energy
        fTetWild's optimisation budget: it stops after this many passes or once the worst
        AMIPS energy is below ``stop_energy`` (its default 10; 20 is faster and still gives
        aspect ratios well below 12 here).
    sizing : (points (k, 3), tets (l, 4), edge length (k,) mm), optional
        Background tet mesh giving a spatially varying target edge length. fTetWild applies
        it only after its main optimisation, which works at ``edge_mm`` everywhere: give a
        coarse ``edge_mm`` (the largest size wanted) so that the main passes run on a coarse
        mesh of the whole bounding box, and let the field refine where the tissue is.

    Returns
    -------
    nodes : (N, 3) float64, mm
    tets : (M, 4) int64, positively oriented
    """
    import pytetwild

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    guard = contextlib.nullcontext() if keep_background else _scratch_cwd()
    with guard:
        nodes, tets = pytetwild.tetrahedralize(
            v,
            f,
            edge_length_abs=float(edge_mm),
            epsilon=float(epsilon_mm) / diag,
            optimize=True,
            simplify=True,
            num_threads=int(threads),
            num_opt_iter=int(optimize_iterations),
            stop_energy=float(stop_energy),
            quiet=True,
            disable_filtering=bool(keep_background),
            **(
                {}
                if sizing is None
                else {"bg_vertices": sizing[0], "bg_tets": sizing[1], "bg_values": sizing[2]}
            ),
        )
    nodes = np.asarray(nodes, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    e = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    neg = np.linalg.det(e) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return nodes, tets
