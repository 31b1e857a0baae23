"""Stage bodies of the subject half of the pipeline: segment one position, register, mesh
the reference, extract the measured skins and assemble the *problem* folder (mesh, measured
skins, gravity, landmarks: :mod:`breastmodel.pipeline.problem`); each returns the function
that fills its stage folder.

The mesh needs only the reference's label map, so :func:`breastmodel.pipeline.run
.prepare_subject` starts it (:class:`meshing.background.mesh_in_background`) as soon as the
reference is segmented and segments and registers the other positions beside it."""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.errors import StageError
from imaging.labels import BREAST, BREAST_TISSUE, MUSCLE

log = logging.getLogger("breastmodel.pipeline")

__all__ = ["mesh_options", "mesh_stage", "problem_stage", "register_stage", "segment_stage",
           "skins_stage"]


def segment_stage(subject, position: str, cfg: Mapping[str, Any]) -> Callable[[Path], None]:
    """The label map of one position (``<position>_labels.nii.gz``): segmented, or copied
    from ``[segment] labels`` (every position, or those of ``labels_positions``); it must
    hold breast tissue and muscle."""

    def fn(d: Path) -> None:
        import SimpleITK as sitk

        from breastmodel.pipeline.config import GIVEN_LABEL_KEYS, given_labels
        from breastmodel.pipeline.segment import segment_position, update_summary
        from imaging.io import read_volume, write_volume

        vol = subject.positions[position].volume_path
        src = given_labels(cfg["segment"], position)  # its file checked before the stages
        seg = {k: v for k, v in cfg["segment"].items() if k not in GIVEN_LABEL_KEYS}
        if src is not None:
            labels = read_volume(src)
            write_volume(labels, d / f"{position}_labels.nii.gz")
        else:
            try:
                summary = segment_position(subject, position, d,
                                           preprocess_options=cfg["preprocess"],
                                           segment_options=seg)
            except ValueError as exc:
                raise StageError("segment", str(exc), vol) from None
            update_summary(d, position, summary)
            labels = read_volume(d / f"{position}_labels.nii.gz")
        a = sitk.GetArrayViewFromImage(labels)
        if not np.isin(a, BREAST_TISSUE).any():
            raise StageError("segment", f"position {position!r}: the segmentation has no "
                             f"breast tissue (label {BREAST})", vol)
        if not (a == MUSCLE).any():
            raise StageError("segment", f"position {position!r}: the segmentation has no "
                             f"muscle / chest wall (label {MUSCLE})", vol)
    return fn



def register_stage(subject, seg_dirs: Mapping[str, Path], cfg: Mapping[str, Any]):
    """Every position registered onto the reference (:func:`breastmodel.pipeline.register
    .register_subject`): transforms, gravity, the label maps in the reference frame."""

    def fn(d: Path) -> None:
        from breastmodel.pipeline.register import register_subject

        labels = d / "labels_in"
        labels.mkdir()
        for pos, folder in seg_dirs.items():
            shutil.copy2(folder / f"{pos}_labels.nii.gz", labels / f"{pos}_labels.nii.gz")
        try:
            # the subject as read once by the run, the [register] table as a value
            register_subject(subject, d, seg_dir=labels, config=cfg["register"])
        except StageError as exc:
            doubt = doubtful_segmentations(seg_dirs)
            if not doubt:
                raise
            raise StageError("register", f"{exc.message}. The chest wall it registers on comes "
                             f"from the segmentation, which doubted itself: {doubt}; look "
                             "at that first", exc.path) from None
        except (ValueError, RuntimeError) as exc:
            raise StageError("register", str(exc), subject.root) from None
        shutil.rmtree(labels)
    return fn


def doubtful_segmentations(seg_dirs: Mapping[str, Path]) -> str:
    """The positions whose segmentation doubted itself (the confidence its stage folder
    keeps), as one sentence; "" where none did (or the label maps were given)."""
    from breastmodel.pipeline.segment import read_confidences

    said = []
    for pos, conf in read_confidences(seg_dirs).items():
        if conf and not conf.get("confident", True):
            said.append(f"{pos!r} ({'; '.join(conf.get('warnings') or ['not confident'])})")
    return "; ".join(said)




def mesh_stage(labels: Path, options: Mapping[str, Any], job=None) -> Callable[[Path], None]:
    """The tet mesh of the reference's label map ``labels`` (``mesh.npz``, ``mesh.json``:
    size and how it was chosen, counts, the label map's repairs), from ``job`` (a started
    :class:`meshing.background.mesh_in_background`) or made now; ``options`` is the
    ``[mesh]`` table with ``threads`` resolved."""

    def fn(d: Path) -> None:
        from breastmodel.config import write_json
        from meshing.background import mesh_label_file
        from meshing.labels import collect_repairs

        try:
            with collect_repairs() as repairs:
                mesh, size, why = job.result() if job else mesh_label_file(labels, **options)
        except (ValueError, RuntimeError) as exc:
            raise StageError("mesh", str(exc), labels) from None
        mesh.save_npz(d / "mesh.npz")
        write_json(d / "mesh.json", {"mesh_size_mm": size, "mesh_size": why,
                                     "n_nodes": mesh.n_nodes, "n_tets": mesh.n_tets,
                                     "repairs": repairs})
    return fn


