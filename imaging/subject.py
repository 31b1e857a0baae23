"""The subject folder: MRI volumes of one person in several positions, with metadata.

Layout::

    subject.toml      subject id, reference position, one table per position
    <volumes>         one 3-D volume per position (NIfTI/NRRD/MHA file or DICOM folder)
    fiducials.csv     optional: position,label,x,y,z (physical mm, that position's image frame)
                      (or 3D Slicer markups: fiducials.mrk.json, <position>_fiducials.mrk.json;
                      see :mod:`imaging.markups`)
    landmarks.csv     optional: internal anatomical landmarks, same columns

``subject.toml``::

    subject = "phantom-0000"
    reference = "supine"              # optional; default "supine" when present
    [positions.supine]
    volume = "supine.nii.gz"
    gravity = [0.0, 1.0, 0.0]         # unit vector in this image's physical (LPS) frame
    notes = "supine"                  # optional
    [positions.supine_tilted]
    volume = "supine_tilted.nii.gz"
    gravity = [-0.707, 0.707, 0.0]
    tilt_deg = 45.0                   # optional

:func:`read_subject` validates all of it and fails with one :class:`SubjectError` naming the
file and the problem.
"""

from __future__ import annotations

import csv
import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from imaging.io import VolumeError, check_path, read_volume

__all__ = ["SubjectError", "Position", "Subject", "read_subject", "read_points_csv"]

_TOP_KEYS = {"subject", "reference", "positions"}
_POSITION_KEYS = {"volume", "gravity", "notes", "tilt_deg"}
_CSV_COLUMNS = ["position", "label", "x", "y", "z"]
#: Largest accepted deviation of |gravity| from 1.
GRAVITY_TOLERANCE = 1e-3
#: A position name is an identifier: it names output files, so no path separators or dots.
POSITION_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,63}")


class SubjectError(ValueError):
    """The subject folder is invalid; the message names the file and the problem."""


@dataclass(frozen=True)
class Position:
    """One scanned position.

    Attributes
    ----------
    name : str
    volume_path : Path
        File or DICOM folder of the volume.
    gravity : (3,) float
        Unit gravity direction in this image's physical (LPS) frame (read-only array).
    notes : str
    tilt_deg : float or None
    """

    name: str
    volume_path: Path
    gravity: np.ndarray
    notes: str = ""
    tilt_deg: float | None = None


@dataclass(frozen=True)
class Subject:
    """A validated subject folder.

    Attributes
    ----------
    id : str
    root : Path
    reference : str
        Name of the position whose image frame is the reference frame.
    positions : mapping str -> Position
    fiducials : mapping position -> label -> (3,) float, mm
        Skin markers (empty if there is no ``fiducials.csv``).
    landmarks : mapping position -> label -> (3,) float, mm
        Internal anatomical landmarks (empty if there is no ``landmarks.csv``).
    """

    id: str
    root: Path
    reference: str
    positions: dict[str, Position]
    fiducials: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    landmarks: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def load(self, position: str) -> sitk.Image:
        """Read (and validate) the volume of ``position``."""
        if position not in self.positions:
            raise SubjectError(
                f"subject {self.root}: no position {position!r}; has {sorted(self.positions)}"
            )
        try:
            return read_volume(self.positions[position].volume_path)
        except VolumeError as exc:
            raise SubjectError(f"subject {self.root}: {exc}") from None


