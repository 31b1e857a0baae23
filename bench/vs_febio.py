"""Benchmark: our solver against FEBio 4 on the same hanging-hemisphere meshes, in one run.

Problem (``../shared/febio/hemisphere/``): radius 60 mm, flat face fixed, gravity -z, rho
1000 kg/m^3, E = 1 kPa, nu = 0.49; Neo-Hookean and Gent (Jm 5); meshes hemi_20k (19959
tets) and hemi_150k (162048 tets). Every run is a child process started from here, measured
the same way for both codes: wall time from start to exit, its CPU time (user + sys, all
threads) and its peak resident memory (``os.wait4``'s ``ru_maxrss``), with the 1-minute load
average before and after (the machine is shared: CPU times and counts are the figures to
decide on; wall times follow the load). Both codes get the same explicit thread count
(``--threads``, default: the cores of this process): FEBio ``OMP_NUM_THREADS`` and
``MKL_NUM_THREADS``, ours ``BREASTMODEL_THREADS``.

Accuracy, two kinds:
- solver error: |tip displacement - the same code's tightly converged tip| (ours: the
  solve continued to a relative residual of 1e-13, not timed; FEBio: its full Newton at
  tight tolerances against its BFGS at default ones, both in ``summary.json``);
- discretisation error (Neo-Hookean): |tip| against the continuum 12.22 +/- 0.03 mm of
  ``reference.json``. FEBio's plain tet4 locks (11.48 / 11.98 mm); our averaged nodal
  pressure does not.

FEBio rows are live runs when ``breastmodel.febio`` (the .feb writer and runner) and the
FEBio build are found, else the figures recorded in ``summary.json`` on a quiet 2-core
machine, labelled ``recorded``. Our rows are one per configuration (``--configs``): each
is the default solver with one lever changed, so the table says what each lever buys.

Measured 2026-11-26 on the 2-core machine with nothing else running (1-minute load 0.4-1.8,
the load being these runs), 2 threads each, FEBio live in the same run (its BFGS only; its
full Newton rows of the run before are kept in ``bench/results/vs_febio.json``), after the
right-preconditioned GMRES below. A second 20k run beside it is in brackets: FEBio itself
varies by 15-30 % between runs.

case        FEBio BFGS (its best)          ours (default)              time ratio   memory
            wall s  CPU s  MiB  fact.      wall s  CPU s  MiB   fact.   wall  CPU
20k NH       2.45   4.16   123  10           1.26   1.45   203  1       0.51  0.35   1.7x
  [second]  [2.13   3.61]                   [1.23   1.42]               [0.58]
20k Gent 5   2.15   3.59   124  10           1.17   1.36   203  1       0.55  0.38   1.6x
  [second]  [2.77   4.73]                   [1.29   1.49]               [0.47]
150k NH     48.6   91.3    990  10          16.2   20.1   1282  1       0.33  0.22   1.3x
150k Gent 5 45.0   84.7    990  10          14.6   18.3   1285  1       0.32  0.22   1.3x

FEBio's full Newton: 20k 5.1-5.6 s, 150k 170-212 s. The time target (<= 0.5x FEBio's best)
is met at 150k and at 20k only in some runs (0.47-0.58): there a whole process of ours is
1.17-1.29 s, of which the interpreter and imports about 0.25 s (scipy.sparse 0.14 s, half of
it numpy.f2py and numpy.testing that SciPy's array-API layer imports) and the solve about
0.8 s (cProfile: the sparsity pattern 0.09, PARDISO's analysis 0.09 and one factorisation
0.09-0.11, 28 triangular solves of 6.5-7 ms for 26 GMRES iterations, 7 evaluations of the
solid 0.29). The earlier table (2026-11-23, load 10-14) gave 0.18-0.49 at 20k: the load
slowed FEBio's OpenMP threads more than ours, so those ratios did not hold on a quiet
machine. A looser tolerance (config "tol 1e-6": solver error 8e-8 to 3e-7 mm, still 100
times below FEBio BFGS's 1e-5 to 4e-5 mm) saves one Newton iteration and nothing measurable
(1.25-1.40 s). The memory target (<= FEBio's) is missed at both sizes: at 20k our process
is 70 MiB of interpreter and libraries before any mesh; at 150k PARDISO alone holds 600
MiB (the 114k-unknown saddle-point system with one pressure per node: 4 unknowns per node
against FEBio's 3), the interpreter 70, and the numpy arrays of the Newton loop about 520-570
at the peak (tracemalloc: the scatter maps 78, the matrices the line search keeps 70, the
kept evaluations' F and stress 70, one evaluation's element arrays about 200, the solid's
constant arrays 40). Reaching FEBio's 990 MiB would need the whole evaluation streamed in
element blocks (not only the stiffness, as now) and fewer kept evaluations.

What each lever bought (counts and CPU; loads as stated):
- right-preconditioned flexible GMRES of our own (``mechanics/krylov.py``) instead of
  SciPy's, and a fresh factorisation's solve refined to 1e-10 instead of the rounding floor
  (2026-11-26): 20k NH 40 -> 28 triangular solves of 6.5 ms for the same 26 GMRES
  iterations (SciPy's spent two solves per call beyond its iterations; the refinement 3 -> 1
  steps), and the solver process no longer imports scipy.sparse.linalg (imports 0.26 ->
  0.22 s); whole process 1.25-1.34 -> 1.17-1.29 s (20k), 150k 15.5-17.5 -> 14.6-16.2 s.
- element stiffness scattered into the matrix block by block (32768 tets) as the solid
  computes it, int32 scatter maps above one block, the element stiffness and dv dropped from
  kept evaluations (2026-11-26): 150k NH peak 1494 -> 1356 MiB in one process (the bench:
  1461 -> 1288), the solve unchanged (18.1 s before, 17.7-20.0 after, one process each); below
  one block the whole-mesh scatter is kept (measured faster there).
- scipy.spatial imported only by the contact search: every process 0.2 s sooner to start
  (the imports 0.46-0.72 -> 0.36 s).
- factor reuse, GMRES right-preconditioned by the last factorisation from the first
  iteration on (symmetric tangents): 150k NH 11 factorisations (a failed full-load step, then
  two half steps; CPU 150 s at load 1.2-2.7) -> 1 factorisation, 7 Newton, 39 GMRES
  iterations (CPU 24-34 s); 20k NH 5 -> 1 (CPU 3.25 -> 2.26 s, row "no factor reuse").
  SciPy's left-preconditioned GMRES had stopped after 3-4 iterations on the preconditioned
  residual; that, not the factor, made reuse fail.
- MKL loaded directly instead of through pypardiso's search: 0.8 s -> 0.001 s per process.
- element stiffness dropped once assembled: 150k peak 1815 -> 1525 MiB (same 11-factorisation
  path).
- explicit threads: the count is the setting (row "1 thread": at load 10 one thread costs
  the same CPU as two; on a quiet machine two threads factorise the 150k tangent in 1.7 s
  against 3.0 s, bench/gravity.py).
- PARDISO against SciPy SuperLU (row "scipy SuperLU"): 20k CPU 2.26 vs 6.62 s, 232 vs
  372 MiB.
- orderings (one analysis of the 150k tangent, load 0.8): METIS 118M entries in L, 314
  GFLOP; AMD 373M, 3.0 TFLOP (rejected); parallel METIS (iparm 2 = 3) the same fill, analysis
  1.0 s against 1.4 s (not adopted: one measurement); two-level factorisation (iparm 24) the
  same fill.
- initial_steps 2: no longer pays (20k: 1 factorisation either way, 8 against 6 Newton).
- measured 2026-11-29 and not kept (20k NH, 2 threads, best of 40 evaluations of the solid):
  the element stiffness kernel's 2048-tet chunks on a pool of the solve's threads, 39.5 ->
  34-37 ms per evaluation (the kernel alone 17 -> 10 ms), 150k 296 -> 291 ms; the
  kinematics and the closed-form laws in chunks as well, nothing more. The kernels stream
  mesh-sized arrays through memory, so a second thread mostly shares the bandwidth; about
  0.03 s of a 20k solve was not worth a thread pool in the solid. PARDISO's parallel
  forward/backward solve (iparm 25 = 1 or 2): the 23 GMRES iterations' solves 0.22-0.24 s
  either way. glibc's malloc kept from returning memory (MALLOC_TOP_PAD_, _TRIM_THRESHOLD_,
  _MMAP_THRESHOLD_): the first 20k solve of a process 1.15-1.26 -> 1.09-1.13 s (page faults
  of freshly mapped arrays), but that is the host process's setting, not a library's.
- the solid drops F^-1, the element forces, g and the laws' f and q (once transposed) before
  the element stiffness (2026-11-29): 150k NH / Gent peak 1282 / 1285 -> 1170 / 1184 MiB
  (FEBio 988), the same tips; time 21.0 / 18.2 s against FEBio BFGS 58.8 / 59.9 s that day.
  Then the whole evaluation in element blocks, two passes (F and volumes, then forces and
  stiffness): 1125 / 1130 MiB (1.14x), 20.0 / 19.6 s; one evaluation 280 -> 297 ms.
- our children run from byte-compiled modules (compiled before the runs): with
  PYTHONDONTWRITEBYTECODE=1 in the environment each had compiled the solver's modules again,
  0.06-0.1 s per 20k process. Same day, one machine slower than on 2026-11-26 (FEBio BFGS
  3.2-3.45 s against 2.1-2.8): two runs of 20k NH / Gent, ratio 0.46 / 0.53 and 0.54 / 0.57.
- memory at 150k (2026-11-29, evening; the README has each step's figure): the scatter in
  place with np.add.at (no nnz-sized bincount sum, no int64 copy of the map), no evaluation
  or matrix kept past its use in the Newton loop (PARDISO's solver lets go of the factorised
  matrix once its refined solve is done), the scatter maps of a mesh above one block made
  per block from the node-pair tables, and such a mesh streamed in blocks of 16384 tets:
  1125 / 1130 -> 958 / 960 MiB against FEBio's 988 (0.97x), 13.6 / 13.8 s against 42.0 /
  46.4 (0.32x / 0.30x); 20k 0.50x / 0.52x, 195 MiB (1.61x)
  (``bench/results/vs_febio_2026-11-29_streamed16k.json``). With dN.dN made per block as
  well, on a slower hour (FEBio 3.3-3.7 s at 20k): 150k 946 / 948 MiB (0.96x), 0.31x /
  0.33x; 20k 0.51x / 0.55x, 196 / 195 MiB (``vs_febio_2026-11-29_final.json``).

Usage: ``python bench/vs_febio.py [--sizes 20k,150k] [--materials nh,gent]
[--configs default,...] [--threads N] [--febio live|recorded|none]``; writes
``bench/results/vs_febio.json`` (rows not run this time are kept).
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

RHO, G = 1000.0, 9.81
MATERIALS = {"nh": {"name": "neo_hookean", "E": 1.0, "nu": 0.49},
             "gent": {"name": "gent", "E": 1.0, "nu": 0.49, "Jm": 5.0}}
#: Our configurations: SolverOptions fields changed from the defaults (tol 1e-8).
CONFIGS: dict[str, dict] = {
    "default": {},
    "1 thread": {"threads": 1},
    "no factor reuse": {"reuse_factor": False},
    "initial_steps 2": {"initial_steps": 2},
    "reuse at any residual": {"reuse_below": 1.0, "reuse_max_iterations": 150},
    "steps 2 + reuse any": {"initial_steps": 2, "reuse_below": 1.0,
                            "reuse_max_iterations": 150},
    "scipy SuperLU": {"linear_solver": "scipy"},
    "tol 1e-6": {"tol": 1e-6},
}
REFERENCE_TIP_NH = 12.22  # mm, continuum (reference.json)


def febio_dir() -> Path | None:
    """The FEBio build: $BREASTMODEL_FEBIO_DIR, else ``shared/febio`` beside a checkout."""
    env = os.environ.get("BREASTMODEL_FEBIO_DIR")
    cands = [Path(env)] if env else []
    cands += [p / "shared" / "febio" for p in (ROOT.parent, ROOT.parent.parent)]
    return next((p for p in cands if (p / "hemisphere").is_dir()), None)


def load_mesh(size: str):
    from mechanics.mesh import Mesh

    d = np.load(febio_dir() / "hemisphere" / f"hemi_{size}.npz")
    mesh = Mesh(d["nodes"], d["tets"].astype(np.int64), np.ones(len(d["tets"]), np.int64),
                node_sets={"fixed": d["base"].astype(np.int64),
                           "tip": np.array([int(d["tip"])])})
    return mesh, int(d["tip"])


# ------------------------------------------------------------------------------- ours
def _ours_worker(size: str, material: str, options: dict) -> dict:
    """Runs in the child: load, build, solve (timed by the parent), then the untimed
    accuracy continuation; reports what the parent must subtract."""
    import resource

    from mechanics.model import build_model
    from mechanics.solver import SolverOptions, solve

    mesh, tip = load_mesh(size)
    model = build_model(mesh, {1: MATERIALS[material]},
                        {"gravity": {"direction": (0, 0, -1), "density": RHO, "g": G},
                         "fixed": {"node_set": "fixed"}})
    opt = SolverOptions(**{"tol": 1e-8, **options})
    st = solve(model, options=opt)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    w0, c0 = time.perf_counter(), time.process_time()
    tight = solve(model, u0=st.u, options=SolverOptions(tol=1e-13, threads=opt.threads))
    tip_u, tip_t = st.u[tip], tight.u[tip]
    return {
        "tip_mm": float(np.linalg.norm(tip_u)), "tip_tight_mm": float(np.linalg.norm(tip_t)),
        "solver_error_mm": float(np.linalg.norm(tip_u - tip_t)),
        "max_disp_mm": st.max_displacement(), "converged": st.converged,
        "newton": st.newton_iterations, "load_steps": st.load_steps,
        "stats": st.stats, "peak_before_check_mb": peak,
        "steps": [{"load": e["load"], "converged": e["converged"], "linear": e["linear"],
                   "residuals": e["residuals"]} for e in st.log],
        "untimed_wall_s": time.perf_counter() - w0, "untimed_cpu_s": time.process_time() - c0,
        "n_tets": mesh.n_tets, "n_nodes": mesh.n_nodes,
    }


def measure(cmd: list[str], env: dict, cwd: str | None = None,
            timeout: float = 3600.0) -> dict:
    """Run ``cmd``; wall, CPU (user + sys) and peak RSS (MB) of the child and its waited
    children, its stdout, and the load average before and after."""
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryFile("w+") as out:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=cwd)
        deadline = t0 + timeout
        while True:
            pid, status, ru = os.wait4(p.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() > deadline:
                p.kill()
                pid, status, ru = os.wait4(p.pid, 0)
                break
            time.sleep(0.02)
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        text = out.read()
    return {"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime, "peak_mb": ru.ru_maxrss / 1024,
            "rc": p.returncode, "stdout": text, "load_before": load0,
            "load_after": os.getloadavg()[0]}


def run_ours(size: str, material: str, config: str, threads: int) -> dict:
    options = CONFIGS[config]
    env = {**os.environ, "BREASTMODEL_THREADS": str(threads)}
    cmd = [sys.executable, __file__, "--worker", json.dumps([size, material, options])]
    m = measure(cmd, env)
    row = {"code": "ours", "config": config, "size": size, "material": material,
           "threads": options.get("threads", threads), "source": "live",
           "load_before": m["load_before"], "load_after": m["load_after"]}
    res = next((json.loads(line[7:]) for line in m["stdout"].splitlines()
                if line.startswith("RESULT ")), None)
    if m["rc"] != 0 or res is None:
        return {**row, "error": m["stdout"][-800:]}
    st = res.pop("stats")
    row.update(res)
    row.update({
        "wall_s": m["wall_s"] - res["untimed_wall_s"], "cpu_s": m["cpu_s"] - res["untimed_cpu_s"],
        "peak_mb": res["peak_before_check_mb"], "solve_wall_s": st["wall_s"],
        "factorizations": st["factorizations"], "analyses": st["analyses"],
        "krylov_iterations": st["krylov_iterations"], "unknowns": st["unknowns"],
        "krylov_failed": st.get("krylov_failed"),
        "pardiso_mb": st.get("linear_solver_mb"),  # PARDISO's own account, part of peak_mb
        "phases_cpu_s": {k[4:]: st[k] for k in st if k.startswith("cpu_")
                         and isinstance(st[k], float)},
    })
    return row


# ------------------------------------------------------------------------------ FEBio
def febio_recorded(size: str, material: str, config: str, threads: int) -> dict | None:
    """The run of ``summary.json`` (quiet 2-core machine), or None."""
    name = f"hemi_{size}_{'nh' if material == 'nh' else 'gent_Jm5'}_{config}"
    rows = json.loads((febio_dir() / "hemisphere" / "summary.json").read_text())
    hit = next((r for r in rows if r["case"] == name and r["threads"] == threads), None)
    if hit is None:
        return None
    return {"code": "febio", "config": config, "size": size, "material": material,
            "threads": threads, "source": "recorded (summary.json)", "wall_s": hit["wall_s"],
            "cpu_s": None, "peak_mb": hit["peak_rss_MiB"],
            "newton": hit["equilibrium_iterations"],
            "factorizations": hit["stiffness_reformations"], "load_steps": hit["time_steps"],
            "tip_mm": hit["tip_disp_mag"], "tip_vec": hit["tip_disp"],
            "load_before": None, "load_after": None}


#: FEBio's solver settings per configuration: BFGS at FEBio's defaults, full Newton tight
#: (as in ``summary.json``); 10 equal load steps, plain tet4 (its fastest element).
FEBIO_TOL = {"bfgs": {"dtol": 1e-3, "etol": 1e-2, "rtol": 0.0},
             "newton": {"dtol": 1e-6, "etol": 1e-8, "rtol": 0.0}}


def febio_live(size: str, material: str, config: str, threads: int,
               element: str = "tet4") -> dict | None:
    """A live FEBio run of the model our solver gets, written by ``mechanics.febio`` and
    measured like ours (None when the writer or FEBio is not there)."""
    import re

    try:
        from breastmodel.febio import find_febio
        from mechanics.febio import DISPLACEMENT_FILE, feb_text, read_node_data
        from mechanics.model import build_model

        exe = find_febio()
    except Exception:  # noqa: BLE001  (no writer, no FEBio: fall back to recorded)
        return None
    mesh, tip = load_mesh(size)
    model = build_model(mesh, {1: MATERIALS[material]},
                        {"gravity": {"direction": (0, 0, -1), "density": RHO, "g": G},
                         "fixed": {"node_set": "fixed"}})
    text = feb_text(model, element=element, steps=10, solver=config, **FEBIO_TOL[config])
    row = {"code": "febio", "config": config if element == "tet4" else f"{config} {element}",
           "size": size, "material": material, "threads": threads, "source": "live",
           "element": element}
    with tempfile.TemporaryDirectory() as work:
        Path(work, "model.feb").write_text(text, encoding="latin-1")
        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
        env.setdefault("FEBIO_MKL_LIB", os.path.join(sys.prefix, "lib"))
        m = measure([str(exe), "-i", "model.feb", "-silent"], env, cwd=work)
        log = Path(work, "model.log")
        log = log.read_text(errors="replace") if log.exists() else m["stdout"]
        out = Path(work, DISPLACEMENT_FILE)
        if not out.exists():
            return {**row, "error": log[-800:]}
        u, t_end = read_node_data(out.read_text(), mesh.n_nodes)

    def count(pattern):
        hit = re.findall(pattern + r"\s*\.*\s*:\s*(\d+)", log)
        return int(hit[-1]) if hit else None

    row.update(wall_s=m["wall_s"], cpu_s=m["cpu_s"], peak_mb=m["peak_mb"],
               load_before=m["load_before"], load_after=m["load_after"],
               newton=count("Total number of equilibrium iterations"),
               factorizations=count("Total number of stiffness reformations"),
               tip_mm=float(np.linalg.norm(u[tip])), tip_vec=[float(v) for v in u[tip]],
               converged="N O R M A L   T E R M I N A T I O N" in log and t_end == 1.0)
    return row


def febio_solver_errors(rows: list[dict]) -> None:
    """FEBio's solver error: |tip of a run - tip of its full Newton (tight tolerances)|."""
    for r in rows:
        if r["code"] != "febio" or "tip_vec" not in r:
            continue
        ref = next((q for q in rows if q["code"] == "febio" and q["config"] == "newton"
                    and q["size"] == r["size"] and q["material"] == r["material"]
                    and "tip_vec" in q), None)
        if ref is not None:
            r["solver_error_mm"] = float(np.linalg.norm(np.subtract(r["tip_vec"],
                                                                    ref["tip_vec"])))


