"""Benchmark: the hanging hemisphere in FEBio (through our writer) against our own solver.

Mesh ``../shared/febio/hemisphere/hemi_20k.npz`` (or ``--mesh``): E = 1 kPa, nu = 0.49,
1000 kg/m^3, g = 9.81 m/s^2 along -z, base fixed. For each law (neo_hookean, gent Jm 5) and
each FEBio element (tet4, ut4, tet10) prints and writes the tip displacement, FEBio's wall
time and iterations, and our solver's tip for "anp" and "standard".

Usage: ``python bench/febio_hemisphere.py [--laws neo_hookean,gent] [--elements tet4,ut4,tet10]
[--threads 1] [--steps 10] [--out bench/results/febio_hemisphere.json]``. UT4 is slow in FEBio (its
stiffness costs about 8 s per evaluation on 20k tets, 1 thread), so a full run takes long.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]


def main(argv=None) -> int:
    from breastmodel.febio import shared_path, solve_with_febio
    from breastmodel.reference import hemisphere_model
    from mechanics.solver import SolverOptions, solve

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default_mesh = next((p for p in shared_path("febio", "hemisphere", "hemi_20k.npz")
                         if p.exists()), None)
    ap.add_argument("--mesh", type=Path, default=default_mesh)
    ap.add_argument("--laws", default="neo_hookean,gent")
    ap.add_argument("--elements", default="tet4,ut4,tet10")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--solver", default="newton", choices=("newton", "bfgs"))
    ap.add_argument("--steps", type=int, default=10, help="load steps in FEBio (default 10)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" /
                    "febio_hemisphere.json")
    args = ap.parse_args(argv)
    rows = json.loads(args.out.read_text()) if args.out.exists() else []
    for law in args.laws.split(","):
        for form in ("anp", "standard"):
            model, tip = hemisphere_model(args.mesh, law, formulation=form)
            t0 = time.perf_counter()
            r = solve(model, options=SolverOptions(tol=1e-10))
            row = {"code": "ours", "law": law, "element": form, "mesh": args.mesh.name,
                   "tip_mm": float(np.linalg.norm(r.u[tip])),
                   "wall_s": round(time.perf_counter() - t0, 2), "converged": r.converged}
            print(json.dumps(row), flush=True)
            rows.append(row)
        ours = rows[-2]["tip_mm"]
        for element in args.elements.split(","):
            model, tip = hemisphere_model(args.mesh, law, formulation="anp")
            with tempfile.TemporaryDirectory() as work:
                run = solve_with_febio(model, work_dir=work, element=element,
                                       threads=args.threads, solver=args.solver,
                                       steps=args.steps)
            t = float(np.linalg.norm(run.displacement[tip]))
            row = {"code": "febio", "law": law, "element": element, "mesh": args.mesh.name,
                   "tip_mm": t, "wall_s": round(run.wall_s, 2), "iterations": run.iterations,
                   "threads": args.threads, "solver": args.solver, "steps": args.steps,
                   "converged": run.converged, "vs_ours_anp": t / ours - 1.0}
            print(json.dumps(row), flush=True)
            rows.append(row)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
