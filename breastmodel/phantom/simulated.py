"""Phantoms deformed by a finite-element simulation of gravity (with a known truth model).

The stress-free anatomy is voxelised in the patient frame (no rigid motion), meshed with
:func:`meshing.mesh_labels`, and solved under each position's gravity with the physics of a
:class:`~breastmodel.phantom.truth_model.TruthModel`. Each position is then rendered by
:func:`~breastmodel.phantom.writer.make_phantom` with a deformation that pulls voxel points
back through the solved tet mesh (:class:`~breastmodel.phantom.warp.PullBack`).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from breastmodel.phantom.anatomy import FAT, GLAND, MUSCLE, SKIN, Anatomy
from breastmodel.phantom.motion import patient_gravity
from breastmodel.phantom.truth_model import TruthModel, default_truth_model
from breastmodel.phantom.warp import PullBack

__all__ = [
    "SimulatedPosition", "stress_free_labels", "simulate_positions", "position_deformation",
    "make_simulated_phantom", "TRUTH_SOLVERS",
]

log = logging.getLogger("breastmodel.phantom")

#: Tissue that the mesh carries: far outside the deformed mesh such a code means "moved away".
_MESHED = np.array([FAT, MUSCLE, GLAND, SKIN])
#: A patient-frame point far in front of the body: air for any anatomy (outside every
#: primitive), used as the material point of voxels the tissue has left.
AIR_POINT = np.array([0.0, -1.0e5, 0.0])


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
    2 muscle, 3 gland) of the stress-free anatomy over its field of view, patient frame."""
    import SimpleITK as sitk

    from breastmodel.phantom.voxelize import Grid, voxelize

    grid = Grid.from_box(anatomy.fov_min, anatomy.fov_max, voxel_size)
    tissue = voxelize(anatomy, grid)
    img = sitk.GetImageFromArray(tissue.seg)
    img.SetSpacing(tuple(map(float, grid.spacing_xyz)))
    img.SetOrigin(grid.origin)
    return img


def _boundary_faces(tets: np.ndarray) -> np.ndarray:
    """(F, 3) faces used by one tet only (the outer surface, and both interface sides of a
    split mesh)."""
    f = tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3)
    _, inv, cnt = np.unique(np.sort(f, axis=1), axis=0, return_inverse=True,
                            return_counts=True)
    return f[cnt[inv.ravel()] == 1]


