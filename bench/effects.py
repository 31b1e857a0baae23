"""Benchmark: the paper-like model (every effect on) on a ~20k-tet breast-like mesh.

Prints a table and writes ``bench/results/effects.json``:
- time per position (prone, supine, 45 deg tilted), load steps and Newton iterations per step;
- the cost of each effect: seconds per ``contribute`` call on this mesh, and the supine solve
  time without it (``sliding`` is replaced by ``tied``, ``supports`` by the muscle support
  only, ``strain_stiffening`` is added instead of removed).

Run: ``.venv/bin/python bench/effects.py [--cells 26,16,6,2] [--skip-ablation]
[--positions prone,supine]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent
# The repository first, tests last, bench/ not at all: bench/meshing.py and the namespace
# directory tests/meshing/ would shadow the meshing package.
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.append(str(_HERE.parent / "tests"))
from breastlike import add_mesh_arguments, bench_mesh  # noqa: E402

from mechanics.model import build_model  # noqa: E402
from mechanics.solver import SolverError, SolverOptions, solve  # noqa: E402

GRAVITY = {"supine": (0.0, 1.0, 0.0), "tilted": (np.sqrt(0.5), np.sqrt(0.5), 0.0),
           "prone": (0.0, -1.0, 0.0)}
PAPER = {"E_left": 0.2, "E_right": 0.3, "skin": 4.0, "fascia": 120.0, "friction": 0.1,
         "skin_lateral": False, "path_steps": 1}


def effects_config(position: str) -> dict:
    return {
        "gravity": {"direction": GRAVITY[position]},
        "supports": {"skin_lateral": PAPER["skin_lateral"]},
        "skin": {"E": PAPER["skin"]},
        "fascia": {"E": PAPER["fascia"]},
        "ligaments": {"E": 100.0},
        "sliding": {"friction": PAPER["friction"], "path_steps": PAPER["path_steps"]},
        "regions": {"E_left": PAPER["E_left"], "E_right": PAPER["E_right"], "gland": False},
    }


def materials() -> dict:
    mats = {r: {"name": "neo_hookean", "E": 0.3, "nu": 0.49} for r in (1, 3, 4, 5)}
    mats[2] = {"name": "neo_hookean", "E": 10.0, "nu": 0.49}
    return mats


def timed_solve(mesh, effects, options) -> dict:
    """Wall and CPU seconds of one solve, with the 1-min load average before and after it
    (the machine is shared: CPU time is the figure to compare)."""
    model = build_model(mesh, materials(), effects)
    load_before = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        st = solve(model, options=options)
    except SolverError as exc:
        return {"converged": False, "seconds": time.perf_counter() - t0,
                "cpu_seconds": time.process_time() - c0, "error": str(exc),
                "load_average_before": load_before, "load_average": os.getloadavg()[0],
                "load": None if exc.state is None else float(exc.state.load)}
    steps = [e for e in st.log if e["converged"]]
    return {
        "converged": True,
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
        "load_average_before": load_before,
        "load_average": os.getloadavg()[0],
        "load_steps": len(steps),
        "newton_per_step": [e["newton"] for e in steps],
        "newton_total": st.newton_iterations,
        "cutbacks": sum(1 for e in st.log if not e["converged"]),
        "max_displacement_mm": st.max_displacement(),
        **{k: v for k, v in st.stats.items() if k.startswith(("t_", "cpu_"))},
        "factorizations": st.stats["factorizations"], "threads": st.stats["threads"],
        "peak_rss_mb": st.stats["peak_rss_mb"],
    }


def contribute_seconds(mesh, effects, repeat=5) -> dict:
    """Median CPU seconds of one ``contribute`` call of each effect at a deformed state (the
    sliding effect's includes summing its tangent blocks, which the solver no longer does)."""
    model = build_model(mesh, materials(), effects)
    X = mesh.nodes
    x = X + 0.5 * np.sin(X / 20.0)
    out = {}
    for eff in model.effects:
        eff.begin_step(X, x)
        ts = []
        for _ in range(repeat):
            t0 = time.process_time()
            eff.contribute(X, x, 1.0)
            ts.append(time.process_time() - t0)
        out[eff.name] = float(np.median(ts))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default="26,16,6,2", help="nx,nz,breast layers,muscle layers")
    ap.add_argument("--skip-ablation", action="store_true", help="only the three positions")
    ap.add_argument("--breast", type=float, default=None,
                    help="breast E for both sides, kPa (default: the paper's 0.2 left, 0.3 right)")
    ap.add_argument("--skin", type=float, default=PAPER["skin"], help="skin E, kPa")
    ap.add_argument("--fascia", type=float, default=PAPER["fascia"], help="fascia E, kPa")
    ap.add_argument("--friction", type=float, default=0.1, help="Coulomb coefficient k")
    ap.add_argument("--path-steps", type=int, default=1,
                    help="load steps of the friction path (sliding option path_steps)")
    ap.add_argument("--positions", default=",".join(GRAVITY), help="comma-separated positions")
    add_mesh_arguments(ap, phantom_size=4.3)  # 4.3 mm: ~20k tets
    ap.add_argument("--skin-lateral", action="store_true",
                    help="hold the skin's lateral cut too (supports option skin_lateral): on "
                         "this flat slab nothing else holds the breast sideways")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "effects.json"))
    args = ap.parse_args()
    cells = tuple(int(c) for c in args.cells.split(","))
    if args.breast is not None:
        PAPER["E_left"] = PAPER["E_right"] = args.breast
    PAPER["skin"], PAPER["fascia"], PAPER["friction"] = args.skin, args.fascia, args.friction
    PAPER["skin_lateral"] = args.skin_lateral
    PAPER["path_steps"] = args.path_steps
    mesh, source = bench_mesh(cells, args.phantom_mesh, args.phantom_size)
    options = SolverOptions()
    result = {
        "mesh": {**source, "tets": mesh.n_tets, "nodes": mesh.n_nodes,
                 "skin_triangles": len(mesh.face_sets["skin"]),
                 "interface_triangles": len(mesh.face_sets["interface"])},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "parameters": PAPER,
        "positions": {},
        "contribute_seconds": contribute_seconds(mesh, effects_config("supine")),
        "ablation_supine": {},
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    def save():  # after every solve, so that an interrupted run keeps what it measured
        tmp = out.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(result, indent=2, default=float))
        tmp.replace(out)

    print(f"mesh: {mesh.n_tets} tets, {mesh.n_nodes} nodes")
    print(f"{'position':<10}{'s':>8}{'cpu s':>8}{'load':>6}{'steps':>7}{'newton/step':>40}"
          f"{'max u mm':>10}")
    for pos in args.positions.split(","):
        r = timed_solve(mesh, effects_config(pos), options)
        result["positions"][pos] = r
        save()
        if r["converged"]:
            print(f"{pos:<10}{r['seconds']:8.1f}{r['cpu_seconds']:8.1f}{r['load_average']:6.2f}"
                  f"{r['load_steps']:7d}{str(r['newton_per_step']):>40}"
                  f"{r['max_displacement_mm']:10.1f}  ({r['newton_total']} Newton iterations, "
                  f"{r['cutbacks']} cut-backs)", flush=True)
        else:
            print(f"{pos:<10}{r['seconds']:8.1f}  FAILED: {r['error'][:80]}")
    print("\ncost of one contribute() call (s):")
    for k, v in result["contribute_seconds"].items():
        print(f"  {k:<18}{v:8.3f}")
    if not args.skip_ablation:
        base = result["positions"]["supine"]
        print(f"\nsupine solve without each effect (all effects: {base['seconds']:.1f} s)")
        variants = {
            "skin": {"skin": None},
            "fascia": {"fascia": None},
            "ligaments": {"ligaments": None},
            "sliding (-> tied)": {"sliding": None, "tied": {}},
            "sliding friction (k=0)": {"sliding": {"friction": 0.0}},
            "supports (-> muscle only)": {"supports": {"skin_ends": False, "fascia_ends": False}},
            "regions": {"regions": None},
            "+strain_stiffening": {"strain_stiffening": {"Jm": 10.0}},
        }
        for label, change in variants.items():
            eff = effects_config("supine")
            for k, v in change.items():
                if v is None:
                    eff.pop(k)
                else:
                    eff[k] = v
            r = timed_solve(mesh, eff, options)
            result["ablation_supine"][label] = r
            save()
            state = f"{r['seconds']:8.1f} s, {r.get('newton_total', '-')} Newton" \
                if r["converged"] else f"FAILED after {r['seconds']:.1f} s"
            print(f"  {label:<28}{state}", flush=True)
    save()
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
