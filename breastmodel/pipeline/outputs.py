"""The run's outputs, in the formats the tools users look with open directly.

``DIR/`` after ``breastmodel run``:

===============================================  ==============================================
``metrics.json``, ``params.json``                 per-position distances, the parameters used
``report.html``                                   the whole run on one page (browser)
``run.vtm``                                       ParaView: every position's blocks below
``<position>.vtu``                                deformed tet mesh (points = predicted node
                                                  positions, mm): point data ``displacement``
                                                  (from the stress-free geometry), ``pressure``,
                                                  node sets; cell data ``region``, ``stress``
                                                  (Cauchy, kPa), ``von_mises``, ``J``,
                                                  ``stretch``
``<position>_skin.vtp``                           predicted skin: ``signed_error_mm`` (to the
                                                  measured skin, + outside), ``region``,
                                                  ``displacement``
``<position>_measured_skin.vtp``                  measured skin (reference frame)
``<position>_predicted.ply``                      predicted skin, plain geometry
``model_<position>.feb``                          FEBio Studio / FEBio 4: the model of the
                                                  position (fitted parameters, gravity,
                                                  supports, membranes, ligaments, contact) on
                                                  the stress-free geometry
``<position>_in_reference.nii.gz``                3D Slicer / ITK-SNAP: the position's volume
``<position>_labels_in_reference.nii.gz``         and label map resampled into the reference
                                                  frame (the reference's own for it)
``<position>.tfm``                                ITK rigid transform, reference -> position
                                                  image (identity for the reference)
``<position>_labels_in_reference.seg.nrrd``      3D Slicer segmentation: the same label map
                                                  with named, coloured segments
``labels.ctbl``, ``labels_itksnap.txt``           colour tables of the label codes (Slicer,
                                                  ITK-SNAP)
``<position>_fiducials.mrk.json``,                detected fiducials in the reference frame
``fiducials_in_reference.csv``                    (Slicer markups, LPS; CSV as the input's)
===============================================  ==============================================

All of it is assembled from finished stages under ``DIR/cache`` (cheap; redone on every
run); every file is written atomically.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.config import write_atomic, write_atomic_with
from imaging.labels import LABEL_NAMES, LABEL_RGB

log = logging.getLogger("breastmodel.pipeline")

__all__ = ["LABEL_TABLE", "export_images", "write_colour_tables", "write_febio",
           "write_outputs", "write_position_meshes", "write_slicer_segmentation",
           "write_vtm"]

_SUMMARY_KEYS = ("mhd_mm", "hausdorff_mm", "rmse_mm", "p95_mm", "median_mm",
                 "mean_pred_to_meas_mm", "mean_meas_to_pred_mm", "n_pred", "n_meas",
                 "mhd_overlap_mm", "uncovered_pred_fraction", "uncovered_meas_fraction",
                 "converged", "load_reached", "max_displacement_mm", "error")

#: label code -> (name, RGB 0-255), as drawn by :mod:`imaging.views`
LABEL_TABLE = {code: (name, LABEL_RGB[code]) for code, name in LABEL_NAMES.items()}


def _copy(src: Path, dst: Path) -> None:
    write_atomic_with(dst, lambda tmp: shutil.copyfile(src, tmp))


def write_position_meshes(out: Path, problem, position: str,
                          predicted: Mapping[str, np.ndarray]) -> dict[str, str]:
    """Write ``<position>.vtu``, ``<position>_skin.vtp`` and ``<position>_measured_skin.vtp``.

    Parameters
    ----------
    out : output folder
    problem : :class:`breastmodel.pipeline.problem.Problem`
    position : position name
    predicted : the predict stage's arrays: ``x`` (N, 3) mm predicted nodes, ``X`` (N, 3)
        mm stress-free nodes, ``stress`` (M, 9) kPa, ``J`` (M,), ``pressure`` (N,) kPa,
        ``signed_error`` (n_skin,) mm, ``skin_nodes`` (n_skin,)

    Returns
    -------
    dict
        ``{"mesh", "skin", "measured_skin"}`` file names.
    """
    from breastmodel.pipeline.problem import mesh_of, skin_node_regions
    from mechanics.export import result_fields
    from mechanics.state import State
    from meshing.export import write_vtp, write_vtu

    x = np.asarray(predicted["x"], float)
    mesh = mesh_of(problem, len(x))
    X = np.asarray(predicted["X"], float) if "X" in predicted else np.array(mesh.nodes, float)
    if "stress" in predicted:
        stress = np.asarray(predicted["stress"], float).reshape(-1, 3, 3)
        J = np.asarray(predicted["J"], float)
    else:  # a prediction cached before stresses were stored
        log.warning("outputs: %s: the cached prediction has no stresses; %s.vtu carries NaN "
                    "stress (rerun with a fresh cache to fill them)", position, position)
        stress = np.full((mesh.n_tets, 3, 3), np.nan)
        J = np.full(mesh.n_tets, np.nan)
    pressure = predicted.get("pressure")
    state = State(x - X, True, 1.0, stress, J, pressure=pressure, X=X)
    names = {"mesh": f"{position}.vtu", "skin": f"{position}_skin.vtp",
             "measured_skin": f"{position}_measured_skin.vtp"}
    pts, fields, cell_fields = result_fields(mesh, state, deformed=True)
    write_vtu(out / names["mesh"], mesh, points=pts, fields=fields, cell_fields=cell_fields)

    nodes = np.asarray(predicted["skin_nodes"])
    faces = np.asarray(mesh.face_sets["skin"])
    remap = np.full(len(x), -1, np.int64)
    remap[nodes] = np.arange(len(nodes))
    write_vtp(x[nodes], remap[faces], out / names["skin"], point_data={
        "signed_error_mm": np.asarray(predicted["signed_error"], float),
        "region": skin_node_regions(mesh)[nodes],
        "displacement": (x - X)[nodes]})
    mv, mf = problem.skins[position]
    write_vtp(mv, mf, out / names["measured_skin"])
    return names


def write_febio(out: Path, problem, model: Mapping[str, Any], position: str,
                X: np.ndarray) -> dict[str, Any]:
    """Write ``model_<position>.feb``: the position's model (materials, that position's
    gravity, every effect) on the stress-free geometry ``X``, through the one FEBio writer
    (:func:`mechanics.febio.feb_text`). FEBio's element is the one closest to the model's
    formulation: UT4 (nodally integrated) for ``"anp"``, the standard tet4 for
    ``"standard"``, which reproduces our solver exactly.

    Parameters
    ----------
    out : output folder
    problem : :class:`breastmodel.pipeline.problem.Problem`
    model : the model table the run used (materials, effects, density kg/m^3, g m/s^2,
        formulation)
    position : position name
    X : (N, 3) stress-free node positions, mm

    Returns
    -------
    dict
        ``{"file", "element", "approximations", "notes"}``, or ``{"file": None, "why"}`` when FEBio
        cannot express the model (the file is then not written).
    """
    from breastmodel.pipeline.problem import position_model
    from mechanics.febio import FebioUnsupported, feb_comments, feb_text

    element = "tet4" if model.get("formulation") == "standard" else "ut4"
    m = position_model(problem, model, position)
    try:
        text = feb_text(m, X=np.asarray(X, float), element=element, approximate=True,
                        export_sets=True)
    except FebioUnsupported as exc:
        log.warning("outputs: no model_%s.feb: %s", position, exc)
        return {"file": None, "why": str(exc)}
    name = f"model_{position}.feb"
    write_atomic(out / name, text.encode("latin-1"))
    return {"file": name, "element": element,
            "approximations": feb_comments(text, "approximation"),
            "notes": feb_comments(text, "note")}


def write_vtm(path: Path, blocks: Mapping[str, Mapping[str, str]]) -> Path:
    """A VTK multiblock file (``.vtm``) that opens every listed file in ParaView at once.

    Parameters
    ----------
    path : output file
    blocks : block name -> dataset name -> file name (relative to ``path``'s folder)
    """
    from xml.sax.saxutils import quoteattr


    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="vtkMultiBlockDataSet" version="1.0" byte_order="LittleEndian" '
             'header_type="UInt64">', "  <vtkMultiBlockDataSet>"]
    for i, (name, files) in enumerate(blocks.items()):
        lines.append(f"    <Block index=\"{i}\" name={quoteattr(name)}>")
        for j, (label, file) in enumerate(files.items()):
            lines.append(f"      <DataSet index=\"{j}\" name={quoteattr(label)} "
                         f"file={quoteattr(file)}/>")
        lines.append("    </Block>")
    lines += ["  </vtkMultiBlockDataSet>", "</VTKFile>"]
    write_atomic(path, "\n".join(lines) + "\n")
    return path


def write_colour_tables(out: Path) -> list[str]:
    """``labels.ctbl`` (3D Slicer colour table) and ``labels_itksnap.txt`` (ITK-SNAP label
    description) for the label codes of :data:`LABEL_TABLE`; returns the file names."""

    ctbl = ["# 3D Slicer colour table of breastmodel label maps",
            "# index name R G B A (0-255)"]
    ctbl += [f"{c} {n} {r} {g} {b} {0 if c == 0 else 255}"
             for c, (n, (r, g, b)) in LABEL_TABLE.items()]
    write_atomic(out / "labels.ctbl", "\n".join(ctbl) + "\n")
    snap = ["################################################",
            "# ITK-SnAP Label Description File",
            "# IDX   -R-  -G-  -B-  -A--  VIS MSH  LABEL",
            "################################################"]
    snap += [f"{c:5d} {r:5d} {g:4d} {b:4d} {0 if c == 0 else 1:8d} {int(c > 0):2d} "
             f"{int(c > 0):2d}    \"{'Clear Label' if c == 0 else n}\""
             for c, (n, (r, g, b)) in LABEL_TABLE.items()]
    write_atomic(out / "labels_itksnap.txt", "\n".join(snap) + "\n")
    return ["labels.ctbl", "labels_itksnap.txt"]


def write_slicer_segmentation(labels, path: Path) -> Path:
    """Write a label map as a 3D Slicer segmentation (``.seg.nrrd``): one segment per label
    code present (names and colours of :data:`LABEL_TABLE`), read by Slicer as named,
    coloured segments and by any NRRD reader as the plain label map.

    Parameters
    ----------
    labels : SimpleITK.Image, integer label map (0 background)
    path : output file, ending in ``.seg.nrrd``
    """
    import SimpleITK as sitk

    img = sitk.Cast(labels, sitk.sitkUInt8)
    codes = [int(c) for c in np.unique(sitk.GetArrayViewFromImage(img)) if c > 0]
    size = img.GetSize()
    extent = " ".join(f"0 {n - 1}" for n in size)
    img.SetMetaData("Segmentation_MasterRepresentation", "Binary labelmap")
    img.SetMetaData("Segmentation_ContainedRepresentationNames", "Binary labelmap|")
    img.SetMetaData("Segmentation_ReferenceImageExtentOffset", "0 0 0")
    for i, c in enumerate(codes):
        name, rgb = LABEL_TABLE.get(c, (f"label_{c}", (128, 128, 128)))
        for key, value in (("ID", f"Segment_{c}"), ("Name", name),
                           ("Color", " ".join(f"{v / 255:.4f}" for v in rgb)),
                           ("LabelValue", str(c)), ("Layer", "0"), ("Extent", extent)):
            img.SetMetaData(f"Segment{i}_{key}", value)
    write_atomic_with(path, lambda tmp: sitk.WriteImage(img, str(tmp), useCompression=True),
                      suffix=".seg.nrrd")
    return path


def export_images(out: Path, register_dir: Path, reference: str,
                  positions) -> dict[str, Any]:
    """Copy the registered volumes, label maps and transforms out of the register stage,
    with colour tables, and write the detected fiducials in the reference frame.

    Parameters
    ----------
    out : output folder
    register_dir : the register stage's folder (see ``breastmodel register``)
    reference : reference position
    positions : every position name

    Returns
    -------
    dict
        ``{"volumes": {position: file}, "labels": {...}, "transforms": {...},
        "fiducials": {position: {label: (3,) mm}}}`` (reference frame, LPS).
    """
    import SimpleITK as sitk

    from imaging.markups import write_markups
    from registration.transforms import read_transform, transform_points, transform_text

    reg = json.loads((register_dir / "registration.json").read_text())
    files: dict[str, Any] = {"volumes": {}, "labels": {}, "transforms": {}, "fiducials": {}}
    for pos in positions:
        ref = pos == reference
        vol = f"{pos}_in_reference.nii.gz"
        lab = f"{pos}_labels_in_reference.nii.gz"
        _copy(register_dir / ("reference.nii.gz" if ref else vol), out / vol)
        _copy(register_dir / ("reference_labels.nii.gz" if ref else lab), out / lab)
        files["volumes"][pos], files["labels"][pos] = vol, lab
        seg = out / lab.replace(".nii.gz", ".seg.nrrd")
        write_slicer_segmentation(sitk.ReadImage(str(out / lab)), seg)
        files.setdefault("segmentations", {})[pos] = seg.name
        tfm = out / f"{pos}.tfm"
        if ref:
            write_atomic(tfm, transform_text(sitk.Euler3DTransform()))
            pts = reg.get("fiducials_reference_mm", {})
        else:
            _copy(register_dir / f"{pos}.tfm", tfm)
            own = reg.get("positions", {}).get(pos, {}).get("fiducials_mm", {})
            pts = {}
            if own:
                back = transform_points(read_transform(tfm).GetInverse(),
                                        np.array(list(own.values()), float))
                pts = dict(zip(own, back.tolist()))
        files["transforms"][pos] = tfm.name
        files["fiducials"][pos] = {k: np.asarray(v, float) for k, v in pts.items()}
    for pos, pts in files["fiducials"].items():
        if pts:
            write_markups(out / f"{pos}_fiducials.mrk.json", {pos: pts})
    rows = ["position,label,x,y,z"] + [
        f"{pos},{k},{v[0]:.4f},{v[1]:.4f},{v[2]:.4f}"
        for pos, pts in files["fiducials"].items() for k, v in pts.items()]
    write_atomic(out / "fiducials_in_reference.csv", "\n".join(rows) + "\n")
    files["colour_tables"] = write_colour_tables(out)
    files["registration"] = reg
    return files


def write_outputs(out: Path, problem_dir: Path, sf_dir: Path, pred_dirs: Mapping[str, Path],
                  params: Mapping[str, Any], fit_info: Mapping[str, Any] | None, *,
                  subject_id: str, register_dir: Path | None = None,
                  segment_dirs: Mapping[str, Path] | None = None,
                  volumes: Mapping[str, Path] | None = None,
                  config: Mapping[str, Any] | None = None,
                  refinement: Mapping[str, Any] | None = None) -> dict:
    """Assemble the run's outputs from finished stages (see the module notes).

    Parameters
    ----------
    out : output folder
    problem_dir, sf_dir : the problem and stress-free stage folders
    pred_dirs : position -> predict stage folder
    params : the parameters used (``params.json``)
    fit_info : the fit stage's result, or None
    subject_id : subject name for the report
    register_dir : the register stage folder (volumes, labels, transforms; None for a
        given problem folder: no images are exported)
    segment_dirs : position -> segment stage folder (label maps on each position's grid)
    volumes : position -> the subject's input volume (segmentation QA in the report)
    config : the resolved run config (shown in the report)
    refinement : the mesh-refinement check (``metrics.json`` and the report), or None

    Returns
    -------
    dict
        The metrics written to ``metrics.json`` ({"positions": {position: {mhd_mm, ...,
        "regions", "landmarks"}}, "stress_free": {...}}).
    """
    from breastmodel.config import write_json
    from breastmodel.pipeline.problem import load_problem
    from breastmodel.pipeline.report import write_report

    out = Path(out)
    problem = load_problem(problem_dir)
    sf = json.loads((sf_dir / "stress_free.json").read_text())
    metrics: dict[str, Any] = {"subject": subject_id, "reference": problem.reference,
                               "units": "mm", "positions": {},
                               "stress_free": {k: v for k, v in sf.items() if k != "history"}}
    pictures, blocks, febio = {}, {}, {}
    for pos, d in pred_dirs.items():
        metrics["positions"][pos], blocks[pos], pictures[pos], febio[pos] = _position_outputs(
            out, problem, sf_dir, params["model"], pos, d)
    write_vtm(out / "run.vtm", blocks)
    images = None
    if register_dir is not None:
        images = export_images(out, Path(register_dir), problem.reference, list(problem.gravity))
        images.update(segment_dirs=dict(segment_dirs or {}), input_volumes=dict(volumes or {}),
                      reference=problem.reference, out=out)
    meta = json.loads((Path(problem_dir) / "problem.json").read_text())
    metrics["mesh"] = {k: meta[k] for k in ("n_nodes", "n_tets", "mesh_size_mm", "mesh_size",
                                            "repairs", "skin_repairs", "field_of_view")
                       if k in meta}
    if refinement is not None:
        metrics["refinement"] = dict(refinement)
    metrics["files"] = {"paraview": "run.vtm", "positions": blocks, "febio": febio,
                        **({k: images[k] for k in ("volumes", "labels", "transforms",
                                                   "colour_tables")} if images else {})}
    write_json(out / "metrics.json", metrics)
    write_json(out / "params.json", params)
    write_report(out / "report.html", metrics, params, pictures, fit_info, sf,
                 subject_id=subject_id, images=images, config=config,
                 provenance_path=out / "provenance.json")
    return metrics


def _position_outputs(out: Path, problem, sf_dir: Path, model, pos: str, d: Path) -> tuple:
    """One predicted position's files (meshes, ``<pos>_predicted.ply``, FEBio model); its
    metrics summary, ParaView block, error-map picture and FEBio entry."""
    from breastmodel.pipeline.problem import mesh_of
    from meshing.export import write_ply

    m = json.loads((d / "metrics.json").read_text())
    with np.load(d / "predicted.npz") as z:
        pred = {k: z[k] for k in z.files}
    err = np.asarray(pred["signed_error"], float)
    summary = {**{k: m[k] for k in _SUMMARY_KEYS if k in m}, "regions": m.get("regions", {}),
               **({"landmarks": m["landmarks"]} if "landmarks" in m else {})}
    names = write_position_meshes(out, problem, pos, pred)
    block = {"mesh": names["mesh"], "predicted skin": names["skin"],
             "measured skin": names["measured_skin"]}
    x, nodes = pred["x"], pred["skin_nodes"]
    faces = np.asarray(mesh_of(problem, len(x)).face_sets["skin"])
    remap = np.full(len(x), -1, np.int64)
    remap[nodes] = np.arange(len(nodes))
    write_ply(x[nodes], remap[faces], out / f"{pos}_predicted.ply")
    X = pred["X"] if "X" in pred else np.load(sf_dir / "X.npy")
    return (summary, block, (x[nodes], remap[faces], err, problem.skins[pos]),
            write_febio(out, problem, model, pos, X))
