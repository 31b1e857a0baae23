"""Subject pipeline: fitting accuracy and cost, grid vs optimiser, dask scaling, run time.

1. A small phantom (2 mm voxels) goes through the cached preparation stages (truth label
   maps, registration, 12 mm mesh, measured skins).
2. Synthetic measurements with a known modulus: the stress-free geometry of the truth model
   (both breasts E_true) is solved from the reference, every other position is simulated
   from it, and its predicted skin replaces the measured one. The reference keeps its mesh.
3. The paper's breast-modulus grid (0.1-4 kPa step 0.1, both breasts tied) on a local dask
   cluster with 2 workers, then the bounded optimiser: recovered modulus, MHD on the
   calibration (prone, supine) and held-out (supine_tilted) positions, simulations used.
4. Dask scaling: the same points with 1 and 2 workers (points per second).
5. Optionally (``--full-run``) ``breastmodel run`` on a 1 mm phantom with real segmentation.

    python bench/pipeline.py [--work /tmp/bench_pipeline] [--E 0.6] [--full-run]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from breastmodel.config import write_json  # noqa: E402
from breastmodel.pipeline import fit as fitmod  # noqa: E402
from breastmodel.pipeline import prepare_subject, resolve_config  # noqa: E402
from breastmodel.pipeline.config import set_params  # noqa: E402
from breastmodel.pipeline.problem import load_problem  # noqa: E402
from breastmodel.pipeline.synthetic import synthetic_problem  # noqa: E402

TIED = "materials.breast_left.E|materials.breast_right.E"


def _config(truth: Path) -> dict:
    return resolve_config({
        "segment": {"labels": str(truth)},
        "register": {"shrink": [2, 1], "smooth_mm": [2.0, 0.0], "iterations": 30},
        "mesh": {"size_mm": 12.0},
        "surface": {"edge_mm": 4.0},
        "stress_free": {"tol_mm": 0.1, "max_iter": 15},
        "fit": {"calibrate": ["prone", "supine"], "evaluate": ["supine_tilted"],
                "parameters": {TIED: {"min": 0.1, "max": 4.0, "step": 0.1}}},
    })


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_pipeline"))
    ap.add_argument("--E", type=float, default=0.6, help="truth breast modulus, kPa")
    ap.add_argument("--budget", type=int, default=100)
    ap.add_argument("--scaling-points", type=int, default=6)
    ap.add_argument("--full-run", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("bench/results/pipeline.json"))
    args = ap.parse_args()
    from breastmodel.phantom import make_phantom

    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    results: dict = {"E_true_kPa": args.E}
    subj = make_phantom(work / "subject", seed=5, small=True, voxel_size=2.0, progress=False)
    cfg = _config(Path(str(subj) + "_truth"))
    t0 = time.perf_counter()
    prep = prepare_subject(subj, cfg, work / "run", progress=True)
    results["prepare_s"] = time.perf_counter() - t0
    prob = load_problem(prep.problem_dir)
    results["mesh"] = {"n_nodes": prob.mesh.n_nodes, "n_tets": prob.mesh.n_tets}
    synth = synthetic_problem(prep.problem_dir, work / "synthetic_problem",
                              set_params(cfg["model"], {TIED: args.E}), cfg["stress_free"],
                              cfg["solver"])
    settings = {"model": cfg["model"], "solver": cfg["solver"],
                "stress_free": cfg["stress_free"], "calibrate": ["prone", "supine"],
                "evaluate": ["supine_tilted"]}
    params = cfg["fit"]["parameters"]

    # optimiser
    t0 = time.perf_counter()
    opt = fitmod.optimise(synth, settings, params, budget=args.budget,
                          work_dir=work / "fit_opt", progress=True)
    opt_s = time.perf_counter() - t0
    E_opt = opt["best"]["params"][TIED]
    results["optimizer"] = {
        "E_kPa": E_opt, "rel_error": E_opt / args.E - 1, "mhd_mm": opt["best"]["mhd_mm"],
        "objective_mm": opt["best"]["objective"], "simulations": opt["n_simulations"],
        "failed": opt["n_failed"], "forward_solves": opt["forward_solves"], "wall_s": opt_s}

    # least squares on the skin residual
    t0 = time.perf_counter()
    lsq = fitmod.least_squares(synth, settings, params, budget=args.budget,
                               work_dir=work / "fit_lsq", progress=True)
    E_lsq = lsq["best"]["params"][TIED]
    results["least_squares"] = {
        "E_kPa": E_lsq, "rel_error": E_lsq / args.E - 1, "mhd_mm": lsq["best"]["mhd_mm"],
        "objective_mm": lsq["best"]["objective"], "simulations": lsq["n_simulations"],
        "failed": lsq["n_failed"], "forward_solves": lsq["forward_solves"],
        "wall_s": time.perf_counter() - t0, "termination": lsq["termination"]}

    # the paper's grid on 2 dask workers
    shutil.rmtree(work / "fit_grid", ignore_errors=True)
    t0 = time.perf_counter()
    grid = fitmod.grid_search(synth, settings, params, work_dir=work / "fit_grid",
                              n_workers=2, progress=False)
    grid_s = time.perf_counter() - t0
    E_grid = grid["best"]["params"][TIED]
    results["grid"] = {
        "E_kPa": E_grid, "rel_error": E_grid / args.E - 1, "mhd_mm": grid["best"]["mhd_mm"],
        "objective_mm": grid["best"]["objective"], "points": grid["n_simulations"],
        "failed": grid["n_failed"], "forward_solves": grid["forward_solves"],
        "wall_s": grid_s, "curve": [(h["params"][TIED], h["objective"])
                                    for h in grid["history"]]}
    results["optimizer_vs_grid_objective"] = (opt["best"]["objective"]
                                              / grid["best"]["objective"])
    results["least_squares_vs_grid_objective"] = (lsq["best"]["objective"]
                                                  / grid["best"]["objective"])

    # dask scaling on the same few points
    pts = {TIED: {"values": [round(0.5 + 0.1 * i, 1) for i in range(args.scaling_points)]}}
    scaling = {}
    for n in (1, 2):
        shutil.rmtree(work / f"scale{n}", ignore_errors=True)
        t0 = time.perf_counter()
        fitmod.grid_search(synth, settings, pts, work_dir=work / f"scale{n}", n_workers=n,
                           progress=False)
        scaling[n] = time.perf_counter() - t0
    results["dask_scaling"] = {"points": args.scaling_points, "wall_s_1_worker": scaling[1],
                               "wall_s_2_workers": scaling[2],
                               "speedup": scaling[1] / scaling[2]}

    # score the held-out position with the optimiser's modulus on real (non-synthetic) data
    if args.full_run:
        from breastmodel.pipeline import run_subject

        full = make_phantom(work / "subject1mm", seed=0, small=True, progress=False)
        t0 = time.perf_counter()
        res = run_subject(full, resolve_config({"mesh": {"size_mm": 8.0}}), work / "run1mm")
        results["full_run"] = {"wall_s": time.perf_counter() - t0,
                               "stages": res["stages"],
                               "mhd_mm": {p: m["mhd_mm"] for p, m in
                                          res["metrics"]["positions"].items()}}

    o, g, q = results["optimizer"], results["grid"], results["least_squares"]
    print(f"\nmesh {prob.mesh.n_tets} tets; truth E = {args.E} kPa (both breasts)")
    print(f"{'method':10s} {'E kPa':>7s} {'rel err':>8s} {'sims':>5s} {'fail':>5s} "
          f"{'obj mm':>8s} {'prone':>7s} {'supine':>7s} {'tilted':>7s} {'wall s':>7s}")
    for name, r, n in (("optimizer", o, o["simulations"]), ("lsq", q, q["simulations"]),
                       ("grid", g, g["points"])):
        m = r["mhd_mm"]
        print(f"{name:10s} {r['E_kPa']:7.3f} {r['rel_error']:8.3f} {n:5d} {r['failed']:5d} "
              f"{r['objective_mm']:8.4f} {m.get('prone', np.nan):7.3f} "
              f"{m.get('supine', np.nan):7.3f} {m.get('supine_tilted', np.nan):7.3f} "
              f"{r['wall_s']:7.1f}")
    s = results["dask_scaling"]
    print(f"dask: {s['points']} points, 1 worker {s['wall_s_1_worker']:.1f} s, 2 workers "
          f"{s['wall_s_2_workers']:.1f} s, speedup {s['speedup']:.2f}")
    if "full_run" in results:
        print(f"breastmodel run (1 mm phantom, real segmentation): "
              f"{results['full_run']['wall_s']:.0f} s; MHD {results['full_run']['mhd_mm']}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, results)


if __name__ == "__main__":
    main()