def mesh_options(cfg: Mapping[str, Any]) -> dict:
    """The ``[mesh]`` table as :func:`meshing.background.mesh_label_file` takes it (threads
    0: the run's cores)."""
    from mechanics.threads import resolve_threads

    m = cfg["mesh"]
    return {"size_mm": m["size_mm"], "keep_gland": bool(m["keep_gland"]),
            "threads": int(m["threads"]) or resolve_threads(None)}


def skins_stage(subject, reg_dir: Path, cfg: Mapping[str, Any]) -> Callable[[Path], None]:
    """The measured skin of every position in the reference frame (``<position>_skin.npz``),
    from the registered label maps, and each label map's repairs (``skins.json``); worker
    processes on an adult volume."""

    def fn(d: Path) -> None:
        from breastmodel.config import write_json
        from mechanics.threads import resolve_threads
        from meshing.labels import collect_repairs
        from meshing.surface import skin_surfaces

        positions = list(subject.positions)
        paths = [reg_dir / ("reference_labels.nii.gz" if pos == subject.reference
                            else f"{pos}_labels_in_reference.nii.gz") for pos in positions]
        repairs = {}
        with skin_surfaces(paths, target_edge_mm=float(cfg["surface"]["edge_mm"]),
                           workers=resolve_threads(None)) as skins:
            for pos, path in zip(positions, paths, strict=True):
                try:
                    with collect_repairs() as repairs[pos]:
                        v, f = next(skins)
                except (ValueError, RuntimeError) as exc:
                    raise StageError("surface", f"position {pos!r}: {exc}", path) from None
                np.savez(d / f"{pos}_skin.npz", vertices=v, triangles=f)
        write_json(d / "skins.json", {"repairs": repairs})
    return fn


def problem_stage(subject, reg_dir: Path, mesh_dir: Path,
                  skins_dir: Path) -> Callable[[Path], None]:
    """The problem folder: the mesh and measured skins copied from their stages, and
    ``problem.json`` (reference, gravity, landmarks in the reference frame, mesh size, where
    the reference's field of view cut the breasts: :mod:`meshing.field_of_view`, logged as a
    warning past its share)."""

    def fn(d: Path) -> None:
        from breastmodel.config import write_json
        from registration.transforms import read_transform, transform_points

        shutil.copyfile(mesh_dir / "mesh.npz", d / "mesh.npz")
        for pos in subject.positions:
            shutil.copyfile(skins_dir / f"{pos}_skin.npz", d / f"{pos}_skin.npz")
        ref = subject.reference
        gravity = json.loads((reg_dir / "gravity.json").read_text())
        landmarks = {}
        for pos, pts in (subject.landmarks or {}).items():
            if pos not in gravity or not pts:
                continue
            names = sorted(pts)
            p = np.array([pts[k] for k in names], float)
            if pos != ref:  # reference -> position image; its inverse brings them home
                tfm = read_transform(reg_dir / f"{pos}.tfm")
                p = transform_points(tfm.GetInverse(), p)
            landmarks[pos] = {k: v.tolist() for k, v in zip(names, p)}
        skins = skins_dir / "skins.json"  # absent from a cache made before it was written
        write_json(d / "problem.json", {
            "reference": ref, "gravity": gravity, "landmarks": landmarks,
            "field_of_view": _field_of_view(d / "mesh.npz", reg_dir / "reference_labels.nii.gz",
                                            ref),
            "skin_repairs": json.loads(skins.read_text())["repairs"] if skins.is_file() else {},
            **json.loads((mesh_dir / "mesh.json").read_text())})
    return fn


def _field_of_view(mesh_path: Path, labels_path: Path, reference: str) -> dict:
    """``cut`` (:func:`meshing.field_of_view.breast_cut` of the mesh in the reference label
    map's grid) and ``warning`` (None, or logged here)."""
    from mechanics.mesh import Mesh
    from meshing.field_of_view import breast_cut, cut_warning
    from meshing.labels import Grid

    cut = breast_cut(Mesh.load_npz(mesh_path), Grid.of_file(labels_path))
    warning = cut_warning(cut, reference)
    if warning:
        log.warning("%s", warning)
    return {"cut": cut, "warning": warning}


def mesh_key(mesh: Mapping[str, Any]) -> dict:
    """What the mesh stage is keyed on: the ``[mesh]`` table and the named sets' version (a
    cached mesh without the sets the model now reads is made again)."""
    from meshing.sets import SETS_VERSION

    return {"mesh": mesh, "sets": SETS_VERSION}


def reference_labels(seg_dirs: Mapping[str, Path], pos: str) -> Path:
    """A position's label map in its segmentation stage."""
    return seg_dirs[pos] / f"{pos}_labels.nii.gz"