def read_subject(folder: str | Path, *, check_volumes: bool = True) -> Subject:
    """Read and validate a subject folder.

    Parameters
    ----------
    folder
        The subject folder (holding ``subject.toml``).
    check_volumes
        Also read every volume and check it (3-D, scalar, finite, spacing > 0). Reading is
        the only way to see NaNs; pass False for a quick look at the metadata.

    Returns
    -------
    Subject

    Raises
    ------
    SubjectError
        On the first problem found, naming the file and what is wrong.
    """
    root = Path(folder)
    toml_path, meta = _read_toml(root)
    _check_keys(meta, _TOP_KEYS, f"{toml_path}")
    sid = meta.get("subject")
    if not isinstance(sid, str) or not sid.strip():
        raise SubjectError(f"{toml_path}: 'subject' must be a non-empty string id")
    table = meta.get("positions")
    if not isinstance(table, dict) or not table:
        raise SubjectError(f"{toml_path}: needs at least one [positions.<name>] table")

    positions = {}
    for name, entry in table.items():
        positions[name] = _read_position(root, toml_path, name, entry)
    reference = _reference(meta, positions, toml_path)

    if check_volumes:
        for pos in positions.values():
            try:
                read_volume(pos.volume_path)
            except VolumeError as exc:
                raise SubjectError(f"subject {root} position {pos.name!r}: {exc}") from None

    fiducials = _optional_points(root / "fiducials.csv", positions)
    if not fiducials:
        fiducials = _markups_fiducials(root, positions)
    landmarks = _optional_points(root / "landmarks.csv", positions)
    return Subject(
        id=sid,
        root=root,
        reference=reference,
        positions=positions,
        fiducials=fiducials,
        landmarks=landmarks,
    )


def _read_toml(root: Path) -> tuple[Path, dict]:
    """(path, contents) of the folder's ``subject.toml``, after checking that the folder's
    path is valid UTF-8 and that both exist."""
    try:
        check_path(root)
    except VolumeError:
        raise SubjectError(f"subject folder {os.fspath(root)!a}: the path is not valid UTF-8; "
                           "rename it") from None
    if not root.is_dir():
        raise SubjectError(f"subject folder {root} does not exist")
    toml_path = root / "subject.toml"
    if not toml_path.is_file():
        raise SubjectError(f"subject {root}: subject.toml is missing")
    try:
        with toml_path.open("rb") as f:
            return toml_path, tomllib.load(f)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SubjectError(f"{toml_path}: not valid TOML ({exc})") from None
    except OSError as exc:
        raise SubjectError(f"{toml_path}: cannot be read ({exc.strerror})") from None


def _reference(meta: dict, positions: dict, toml_path: Path) -> str:
    """The reference position: ``reference``, else ``supine`` when there is one."""
    reference = meta.get("reference", "supine" if "supine" in positions else None)
    if reference is not None and not isinstance(reference, str):
        raise SubjectError(f"{toml_path}: 'reference' must be a position name (a string), "
                           f"got {reference!r}")
    if reference is None:
        raise SubjectError(
            f"{toml_path}: no 'reference' given and no 'supine' position to default to"
        )
    if reference not in positions:
        raise SubjectError(
            f"{toml_path}: reference position {reference!r} is not among the positions "
            f"{sorted(positions)}"
        )
    return reference


def _check_keys(table: dict, allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise SubjectError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _read_position(root: Path, toml_path: Path, name: str, entry: Any) -> Position:
    where = f"{toml_path} [positions.{name}]"
    if not POSITION_NAME.fullmatch(name):
        raise SubjectError(
            f"{toml_path}: position name {name!r} is not an identifier (a letter, then "
            "letters, digits, '_' or '-', at most 64): it names output files"
        )
    if not isinstance(entry, dict):
        raise SubjectError(f"{where}: must be a table")
    _check_keys(entry, _POSITION_KEYS, where)
    volume = entry.get("volume")
    if not isinstance(volume, str) or not volume:
        raise SubjectError(f"{where}: 'volume' (file or DICOM folder name) is missing")
    path = Path(volume) if Path(volume).is_absolute() else root / volume
    if "\0" in volume:
        raise SubjectError(f"{where}: 'volume' holds a NUL character")
    if not path.exists():
        raise SubjectError(f"{where}: volume {path} does not exist")
    g = entry.get("gravity")
    if (
        not isinstance(g, list)
        or len(g) != 3
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in g)
    ):
        raise SubjectError(f"{where}: 'gravity' must be a list of 3 numbers, got {g!r}")
    gravity = np.asarray(g, dtype=float)
    norm = float(np.linalg.norm(gravity))
    if not np.all(np.isfinite(gravity)) or abs(norm - 1.0) > GRAVITY_TOLERANCE:
        raise SubjectError(f"{where}: 'gravity' must be a unit vector, got {g} (norm {norm:.4g})")
    gravity.setflags(write=False)
    notes = entry.get("notes", "")
    if not isinstance(notes, str):
        raise SubjectError(f"{where}: 'notes' must be a string")
    tilt = entry.get("tilt_deg")
    if tilt is not None:
        if isinstance(tilt, bool) or not isinstance(tilt, int | float) or not math.isfinite(tilt):
            raise SubjectError(f"{where}: 'tilt_deg' must be a number, got {tilt!r}")
        tilt = float(tilt)
    return Position(name, path, gravity, notes, tilt)


