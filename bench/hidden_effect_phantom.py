"""Benchmark: the diagnosis loop end to end on an MRI phantom made by simulation.

A small phantom is deformed per position by a truth model that has an effect X; the pipeline
(segmentation, registration, meshing, stress-free inverse, least-squares fit of the breast
modulus) runs with the truth's model minus X; ``diagnose`` ranks the candidates; the run is
repeated with X switched on (``--add-effect`` semantics) and the two revisions are compared.
Prints a table and writes ``bench/results/hidden_effect_phantom.json``: X's rank, the
verdict, MHD per position before and after, wall and CPU time of every step.

Run: ``.venv/bin/python bench/hidden_effect_phantom.py [--effect skin] [--voxel 2]
[--out /tmp/hidden]``
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time
from pathlib import Path

# bench/meshing.py would shadow the meshing package that the phantom imports
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]

from breastmodel.config import write_json  # noqa: E402
from breastmodel.diagnosis import diagnose, write_compare  # noqa: E402
from breastmodel.diagnosis.candidates import add_to_config, candidate_by_name  # noqa: E402
from breastmodel.phantom.simulated import make_simulated_phantom  # noqa: E402
from breastmodel.phantom.truth_model import preset  # noqa: E402
from breastmodel.pipeline import resolve_config, run_subject  # noqa: E402

TIED = "materials.breast_left.E|materials.breast_right.E"
#: effect -> (truth preset that has it, effect keys the fitted model drops)
CASES = {"skin": ("default", ("skin",)), "regions:asymmetry": ("asymmetric", ("regions",)),
         "regions:gland": ("gland", ("regions",)),
         "strain_stiffening": ("gent_breast", ("strain_stiffening",))}


def cpu() -> float:
    r, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--effect", default="skin", choices=sorted(CASES))
    ap.add_argument("--voxel", type=float, default=1.0, help="phantom voxel size, mm")
    ap.add_argument("--out", type=Path, default=Path("/tmp/hidden_effect_phantom"))
    ap.add_argument("--budget", type=int, default=25)
    args = ap.parse_args()
    steps, t = {}, {}

    def step(name):
        t[name] = (time.perf_counter(), cpu())

    def done(name):
        w0, c0 = t[name]
        steps[name] = {"wall_s": round(time.perf_counter() - w0, 1),
                       "cpu_s": round(cpu() - c0, 1)}
        print(f"  {name:<12} {steps[name]['wall_s']:8.1f} s wall {steps[name]['cpu_s']:8.1f} s CPU",
              flush=True)

    name, drop = CASES[args.effect]
    tm = preset(name)
    subj = args.out / "subject"
    step("phantom")
    if not (subj / "subject.toml").is_file():
        make_simulated_phantom(subj, seed=1, truth_model=tm, small=True, voxel_size=args.voxel,
                               progress=False)
    done("phantom")
    model = tm.run_model(drop=drop)
    raw = {"model": model, "register": {"shrink": [2, 1], "smooth_mm": [2.0, 0.0]},
           "stress_free": {"tol_mm": 0.1, "max_iter": 15},
           "fit": {"enabled": True, "method": "least_squares", "budget": args.budget,
                   "sensitivity": False, "calibrate": ["prone", "supine"],
                   "parameters": {TIED: {"min": 0.3, "max": 8.0}}}}
    cfg = resolve_config(raw)
    step("run0")
    r0 = run_subject(subj, cfg, args.out / "run0", progress=True)
    done("run0")
    step("diagnose")
    d = diagnose(args.out / "run0", progress=True)["missing"]
    done("diagnose")
    names = [r["name"] for r in d["ranking"]]
    rank = names.index(args.effect) + 1 if args.effect in names else None
    est = next((r["estimate"] for r in d["ranking"] if r["name"] == args.effect), None)
    cfg1 = add_to_config(resolve_config({**raw, "model": r0["params"]["model"]}),
                         candidate_by_name(r0["params"]["model"], args.effect), start=est)
    step("run1")
    r1 = run_subject(subj, cfg1, args.out / "run1", progress=True,
                     cache=args.out / "run0" / "cache")  # same segmentation and mesh
    done("run1")
    cmp = write_compare([args.out / "run0", args.out / "run1"], args.out / "compare")
    mhd = {p: t_["mhd_mm"]["values"] for p, t_ in cmp["positions"].items()}
    out = {"effect": args.effect, "truth_preset": name, "voxel_mm": args.voxel,
           "rank": rank, "top": names[:5], "verdict": d["verdict"],
           "noise_floor_mm": d["noise_floor_mm"], "mhd_mm_before_after": mhd,
           "fitted_before": r0["params"]["parameters"], "fitted_after": r1["params"]["parameters"],
           "truth": tm.to_dict(), "steps": steps, "n_evaluations": d["n_evaluations"],
           "machine": {"cpus": os.cpu_count(), "load": os.getloadavg(),
                       "python": platform.python_version()}}
    print(f"\n{args.effect}: ranked #{rank}; {d['verdict']}")
    print(f"{'position':>14} {'MHD before':>11} {'MHD after':>10}")
    for p, (b, a) in mhd.items():
        print(f"{p:>14} {b:11.3f} {a:10.3f}")
    tag = args.effect.replace(":", "_")
    res = Path(__file__).parent / "results" / f"hidden_effect_phantom_{tag}.json"
    write_json(res, out)
    print(f"wrote {res}")


if __name__ == "__main__":
    main()