# ------------------------------------------------------------------------------ table
def fmt(r: dict, best: dict | None) -> str:
    if "error" in r:
        return f"{r['size']:>5} {r['material']:<4} {r['code']:<5} {r['config']:<16} ERROR " \
               f"{r['error'][-300:]}"

    def f(x, spec):
        return format(x, spec) if isinstance(x, (int, float)) else f"{'-':>{spec[:-3] or 1}}"

    ratio = ""
    if best is not None and r["code"] == "ours":
        ratio = (f" x{r['wall_s'] / best['wall_s']:.2f} time"
                 f" x{r['peak_mb'] / best['peak_mb']:.2f} mem")
    disc = ""
    if r["material"] == "nh" and "tip_mm" in r:
        disc = f"{abs(r['tip_mm'] - REFERENCE_TIP_NH):6.3f}"
    load = "" if r.get("load_before") is None else \
        f"{r['load_before']:.1f}->{r['load_after']:.1f}"
    return (f"{r['size']:>5} {r['material']:<4} {r['code']:<5} {r['config']:<16} "
            f"{r['threads']:>2} {f(r['wall_s'], '7.2f')} {f(r.get('cpu_s'), '7.2f')} "
            f"{f(r['peak_mb'], '6.0f')} {f(r.get('newton'), '4d')} "
            f"{f(r.get('factorizations'), '4d')} {r['tip_mm']:8.4f} "
            f"{f(r.get('solver_error_mm'), '8.1e')} {disc:>6} {load:>9}"
            f"{'' if r['source'] == 'live' else ' recorded'}{ratio}")


