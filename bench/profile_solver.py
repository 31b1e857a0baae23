"""Profile one gravity solve of the benchmark hemisphere (cProfile, wall and CPU time).

Usage: ``python bench/profile_solver.py [--size 20k] [--top 25] [--no-profile]``. Prints the
solve's wall and CPU time, Newton iterations, the split assembly / factor / solve, max |u|,
and (unless ``--no-profile``) the cProfile functions with the largest cumulative time.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import os
import pstats
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from gravity import RADIUS, SIZES, peak_rss_mb  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="20k", choices=sorted(SIZES))
    ap.add_argument("--E", type=float, default=1.0)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--no-profile", action="store_true")
    ap.add_argument("--residuals", action="store_true", help="print the residual history")
    ap.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                    help="a SolverOptions field, e.g. --option reuse_below=1.0")
    ap.add_argument("--repeat", type=int, default=2, help="solves (the first is cold)")
    args = ap.parse_args(argv)
    from zoo import hemisphere

    from mechanics.model import build_model
    from mechanics.solver import SolverOptions, solve

    mesh = hemisphere(RADIUS, SIZES[args.size])
    model = build_model(mesh, {1: {"name": "neo_hookean", "E": args.E, "nu": 0.49}},
                        {"gravity": {"direction": (0, 0, -1), "density": 1000.0, "g": 9.81},
                         "fixed": {"node_set": "fixed"}})
    fields = {f.name: f.type for f in dataclasses.fields(SolverOptions)}
    extra = {}
    for item in args.option:
        key, val = item.split("=", 1)
        if key not in fields:
            ap.error(f"unknown solver option {key!r}")
        extra[key] = val if fields[key] in ("str", str) else (
            val.lower() in ("1", "true") if fields[key] in ("bool", bool) else
            type(getattr(SolverOptions(), key))(val))
    opt = SolverOptions(tol=1e-8, **extra)
    prof = None if args.no_profile else cProfile.Profile()
    for k in range(args.repeat):
        if prof is not None and k == args.repeat - 1:
            prof.enable()
        w0, c0 = time.perf_counter(), time.process_time()
        st = solve(model, options=opt)
        w, c = time.perf_counter() - w0, time.process_time() - c0
        if prof is not None and k == args.repeat - 1:
            prof.disable()
        parts = ("material", "effects", "assembly", "factor", "solve")
        split = {key: st.stats[f"t_{key}"] for key in parts}
        cpu = {key: st.stats[f"cpu_{key}"] for key in parts}
        fac = sum(e.get("factorizations", 0) for e in st.log)
        kry = sum(e.get("krylov_iterations", 0) for e in st.log)
        print(f"solve {k} ({'cold' if k == 0 else 'warm'}): wall {w:.2f} s cpu {c:.2f} s "
              f"newton {st.newton_iterations} steps {st.load_steps} factorizations {fac} "
              f"krylov {kry} wall/cpu "
              + " ".join(f"{key} {split[key]:.2f}/{cpu[key]:.2f}" for key in parts)
              + f" max|u| {st.max_displacement():.10f} mm res "
              f"{st.log[-1]['residuals'][-1]:.2e} peak {peak_rss_mb():.0f} MB "
              f"threads {st.stats['threads']} load {os.getloadavg()[0]:.1f}", flush=True)
        if args.residuals:
            print("  residuals " + " ".join(f"{r:.1e}" for e in st.log
                                            for r in e["residuals"]))
    if prof is not None:
        pstats.Stats(prof).sort_stats("cumulative").print_stats(args.top)
    return 0


if __name__ == "__main__":
    sys.exit(main())
