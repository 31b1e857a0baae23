"""Accuracy study: our membrane skin against FEBio's shells, by shell thinning and mesh size.

Problem: the hanging hemisphere of ``../shared/febio/hemisphere/`` (radius 60 mm, flat face
held, gravity -z, rho 1000 kg/m^3, E 1 kPa, nu 0.49, standard linear tets in both codes, so
the bulk discretisation is the same) with a 0.5 mm, 10 kPa Neo-Hookean skin (plain law, no
wrinkling) on its curved face. Ours: membrane triangles (``mechanics/effects/membrane.py``).
FEBio: the writer's tri3 ``elastic-shell`` domain, written ``thinning`` times thinner and
stiffer than the skin (same E H). The writer's default is
``mechanics.effects.membrane.FEBIO_THINNING``; this script sets it per row.

Columns: tip displacement (z) of both codes and of the bare hemisphere (ours), the tip's
relative difference, the 99th percentile and the maximum of |u_FEBio - u_ours| over the nodes
relative to max |u|, and the ratio of the sag the skin removes at the tip (FEBio / ours).

    python bench/membrane_vs_febio.py                      # 20k mesh, thinning 1, 10, 100, 1000
    python bench/membrane_vs_febio.py --sizes 20k,150k --thinning 1,10,100

Measured 2026-11-23 on the 2-core machine (FEBio on 2 threads, other work beside it, so its
seconds are not a timing):

mesh  thinning  tip ours  tip FEBio  tip diff  p99 diff  worst diff  share  FEBio s
20k          1  -10.6258   -10.3507    2.59%    2.79%      3.16%   1.297     2.5
20k         10  -10.6258   -10.5772    0.46%    0.90%      1.43%   1.052     2.4
20k        100  -10.6258   -10.6028    0.22%    0.77%      1.32%   1.025     2.4
20k       1000  -10.6258   -10.6054    0.20%    0.76%      1.31%   1.022     2.4
150k         1  -11.0127   -10.7307    2.56%    2.42%      2.62%   1.267    83.2
150k        10  -11.0127   -10.9706    0.38%    0.40%      0.74%   1.040   184.7
150k       100  -11.0127   -10.9971    0.15%    0.30%      0.67%   1.015   116.7

Reading: at the skin's own thickness FEBio's shell also bends, and carries 27-30 % more of the
sag than a membrane; thinning at equal E H removes the bending (E H^3) and leaves FEBio's tri3
transverse shear (G H, unchanged by the thinning), which shrinks with refinement (worst node
1.3 % -> 0.67 %, share x 1.025 -> x 1.015 from 20k to 150k tets). Rows in
``bench/results/membrane_vs_febio.json`` (the 1000 row from a separate 20k run).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from breastmodel.febio import find_febio, shared_path, solve_with_febio  # noqa: E402
from breastmodel.reference import hemisphere_model  # noqa: E402
from mechanics.effects import membrane  # noqa: E402
from mechanics.solver import SolverOptions, solve  # noqa: E402

SKIN = {"E": 10.0, "thickness": 0.5, "wrinkling": "none"}


def rows_for(size: str, thinnings: list[float], febio, work: Path, threads: int) -> list[dict]:
    path = next((p for p in shared_path("febio", "hemisphere", f"hemi_{size}.npz")
                 if p.exists()), None)
    if path is None:
        raise SystemExit(f"membrane_vs_febio: hemi_{size}.npz not found under shared/febio")
    bare_model, tip = hemisphere_model(path, formulation="standard")
    bare = solve(bare_model, options=SolverOptions(tol=1e-10)).u
    model, _ = hemisphere_model(path, formulation="standard", skin=SKIN)
    ours = solve(model, options=SolverOptions(tol=1e-10)).u
    scale = float(np.linalg.norm(ours, axis=1).max())
    out = []
    for s in thinnings:
        membrane.FEBIO_THINNING = s
        t0 = time.perf_counter()
        run = solve_with_febio(model, work_dir=work / f"{size}_{s:g}", febio=febio,
                               element="tet4", steps=2, threads=threads)
        wall = time.perf_counter() - t0
        diff = np.linalg.norm(run.displacement - ours, axis=1)
        out.append({
            "mesh": size, "tets": int(model.mesh.n_tets), "thinning": s,
            "tip_ours_mm": float(ours[tip, 2]), "tip_febio_mm": float(run.displacement[tip, 2]),
            "tip_bare_mm": float(bare[tip, 2]),
            "tip_diff": float(np.linalg.norm(run.displacement[tip] - ours[tip])
                              / np.linalg.norm(ours[tip])),
            "p99_diff": float(np.percentile(diff, 99) / scale),
            "worst_diff": float(diff.max() / scale),
            "share_ratio": float((bare[tip, 2] - run.displacement[tip, 2])
                                 / (bare[tip, 2] - ours[tip, 2])),
            "febio_wall_s": wall, "febio_converged": bool(run.converged)})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="20k", help="hemisphere meshes, e.g. 20k,150k")
    ap.add_argument("--thinning", default="1,10,100,1000", help="shell thinning factors")
    ap.add_argument("--threads", type=int, default=2, help="FEBio threads (default 2)")
    ap.add_argument("--work", default="/tmp/membrane_vs_febio", help="FEBio work folder")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" /
                                          "membrane_vs_febio.json"))
    a = ap.parse_args(argv)
    febio = find_febio()
    thinnings = [float(v) for v in a.thinning.split(",")]
    rows = []
    print("mesh  thinning  tip ours  tip FEBio  tip diff  p99 diff  worst diff  share  FEBio s")
    for size in a.sizes.split(","):
        for r in rows_for(size, thinnings, febio, Path(a.work), a.threads):
            rows.append(r)
            print(f"{r['mesh']:5s} {r['thinning']:8g}  {r['tip_ours_mm']:8.4f}  "
                  f"{r['tip_febio_mm']:9.4f}  {r['tip_diff']:7.2%}  {r['p99_diff']:7.2%}  "
                  f"{r['worst_diff']:9.2%}  {r['share_ratio']:6.3f}  {r['febio_wall_s']:6.1f}",
                  flush=True)
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps({"skin": SKIN, "rows": rows}, indent=1) + "\n")
    print(f"rows in {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
