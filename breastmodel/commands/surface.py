"""``breastmodel surface``: the measured skin surface of a label map, as PLY."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger("breastmodel.surface")


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "surface",
        help="extract the measured skin surface of a label map (PLY)",
        description=(
            "Outer surface of the breast tissue (label 1, and 3) without the breast-muscle "
            "interface and the field-of-view cut planes: what predictions are scored "
            "against. Vertices in physical LPS mm."
        ),
    )
    p.add_argument("labels", type=Path, help="label map (NIfTI, NRRD, MHA...)")
    p.add_argument("--out", type=Path, required=True, help="output .ply file")
    p.add_argument("--edge", type=float, default=2.0, help="triangle edge length, mm (default 2)")
    return p


def run(args: argparse.Namespace) -> int:
    import SimpleITK as sitk

    from meshing.export import write_ply
    from meshing.surface import skin_surface

    if not args.labels.exists():
        raise FileNotFoundError(f"surface: label map not found: {args.labels}")
    try:
        labels = sitk.ReadImage(str(args.labels))
    except RuntimeError as exc:
        raise OSError(f"surface [{args.labels}]: cannot read the label map ({exc})") from exc
    try:
        v, f = skin_surface(labels, target_edge_mm=args.edge)
    except (ValueError, RuntimeError) as exc:
        raise type(exc)(f"surface [{args.labels}]: {exc}") from exc
    write_ply(v, f, args.out)
    log.info("surface: %d vertices, %d triangles -> %s", len(v), len(f), args.out)
    return 0