HEADER = (f"{'size':>5} {'mat':<4} {'code':<5} {'config':<16} {'th':>2} {'wall s':>7} "
          f"{'cpu s':>7} {'MB':>6} {'its':>4} {'fact':>4} {'tip mm':>8} {'solv err':>8} "
          f"{'|tip-12.22|':>6} {'load':>9}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="20k,150k")
    ap.add_argument("--materials", default="nh,gent")
    ap.add_argument("--configs", default="default",
                    help=f"comma list of our configurations: {', '.join(CONFIGS)}")
    ap.add_argument("--threads", type=int, default=None,
                    help="threads of both codes (default: the cores of this process)")
    ap.add_argument("--febio", default="live", choices=("live", "recorded", "none"),
                    help="live runs (falls back to recorded when the runner is missing)")
    ap.add_argument("--febio-configs", default="bfgs,newton",
                    help="FEBio configurations: bfgs (its defaults), newton (tight)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "vs_febio.json")
    args = ap.parse_args(argv)
    if args.worker:
        size, material, options = json.loads(args.worker)
        print("RESULT " + json.dumps(_ours_worker(size, material, options)))
        return 0
    from mechanics.linear_solvers import resolve_threads

    threads = resolve_threads(args.threads)
    # Our children import byte-compiled modules, as an installed package's processes do;
    # where the environment forbids writing bytecode (PYTHONDONTWRITEBYTECODE=1, set on the
    # machines these runs were made on), every child compiled the solver's 50 modules
    # again: 0.06-0.1 s of a 20k process's 1.2-1.9 s (2026-11-29)
    compileall.compile_dir(str(ROOT / "mechanics"), quiet=1)
    rows: list[dict] = []
    print(f"threads {threads}; wall s: start to exit of the process; cpu s: user + sys of "
          f"all its threads; MB: its peak RSS; load: 1-min load average before->after "
          f"(shared machine: compare cpu s and counts)")
    print(HEADER, flush=True)
    for size in args.sizes.split(","):
        for material in args.materials.split(","):
            here = []
            if args.febio != "none":
                for cfg in args.febio_configs.split(","):
                    r = febio_live(size, material, cfg, threads) if args.febio == "live" \
                        else None
                    r = r or febio_recorded(size, material, cfg, threads)
                    if r is not None:
                        here.append(r)
                febio_solver_errors(here)
            best = min((r for r in here if r["code"] == "febio" and "wall_s" in r),
                       key=lambda r: r["wall_s"], default=None)
            for r in here:
                print(fmt(r, None), flush=True)
            for cfg in args.configs.split(","):
                r = run_ours(size, material, cfg.strip(), threads)
                if best is not None and "error" not in r:
                    r["vs_febio_best"] = {"config": best["config"],
                                          "time_ratio": r["wall_s"] / best["wall_s"],
                                          "memory_ratio": r["peak_mb"] / best["peak_mb"],
                                          "febio_source": best["source"]}
                here.append(r)
                print(fmt(r, best), flush=True)
            rows += here
    meta = {"problem": "hanging hemisphere R 60 mm, E 1 kPa, nu 0.49, rho 1000, g 9.81",
            "threads": threads, "cpu_count": os.cpu_count(),
            "ours_tol": "relative residual 1e-8 (||R_free|| / max(||R_fixed||, ||R_0||))",
            "febio_tol": "BFGS: FEBio defaults (dtol 1e-3, etol 1e-2); newton: tight",
            "targets": "time <= 0.5 x FEBio's best, peak memory <= FEBio's",
            "bytecode": "the solver's modules byte-compiled before the runs",
            "configs": CONFIGS, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.out.exists():
        done = {(r["code"], r["config"], r["size"], r["material"]) for r in rows}
        old = json.loads(args.out.read_text()).get("rows", [])
        rows = [r for r in old if (r["code"], r["config"], r["size"], r["material"])
                not in done] + rows
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