def _markups_fiducials(root: Path, positions: dict) -> dict[str, dict[str, np.ndarray]]:
    """Fiducials from 3D Slicer markups when the folder has no ``fiducials.csv``."""
    from imaging.markups import MarkupsError, read_fiducial_markups

    try:
        return read_fiducial_markups(root, list(positions))
    except MarkupsError as exc:
        raise SubjectError(str(exc)) from None


def _optional_points(path: Path, positions: dict) -> dict[str, dict[str, np.ndarray]]:
    if not path.exists():
        return {}
    return read_points_csv(path, positions=list(positions))


def read_points_csv(path: str | Path, *, positions: list[str] | None = None):
    """Read a ``position,label,x,y,z`` CSV of points in physical mm.

    Checks the header, that coordinates are finite numbers, that (position, label) pairs are
    unique, that positions are known (when ``positions`` is given) and that every position
    listed has the same set of labels.

    Returns
    -------
    dict
        position -> label -> (3,) float array (read-only), mm.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SubjectError(f"{path}: cannot be read ({exc})") from None
    rows = list(csv.reader(text.splitlines()))
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if not rows:
        raise SubjectError(f"{path}: empty; expected header {','.join(_CSV_COLUMNS)}")
    header = [c.strip().lower() for c in rows[0]]
    if header != _CSV_COLUMNS:
        raise SubjectError(
            f"{path}: header must be {','.join(_CSV_COLUMNS)}, got {','.join(rows[0])}"
        )
    out: dict[str, dict[str, np.ndarray]] = {}
    for line_no, row in enumerate(rows[1:], start=2):
        if len(row) != 5:
            raise SubjectError(f"{path} line {line_no}: expected 5 columns, got {len(row)}")
        pos, label = row[0].strip(), row[1].strip()
        if not pos or not label:
            raise SubjectError(f"{path} line {line_no}: empty position or label")
        try:
            xyz = np.array([float(c) for c in row[2:]])
        except ValueError:
            raise SubjectError(
                f"{path} line {line_no}: coordinates must be numbers, got {row[2:]}"
            ) from None
        if not np.all(np.isfinite(xyz)):
            raise SubjectError(f"{path} line {line_no}: coordinates must be finite")
        if positions is not None and pos not in positions:
            raise SubjectError(
                f"{path} line {line_no}: unknown position {pos!r}; subject.toml has "
                f"{sorted(positions)}"
            )
        if label in out.get(pos, {}):
            raise SubjectError(f"{path} line {line_no}: duplicate label {label!r} in {pos!r}")
        xyz.setflags(write=False)
        out.setdefault(pos, {})[label] = xyz
    labels = {p: sorted(v) for p, v in out.items()}
    if len({tuple(v) for v in labels.values()}) > 1:
        detail = "; ".join(f"{p}: {','.join(v)}" for p, v in sorted(labels.items()))
        raise SubjectError(f"{path}: labels differ between positions ({detail})")
    return out
