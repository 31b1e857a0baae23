"""3D Slicer markups (``.mrk.json``) point lists: read and write, always returned in LPS.

A Slicer point list holds labelled control points in the ``coordinateSystem`` its file names
(``"LPS"``, the default Slicer writes, or ``"RAS"``; RAS = LPS with x and y negated). Our
convention is SimpleITK's physical space (LPS, mm), so reading converts RAS files.

A subject folder may give its fiducials as markups instead of ``fiducials.csv``:

- ``fiducials.mrk.json`` with one point list per position, each named after its position
  (the markup's ``"name"``), or
- ``<position>_fiducials.mrk.json``, one point list per file (as Slicer saves one node).

Points are in that position's image frame, as in the CSV.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from imaging.atomic import write_atomic

__all__ = ["MarkupsError", "read_markups", "read_fiducial_markups", "write_markups",
           "markups_files"]

SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
          "Resources/Schema/markups-schema-v1.0.3.json#")
_LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])


class MarkupsError(ValueError):
    """A markups file is invalid; the message names the file and the problem."""


def read_markups(path: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """Read every point list of a ``.mrk.json`` file.

    Parameters
    ----------
    path : the markups file

    Returns
    -------
    dict
        markup name (``"name"``, else the file name without ``.mrk.json``, numbered when a
        file holds several unnamed lists) -> control point label -> (3,) float, LPS mm.

    Raises
    ------
    MarkupsError
        Not JSON, no ``markups`` list, an unknown coordinate system or units, a control point
        without a finite 3-vector position, or a label used twice in one list.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MarkupsError(f"{path}: cannot be read as markups JSON ({exc})") from None
    lists = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(lists, list) or not lists:
        raise MarkupsError(f"{path}: no 'markups' list")
    stem = path.name.removesuffix(".json").removesuffix(".mrk")
    out: dict[str, dict[str, np.ndarray]] = {}
    for i, m in enumerate(lists):
        where = f"{path} markups[{i}]"
        if not isinstance(m, dict):
            raise MarkupsError(f"{where}: must be an object")
        system = str(m.get("coordinateSystem", "LPS")).upper()
        if system not in ("LPS", "RAS"):
            raise MarkupsError(f"{where}: coordinateSystem {system!r} is neither LPS nor RAS")
        units = m.get("coordinateUnits", "mm")
        if units != "mm":
            raise MarkupsError(f"{where}: coordinateUnits {units!r}; only mm is supported")
        name = m.get("name") or (stem if len(lists) == 1 else f"{stem}_{i}")
        points: dict[str, np.ndarray] = {}
        for j, cp in enumerate(m.get("controlPoints") or []):
            label = str(cp.get("label") or f"F-{j + 1}")
            if cp.get("positionStatus", "defined") != "defined":
                continue  # a placeholder Slicer keeps for a point not placed yet
            p = cp.get("position")
            if (not isinstance(p, list) or len(p) != 3
                    or not all(isinstance(v, int | float) and math.isfinite(v) for v in p)):
                raise MarkupsError(f"{where} control point {label!r}: position must be 3 "
                                   f"finite numbers, got {p!r}")
            if label in points:
                raise MarkupsError(f"{where}: control point label {label!r} is used twice")
            v = np.asarray(p, float) * (_LPS_TO_RAS if system == "RAS" else 1.0)
            v.setflags(write=False)
            points[label] = v
        out[str(name)] = points
    return out


def markups_files(folder: str | Path, positions) -> list[Path]:
    """The fiducial markups files of a subject folder (see the module notes), sorted."""
    folder = Path(folder)
    found = [folder / "fiducials.mrk.json"] if (folder / "fiducials.mrk.json").is_file() else []
    found += [folder / f"{p}_fiducials.mrk.json" for p in positions
              if (folder / f"{p}_fiducials.mrk.json").is_file()]
    return found


def read_fiducial_markups(folder: str | Path,
                          positions) -> dict[str, dict[str, np.ndarray]]:
    """A subject folder's fiducials from its markups files (empty when it has none).

    Parameters
    ----------
    folder : subject folder
    positions : the subject's position names

    Returns
    -------
    dict
        position -> label -> (3,) float, LPS mm in that position's image frame.

    Raises
    ------
    MarkupsError
        A list named after no position, a position given twice, or positions whose labels
        differ.
    """
    positions = list(positions)
    out: dict[str, dict[str, np.ndarray]] = {}
    for path in markups_files(folder, positions):
        lists = read_markups(path)
        if path.name != "fiducials.mrk.json":
            pos = path.name.removesuffix("_fiducials.mrk.json")
            lists = {pos: next(iter(lists.values()))} if len(lists) == 1 else lists
        for name, pts in lists.items():
            if name not in positions:
                raise MarkupsError(f"{path}: point list {name!r} is named after no position "
                                   f"(positions: {positions})")
            if name in out:
                raise MarkupsError(f"{path}: fiducials of position {name!r} are given twice")
            out[name] = pts
    labels = {p: sorted(v) for p, v in out.items()}
    if len({tuple(v) for v in labels.values()}) > 1:
        raise MarkupsError(f"{folder}: fiducial labels differ between positions: {labels}")
    return out


def write_markups(path: str | Path, lists: Mapping[str, Mapping[str, np.ndarray]], *,
                  coordinate_system: str = "LPS") -> Path:
    """Write point lists as one Slicer ``.mrk.json`` file (atomically).

    Parameters
    ----------
    path : output file (name it ``*.mrk.json`` for Slicer to recognise it)
    lists : list name -> label -> (3,) LPS mm
    coordinate_system : ``"LPS"`` (Slicer's own default for files) or ``"RAS"``
    """
    system = coordinate_system.upper()
    if system not in ("LPS", "RAS"):
        raise ValueError(f"markups: coordinate system {coordinate_system!r} is neither LPS "
                         "nor RAS")
    flip = _LPS_TO_RAS if system == "RAS" else np.ones(3)
    markups = []
    for name, pts in lists.items():
        cps = [{"id": str(i + 1), "label": str(k), "description": "", "associatedNodeID": "",
                "position": (np.asarray(v, float) * flip).tolist(),
                "orientation": [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0],
                "selected": True, "locked": False, "visibility": True,
                "positionStatus": "defined"} for i, (k, v) in enumerate(pts.items())]
        markups.append({"type": "Fiducial", "name": str(name), "coordinateSystem": system,
                        "coordinateUnits": "mm", "locked": False, "labelFormat": "%N-%d",
                        "lastUsedControlPointNumber": len(cps), "controlPoints": cps})
    return write_atomic(path, json.dumps({"@schema": SCHEMA, "markups": markups}, indent=2)
                        + "\n")
