"""``breastmodel phantom OUT``: write a synthetic subject folder and ``OUT_truth``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "phantom",
        help="make a synthetic MRI subject (phantom) with known truth",
        description=(
            "Write a synthetic subject folder OUT (subject.toml, one NIfTI volume per "
            "position, fiducials.csv, landmarks.csv) and OUT_truth/ (clean tissue and label "
            "volumes, rigid motions, marker positions, anatomy parameters). The same seed "
            "gives byte-identical volumes."
        ),
    )
    p.add_argument("out", type=Path, metavar="OUT", help="subject folder to write")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--voxel-size", type=float, default=1.0, help="voxel size, mm (default 1)")
    p.add_argument("--snr", type=float, default=20.0, help="mean fat signal / noise sigma")
    p.add_argument("--bias", type=float, default=0.3, help="bias-field amplitude (default 0.3)")
    p.add_argument(
        "--positions",
        default="prone,supine,supine_tilted",
        help="comma-separated positions: prone, supine, upright, supine_tilted[_<deg>]",
    )
    p.add_argument("--max-rotation-deg", type=float, default=5.0, help="rigid motion bound")
    p.add_argument("--max-translation-mm", type=float, default=10.0, help="rigid motion bound")
    p.add_argument("--small", action="store_true", help="half-size torso, small field of view")
    from breastmodel.phantom.simulated import add_simulation_arguments

    add_simulation_arguments(p)
    return p


def run(args: argparse.Namespace) -> int:
    if args.simulate:
        from breastmodel.phantom.simulated import run_simulated

        print(f"wrote {run_simulated(args)} (deformed by simulation)")
        return 0
    from breastmodel.phantom import make_phantom, truth_folder

    positions = tuple(p.strip() for p in args.positions.split(",") if p.strip())
    t0 = time.perf_counter()
    out = make_phantom(
        args.out,
        seed=args.seed,
        voxel_size=args.voxel_size,
        snr=args.snr,
        bias=args.bias,
        positions=positions,
        max_rotation_deg=args.max_rotation_deg,
        max_translation_mm=args.max_translation_mm,
        small=args.small,
    )
    print(f"wrote {out} and {truth_folder(out)} in {time.perf_counter() - t0:.1f} s")
    return 0
