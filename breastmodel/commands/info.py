"""``breastmodel info SUBJECT``: what a subject folder holds, and whether it is valid."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "info",
        help="describe and validate a subject folder",
        description=(
            "Print the subject id, the reference position and, per position, the volume file, "
            "size, spacing, origin, direction, intensity range and gravity; the number of "
            "fiducials and landmarks; then 'valid' or the first problem found."
        ),
    )
    p.add_argument("subject", type=Path, metavar="SUBJECT", help="subject folder")
    return p


def _fmt(values, digits: int = 3) -> str:
    return "(" + ", ".join(f"{float(v):.{digits}f}" for v in values) + ")"


def describe(folder: str | Path) -> str:
    """Multi-line description of a valid subject folder (raises SubjectError otherwise)."""
    import numpy as np
    import SimpleITK as sitk

    from imaging.subject import read_subject

    subject = read_subject(folder, check_volumes=False)
    lines = [f"subject   {subject.id}", f"folder    {subject.root}",
             f"reference {subject.reference}"]
    for name, pos in subject.positions.items():
        image = subject.load(name)
        arr = sitk.GetArrayViewFromImage(image)
        lines += [
            f"position  {name}{'  (reference)' if name == subject.reference else ''}",
            f"  volume    {pos.volume_path.name}  {image.GetPixelIDTypeAsString()}",
            f"  size      {'x'.join(str(s) for s in image.GetSize())} voxels",
            f"  spacing   {_fmt(image.GetSpacing())} mm",
            f"  origin    {_fmt(image.GetOrigin())} mm",
            f"  direction {_fmt(image.GetDirection(), 4)}",
            f"  range     [{float(np.min(arr)):.4g}, {float(np.max(arr)):.4g}]",
            f"  gravity   {_fmt(pos.gravity, 4)}"
            + (f"  tilt {pos.tilt_deg:g} deg" if pos.tilt_deg is not None else ""),
        ]
        if pos.notes:
            lines.append(f"  notes     {pos.notes}")
        nf = len(subject.fiducials.get(name, {}))
        nl = len(subject.landmarks.get(name, {}))
        lines.append(f"  points    {nf} fiducials, {nl} landmarks")
    return "\n".join(lines)


def main_info(folder: str | Path) -> int:
    """Print the description and 'valid', or the error; return 0 if valid, 1 otherwise."""
    from imaging.io import VolumeError
    from imaging.subject import SubjectError

    try:
        text = describe(folder)
    except (SubjectError, VolumeError) as exc:
        print(f"invalid: {exc}", file=sys.stderr)
        return 1
    print(text)
    print("valid")
    return 0


def run(args: argparse.Namespace) -> int:
    return main_info(args.subject)