def closest_on_triangles(p: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of each of k candidate triangles to each point.

    Parameters
    ----------
    p : (n, 3) points, mm
    tri : (n, k, 3, 3) candidate triangle corners, mm

    Returns
    -------
    d2 : (n, k) squared distances, mm^2
    bary : (n, k, 3) barycentric coordinates of the closest points
    """
    A, e0, e1 = tri[..., 0, :], tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]
    v = p[:, None, :] - A
    d00, d01, d11 = (np.einsum("nki,nki->nk", a, b) for a, b in ((e0, e0), (e0, e1), (e1, e1)))
    d20, d21 = np.einsum("nki,nki->nk", v, e0), np.einsum("nki,nki->nk", v, e1)
    den = d00 * d11 - d01 * d01
    den = np.where(den > 0, den, np.inf)
    b1, b2 = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    bary = np.stack([1.0 - b1 - b2, b1, b2], axis=-1)
    # Projection inside the triangle: it is the closest point; otherwise the closest point
    # lies on one of the three edges.
    best_d2 = np.full(b1.shape, np.inf)
    best_b = np.zeros(bary.shape)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        P, Q = tri[..., i, :], tri[..., j, :]
        e = Q - P
        ee = np.einsum("nki,nki->nk", e, e)
        t = np.clip(np.einsum("nki,nki->nk", p[:, None, :] - P, e) / np.maximum(ee, 1e-300),
                    0.0, 1.0)
        d2 = np.sum((P + t[..., None] * e - p[:, None, :]) ** 2, axis=-1)
        better = d2 < best_d2
        best_d2 = np.where(better, d2, best_d2)
        b = np.zeros(bary.shape)
        b[..., i], b[..., j] = 1.0 - t, t
        best_b = np.where(better[..., None], b, best_b)
    inside = np.all(bary >= 0.0, axis=-1)
    q = A + b1[..., None] * e0 + b2[..., None] * e1
    d2_plane = np.sum((q - p[:, None, :]) ** 2, axis=-1)
    return (np.where(inside, d2_plane, best_d2),
            np.where(inside[..., None], bary, best_b))


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

    With ``truth_solver="febio"`` every position is solved by FEBio
    (:func:`breastmodel.febio.solve_with_febio`, locking-free UT4 tets), an FE code
    independent of ours; the truth then does not share our solver's errors.

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
        ``"ours"`` (:func:`mechanics.solver.solve`) or ``"febio"``.
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
    from mechanics.effects._interface import split_interface
    from mechanics.model import build_model
    from mechanics.solver import SolverError, SolverOptions, solve

    tm = truth_model if truth_model is not None else default_truth_model()
    if truth_solver not in TRUTH_SOLVERS:
        raise ValueError(f"phantom: unknown truth solver {truth_solver!r}; use one of "
                         f"{TRUTH_SOLVERS}")
    say = log.info if progress else log.debug
    timings = timings if timings is not None else {}
    febio_path = _find_febio(febio) if truth_solver == "febio" else None
    mesh_file = None
    if mesh is None and cache_dir is not None:
        from dataclasses import asdict

        from breastmodel.cache import canonical_json

        key = hashlib.sha256(canonical_json({
            "anatomy": asdict(anatomy), "size_mm": float(tm.mesh_size_mm),
            "voxel_size": np.broadcast_to(np.asarray(voxel_size, float), (3,)).tolist(),
            "keep_gland": bool(tm.has_gland), "version": MESH_CACHE_VERSION,
        }).encode()).hexdigest()
        mesh_file = Path(cache_dir) / f"mesh-{key}.npz"
        if mesh_file.exists():
            from mechanics.mesh import Mesh

            mesh = Mesh.load_npz(mesh_file)
            timings["mesh_cached"] = True
            say("phantom: truth mesh from the cache %s", mesh_file)
    if mesh is None:
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
    solved_mesh = split_interface(mesh) if tm.split_interface else mesh
    materials = {int(k): dict(v) for k, v in tm.materials.items()}
    for gland, breast in ((4, 1), (5, 3)):  # gland tissue inherits its side's bulk law
        if gland in solved_mesh.region and gland not in materials and breast in materials:
            materials[gland] = dict(materials[breast])
    for code in set(solved_mesh.region.tolist()) - set(materials):
        raise ValueError(f"phantom: truth model has no material for mesh region {code}")
    X = np.asarray(solved_mesh.nodes, float)
    out: dict[str, SimulatedPosition] = {}
    for name in positions:
        g, _ = patient_gravity(name)
        effects = {k: dict(v) for k, v in tm.effects.items()}
        effects["gravity"] = {"direction": g.tolist(), "density": 1000.0, "g": 9.81}
        model = build_model(solved_mesh, materials, effects)
        t0 = time.perf_counter()
        if truth_solver == "febio":
            u, info = _solve_febio(model, name, tm, febio_path, cache_dir=cache_dir,
                                   work_dir=work_dir)
        else:
            try:
                state = solve(model, options=SolverOptions(initial_steps=2))
            except SolverError as exc:
                raise RuntimeError(f"phantom: simulation of position {name!r} with truth "
                                   f"model {tm.name!r} failed: {exc}") from None
            u = state.u
            info = {"converged": bool(state.converged), "load_steps": state.load_steps,
                    "newton_iterations": state.newton_iterations}
        dt = time.perf_counter() - t0
        timings[f"solve_{name}"] = dt
        info.update(solver=truth_solver, wall_time_s=dt,
                    max_displacement_mm=float(np.linalg.norm(u, axis=1).max()))
        say("phantom: %s solved by %s in %.1f s, max displacement %.1f mm", name,
            truth_solver, dt, info["max_displacement_mm"])
        out[name] = SimulatedPosition(solved_mesh, X, X + u, info)
    return out


#: Truth solvers of :func:`simulate_positions`.
TRUTH_SOLVERS = ("ours", "febio")
#: Load steps of an FEBio truth. FEBio's UT4 tets cost ~15x its standard tets per iteration;
#: two steps reach the same equilibrium as ten (to 1e-13 mm on a small subject) at a fifth of
#: the time, and FEBio's time stepper halves a step that fails to converge.
FEBIO_STEPS = 2
#: Effects that FEBio can only approximate, and how (recorded with each truth that has them).
FEBIO_APPROXIMATIONS = {
    "skin": "FEBio shell: carries compression and bends (no tension-field wrinkling)",
}
#: Part of every cached mesh's key: bump when the meshing of phantoms changes.
MESH_CACHE_VERSION = 1


def _find_febio(febio):
    """The FEBio executable, or a RuntimeError saying how to give one."""
    try:
        from breastmodel.febio import find_febio
    except ImportError as exc:
        raise RuntimeError(f"phantom: the FEBio truth solver is not available in this build "
                           f"({exc})") from None
    try:
        return find_febio(febio)
    except Exception as exc:  # noqa: BLE001 - re-raised with the stage and the remedy
        raise RuntimeError(f"phantom: truth solver 'febio' needs FEBio 4: {exc} (pass "
                           "--febio PATH or set $FEBIO)") from None


def _solve_febio(model, name: str, tm, febio_path, *, cache_dir, work_dir):
    """Displacement (N, 3) mm and info of one position solved by FEBio."""
    import tempfile

    from breastmodel.febio import solve_with_febio

    febio_cache = Path(cache_dir) / "febio" if cache_dir is not None else None
    approx = sorted(set(tm.effects) & set(FEBIO_APPROXIMATIONS))
    with tempfile.TemporaryDirectory(prefix=f"febio-{name}-") as tmp:
        wd = Path(work_dir) / name if work_dir is not None else Path(tmp)
        try:
            run = solve_with_febio(model, work_dir=wd, febio=febio_path, element="ut4",
                                   threads=1, cache_dir=febio_cache, steps=FEBIO_STEPS,
                                   approximate=bool(approx))
        except Exception as exc:  # noqa: BLE001 - re-raised naming the position and model
            raise RuntimeError(f"phantom: FEBio truth of position {name!r} with truth model "
                               f"{tm.name!r} failed: {exc}") from None
    if not run.converged:
        tail = "\n".join(str(run.log_tail).splitlines()[-8:])
        raise RuntimeError(f"phantom: FEBio did not converge for position {name!r} with "
                           f"truth model {tm.name!r}; log tail:\n{tail}")
    info = {"converged": True, "febio_wall_s": float(run.wall_s),
            "cached": bool(getattr(run, "cached", False)), "element": "ut4",
            "febio_approximations": {k: FEBIO_APPROXIMATIONS[k] for k in approx}}
    return np.asarray(run.displacement, float), info


def position_deformation(anatomy: Anatomy, sim: SimulatedPosition, *,
                         field_box: tuple | None = None, band_mm: float = 6.0, candidates: int = 8,
                         chunk: int = 50_000) -> Callable[[np.ndarray], np.ndarray]:
    """The ``u(x)`` of :func:`make_phantom`'s ``deformation`` contract for one position.

    Inside the deformed mesh, X(x) comes from the tet pull-back (exact on the mesh).
    Outside it, x takes the displacement of its closest point on the deformed mesh surface
    (interpolated on that triangle), so u is continuous across the surface: the skin layer
    and the markers just outside the (voxel-smoothed) mesh surface move with it, and the
    fixed-point solve of marker positions in :func:`make_phantom` converges. Where the
    tissue has moved away, this extrapolation maps x to air in the reference anatomy; where
    a point farther than ``band_mm`` from the deformed surface (beyond the skin layer and
    markers that the voxel-smoothed mesh surface may leave outside) still lands on tissue
    that the mesh carries (fat, gland, skin, muscle) inside the meshed box, that tissue has
    left x, so x must render as air: it is mapped to ``AIR_POINT``, a point far in front of
    the body that every anatomy classifies as air.

    Parameters
    ----------
    anatomy
        The anatomy the mesh was made from.
    sim
        A solved position.
    field_box
        (lo, hi) patient-frame box, mm, in which the mesh holds all carried tissue (default
        the anatomy's field of view); outside it the extrapolated field is used as is.
    band_mm
        Distance outside the deformed surface within which the extrapolation is trusted, mm
        (markers reach 2 r + gap = 4.5 mm out; the mesh surface lies up to ~1 mm inside).
    candidates
        Surface triangles (nearest centroids) searched per point.
    chunk
        Points per batch of the closest-point search (bounds memory).
    """
    mesh, X, x = sim
    pull = PullBack(X, x, mesh.tets)
    faces = _boundary_faces(np.asarray(mesh.tets, np.int64))
    corners = x[faces]  # (F, 3, 3)
    tree = cKDTree(corners.mean(axis=1))
    u_nodes = x - X
    surf = np.unique(faces)
    node_tree = cKDTree(x[surf])
    tet_x = x[np.asarray(mesh.tets)]
    edge = float(max(np.linalg.norm(tet_x[:, i] - tet_x[:, j], axis=1).max()
                     for i in range(4) for j in range(i + 1, 4)))
    all_tree = cKDTree(x)
    reach = band_mm + edge
    k = min(int(candidates), len(faces))
    lo, hi = (np.asarray(b, float) for b in (field_box or (anatomy.fov_min, anatomy.fov_max)))

    def u(points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, float)
        # Only points within an element edge of a node can lie in a tet; the pull-back's
        # search is costly for the many points (air, thorax) that lie in no tet.
        dn_all, _ = all_tree.query(p, k=1, distance_upper_bound=edge)
        maybe = np.flatnonzero(dn_all <= edge)
        ref, hit = pull(p[maybe])
        inside = np.zeros(len(p), bool)
        inside[maybe[hit]] = True
        disp = np.zeros_like(p)
        disp[maybe[hit]] = p[maybe[hit]] - ref[hit]
        out = np.flatnonzero(~inside)
        # Points far from the surface (beyond the band by more than an element) keep u = 0:
        # only the air check below concerns them.
        dn, _ = node_tree.query(p[out], k=1, distance_upper_bound=reach)
        near = out[dn <= reach]
        dist2 = np.full(len(out), np.inf)
        dist2_near = np.empty(len(near))
        for s in range(0, len(near), chunk):
            sel = near[s:s + chunk]
            q = p[sel]
            _, cand = tree.query(q, k=k)
            cand = cand.reshape(len(q), k)
            d2, bary = closest_on_triangles(q, corners[cand])
            j = np.argmin(d2, axis=1)
            rows = np.arange(len(q))
            dist2_near[s:s + chunk] = d2[rows, j]
            f = faces[cand[rows, j]]  # (n, 3) nodes of the closest triangle
            disp[sel] = np.einsum("nc,ncd->nd", bary[rows, j], u_nodes[f])
        dist2[dn <= reach] = dist2_near
        in_box = np.all((p[out] >= lo) & (p[out] <= hi), axis=1) & (dist2 > band_mm**2)
        chk = out[in_box]
        if len(chk):
            code = anatomy.classify(p[chk] - disp[chk])
            gone = chk[np.isin(code, _MESHED)]
            disp[gone] = p[gone] - AIR_POINT
        return disp

    return u


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
    from breastmodel.config import write_atomic
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
    truth = truth_folder(out)
    first = sims[positions[0]]
    first.mesh.save_npz(truth / "stress_free_mesh.npz")
    for p, s in sims.items():
        np.save(truth / f"{p}_displacement.npy", s.x - s.X)
    doc = tm.to_dict()
    doc["solves"] = {p: s.info for p, s in sims.items()}
    import json

    write_atomic(truth / "truth_model.json", json.dumps(doc, indent=2, sort_keys=True))
    return Path(out)
