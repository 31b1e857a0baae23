"""Stress-free geometry: the paper's fixed point vs the Anderson-accelerated full-field inverse.

A half ball (radius R, flat face fixed) sags under gravity from a known unloaded shape; each
method starts from the loaded shape and recovers the unloaded one. Reports forward solves,
wall time and the recovered-shape error against the truth.

    python bench/stress_free.py [--n 8] [--radius 40] [--E 0.5]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from zoo import hemisphere  # noqa: E402

from mechanics.model import build_model  # noqa: E402
from mechanics.solver import solve  # noqa: E402
from mechanics.stress_free import inverse_fixed_point, paper_fixed_point  # noqa: E402


def _model(mesh, E):
    mats = {int(r): {"name": "neo_hookean", "E": E, "nu": 0.49} for r in np.unique(mesh.region)}
    return build_model(mesh, mats, {"gravity": {"direction": (0.0, 0.0, -1.0)},
                                    "fixed": {"node_set": "fixed"}})


def _surface_nodes(mesh):
    faces = np.sort(mesh.tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), 1)
    uniq, counts = np.unique(faces, axis=0, return_counts=True)
    return np.setdiff1d(np.unique(uniq[counts == 1]), mesh.node_sets["fixed"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=8, help="cells across the diameter")
    ap.add_argument("--radius", type=float, default=40.0, help="mm")
    ap.add_argument("--E", type=float, default=0.5, help="kPa")
    ap.add_argument("--out", type=Path, default=Path("bench/results/stress_free.json"))
    args = ap.parse_args()

    mesh = hemisphere(radius=args.radius, n=args.n)
    truth = solve(_model(mesh, args.E))
    x = truth.x
    model = _model(mesh.with_nodes(x), args.E)
    active = _surface_nodes(mesh)
    rows = []
    runs = {
        "paper fixed point (lam=0.5)": lambda: paper_fixed_point(
            model, lambda y: x[active], active, mesh.node_sets["fixed"], lam=0.5,
            min_improvement=1e-3, max_iter=40),
        "inverse fixed point (plain)": lambda: inverse_fixed_point(
            model, x, tol=1e-3, anderson=0, max_iter=80),
        "inverse fixed point (Anderson m=5)": lambda: inverse_fixed_point(
            model, x, tol=1e-3, anderson=5, max_iter=80),
    }
    for name, fn in runs.items():
        t0 = time.perf_counter()
        res = fn()
        wall = time.perf_counter() - t0
        err = np.linalg.norm(res.X - mesh.nodes, axis=1)
        rows.append({"method": name, "forward_solves": len(res.history), "wall_s": wall,
                     "max_error_mm": float(err.max()), "mean_error_mm": float(err.mean()),
                     "converged": res.converged})
    sag = float(np.linalg.norm(x - mesh.nodes, axis=1).max())
    print(f"half ball R={args.radius} mm, {mesh.n_tets} tets, E={args.E} kPa, max sag {sag:.2f} mm")
    print(f"{'method':38s} {'solves':>6s} {'wall s':>8s} {'max err mm':>11s} {'mean err mm':>12s}")
    for r in rows:
        print(f"{r['method']:38s} {r['forward_solves']:6d} {r['wall_s']:8.2f} "
              f"{r['max_error_mm']:11.4f} {r['mean_error_mm']:12.4f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"n_tets": mesh.n_tets, "sag_mm": sag, "E_kPa": args.E,
                                    "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
