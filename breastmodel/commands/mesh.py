"""``breastmodel mesh``: label map -> tagged tetrahedral mesh, skin surface and quality."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

log = logging.getLogger("breastmodel.mesh")


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "mesh",
        help="mesh a label map into tagged tetrahedra (VTU, FEBio, skin PLY, quality)",
        description=(
            "Build the finite-element mesh from a label map (0 background, 1 breast, "
            "2 muscle, 3 gland): marching cubes, surface repair and remeshing, conforming "
            "tetrahedralisation of breast and muscle, regions (left/right breast, muscle) "
            "and named sets (skin, interface, fixed, end bands, ligament anchors). Writes "
            "OUT/mesh.vtu, OUT/mesh.feb, OUT/mesh.npz, OUT/skin.ply and OUT/quality.json."
        ),
    )
    p.add_argument("labels", type=Path, help="label map (NIfTI, NRRD, MHA...)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--size", type=float, default=8.0, help="target element size, mm (default 8)")
    p.add_argument(
        "--keep-gland", action="store_true", help="tag gland (label 3) as its own regions"
    )
    p.add_argument("--threads", type=int, default=0, help="tetrahedraliser threads (0: all)")
    return p


def mesh_file(
    labels_path: Path, out: Path, *, size_mm: float = 8.0, keep_gland: bool = False,
    threads: int = 0,
) -> dict:
    """Mesh one label-map file into ``out`` (mesh.vtu, mesh.feb, mesh.npz, skin.ply,
    quality.json) and return the quality report.

    Raises
    ------
    OSError
        Missing or unreadable file.
    ValueError, RuntimeError
        Bad label map or failed meshing; the message names the file.
    """
    import SimpleITK as sitk

    from breastmodel.config import write_json
    from breastmodel.febio import write_mesh_feb
    from meshing import mesh_labels
    from meshing.export import write_ply, write_vtu
    from meshing.quality import report
    from meshing.surface import skin_surface

    labels_path, out = Path(labels_path), Path(out)
    if not labels_path.exists():
        raise FileNotFoundError(f"mesh: label map not found: {labels_path}")
    try:
        labels = sitk.ReadImage(str(labels_path))
    except RuntimeError as exc:
        raise OSError(f"mesh [{labels_path}]: cannot read the label map ({exc})") from exc
    t0 = time.perf_counter()
    try:
        mesh = mesh_labels(
            labels, size_mm=size_mm, progress=True, keep_gland=keep_gland, threads=threads
        )
        skin_v, skin_f = skin_surface(labels)
    except (ValueError, RuntimeError) as exc:
        raise type(exc)(f"mesh [{labels_path}]: {exc}") from exc
    out.mkdir(parents=True, exist_ok=True)
    write_vtu(out / "mesh.vtu", mesh)
    write_mesh_feb(mesh, out / "mesh.feb")
    mesh.save_npz(out / "mesh.npz")
    write_ply(skin_v, skin_f, out / "skin.ply")
    q = report(mesh)
    q["seconds"] = round(time.perf_counter() - t0, 2)
    q["size_mm"] = size_mm
    q["labels"] = str(labels_path)
    write_json(out / "quality.json", q)
    log.info(
        "mesh: %d tets, %d nodes, aspect ratio <= %.2f, skewness <= %.3f, %d inverted -> %s",
        q["n_tets"], q["n_nodes"], q["aspect_ratio"]["max"], q["skewness"]["max"],
        q["n_inverted"], out,
    )
    return q


def run(args: argparse.Namespace) -> int:
    mesh_file(args.labels, args.out, size_mm=args.size, keep_gland=args.keep_gland,
              threads=args.threads)
    return 0
