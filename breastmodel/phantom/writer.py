"""Make a synthetic subject folder (the pipeline's input) and its truth folder.

Per position: draw a rigid motion, map the scanner grid back into the patient frame (inverse
motion, then the inverse of the position's deformation), voxelise the anatomy there, render
the MRI-like image, and write everything. The deformation is the identity today; when the
mechanics solver exists, :func:`displacement` returns the simulated field and nothing else
changes.
"""

from __future__ import annotations

import csv
import io
import logging
import zlib
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import tomli_w

from breastmodel.config import write_atomic, write_json
from breastmodel.phantom.anatomy import TISSUE_NAMES, Anatomy
from breastmodel.phantom.motion import patient_gravity, random_motion
from breastmodel.phantom.placement import deformed_point, no_displacement
from breastmodel.phantom.rendering import intensity_table, render
from breastmodel.phantom.voxelize import Grid, voxelize
from imaging.io import write_volume
from registration.transforms import transform_text

__all__ = ["make_phantom", "displacement", "truth_folder", "INTENSITY_SCALE"]

log = logging.getLogger("breastmodel.phantom")

#: Stored voxel value = relative intensity x this (int16 volumes; fat ~ 1000).
INTENSITY_SCALE = 1000.0


def truth_folder(out: str | Path) -> Path:
    """The truth folder that goes with subject folder ``out``: ``<out>_truth``."""
    out = Path(out)
    return out.with_name(out.name + "_truth")


def displacement(
    position: str, anatomy: Anatomy | None = None
) -> Callable[[np.ndarray], np.ndarray]:
    """Deformation of the anatomy in ``position``, sampled at deformed (current) points.

    Returns a callable taking current patient-frame points x (n, 3) mm and returning u (n, 3)
    mm such that the material point is X = x - u(x). The identity (u = 0) for now; a simulated
    gravity deformation plugs in here.
    """
    del position, anatomy
    return no_displacement


def _stream(seed: int, position: str, purpose: int) -> np.random.Generator:
    # Independent of the order and set of positions: keyed by the position's name.
    return np.random.default_rng([int(seed), zlib.crc32(position.encode()), purpose])


