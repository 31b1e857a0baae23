"""Benchmark: the load stepping's predictor and its cut-back after a first Newton direction
that inverts an element, on the paper's softest moduli (issue 20).

Runs the paper-like model (``tests/breastlike.paper_model``: skin, fascia, ligaments,
sliding with friction 0.1) on pipeline meshes of suite subjects (``bench/results/
suite_meshes/``) at points of the paper's box that take several load steps, in four solver
configurations, each on the same cases in one run:

- ``auto``: each step starts from whichever of the two below leaves the
  smaller residual; a path that ends without equilibrium is solved once more from the
  extrapolation;
- ``secant``: the step's first iterate extrapolated from the last two converged states
  (``predictor = "secant"``, the default) and a failing step halved;
- ``converged``: the first iterate is the last converged state (``predictor =
  "converged"``; a step that fails from there is tried once more from the extrapolation
  before it is cut back);
- ``first cut``: that, and a first step from rest whose first Newton direction inverts an
  element unless scaled by eta is cut back at once to eta / 2 of the load
  (``first_inversion_shrink = 0.5``).

Then the paper's best moduli on the 17k-tet mesh in every position with the pipeline's
``[solver]`` (two initial load steps), where the predictor matters most.

Prints a table (Newton iterations, cut-backs, wall and CPU seconds per case) and the
softest corner's time over the paper's best moduli on the 17k-tet mesh, and writes JSON.

    python bench/step_control.py [--out bench/results/step_control.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

_HERE = Path(__file__).resolve().parent
# The repository first, tests last, bench/ not at all (bench/meshing.py would shadow the
# meshing package); effects_box is loaded from its path.
sys.path[:] = [str(_HERE.parent)] + [p for p in sys.path if Path(p or ".").resolve() != _HERE]
sys.path.append(str(_HERE.parent / "tests"))

from mechanics.solver import SolverOptions  # noqa: E402

MESHES = _HERE / "results" / "suite_meshes"
#: (mesh, box point (index into effects_box.BOX, or "best"), position)
CASES = [("small-000_labels", 0, "prone"), ("small-000_labels", 2, "prone"),
         ("small-000_labels", 3, "prone"), ("small-000_labels", 0, "tilted"),
         ("small-003_labels", 0, "prone"), ("small-003_labels", 0, "supine"),
         ("small-003_labels", 1, "tilted"), ("small-003_labels", 2, "prone"),
         ("truth_17k", "best", "prone"), ("truth_17k", 0, "prone")]
#: The same, with the pipeline's ``[solver]`` (``breastmodel.pipeline.config``: two initial
#: load steps, tolerance 1e-6): the paper's best moduli in every position.
PIPELINE_CASES = [("truth_17k", "best", p) for p in ("prone", "supine", "tilted")]
CONFIGS = {"auto": {"predictor": "auto"}, "secant": {"predictor": "secant"},
           "converged": {"predictor": "converged"},
           "first cut": {"predictor": "converged", "first_inversion_shrink": 0.5}}


def _effects_box():
    import importlib.util

    spec = importlib.util.spec_from_file_location("effects_box", _HERE / "effects_box.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(_HERE / "results" / "step_control.json"))
    args = ap.parse_args()
    box = _effects_box()
    meshes = {name: box.suite_mesh(MESHES / f"{name}.npz")[0] for name in {c[0] for c in CASES}}
    rows = []
    print(f"{'mesh':>17} {'point':>5} {'position':>8} {'config':>9} {'outcome':>14} "
          f"{'init':>4} {'newton':>6} {'cuts':>4} {'s':>6} {'cpu_s':>6}")
    from breastmodel.pipeline.config import DEFAULTS

    cases = [(c, {"max_newton": 30, "max_cutbacks": 12}) for c in CASES] + \
        [(c, dict(DEFAULTS["solver"])) for c in PIPELINE_CASES]
    for (name, point, position), solver in cases:
        for config, changes in CONFIGS.items():
            opts = SolverOptions(**{**solver, **changes})
            moduli = box.BEST if point == "best" else box.BOX[point]
            row = box.run_point(meshes[name], moduli, position, {"friction": 0.1}, opts,
                                anatomy=name)
            row.update(point=point, config=config, tets=meshes[name].n_tets,
                       solver=solver)
            rows.append(row)
            print(f"{name:>17} {point!s:>5} {position:>8} {config:>9} {row['outcome']:>14} "
                  f"{opts.initial_steps:>4} {row['newton_total']!s:>6} {row['cutbacks']!s:>4} "
                  f"{row['seconds']:6.1f} {row['cpu_seconds']:6.1f}", flush=True)
    summary = {}
    for config in CONFIGS:
        mine = [r for r in rows if r["config"] == config]
        soft = next(r for r in mine if r["anatomy"] == "truth_17k" and r["point"] == 0)
        best = next(r for r in mine if r["anatomy"] == "truth_17k" and r["point"] == "best"
                    and r["solver"].get("initial_steps", 1) == 1)
        summary[config] = {"newton_total": sum(r["newton_total"] or 0 for r in mine),
                           "cutbacks": sum(r["cutbacks"] or 0 for r in mine),
                           "converged": sum(r["converged"] for r in mine),
                           "softest_over_best_cpu_17k": soft["cpu_seconds"] / best["cpu_seconds"]}
        print(f"{config:>9}: {summary[config]['converged']}/{len(mine)} converged, "
              f"{summary[config]['newton_total']} Newton iterations, "
              f"{summary[config]['cutbacks']} cut-backs; 17k prone softest / best CPU "
              f"{summary[config]['softest_over_best_cpu_17k']:.2f}")
    out = {"machine": {"cpus": len(os.sched_getaffinity(0)),
                       "python": platform.python_version()},
           "configs": CONFIGS, "summary": summary, "rows": rows}
    Path(args.out).write_text(json.dumps(out, indent=1, default=str))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
