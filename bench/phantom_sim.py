"""Benchmark: a phantom deformed by simulated gravity, time per stage (voxelise the
stress-free anatomy, mesh it, solve each position, render every position) and the
displacements obtained (maximum over the mesh nodes, and at the nipples).

Usage: .venv/bin/python bench/phantom_sim.py [--size 6] [--voxel 1] [--mesh-voxel V]
       [--small] [--preset default] [--positions prone,supine,supine_tilted]
Prints a table and writes bench/results/phantom_sim.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=float, default=6.0, help="truth mesh size, mm")
    ap.add_argument("--voxel", type=float, default=1.0, help="phantom voxel size, mm")
    ap.add_argument("--mesh-voxel", type=float, default=None, help="voxel of the meshed labels")
    ap.add_argument("--small", action="store_true", help="half-size anatomy")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--positions", default="prone,supine,supine_tilted")
    ap.add_argument("--out", type=Path, default=_HERE / "results" / "phantom_sim.json")
    args = ap.parse_args(argv)

    from breastmodel.phantom import Anatomy
    from breastmodel.phantom.simulated import make_simulated_phantom
    from breastmodel.phantom.truth_model import preset

    anatomy = Anatomy.small() if args.small else Anatomy()
    tm = replace(preset(args.preset), mesh_size_mm=args.size)
    positions = [p for p in args.positions.split(",") if p]
    tmp = Path(tempfile.mkdtemp(prefix="bench_phantom_sim_"))
    timings: dict = {}
    t0 = time.perf_counter()
    out = make_simulated_phantom(tmp / "s", seed=0, truth_model=tm, anatomy=anatomy,
                                 positions=positions, voxel_size=args.voxel,
                                 mesh_voxel_size=args.mesh_voxel, progress=False,
                                 timings=timings)
    total = time.perf_counter() - t0
    truth = Path(f"{out}_truth")
    doc = json.loads((truth / "truth_model.json").read_text())
    tj = json.loads((truth / "truth.json").read_text())
    from mechanics.mesh import Mesh

    mesh = Mesh.load_npz(truth / "stress_free_mesh.npz")
    nip = {k: v for k, v in anatomy.landmarks().items() if k.startswith("nipple")}
    disp = {}
    for p in positions:
        u = np.load(truth / f"{p}_displacement.npy")
        row = {"max_mm": float(np.linalg.norm(u, axis=1).max())}
        for k, X in nip.items():
            # motion is rigid per position; compare in the patient frame via the solved field
            i = int(np.argmin(np.linalg.norm(mesh.nodes - X, axis=1)))
            row[f"{k}_mm"] = float(np.linalg.norm(u[i]))
        row["solve"] = doc["solves"][p]
        disp[p] = row
    result = {
        "anatomy": "small" if args.small else "default", "preset": args.preset,
        "mesh_size_mm": args.size, "voxel_mm": args.voxel, "mesh_voxel_mm": args.mesh_voxel,
        "n_nodes": mesh.n_nodes, "n_tets": mesh.n_tets, "timings_s": timings,
        "total_s": total, "displacement": disp,
        "tissue_volumes_mm3": {p: tj["positions"][p]["tissue_volumes_mm3"] for p in positions},
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "machine": platform.platform(), "python": platform.python_version(),
    }
    print(f"phantom_sim: {result['anatomy']} anatomy, mesh {args.size} mm "
          f"({mesh.n_tets} tets, {mesh.n_nodes} nodes), voxel {args.voxel} mm")
    print(f"{'stage':<24}{'time s':>10}")
    for k, v in timings.items():
        print(f"{k:<24}{v:>10.1f}")
    print(f"{'total':<24}{total:>10.1f}")
    print(f"{'position':<16}{'max |u| mm':>12}{'nipple L mm':>13}{'nipple R mm':>13}"
          f"{'newton':>8}")
    for p, r in disp.items():
        print(f"{p:<16}{r['max_mm']:>12.1f}{r['nipple_left_mm']:>13.1f}"
              f"{r['nipple_right_mm']:>13.1f}{r['solve']['newton_iterations']:>8d}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
