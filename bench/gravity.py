"""Benchmark: a hemisphere (radius 60 mm, flat face fixed) hanging under gravity.

E = 1 kPa, nu = 0.49, rho = 1000 kg/m^3, g = 9.81 m/s^2, Neo-Hookean, relative residual 1e-8.
Meshes: the structured hemisphere of ``tests/zoo.py`` at ~20k tets (n = 19), ~150k
(n = 37) and ~300k (n = 47, 305k tets; ``BENCH_COLD_ONLY=1`` runs one solve per size).
Each solver runs in its own subprocess so that its peak memory (VmHWM) is its own.
Reported: wall time (cold: pattern + symbolic analysis included; warm: a second solve of the
same model, as in a fit), Newton iterations, time split, peak memory, max displacement, and
SfePy (P1 total-Lagrangian Neo-Hookean + bulk penalty, ScipyDirect) on the same mesh.

The full paper-like model (every effect on: skin, fascia, ligaments, sliding with friction,
supports, regions) on a ~20k-tet phantom mesh is ``python bench/gravity.py --effects
[bench/effects.py options]``, which runs ``bench/effects.py`` (time per position, Newton
iterations per load step, the cost of each effect).

Usage: ``python bench/gravity.py [--sizes 20k,150k] [--no-sfepy] [--E 1.0]
[--initial-steps 1]``; writes ``bench/results/gravity.json`` (rows of solvers and sizes not
run this time are kept). The 150k row in ``bench/results/gravity_150k.json`` is made with
``--sizes 150k --no-sfepy --initial-steps 2 --out bench/results/gravity_150k.json`` (SfePy
takes tens of minutes there). The comparison with FEBio on its own meshes, and what each
solver lever buys, is ``bench/vs_febio.py``. CPU times (``time.process_time``, all threads)
are reported beside wall times and the load average: the machine is shared, and wall time
follows its load.

Where the time goes (2-core machine, 150k tets, 105k unknowns): a PARDISO factorisation is
206 GFLOP (99M entries in L; single precision, one thread: 3.0 s, double 5.5 s, double with
Bunch-Kaufman pivots 7.4 s), a triangular solve 0.07 s, an evaluation of residual and
tangent about 0.5 s, the pattern build 0.7 s, the symbolic analysis 0.8 s.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

SIZES = {"2k": 8, "20k": 19, "150k": 37, "300k": 47}
RHO, G, RADIUS = 1000.0, 9.81, 60.0


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def hemisphere_mesh(n: int):
    from zoo import hemisphere

    return hemisphere(RADIUS, n)


def run_ours(n: int, E: float, nu: float, formulation: str, linear_solver: str,
             initial_steps: int = 1) -> dict:
    from mechanics.model import build_model
    from mechanics.solver import SolverOptions, solve

    mesh = hemisphere_mesh(n)
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": E, "nu": nu}},
                        {"gravity": {"direction": (0, 0, -1), "density": RHO, "g": G},
                         "fixed": {"node_set": "fixed"}}, formulation=formulation)
    opt = SolverOptions(tol=1e-8, linear_solver=linear_solver, initial_steps=initial_steps)
    t0, c0 = time.perf_counter(), time.process_time()
    cold = solve(model, options=opt)
    t_cold, c_cold = time.perf_counter() - t0, time.process_time() - c0
    if os.environ.get("BENCH_COLD_ONLY"):  # the largest sizes: one solve
        warm, t_warm, c_warm = cold, t_cold, c_cold
    else:
        t0, c0 = time.perf_counter(), time.process_time()
        warm = solve(model, options=opt)
        t_warm, c_warm = time.perf_counter() - t0, time.process_time() - c0
    keys = ("material", "effects", "assembly", "factor", "solve")
    split = {k: float(warm.stats[f"t_{k}"]) for k in keys}
    cpu_split = {k: float(warm.stats[f"cpu_{k}"]) for k in keys}
    return {
        "solver": f"ours ({formulation}, {linear_solver})", "n_tets": mesh.n_tets,
        "n_nodes": mesh.n_nodes, "wall_cold_s": t_cold, "wall_s": t_warm,
        "cpu_cold_s": c_cold, "cpu_s": c_warm, "cpu_split_s": cpu_split,
        "factorizations": int(sum(e.get("factorizations", 0) for e in warm.log)),
        "krylov_iterations": int(sum(e.get("krylov_iterations", 0) for e in warm.log)),
        "newton": warm.newton_iterations, "load_steps": warm.load_steps,
        "final_residual": float(warm.log[-1]["residuals"][-1]),
        "split_s": split, "max_disp_mm": warm.max_displacement(),
        "converged": warm.converged, "peak_mb": peak_rss_mb(),
        "agree_cold_warm": float(np.abs(cold.u - warm.u).max()),
        "initial_steps": initial_steps, "cpu_count": os.cpu_count(),
        "threads": warm.stats["threads"],
        "loadavg_1min_after": os.getloadavg()[0],
        "factorizations_cold": int(cold.stats["factorizations"]),
        "peak_rss_mb_solver": float(cold.stats["peak_rss_mb"]),
    }


def solve_sfepy(mesh, *, E: float, nu: float, rho_g: float, direction=(0.0, 0.0, -1.0),
                fixed: str = "fixed", mixed: bool = False):
    """SfePy total-Lagrangian Neo-Hookean on the same mesh, an independent code.

    ``mixed=False``: P1 displacement, dw_tl_he_neohook + dw_tl_bulk_penalty (the same
    discrete energy as our ``formulation="standard"``). ``mixed=True``: P1 displacement and
    P1 pressure (dw_tl_bulk_pressure, dw_tl_volume, dw_dot(1/K)), a locking-free mixed
    formulation to compare with our averaged nodal pressure.
    Returns (u (N, 3) mm, wall s, Newton iterations)."""
    from sfepy.base.base import IndexedStruct, output
    from sfepy.discrete import Equation, Equations, FieldVariable, Integral, Material, Problem
    from sfepy.discrete.conditions import Conditions, EssentialBC
    from sfepy.discrete.fem import FEDomain, Field
    from sfepy.discrete.fem import Mesh as SfMesh
    from sfepy.solvers.ls import ScipyDirect
    from sfepy.solvers.nls import Newton
    from sfepy.terms import Term

    output.set_output(quiet=True)
    t0 = time.perf_counter()
    sm = SfMesh.from_data("m", mesh.nodes, None, [mesh.tets.astype(np.int32)],
                          [np.ones(mesh.n_tets, np.int32)], ["3_4"])
    domain = FEDomain("d", sm)
    omega = domain.create_region("Omega", "all")
    ids = mesh.node_sets[fixed]
    fixed_r = domain.create_region("Fixed", "vertex " + ", ".join(map(str, ids)), "vertex")
    field = Field.from_args("fu", np.float64, "vector", omega, approx_order=1)
    u = FieldVariable("u", "unknown", field)
    v = FieldVariable("v", "test", field, primary_var_name="u")
    K = E / (3 * (1 - 2 * nu))
    m = Material("m", mu=E / (2 * (1 + nu)), K=K, iK=1.0 / K)
    f = Material("f", val=(rho_g * np.asarray(direction, float)).reshape(3, 1))
    integral = Integral("i", order=2)
    t1 = Term.new("dw_tl_he_neohook(m.mu, v, u)", integral, omega, m=m, v=v, u=u)
    t3 = Term.new("dw_volume_lvf(f.val, v)", integral, omega, f=f, v=v)
    if mixed:
        fp = Field.from_args("fp", np.float64, "scalar", omega, approx_order=1)
        p = FieldVariable("p", "unknown", fp)
        q = FieldVariable("q", "test", fp, primary_var_name="p")
        t2 = Term.new("dw_tl_bulk_pressure(v, u, p)", integral, omega, v=v, u=u, p=p)
        vol = (Term.new("dw_tl_volume(q, u)", integral, omega, q=q, u=u, term_mode="volume")
               - Term.new("dw_integrate(q)", integral, omega, q=q)
               + Term.new("dw_dot(m.iK, q, p)", integral, omega, m=m, q=q, p=p))
        eqs = [Equation("balance", t1 + t2 - t3), Equation("volume", vol)]
    else:
        t2 = Term.new("dw_tl_bulk_penalty(m.K, v, u)", integral, omega, m=m, v=v, u=u)
        eqs = [Equation("balance", t1 + t2 - t3)]
    pb = Problem("hemisphere", equations=Equations(eqs))
    pb.set_bcs(ebcs=Conditions([EssentialBC("fix", fixed_r, {"u.all": 0.0})]))
    status = IndexedStruct()
    pb.set_solver(Newton({"i_max": 30, "eps_a": 1e-10, "eps_r": 1e-8},
                         lin_solver=ScipyDirect({}), status=status))
    variables = pb.solve(save_results=False)
    wall = time.perf_counter() - t0
    return variables["u"].get_state_in_region(omega), wall, int(status.n_iter)


def run_sfepy(n: int, E: float, nu: float, mixed: bool) -> dict:
    mesh = hemisphere_mesh(n)
    U, wall, its = solve_sfepy(mesh, E=E, nu=nu, rho_g=RHO * G * 1e-6, mixed=mixed)
    name = "sfepy (P1-P1 u-p, TL)" if mixed else "sfepy (P1 TL, penalty)"
    return {"solver": name, "n_tets": mesh.n_tets,
            "n_nodes": mesh.n_nodes, "wall_s": wall, "wall_cold_s": wall, "newton": its,
            "max_disp_mm": float(np.linalg.norm(U, axis=1).max()), "peak_mb": peak_rss_mb(),
            "converged": True}


def _worker(args) -> None:
    if args.worker.startswith("sfepy"):
        out = run_sfepy(args.n, args.E, args.nu, mixed=args.worker == "sfepy_mixed")
    else:
        out = run_ours(args.n, args.E, args.nu, args.worker, args.linear_solver,
                       args.initial_steps)
    print("RESULT " + json.dumps(out))


def _spawn(kind: str, n: int, E: float, nu: float, linear_solver: str, timeout: float,
           initial_steps: int = 1):
    cmd = [sys.executable, __file__, "--worker", kind, "--n", str(n), "--E", str(E),
           "--nu", str(nu), "--linear-solver", linear_solver,
           "--initial-steps", str(initial_steps)]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"solver": kind, "error": f"timeout after {timeout:.0f} s"}
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    return {"solver": kind, "error": (p.stderr or p.stdout)[-500:]}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--effects" in argv:  # the paper-like model: bench/effects.py with the other options
        argv.remove("--effects")
        return subprocess.call([sys.executable, str(ROOT / "bench" / "effects.py"), *argv])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="20k", help="comma list of 2k, 20k, 150k")
    ap.add_argument("--E", type=float, default=1.0, help="Young's modulus, kPa")
    ap.add_argument("--nu", type=float, default=0.49)
    ap.add_argument("--no-sfepy", action="store_true")
    ap.add_argument("--standard", action="store_true",
                    help="also run the plain-tet formulation (same energy as SfePy P1)")
    ap.add_argument("--linear-solver", default="auto")
    ap.add_argument("--initial-steps", type=int, default=1,
                    help="first load increment 1/N (measured: 2 at 150k tets halves the "
                         "factorisations; 1 is best at 20k)")
    ap.add_argument("--timeout", type=float, default=1800.0)
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "gravity.json")
    args = ap.parse_args(argv)
    if args.worker:
        _worker(args)
        return 0
    rows = []
    for size in args.sizes.split(","):
        n = SIZES[size.strip()]
        kinds = ["anp"] + (["standard"] if args.standard else [])
        kinds += [] if args.no_sfepy else ["sfepy", "sfepy_mixed"]
        for kind in kinds:
            r = _spawn(kind, n, args.E, args.nu, args.linear_solver, args.timeout,
                       args.initial_steps)
            r.update(size=size, E_kPa=args.E, nu=args.nu)
            rows.append(r)
            print(_fmt(r), flush=True)
    meta = {"problem": "hemisphere R=60 mm, flat face fixed, gravity -z, Neo-Hookean",
            "rho": RHO, "g": G, "tol": 1e-8, "febio_reference_s": {"20k": 2.4, "150k": 57.0}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.out.exists():  # keep earlier rows of solvers and sizes not run this time
        done = {(r.get("solver"), r.get("size"), r.get("E_kPa")) for r in rows}
        old = json.loads(args.out.read_text()).get("rows", [])
        rows = [r for r in old if (r.get("solver"), r.get("size"), r.get("E_kPa")) not in done
                and "error" not in r] + rows
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


def _fmt(r: dict) -> str:
    if "error" in r:
        return f"{r.get('size', ''):>5} {r['solver']:<28} ERROR {r['error']}"
    split = r.get("split_s", {})
    sp = " / ".join(f"{split.get(k, float('nan')):.2f}"
                    for k in ("material", "assembly", "factor", "solve"))
    cpu = f"cpu {r['cpu_s']:6.2f} s " if "cpu_s" in r else ""
    return (f"{r['size']:>5} {r['solver']:<28} tets {r['n_tets']:>7} wall {r['wall_s']:7.2f} s "
            f"(cold {r['wall_cold_s']:6.2f}) {cpu}newton {r['newton']:>3} "
            f"mat/asm/fac/sol {sp:>22} peak {r['peak_mb']:7.0f} MB "
            f"max|u| {r['max_disp_mm']:.4f} mm")


if __name__ == "__main__":
    sys.exit(main())
