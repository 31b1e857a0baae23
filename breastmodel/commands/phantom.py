"""``breastmodel phantom OUT``: write a synthetic subject folder and ``OUT_truth``."""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "phantom",
        help="make a synthetic MRI subject (phantom) with known truth",
        description=(
            "Write a synthetic subject folder OUT (subject.toml, one NIfTI volume per "
            "position, fiducials.csv, landmarks.csv) and OUT_truth/ (clean tissue and label "
            "volumes, rigid motions, marker positions, anatomy parameters). The same seed "
            "gives byte-identical volumes. With --family, a varied subject is drawn from the "
            "seed (anatomy, field of view, voxels, contrast, motion, tilt) and its truth "
            "deformation is computed (by FEBio unless --truth-solver ours)."
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
    add_simulation_arguments(p)
    f = p.add_argument_group("phantom family (a varied subject drawn from --seed)")
    f.add_argument("--family", choices=("small", "full"), default=None,
                   help="draw a subject of this size from --seed (other image options are "
                        "drawn too; --truth-solver, --febio and --truth-cache apply)")
    f.add_argument("--spec", type=Path, default=None, metavar="JSON",
                   help="make the subject of a spec file (spec.json of a truth folder)")
    f.add_argument("--physics", default=None, metavar="NAME[+NAME]",
                   help="truth physics of a family subject (bulk, or bulk with one hidden "
                        "effect: asymmetric, gland, gent_breast, skin, fascia, ligaments)")
    f.add_argument("--band", choices=("standard", "soft"), default="standard",
                   help="the breast modulus' band of a family subject (soft: twice the sag)")
    return p


def add_simulation_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the simulated (gravity-deformed) phantom."""
    from breastmodel.phantom.simulated import TRUTH_SOLVERS
    from breastmodel.phantom.truth_model import PRESETS

    g = parser.add_argument_group("simulated deformation (slow: meshes and solves the FE model)")
    g.add_argument("--simulate", action="store_true",
                   help="deform each position by simulated gravity (default: rigid only; "
                        "implied by --truth-solver)")
    g.add_argument("--truth-solver", choices=TRUTH_SOLVERS, default=None,
                   help="FE code that computes the truth deformation: ours, or febio (an "
                        "independent code; FEBio 4 from --febio or $FEBIO)")
    g.add_argument("--febio", type=Path, default=None, metavar="PATH",
                   help="FEBio 4 executable (default: $FEBIO, then the project's build)")
    g.add_argument("--truth-cache", type=Path, default=None, metavar="DIR",
                   help="cache of truth meshes and FEBio results keyed by their inputs "
                        "(default: none)")
    g.add_argument("--truth-preset", default="default", metavar="NAME",
                   help=f"truth physics preset, one of {sorted(PRESETS)}; join with '+' "
                        "(default: default = the paper's model)")
    g.add_argument("--truth-effects", default=None, metavar="NAME[,NAME]",
                   help="comma-separated presets applied on top of --truth-preset "
                        "(each changes one hidden effect)")
    g.add_argument("--truth-config", type=Path, default=None, metavar="TOML",
                   help="truth physics from a file: [materials.<region name>] tables and "
                        "[effects.<registered effect>] tables (any effects and parameters; "
                        "replaces the presets)")
    g.add_argument("--truth-mesh-size", type=float, default=None, metavar="MM",
                   help="tet size of the truth mesh, mm (default 6 with our solver, 5 with "
                        "FEBio and for family subjects)")


def truth_model_from_args(args: argparse.Namespace):
    """The truth physics named by --truth-config or --truth-preset/--truth-effects."""
    from breastmodel.phantom.truth_model import from_toml, preset

    if args.truth_config:
        tm = from_toml(args.truth_config)
    else:
        name = args.truth_preset
        if args.truth_effects:
            name = "+".join([name] + [s.strip() for s in args.truth_effects.split(",")
                                      if s.strip()])
        tm = preset(name)
    size = args.truth_mesh_size or (5.0 if args.truth_solver == "febio" else None)
    return replace(tm, mesh_size_mm=float(size)) if size else tm


def _positions(text: str) -> tuple[str, ...]:
    return tuple(p.strip() for p in text.split(",") if p.strip())


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    if args.family or args.spec:
        from breastmodel.phantom.family import SubjectSpec, draw_spec, make_subject

        if args.spec:
            spec = SubjectSpec.from_json(args.spec.read_text())
        else:
            over = {"physics": args.physics} if args.physics else {}
            if args.truth_mesh_size:
                over["truth_mesh_size_mm"] = args.truth_mesh_size
            spec = draw_spec(args.seed, size=args.family, band=args.band, **over)
        out = make_subject(spec, args.out, truth_solver=args.truth_solver or "febio",
                           febio=args.febio, cache_dir=args.truth_cache, progress=True)
        print(f"wrote {out} ({spec.name}: {json.dumps(spec.to_dict(), sort_keys=True)}) in "
              f"{time.perf_counter() - t0:.1f} s")
        return 0
    if args.simulate or args.truth_solver:
        from breastmodel.phantom.simulated import make_simulated_phantom

        out = make_simulated_phantom(
            args.out, seed=args.seed, truth_model=truth_model_from_args(args),
            positions=_positions(args.positions), small=args.small, progress=True,
            truth_solver=args.truth_solver or "ours", febio=args.febio,
            cache_dir=args.truth_cache, voxel_size=args.voxel_size, snr=args.snr,
            bias=args.bias, max_rotation_deg=args.max_rotation_deg,
            max_translation_mm=args.max_translation_mm)
        print(f"wrote {out} (deformed by simulation, solver {args.truth_solver or 'ours'}) in "
              f"{time.perf_counter() - t0:.1f} s")
        return 0
    from breastmodel.phantom import make_phantom, truth_folder

    out = make_phantom(
        args.out,
        seed=args.seed,
        voxel_size=args.voxel_size,
        snr=args.snr,
        bias=args.bias,
        positions=_positions(args.positions),
        max_rotation_deg=args.max_rotation_deg,
        max_translation_mm=args.max_translation_mm,
        small=args.small,
    )
    print(f"wrote {out} and {truth_folder(out)} in {time.perf_counter() - t0:.1f} s")
    return 0
