"""``breastmodel demo``: the toolkit's story on a phantom with a hidden effect.

The shipped subject (``breastmodel/demo_data``, a small phantom whose deformation FEBio
computed on its own mesh) has different moduli in its left and right breast. The demo fits
the bulk model (one breast modulus) and predicts every position (run 1), the report shows
where it fails, ``diagnose`` ranks the missing effects, the best candidate is switched on and
fitted (run 2, the same segmentation, registration and mesh), and ``compare`` shows the error
fall. It prints the MHD per position before and after and the path of ``OUT/index.html``,
one page that links and embeds the reports, the diagnosis and the comparison.

The segmentation stage reads the truth label maps shipped with the subject (the phantom's
MRI volumes are registered, meshed and measured as usual); ``breastmodel run`` on
``breastmodel/demo_data/subject`` runs the active-contour segmentation instead.
``--regenerate-data`` rewrites the shipped subject with FEBio and exits.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from breastmodel.demo import RIM_MM, cpu_seconds, run_story


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo",
        help="the story on a phantom with a hidden effect: fit, diagnose, refit, compare",
        description=__doc__.split("\n\n", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--data", type=Path, default=None,
                   help="demo subject folder holding subject/ and subject_truth/ (default: "
                        "the shipped breastmodel/demo_data)")
    p.add_argument("--mesh-mm", type=float, default=8.0,
                   help="tet edge of the fitted model, mm (default 8; the truth's is 5)")
    p.add_argument("--rim-mm", type=float, default=RIM_MM,
                   help=f"skin nodes this close to the skin's open edge (the field-of-view cut) "
                        f"stay out of the diagnosis, mm (default {RIM_MM:g}: the half-size "
                        f"phantom's skin is small)")
    p.add_argument("--workers", type=int, default=0,
                   help="local dask workers for the diagnosis (default 0: in this process)")
    p.add_argument("--regenerate-data", action="store_true",
                   help="rewrite the demo subject (--data or the shipped one) with FEBio, "
                        "then exit")
    p.add_argument("--febio", type=Path, help="FEBio executable for --regenerate-data")
    return p


def run(args: argparse.Namespace) -> int:
    from breastmodel.phantom.demo_data import DEMO_DATA, make_demo_data

    data = args.data or DEMO_DATA
    if args.regenerate_data:
        make_demo_data(data, febio=args.febio)
        print(f"demo data written to {Path(data).resolve()}")
        return 0
    t0, c0 = time.perf_counter(), cpu_seconds()
    res = run_story(data, args.out, mesh_size_mm=args.mesh_mm, rim_mm=args.rim_mm,
                    n_workers=args.workers)
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    print(f"\nhidden effect: {res['hidden_effect']}; the diagnosis names: {res['named']} "
          f"({'correct' if res['named'] == res['hidden_effect'] else 'WRONG'}; the hidden "
          f"effect ranks #{res['rank']})")
    print(f"{'position':>18} {'MHD before':>11} {'MHD after':>10}   (mm)")
    for p, (b, a) in res["mhd_mm"].items():
        print(f"{p:>18} {b:11.2f} {a:10.2f}")
    regions = res["compare"].get("regions") or {}
    sides = [(reg[k]["rmse_mm"][0], p, k) for p, reg in regions.items()
             for k in ("left", "right") if k in reg]
    if sides:
        rmse, p, k = max(sides)
        other = regions[p]["right" if k == "left" else "left"]["rmse_mm"][0]
        print(f"where the bulk model fails most: {p}, {k} breast (skin RMSE {rmse:.2f} mm; "
              f"the other breast {other:.2f} mm)")
    print(f"demo finished in {wall:.0f} s wall, {cpu:.0f} s CPU (load {os.getloadavg()[0]:.1f})")
    print(f"the whole story: {Path(res['page']).resolve()}")
    return 0
