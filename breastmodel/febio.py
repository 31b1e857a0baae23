"""Running FEBio 4 on a model: find the program, write the ``.feb``, run it, read the result.

The file itself comes from :func:`mechanics.febio.feb_text` (the one writer); this module
adds the process: the program's location, explicit thread counts, a timeout, clear errors that
quote FEBio's own, and a cache keyed by the hash of the file's text so that a truth is
computed once per input.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from breastmodel.config import write_atomic, write_atomic_with
from mechanics.febio import DISPLACEMENT_FILE, feb_comments, feb_text, read_node_data

REPO_ROOT = Path(__file__).resolve().parents[1]
FEB_NAME = "model.feb"


class FebioError(RuntimeError):
    """FEBio is missing, failed, timed out or wrote no result (the message says which)."""


@dataclass(frozen=True)
class FebioRun:
    """The outcome of one FEBio run.

    displacement : (N, 3) mm, in the model's node order (mesh nodes; tet10 mid-edge nodes
        dropped); read-only
    converged : FEBio ended with NORMAL TERMINATION and reached full load
    wall_s : wall time of the FEBio process, s (of the original run for a cached result)
    iterations : total equilibrium (Newton/BFGS) iterations, or None if not in the log
    log_tail : the last lines of FEBio's log
    feb : path of the input file that produced it
    cached : True when read from the cache
    approximations : what the input file wrote approximately (its ``approximation``
        comments, :func:`mechanics.febio.feb_comments`)
    """

    displacement: np.ndarray
    converged: bool
    wall_s: float
    iterations: int | None
    log_tail: str
    feb: Path
    cached: bool = False
    approximations: tuple[str, ...] = ()


def repository_roots() -> list[Path]:
    """The repository root, and for a git worktree also its main checkout's root (a worktree's
    ``.git`` is a file naming ``<main>/.git/worktrees/<name>``)."""
    roots = [REPO_ROOT]
    dotgit = REPO_ROOT / ".git"
    if dotgit.is_file():
        line = dotgit.read_text().strip()
        if line.startswith("gitdir:"):
            gitdir = Path(line.split(":", 1)[1].strip())
            if gitdir.parent.name == "worktrees":
                roots.append(gitdir.parent.parent.parent)
    return roots


def shared_path(*parts: str) -> list[Path]:
    """Candidates for ``../shared/<parts>`` beside each of :func:`repository_roots`."""
    return [(r / ".." / "shared").joinpath(*parts).resolve() for r in repository_roots()]


def find_febio(path: str | os.PathLike | None = None) -> Path:
    """Path of the FEBio 4 executable (or launcher).

    Looks at, in order: ``path``; the environment variable ``$FEBIO``; the project's build
    ``../shared/febio/febio4`` relative to the repository root (for a git worktree, also to
    its main checkout's root).

    Raises
    ------
    FebioError
        None of them is an executable file; the message lists where it looked.
    """
    tried = []
    candidates = []
    if path is not None:
        candidates.append(("argument", Path(path)))
    if os.environ.get("FEBIO"):
        candidates.append(("$FEBIO", Path(os.environ["FEBIO"])))
    candidates += [("project build", p) for p in shared_path("febio", "febio4")]
    for what, p in candidates:
        if p.is_file() and os.access(p, os.X_OK):
            return p
        tried.append(f"{what}: {p}")
        if what == "argument":  # an explicit path that is wrong is an error, not a fallback
            break
    raise FebioError("FEBio 4 not found (looked at " + "; ".join(tried) + "). Point --febio "
                     "or the environment variable FEBIO at an FEBio 4 executable.")


def _env(threads: int) -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("FEBIO_MKL_LIB", os.path.join(sys.prefix, "lib"))
    env["OMP_NUM_THREADS"] = str(int(threads))
    env["MKL_NUM_THREADS"] = str(int(threads))
    return env


_ERROR_RE = re.compile(r"(error|failed|invalid|unknown|not found|cannot|negative jacobian)",
                       re.I)


def _error_lines(log: str, limit: int = 12) -> list[str]:
    lines = [s.strip(" *\t") for s in log.splitlines() if _ERROR_RE.search(s)]
    lines = [s for s in lines if s and s.upper() != "ERROR"]
    return lines[-limit:]


def run_febio(feb_text: str, *, work_dir: str | os.PathLike, febio: str | os.PathLike | None =
              None, threads: int = 1, timeout_s: float | None = None,
              n_nodes: int | None = None, check: bool = True) -> FebioRun:
    """Write ``feb_text`` to ``work_dir/model.feb``, run FEBio there and read the displacement.

    Parameters
    ----------
    feb_text : FEBio 4.0 input (from :func:`mechanics.febio.feb_text`)
    work_dir : folder for the input, FEBio's log and its output (created if missing)
    febio : FEBio executable (default: :func:`find_febio`)
    threads : OpenMP and MKL threads (set explicitly; default 1)
    timeout_s : wall-clock limit, s (None: no limit)
    n_nodes : rows to return (default: every node in the file; give the mesh's node count
        to drop tet10 mid-edge nodes)
    check : raise when FEBio did not reach full load (default); False returns the last
        converged state with ``converged`` False

    Returns
    -------
    FebioRun

    Raises
    ------
    FebioError
        FEBio missing, timed out, wrote no displacement record, or (``check``) did not
        converge; the message names the ``.feb`` and quotes FEBio's error lines.
    """
    exe = find_febio(febio)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    feb = work / FEB_NAME
    log_path = work / "model.log"
    out = work / DISPLACEMENT_FILE
    for p in (log_path, out):
        if p.exists():
            p.unlink()
    feb.write_text(feb_text, encoding="latin-1")
    if n_nodes is None:
        n_nodes = feb_text.count("<node id=")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([str(exe), "-i", FEB_NAME], cwd=work, env=_env(threads),
                              capture_output=True, text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired as exc:
        raise FebioError(f"FEBio [{feb}]: no result within {timeout_s} s "
                         f"(threads={threads})") from exc
    wall = time.perf_counter() - t0
    log = log_path.read_text(errors="replace") if log_path.exists() else ""
    text = "\n".join(s for s in (proc.stdout, proc.stderr, log) if s)
    tail = "\n".join(text.strip().splitlines()[-25:])
    normal = "N O R M A L   T E R M I N A T I O N" in text
    if not out.exists() or not out.read_text().strip():
        errors = _error_lines(text) or tail.splitlines()[-8:]
        src = feb_text.splitlines()
        for ln in sorted({int(k) for k in re.findall(r"\(line (\d+)\)", "\n".join(errors))}):
            if 0 < ln <= len(src):
                errors.append(f"{feb.name} line {ln}: {src[ln - 1].strip()[:200]}")
        raise FebioError(f"FEBio [{feb}]: no displacement written (exit status "
                         f"{proc.returncode}); FEBio said:\n  " + "\n  ".join(errors))
    try:
        u, t_end = read_node_data(out.read_text(), n_nodes, source=str(out))
    except ValueError as exc:
        raise FebioError(f"FEBio [{feb}]: {exc}") from exc
    m = re.findall(r"Total number of equilibrium iterations\s*\.*\s*:\s*(\d+)", text)
    iterations = int(m[-1]) if m else None
    converged = bool(normal and proc.returncode == 0 and abs(t_end - 1.0) < 1e-9)
    if check and not converged:
        errors = _error_lines(text) or tail.splitlines()[-8:]
        raise FebioError(f"FEBio [{feb}]: did not converge (last converged load {t_end:g}, "
                         f"exit status {proc.returncode}); FEBio said:\n  "
                         + "\n  ".join(errors))
    u.setflags(write=False)
    return FebioRun(u, converged, wall, iterations, tail, feb,
                    approximations=tuple(feb_comments(feb_text, "approximation")))


#: Placeholder neo-Hookean Young's moduli (kPa) of the mesh export: the paper's optimum order
#: of magnitude; the user sets the real ones in FEBio.
MESH_YOUNG_KPA = {"breast_left": 0.3, "breast_right": 0.3, "gland_left": 0.3,
                  "gland_right": 0.3, "muscle": 10.0}
MESH_POISSON = 0.49


def mesh_feb_text(mesh, *, element: str = "ut4") -> str:
    """FEBio 4.0 file of a fresh mesh for users to finish in FEBio Studio: every named set
    (node sets, face sets as surfaces, node pairs as discrete sets), one domain per region with
    a placeholder Neo-Hookean (``MESH_YOUNG_KPA``, nu 0.49), gravity along -z (1000 kg/m^3)
    and the node set ``fixed`` held, if the mesh has one."""
    from mechanics.mesh import REGIONS
    from mechanics.model import build_model

    names = {v: k for k, v in REGIONS.items()}
    mats = {int(c): {"name": "neo_hookean", "nu": MESH_POISSON,
                     "E": MESH_YOUNG_KPA.get(names.get(int(c), ""), 1.0)}
            for c in np.unique(mesh.region)}
    effects = {"gravity": {"direction": (0.0, 0.0, -1.0)}}
    if "fixed" in mesh.node_sets and len(mesh.node_sets["fixed"]):
        effects["fixed"] = {"node_set": "fixed"}
    return feb_text(build_model(mesh, mats, effects), element=element, export_sets=True)


def write_mesh_feb(mesh, path: str | os.PathLike, *, element: str = "ut4") -> Path:
    """Write :func:`mesh_feb_text` to ``path`` atomically; returns the path."""
    text = mesh_feb_text(mesh, element=element)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, text.encode("latin-1"))
    return path


def solve_with_febio(model, *, work_dir: str | os.PathLike, febio: str | os.PathLike | None =
                     None, element: str = "ut4", threads: int = 1,
                     cache_dir: str | os.PathLike | None = None, X: np.ndarray | None = None,
                     timeout_s: float | None = None, steps: int = 10, solver: str = "newton",
                     approximate: bool = False, check: bool = True,
                     **tolerances: float) -> FebioRun:
    """Solve ``model`` with FEBio; with ``cache_dir``, once per distinct ``.feb`` text.

    Parameters
    ----------
    model : mechanics.model.Model
    work_dir : folder where FEBio runs (``model.feb``, ``model.log``, the displacement file)
    febio : FEBio executable (default: :func:`find_febio`)
    element, steps, solver, approximate, **tolerances : see :func:`mechanics.febio.feb_text`
    threads : OpenMP/MKL threads for FEBio (default 1)
    cache_dir : where converged results are kept as ``<sha256 of the .feb>.npz`` (written
        atomically); None: no cache
    X : (N, 3) reference positions, mm (default the mesh nodes)
    timeout_s : wall-clock limit for FEBio, s
    check : raise when FEBio does not converge (default); False returns the last converged
        state with ``converged`` False (not cached)

    Returns
    -------
    FebioRun with ``displacement`` (N, 3) mm for the N mesh nodes

    Raises
    ------
    mechanics.febio.FebioUnsupported
        The model holds a material or effect FEBio cannot express (before FEBio runs).
    FebioError
        FEBio is missing, failed, or (``check``) did not converge.
    """
    text = feb_text(model, X=X, element=element, steps=steps, solver=solver,
                    approximate=approximate, **tolerances)
    n = model.mesh.n_nodes
    key = hashlib.sha256(text.encode("latin-1")).hexdigest()
    hit = Path(cache_dir) / f"{key}.npz" if cache_dir is not None else None
    if hit is not None and hit.exists():
        with np.load(hit) as z:
            u = np.array(z["displacement"])
            meta = json.loads(str(z["meta"]))
        if u.shape == (n, 3):
            u.setflags(write=False)
            return FebioRun(u, bool(meta["converged"]), float(meta["wall_s"]),
                            meta["iterations"], meta["log_tail"], Path(meta["feb"]), cached=True,
                            approximations=tuple(feb_comments(text, "approximation")))
    run = run_febio(text, work_dir=work_dir, febio=febio, threads=threads, timeout_s=timeout_s,
                    n_nodes=n, check=check)
    if hit is not None and run.converged:
        meta = {"converged": run.converged, "wall_s": run.wall_s, "iterations": run.iterations,
                "log_tail": run.log_tail, "feb": str(run.feb), "element": element,
                "threads": threads}

        def write(tmp):
            with open(tmp, "wb") as f:
                np.savez_compressed(f, displacement=run.displacement, meta=json.dumps(meta))

        hit.parent.mkdir(parents=True, exist_ok=True)
        write_atomic_with(hit, write)
    return run
