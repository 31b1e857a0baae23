"""``breastmodel demo``: the main job end to end on built-in demo data (a phantom subject).

phantom -> validate -> segment -> register -> mesh -> simulate every position under gravity.
Each step writes into its own sub-folder of ``--out`` and reuses it when it is already
complete, so an interrupted demo resumes.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

log = logging.getLogger("breastmodel.demo")


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo",
        help="run the whole pipeline on a built-in phantom subject",
        description=(
            "Make a synthetic subject, validate it, segment and register its MRI volumes, "
            "mesh the reference position and simulate every position under gravity. "
            "Outputs go to OUT/<step>/; a rerun resumes."
        ),
    )
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--seed", type=int, default=0, help="phantom seed (default 0)")
    p.add_argument(
        "--full",
        action="store_true",
        help="full-size phantom at 1 mm voxels (default: the small, fast phantom)",
    )
    p.add_argument("--size", type=float, default=10.0, help="target element size, mm")
    return p


def _step(name: str, out: Path, fn) -> Path:
    """Run ``fn(dir)`` unless ``dir/.done`` exists; mark completion only on success."""
    d = out / name
    if (d / ".done").exists():
        log.info("%s: already done (%s)", name, d)
        return d
    d.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    log.info("%s: running", name)
    fn(d)
    (d / ".done").write_text(f"{time.perf_counter() - t0:.2f} s\n")
    log.info("%s: done in %.1f s", name, time.perf_counter() - t0)
    return d


def run(args: argparse.Namespace) -> int:
    from breastmodel.commands import info, mesh, register, segment, simulate
    from breastmodel.phantom import make_phantom

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    subject = out / "subject"
    truth = out / "subject_truth"

    _step(
        "phantom",
        out,
        lambda d: make_phantom(subject, seed=args.seed, small=not args.full),
    )
    if info.main_info(subject) != 0:
        return 1
    seg = _step("segment", out, lambda d: segment.segment_subject(subject, d, truth=truth))
    reg = _step(
        "register", out, lambda d: register.register_subject(subject, d, truth=truth, seg_dir=seg)
    )
    meshed = _step(
        "mesh",
        out,
        lambda d: mesh.mesh_file(reg / "reference_labels.nii.gz", d, size_mm=args.size),
    )
    sims = _step(
        "simulate", out, lambda d: simulate.simulate_positions(meshed / "mesh.vtu", reg, d)
    )
    summary = json.loads((sims / "summary.json").read_text())
    print(f"\ndemo finished; outputs in {out.resolve()}")
    for pos, row in summary.items():
        print(f"  {pos:>14}: max displacement {row['max_displacement_mm']:.2f} mm, "
              f"{row['newton_iterations']} Newton iterations, {row['wall_time_s']:.2f} s")
    return 0
