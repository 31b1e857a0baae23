"""Benchmark: does the paper-like model converge over the paper's parameter search box?

Corners and centre of the box (breast 0.1-4 kPa, skin 1-20 kPa, fascia 80-250 kPa) in
prone, supine and 45 deg tilted gravity, every effect on (sliding with Coulomb friction).
Prints a table and writes ``bench/results/effects_box.json``: per point converged or not,
load reached, Newton iterations, cut-backs, seconds, max displacement, and the convergence
rate over the points run.

Run: ``.venv/bin/python bench/effects_box.py [--cells 8,6,3,2] [--positions prone,tilted]
[--points 0,1,8] [--max-cutbacks 8] [--sliding '{"pressure_smoothing": 0.01}']
[--changes '{"ligaments": {"E": 100, "area": 10}}'] [--out bench/results/effects_box_X.json]``

``--changes`` replaces effect tables of the paper-like model (tests/breastlike.py
``paper_model``). With the paper's supports the tilted position has no equilibrium on this
flat muscle slab: nothing but friction and the ligament cables holds the breast sideways
(the fascia ends are fixed in z, the skin ends in y), and the budget printed first shows the
cables would need a mean strain of 176 % even if all pulled along x; the breast slides off
the 200 mm slab first. ``--changes '{"supports": {"skin_lateral": true}}'`` holds the skin's
lateral cut as well (the skin sleeve around a torso): ``bench/results/effects_box_skin_lateral
.json``. ``--phantom-mesh bench/results/phantom_small_8mm.npz`` runs the box with the paper's
supports on a meshed phantom whose chest wall curves round the torso:
``bench/results/effects_box_phantom.json``.

``--suite-mesh`` runs the box on pipeline meshes of the validation suite's subjects
(``bench/results/suite_meshes``: small-000, -001, -002, -003 meshed by the meshing stage
from their truth label maps, small-003 also from its own segmentation, and
``truth_17k.npz``, small-003's 5 mm truth mesh): every point ends converged, or with a
"no equilibrium" verdict and its force budget (``mechanics.solver.NoEquilibrium``), or
stalled (a numerical failure: the target is none). ``--points best,0`` on ``truth_17k.npz``
times the softest corner against the paper's best moduli (target: <= 3x). Results:
``bench/results/effects_box_suite.json``, ``bench/results/effects_box_speed_17k.json``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import sys
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
# The repository first, tests last, bench/ not at all: bench/meshing.py and the namespace
# directory tests/meshing/ would shadow the meshing package.
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.append(str(_HERE.parent / "tests"))
import numpy as np  # noqa: E402
from breastlike import add_mesh_arguments, bench_mesh, paper_model  # noqa: E402

from mechanics.mesh import REGIONS  # noqa: E402
from mechanics.solver import SolverError, SolverOptions, solve  # noqa: E402

#: (breast E, skin E, fascia E) kPa: the 8 corners and the centre of the paper's search box.
BOX = list(itertools.product((0.1, 4.0), (1.0, 20.0), (80.0, 250.0))) + [(2.05, 10.5, 165.0)]
#: The paper's best moduli (its supine match): breast 0.3 kPa right, 0.2 kPa left (mean
#: 0.25), skin 4 kPa, fascia 120 kPa; ``--points best`` (the speed target compares the
#: softest corner, point 0, with it).
BEST = (0.25, 4.0, 120.0)
BEST_REGIONS = {"E_left": 0.2, "E_right": 0.3, "gland": False}


def run_point(mesh, point, position, sliding, options, changes=None, anatomy=None) -> dict:
    E_b, E_s, E_f = point
    row = {"anatomy": anatomy, "E_breast": E_b, "E_skin": E_s, "E_fascia": E_f,
           "position": position}
    model = paper_model(mesh, E_b, E_s, E_f, position, sliding=sliding, **(changes or {}))
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        st = solve(model, options=options)
        error = None
    except SolverError as exc:
        st, error = exc.state, str(exc)
        row["verdict"] = getattr(exc, "verdict", None)
    row["seconds"] = time.perf_counter() - t0
    row["cpu_seconds"] = time.process_time() - c0
    row["load_average"] = os.getloadavg()[0]
    row["converged"] = error is None
    # converged, a physical verdict ("no equilibrium" with its force budget), or stalled
    row["outcome"] = "converged" if error is None else (
        "no equilibrium" if row.get("verdict") else "stalled")
    if st is not None and error is None:
        row["convergence"] = st.stats.get("convergence")
    row["error"] = error
    if st is not None:
        row["load"] = float(st.load) if error is not None else 1.0
        # with predictor "auto", a path abandoned for the extrapolation's counts too
        abandoned = st.stats.get("abandoned_path")
        row["abandoned_path"] = abandoned
        row["newton_total"] = int(sum(e["newton"] for e in st.log)) + \
            (abandoned["newton"] if abandoned else 0)
        row["newton_converged_steps"] = [e["newton"] for e in st.log if e["converged"]]
        row["cutbacks"] = sum(1 for e in st.log if not e["converged"])
        row["max_displacement_mm"] = float(st.max_displacement())
    else:
        row.update(load=0.0, newton_total=None, cutbacks=None, max_displacement_mm=None)
    return row


def suite_mesh(path):
    """A pipeline mesh (.npz of :class:`mechanics.mesh.Mesh`) with its interface split."""
    from mechanics.effects._interface import split_interface
    from mechanics.mesh import Mesh

    return split_interface(Mesh.load_npz(path)), {"suite_mesh": str(path)}


def sideways_budget(mesh, changes) -> dict:
    """Force balance of the tilted position: the sideways weight of the breast, what Coulomb
    friction can carry at most (k times the weight's normal part), and the mean strain the
    ligament cables would need to carry the rest if every one pulled along x (mN)."""
    model = paper_model(mesh, *BOX[-1], "tilted", **(changes or {}))
    eff = {e.name: e for e in model.effects}
    weight = eff["gravity"].nodal_weight(mesh.nodes)
    breast = np.unique(mesh.tets[mesh.region != REGIONS["muscle"]])
    sideways, normal = (abs(float(weight[breast, i].sum())) for i in (0, 1))
    friction = float(eff["sliding"].values.get("friction", 0.0)) * normal if "sliding" in eff \
        else 0.0
    lig = eff.get("ligaments")
    EA = 0.0 if lig is None else float(lig.E.sum()) * lig.values["area"]
    return {"sideways_weight_mN": sideways, "friction_capacity_mN": friction,
            "cables": 0 if lig is None else len(lig.pairs), "cables_EA_total_mN": EA,
            "cable_strain_needed": (sideways - friction) / EA if EA else None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default="12,8,4,2",
                    help="nx,nz,breast layers,muscle layers of breastlike_mesh (12,8,4,2: ~4k "
                         "tets; 8,6,3,2: ~1.4k)")
    ap.add_argument("--positions", default="prone,supine,tilted")
    ap.add_argument("--points", default=None,
                    help="comma-separated indices into the 9 box points (default all); "
                         "'best': the paper's best moduli")
    ap.add_argument("--max-newton", type=int, default=30)
    ap.add_argument("--max-cutbacks", type=int, default=12,
                    help="cut-backs allowed per solve (bounds the time of a failing point)")
    ap.add_argument("--sliding", default='{"friction": 0.1}',
                    help="JSON parameters of the sliding effect")
    ap.add_argument("--changes", default="{}",
                    help="JSON: effect tables of the paper-like model to replace")
    ap.add_argument("--stagnate-after", type=int, default=SolverOptions.stagnate_after,
                    help="SolverOptions.stagnate_after (0: no early cut-back)")
    ap.add_argument("--predictor", default=SolverOptions.predictor,
                    help="SolverOptions.predictor ('secant' or 'converged')")
    ap.add_argument("--first-inversion-shrink", type=float,
                    default=SolverOptions.first_inversion_shrink,
                    help="SolverOptions.first_inversion_shrink (0: off)")
    ap.add_argument("--initial-steps", type=int, default=SolverOptions.initial_steps,
                    help="SolverOptions.initial_steps (the pipeline's run.toml: 2)")
    add_mesh_arguments(ap, phantom_size=8.0)
    ap.add_argument("--suite-mesh", default=None,
                    help="comma-separated Mesh .npz files made by the pipeline's meshing stage "
                         "from suite subjects' label maps (bench/results/suite_meshes/); the "
                         "box runs on each in turn")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "effects_box.json"))
    args = ap.parse_args()
    cells = tuple(int(c) for c in args.cells.split(","))
    positions = args.positions.split(",")
    idx = range(len(BOX)) if args.points is None else [
        "best" if i == "best" else int(i) for i in args.points.split(",")]
    sliding = json.loads(args.sliding)
    changes = json.loads(args.changes)
    options = SolverOptions(max_newton=args.max_newton, max_cutbacks=args.max_cutbacks,
                            stagnate_after=args.stagnate_after, predictor=args.predictor,
                            first_inversion_shrink=args.first_inversion_shrink,
                            initial_steps=args.initial_steps)
    if args.suite_mesh:
        meshes = [(Path(p).stem, *suite_mesh(p)) for p in args.suite_mesh.split(",")]
    else:
        meshes = [("mesh", *bench_mesh(cells, args.phantom_mesh, args.phantom_size))]
    result = {
        "meshes": {name: {**source, "tets": mesh.n_tets, "nodes": mesh.n_nodes}
                   for name, mesh, source in meshes},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "sliding": sliding,
        "changes": changes,
        "solver": {"max_newton": args.max_newton, "max_cutbacks": args.max_cutbacks,
                   "stagnate_after": args.stagnate_after,
                   "singular_shift": SolverOptions.singular_shift,
                   "predictor": args.predictor,
                   "first_inversion_shrink": args.first_inversion_shrink,
                   "initial_steps": args.initial_steps},
        "points": [],
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    for name, mesh, _ in meshes:
        if "tilted" in positions:
            result.setdefault("tilted_budget", {})[name] = budget = sideways_budget(mesh,
                                                                                    changes)
            print(f"{name} tilted: sideways weight {budget['sideways_weight_mN']:.0f} mN, "
                  f"friction carries at most {budget['friction_capacity_mN']:.0f} mN, "
                  f"{budget['cables']} cables of total EA {budget['cables_EA_total_mN']:.0f} mN")
        print(f"{name}: {mesh.n_tets} tets, sliding {sliding}")
        print(f"{'anatomy':>20} {'breast':>6} {'skin':>5} {'fascia':>6} {'position':>8} "
              f"{'outcome':>14} {'load':>6} {'newton':>6} {'cuts':>4} {'u_max':>7} {'s':>6} "
              f"{'cpu_s':>6}")
        for i in idx:
            for position in positions:
                if i == "best":
                    row = run_point(mesh, BEST, position, sliding, options,
                                    {"regions": BEST_REGIONS, **changes}, name)
                    row["point"] = "paper's best"
                else:
                    row = run_point(mesh, BOX[i], position, sliding, options, changes, name)
                    row["point"] = i
                result["points"].append(row)
                ok = result["points"]
                result["converged"] = sum(r["converged"] for r in ok)
                result["verdicts"] = sum(r["outcome"] == "no equilibrium" for r in ok)
                result["stalled"] = sum(r["outcome"] == "stalled" for r in ok)
                result["rate"] = result["converged"] / len(ok)
                tmp = out.with_suffix(".json.tmp")  # after every point: a killed run keeps it
                tmp.write_text(json.dumps(result, indent=1))
                tmp.replace(out)
                print(f"{name:>20} {row['E_breast']:6.2f} {row['E_skin']:5.1f} "
                      f"{row['E_fascia']:6.1f} {position:>8} {row['outcome']:>14} "
                      f"{row['load']:6.3f} {row['newton_total'] or 0:6d} "
                      f"{row['cutbacks'] or 0:4d} {row['max_displacement_mm'] or 0:7.2f} "
                      f"{row['seconds']:6.1f} {row['cpu_seconds']:6.1f}", flush=True)
                if row["outcome"] != "converged":
                    print(f"{'':>20} {row['error']}", flush=True)
    rows = result["points"]
    for name, _, _ in meshes:  # the speed target: softest corner against the paper's best
        for position in positions:
            best = [r for r in rows if r["anatomy"] == name and r["position"] == position
                    and r["point"] == "paper's best" and r["converged"]]
            soft = [r for r in rows if r["anatomy"] == name and r["position"] == position
                    and r["point"] == 0 and r["converged"]]
            if best and soft:
                ratio = soft[0]["cpu_seconds"] / best[0]["cpu_seconds"]
                result.setdefault("softest_over_best_cpu", {}).setdefault(name, {})[
                    position] = ratio
                print(f"{name} {position}: softest corner {soft[0]['cpu_seconds']:.1f} CPU s, "
                      f"paper's best {best[0]['cpu_seconds']:.1f} CPU s: ratio {ratio:.2f}")
    out.write_text(json.dumps(result, indent=1))
    print(f"converged {result['converged']} / {len(result['points'])} "
          f"(rate {result['rate']:.2f}), no equilibrium {result['verdicts']}, "
          f"stalled {result['stalled']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
