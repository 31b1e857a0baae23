"""Phantoms deformed by a finite-element simulation of gravity (with a known truth model).

The stress-free anatomy is voxelised in the patient frame (no rigid motion), meshed with
:func:`meshing.mesh_labels`, and solved under each position's gravity with the physics of a
:class:`~breastmodel.phantom.truth_model.TruthModel`. Each position is then rendered by
:func:`~breastmodel.phantom.writer.make_phantom` with a deformation that pulls voxel points
back through the solved tet mesh (:mod:`breastmodel.phantom.deformation`). Each position is
solved by our solver or by FEBio (:mod:`breastmodel.phantom.truth_solvers`).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from breastmodel.phantom.anatomy import Anatomy
from breastmodel.phantom.deformation import (  # noqa: F401 - re-exported for callers
    AIR_POINT,
    closest_on_triangles,
    position_deformation,
)
from breastmodel.phantom.motion import patient_gravity
from breastmodel.phantom.truth_model import TruthModel, default_truth_model
from breastmodel.phantom.truth_solvers import (  # noqa: F401 - re-exported for callers
    FEBIO_APPROXIMATED,
    FEBIO_STEPS,
    TRUTH_SOLVERS,
    find_febio_for_truth,
    solve_position,
    truth_solver_executable,
)

__all__ = [
    "SimulatedPosition", "stress_free_labels", "simulate_positions", "position_deformation",
    "make_simulated_phantom", "TRUTH_SOLVERS",
]

log = logging.getLogger("breastmodel.phantom")


@dataclass(frozen=True, eq=False)
class SimulatedPosition:
    """Solved position: ``mesh`` (the solved mesh, interface split if the model slides),
    ``X`` (N, 3) stress-free and ``x`` (N, 3) deformed node positions, mm, and solver
    statistics ``info`` (converged, load steps, Newton iterations, wall time s)."""

    mesh: object
    X: np.ndarray
    x: np.ndarray
    info: dict

    def __iter__(self):  # unpacks as (mesh, X, x)
        return iter((self.mesh, self.X, self.x))


def stress_free_labels(anatomy: Anatomy, *, voxel_size: float = 1.0):
    """Segmentation-convention label map (sitk.Image, uint8: 0 background, 1 breast,
    2 muscle, 3 gland) of the stress-free anatomy over its body box (``Anatomy.body_box``:
    the field of view unless the body goes on past it), patient frame."""
    import SimpleITK as sitk

    from breastmodel.phantom.voxelize import Grid, voxelize

    grid = Grid.from_box(*anatomy.body_box, voxel_size)
    tissue = voxelize(anatomy, grid)
    img = sitk.GetImageFromArray(tissue.seg)
    img.SetSpacing(tuple(map(float, grid.spacing_xyz)))
    img.SetOrigin(grid.origin)
    return img


def anatomy_mesh(anatomy: Anatomy, *, size_mm: float = 6.0, voxel_size: float = 1.0,
                 path: str | Path | None = None, keep_gland: bool = False):
    """The stress-free anatomy meshed by the meshing stage (``mechanics.mesh.Mesh``).

    fTetWild meshes differ from run to run: with ``path`` the mesh is read from that .npz
    when it exists, else meshed and saved there, so that runs compare on one mesh.
    """
    from mechanics.mesh import Mesh

    if path is not None and Path(path).exists():
        return Mesh.load_npz(path)
    import meshing

    mesh = meshing.mesh_labels(stress_free_labels(anatomy, voxel_size=voxel_size),
                               size_mm=size_mm, keep_gland=keep_gland)
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        mesh.save_npz(path)
    return mesh


def simulate_positions(
    anatomy: Anatomy,
    truth_model: TruthModel | None = None,
    positions: Sequence[str] = ("prone", "supine", "supine_tilted"),
    *,
    voxel_size: float = 1.0,
    mesh=None,
    progress: bool = True,
    timings: dict | None = None,
    truth_solver: str = "ours",
    febio: str | Path | None = None,
    cache_dir: str | Path | None = None,
    work_dir: str | Path | None = None,
) -> dict[str, SimulatedPosition]:
    """Solve the stress-free anatomy under each position's gravity.

    Parameters
    ----------
    anatomy
        Phantom anatomy (patient frame, mm).
    truth_model
        Physics (default :func:`default_truth_model`).
    positions
        Position names (:func:`breastmodel.phantom.patient_gravity`).
    voxel_size
        Voxel size of the label map that is meshed, mm.
    mesh
        A conforming ``mechanics.mesh.Mesh`` of the anatomy to reuse (fTetWild meshes differ
        from run to run; pass a saved one for reproducible phantoms). Meshed when None.
    progress
        Log each stage at INFO level.
    timings
        Optional dict that receives the wall time (s) of each stage.
    truth_solver
        ``"ours"`` (:func:`mechanics.solver.solve`) or ``"febio"``
        (:func:`breastmodel.febio.solve_with_febio`, locking-free UT4 tets: an FE code
        independent of ours, so the truth does not share our solver's errors).
    febio
        FEBio executable for ``truth_solver="febio"`` (default: ``$FEBIO``, then the
        known places, see :func:`breastmodel.febio.find_febio`).
    cache_dir
        Cache of truths keyed by their inputs: the mesh of this anatomy at this size and
        label voxel size (``mesh-<sha256>.npz``; fTetWild meshes differ from run to run, so
        the cache also makes truths repeatable) and FEBio's results per distinct input file
        (``febio/``). None: no cache.
    work_dir
        Folder where FEBio runs (default: a temporary folder).

    Returns
    -------
    {position: SimulatedPosition}; each unpacks as ``(mesh, X, x)``.

    Raises
    ------
    RuntimeError
        A position whose solve does not reach full load (names the position), or FEBio
        missing (says how to give it).
    """
    from mechanics.model import build_model

    tm = truth_model if truth_model is not None else default_truth_model()
    febio_path = truth_solver_executable(truth_solver, febio)
    timings = timings if timings is not None else {}
    if mesh is None:
        mesh = _truth_mesh(anatomy, tm, voxel_size, cache_dir=cache_dir, progress=progress,
                           timings=timings)
    solved_mesh = _mesh_to_solve(mesh, tm)
    materials = _truth_materials(tm, solved_mesh.region)
    X = np.asarray(solved_mesh.nodes, float)
    out: dict[str, SimulatedPosition] = {}
    for name in positions:
        model = build_model(solved_mesh, materials, _position_effects(tm, name))
        u, info = solve_position(model, name, tm, truth_solver, febio_path=febio_path,
                                 cache_dir=cache_dir, work_dir=work_dir, progress=progress)
        timings[f"solve_{name}"] = info["wall_time_s"]
        out[name] = SimulatedPosition(solved_mesh, X, X + u, info)
    return out


def _mesh_cache_file(anatomy: Anatomy, tm: TruthModel, voxel_size, cache_dir) -> Path:
    """Where the cache keeps the truth mesh of this anatomy, mesh size and label voxel size:
    ``mesh-<sha256 of those inputs>.npz``."""
    from dataclasses import asdict

    from breastmodel.cache import canonical_json

    key = hashlib.sha256(canonical_json({
        "anatomy": asdict(anatomy), "size_mm": float(tm.mesh_size_mm),
        "voxel_size": np.broadcast_to(np.asarray(voxel_size, float), (3,)).tolist(),
        "keep_gland": bool(tm.has_gland), "version": MESH_CACHE_VERSION,
    }).encode()).hexdigest()
    return Path(cache_dir) / f"mesh-{key}.npz"


def _truth_mesh(anatomy: Anatomy, tm: TruthModel, voxel_size, *, cache_dir, progress: bool,
                timings: dict):
    """The stress-free anatomy's truth mesh: from the cache when it holds one, else
    voxelised and meshed (and saved to the cache); stage times go to ``timings``."""
    say = log.info if progress else log.debug
    mesh_file = None
    if cache_dir is not None:
        mesh_file = _mesh_cache_file(anatomy, tm, voxel_size, cache_dir)
        if mesh_file.exists():
            from mechanics.mesh import Mesh

            mesh = Mesh.load_npz(mesh_file)
            timings["mesh_cached"] = True
            say("phantom: truth mesh from the cache %s", mesh_file)
            return mesh
    import meshing

    t0 = time.perf_counter()
    labels = stress_free_labels(anatomy, voxel_size=voxel_size)
    timings["voxelise"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    mesh = meshing.mesh_labels(labels, size_mm=tm.mesh_size_mm, progress=progress,
                               keep_gland=tm.has_gland)
    timings["mesh"] = time.perf_counter() - t0
    say("phantom: truth mesh %d nodes, %d tets", mesh.n_nodes, mesh.n_tets)
    if mesh_file is not None:
        mesh_file.parent.mkdir(parents=True, exist_ok=True)
        mesh.save_npz(mesh_file)
    return mesh


def _mesh_to_solve(mesh, tm: TruthModel):
    """The truth mesh as the truth model solves it: its layers (skin, interface) relabelled
    where the model has them, its breast-muscle interface split when an effect slides on it."""
    from mechanics.effects._interface import split_interface
    from mechanics.mesh import LAYER_REGIONS, with_layer

    for face_set in tm.layers:
        mesh = with_layer(mesh, face_set)
        if not np.isin(mesh.region, LAYER_REGIONS[face_set]).any():
            raise ValueError(f"phantom: truth model {tm.name!r} has a layer on face set "
                             f"{face_set!r}, but the mesh has no breast tet on one of its "
                             "faces")
    return split_interface(mesh) if tm.split_interface else mesh


def _truth_materials(tm: TruthModel, region: np.ndarray) -> dict[int, dict]:
    """Region code -> material of the truth model for the mesh's regions; gland tissue and
    skin layer without their own law inherit their side's bulk law."""
    from mechanics.mesh import BREAST_SIDE

    materials = {int(k): dict(v) for k, v in tm.materials.items()}
    for code, breast in BREAST_SIDE.items():
        if code in region and code not in materials and breast in materials:
            materials[code] = dict(materials[breast])
    for code in set(region.tolist()) - set(materials):
        raise ValueError(f"phantom: truth model has no material for mesh region {code}")
    return materials


def _position_effects(tm: TruthModel, name: str) -> dict[str, dict]:
    """The truth model's effects plus the gravity of position ``name`` (water density)."""
    g, _ = patient_gravity(name)
    effects = {k: dict(v) for k, v in tm.effects.items()}
    effects["gravity"] = {"direction": g.tolist(), "density": 1000.0, "g": 9.81}
    return effects


#: Part of every cached mesh's key: bump when the meshing of phantoms changes.
MESH_CACHE_VERSION = 1


def make_simulated_phantom(
    out: str | Path,
    *,
    seed: int = 0,
    truth_model: TruthModel | None = None,
    positions: Sequence[str] = ("prone", "supine", "supine_tilted"),
    small: bool = False,
    anatomy: Anatomy | None = None,
    mesh=None,
    mesh_voxel_size: float | None = None,
    progress: bool = True,
    timings: dict | None = None,
    truth_solver: str = "ours",
    febio: str | Path | None = None,
    cache_dir: str | Path | None = None,
    **phantom_options,
) -> Path:
    """Write a subject folder whose positions are deformed by simulated gravity.

    Parameters
    ----------
    out
        Subject folder (the truth goes to ``<out>_truth``, see :func:`make_phantom`).
    seed
        Seed of the noise and rigid motions (the simulation itself is deterministic given the
        mesh).
    truth_model
        Physics (default :func:`default_truth_model`).
    positions, small, anatomy, progress
        As for :func:`make_phantom`.
    mesh
        A conforming mesh of this anatomy to reuse (makes repeated phantoms identical).
    mesh_voxel_size
        Voxel size of the label map that is meshed, mm (default: ``voxel_size`` of the
        phantom, at most a third of the mesh size).
    timings
        Optional dict receiving the wall time (s) of each stage.
    truth_solver, febio, cache_dir
        As for :func:`simulate_positions` (``"ours"`` or ``"febio"``, the FEBio
        executable, the cache of truths).
    **phantom_options
        Other keywords of :func:`make_phantom` (voxel_size, snr, bias, motion bounds).

    Returns
    -------
    Path
        The subject folder. The truth folder also holds ``truth_model.json``,
        ``stress_free_mesh.npz`` (the solved mesh, ``Mesh.save_npz``) and per position
        ``<position>_displacement.npy`` (N, 3) mm at the mesh nodes.
    """
    from breastmodel.phantom.writer import make_phantom, truth_folder

    if "deformation" in phantom_options:
        raise ValueError("phantom: make_simulated_phantom makes its own deformation")
    tm = truth_model if truth_model is not None else default_truth_model()
    positions = list(positions)
    for p in positions:
        patient_gravity(p)  # unknown names fail before the (long) simulation
    anatomy = anatomy if anatomy is not None else (Anatomy.small() if small else Anatomy())
    timings = timings if timings is not None else {}
    vs = mesh_voxel_size or min(float(np.min(phantom_options.get("voxel_size", 1.0))),
                                tm.mesh_size_mm / 3.0)
    sims = simulate_positions(anatomy, tm, positions, voxel_size=vs, mesh=mesh,
                              progress=progress, timings=timings, truth_solver=truth_solver,
                              febio=febio, cache_dir=cache_dir)
    fields = {p: position_deformation(anatomy, s) for p, s in sims.items()}
    t0 = time.perf_counter()
    make_phantom(out, seed=seed, positions=positions, anatomy=anatomy, progress=progress,
                 deformation=fields.__getitem__, **phantom_options)
    timings["render"] = time.perf_counter() - t0
    _write_simulation_truth(truth_folder(out), tm, sims, first=positions[0])
    return Path(out)


def _write_simulation_truth(truth: Path, tm: TruthModel, sims: dict[str, SimulatedPosition],
                            *, first: str) -> None:
    """The truth files of the simulation: ``stress_free_mesh.npz`` (the solved mesh of the
    ``first`` position), ``<position>_displacement.npy`` and ``truth_model.json`` (physics and
    per-position solver statistics)."""
    import json

    from breastmodel.config import write_atomic

    sims[first].mesh.save_npz(truth / "stress_free_mesh.npz")
    for p, s in sims.items():
        np.save(truth / f"{p}_displacement.npy", s.x - s.X)
    doc = tm.to_dict()
    doc["solves"] = {p: s.info for p, s in sims.items()}
    write_atomic(truth / "truth_model.json", json.dumps(doc, indent=2, sort_keys=True))