def _image(array: np.ndarray, grid: Grid) -> sitk.Image:
    img = sitk.GetImageFromArray(array)
    img.SetSpacing(tuple(map(float, grid.spacing_xyz)))
    img.SetOrigin(grid.origin)
    img.SetDirection((1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
    return img


def _csv(rows: list[tuple]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["position", "label", "x", "y", "z"])
    for pos, label, p in rows:
        w.writerow([pos, label, *(f"{v:.3f}" for v in p)])
    return buf.getvalue()


def make_phantom(
    out: str | Path,
    *,
    seed: int = 0,
    voxel_size: float | Sequence[float] = 1.0,
    snr: float = 20.0,
    bias: float = 0.3,
    positions: Sequence[str] = ("prone", "supine", "supine_tilted"),
    max_rotation_deg: float = 5.0,
    max_translation_mm: float = 10.0,
    small: bool = False,
    anatomy: Anatomy | None = None,
    progress: bool = True,
    deformation: Callable[[str], Callable[[np.ndarray], np.ndarray]] | None = None,
    contrast: str = "t2",
    fat_suppressed: bool = False,
) -> Path:
    """Write a synthetic subject folder and its truth folder ``<out>_truth``.

    Parameters
    ----------
    out
        Subject folder to create (existing files of the same names are replaced).
    seed
        Seed of every random choice; the same seed gives byte-identical volumes.
    voxel_size
        Voxel size, mm: one number (isotropic) or (x, y, z).
    snr
        Mean fat signal / Rician noise sigma.
    bias
        Bias-field amplitude (relative, 0.3 = +-30 %).
    positions
        Position names (see :func:`breastmodel.phantom.motion.patient_gravity`).
    max_rotation_deg, max_translation_mm
        Bounds of the random rigid motion of each position (degrees, mm).
    small
        Use :meth:`Anatomy.small` (half-size torso, small field of view) when ``anatomy`` is
        None.
    anatomy
        Explicit anatomy parameters (default :class:`Anatomy`).
    progress
        Show a tqdm progress bar.
    deformation
        Optional ``deformation(position) -> u`` replacing :func:`displacement` (same contract:
        u maps deformed patient-frame points (n, 3) mm to displacements (n, 3) mm). Markers
        and landmarks are then moved by the forward map x = X + u(x).
    contrast
        ``"t2"`` or ``"t1"`` tissue intensities (:data:`~breastmodel.phantom.rendering.
        INTENSITY`).
    fat_suppressed
        Suppress the fat signal (SNR then refers to the gland signal).

    Returns
    -------
    Path
        The subject folder. Volumes are int16 NIfTI with fat ~ ``INTENSITY_SCALE``.
    """
    positions = list(positions)
    _check_arguments(positions, seed, voxel_size, max_rotation_deg, max_translation_mm)
    anatomy = anatomy if anatomy is not None else (Anatomy.small() if small else Anatomy())
    gravities = {p: patient_gravity(p) for p in positions}  # fails early on unknown names
    out, truth = Path(out), truth_folder(out)
    for folder in (out, truth):
        folder.mkdir(parents=True, exist_ok=True)
    grid = Grid.from_box(anatomy.fov_min, anatomy.fov_max, voxel_size)
    reference = "supine" if "supine" in positions else positions[0]
    look = {"snr": snr, "bias": bias, "contrast": contrast, "fat_suppressed": fat_suppressed}
    scans = _scan_positions(out, truth, anatomy, grid, gravities, seed=seed, look=look,
                            motion_bounds=(max_rotation_deg, max_translation_mm),
                            deformation=deformation, progress=progress)
    toml = {"subject": f"phantom-{seed:04d}", "reference": reference,
            "positions": {name: sc.entry for name, sc in scans.items()}}
    write_atomic(out / "subject.toml", tomli_w.dumps(toml))
    for file, points in (("fiducials.csv", "markers"), ("landmarks.csv", "landmarks")):
        write_atomic(out / file, _csv([(name, k, p) for name, sc in scans.items()
                                       for k, p in getattr(sc, points).items()]))
    write_json(truth / "truth.json", _truth_doc(toml["subject"], seed, look, grid, anatomy,
                                                reference, scans))
    log.info("phantom: wrote %s and %s", out, truth)
    return out


def _check_arguments(positions: list[str], seed, voxel_size, max_rotation_deg,
                     max_translation_mm) -> None:
    """Refuse no or duplicate positions, a bad seed, voxel size or motion bounds."""
    if not positions:
        raise ValueError("phantom: at least one position is needed")
    if len(set(positions)) != len(positions):
        raise ValueError(f"phantom: duplicate position names in {positions}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"phantom: seed must be a non-negative integer, got {seed}")
    vs = np.asarray(voxel_size, dtype=float)
    if vs.shape not in ((), (3,)) or not np.all(vs > 0):
        raise ValueError(f"phantom: voxel size must be one number or three, all > 0 mm; got "
                         f"{voxel_size!r}")
    if max_rotation_deg < 0 or max_translation_mm < 0:
        raise ValueError("phantom: motion bounds must be >= 0")


@dataclass(frozen=True)
class _Scan:
    """One written position: its ``subject.toml`` entry, marker and landmark positions in
    the image frame (mm) and its ``truth.json`` entry."""

    entry: dict
    markers: dict[str, np.ndarray]
    landmarks: dict[str, np.ndarray]
    truth: dict


def _scan_positions(out: Path, truth: Path, anatomy: Anatomy, grid: Grid, gravities: dict, *,
                    seed: int, look: dict, motion_bounds: tuple[float, float], deformation,
                    progress: bool) -> dict[str, _Scan]:
    """Move, deform, voxelise, render and write every position (one progress bar)."""
    from tqdm import tqdm

    scans = {}
    bar = tqdm(total=100 * len(gravities), desc="phantom", unit="%", disable=not progress)
    for name, (g_patient, tilt) in gravities.items():
        motion = random_motion(
            _stream(seed, name, 0),
            max_rotation_deg=motion_bounds[0],
            max_translation_mm=motion_bounds[1],
            center=anatomy.rotation_center,
        )
        u = deformation(name) if deformation is not None else displacement(name, anatomy)
        tissue = voxelize(
            anatomy,
            grid,
            image_to_patient=np.linalg.inv(motion.matrix()),
            displacement=None if u is no_displacement else u,
            progress=_ticker(bar),
        )
        rendered = render(tissue, _stream(seed, name, 1), **look)
        _write_volumes(out, truth, name, grid, tissue, rendered, motion)
        g_image = motion.apply_vector(g_patient)
        entry = {"volume": f"{name}.nii.gz", "gravity": [round(float(v), 12) for v in g_image]}
        entry["notes"] = f"synthetic {name} scan, rigidly moved"
        if tilt is not None:
            entry["tilt_deg"] = tilt
        r = anatomy.marker_radius
        markers = {k: motion.apply(deformed_point(v, u, radius=r))[0]
                   for k, v in anatomy.markers().items()}
        landmarks = {k: motion.apply(deformed_point(v, u, radius=r))[0]
                     for k, v in anatomy.landmarks().items()}
        scans[name] = _Scan(entry, markers, landmarks, _position_truth(
            motion, g_patient, g_image, tilt, markers, landmarks, rendered, tissue, grid))
    bar.close()
    return scans


def _ticker(bar) -> Callable[[float], None]:
    """Progress callback of one position: moves ``bar`` by its share of 100 per position."""
    done = [0]

    def tick(frac: float, done=done) -> None:
        bar.update(round(100 * frac) - done[0])
        done[0] = round(100 * frac)

    return tick


def _write_volumes(out: Path, truth: Path, name: str, grid: Grid, tissue, rendered,
                   motion) -> None:
    """The position's image (int16, fat ~ ``INTENSITY_SCALE``), its fine tissue and label
    maps and its rigid motion."""
    stored = np.clip(np.rint(rendered.image * INTENSITY_SCALE), 0, 32767).astype(np.int16)
    write_volume(_image(stored, grid), out / f"{name}.nii.gz")
    write_volume(_image(tissue.fine, grid), truth / f"{name}_tissue.nii.gz")
    write_volume(_image(tissue.seg, grid), truth / f"{name}_labels.nii.gz")
    write_atomic(truth / f"{name}_motion.tfm", transform_text(motion.to_sitk()))


def _position_truth(motion, g_patient, g_image, tilt, markers, landmarks, rendered, tissue,
                    grid: Grid) -> dict:
    """The ``truth.json`` entry of one position."""
    volumes = np.bincount(tissue.fine.ravel(), minlength=len(TISSUE_NAMES))
    return {
        "motion": motion.as_dict(),
        "gravity_patient": g_patient.tolist(),
        "gravity_image": g_image.tolist(),
        "tilt_deg": tilt,
        "markers_mm": {k: v.tolist() for k, v in markers.items()},
        "landmarks_mm": {k: v.tolist() for k, v in landmarks.items()},
        "noise_sigma": rendered.noise_sigma * INTENSITY_SCALE,
        "mean_fat_signal": rendered.mean_fat * INTENSITY_SCALE,
        "mean_reference_signal": rendered.mean_reference * INTENSITY_SCALE,
        "tissue_volumes_mm3": {
            n: float(c) * grid.voxel_volume for n, c in zip(TISSUE_NAMES, volumes)
        },
    }


def _truth_doc(subject: str, seed: int, look: dict, grid: Grid, anatomy: Anatomy,
               reference: str, scans: dict[str, _Scan]) -> dict:
    """The subject's ``truth.json``: rendering settings, codes, anatomy and positions."""
    contrast, fat_suppressed = look["contrast"], look["fat_suppressed"]
    return {
        "subject": subject,
        "seed": seed,
        "snr": look["snr"],
        "bias_amplitude": look["bias"],
        "voxel_size_mm": grid.spacing,
        "contrast": contrast,
        "fat_suppressed": bool(fat_suppressed),
        "intensity_scale": INTENSITY_SCALE,
        "intensity": {TISSUE_NAMES[k]: v for k, v in
                      intensity_table(contrast, fat_suppressed=fat_suppressed).items()},
        "tissue_codes": {n: i for i, n in enumerate(TISSUE_NAMES)},
        "label_codes": {"background": 0, "breast": 1, "muscle": 2, "gland": 3},
        "reference": reference,
        "anatomy": asdict(anatomy),
        "markers_patient_mm": {k: v.tolist() for k, v in anatomy.markers().items()},
        "landmarks_patient_mm": {k: v.tolist() for k, v in anatomy.landmarks().items()},
        "patient_frame": "LPS mm, origin on the torso axis; image = motion(patient)",
        "positions": {name: sc.truth for name, sc in scans.items()},
    }
