"""A family of varied synthetic subjects with the variety of real breast MRI.

A :class:`SubjectSpec` (:mod:`breastmodel.phantom.subject_spec`) is plain, frozen, JSON-
serialisable data holding every choice that makes one subject: anatomy (size, cup, left/right
difference, ptosis, subcutaneous fat, gland), field of view (whole torso, cut by a breast
coil's box, or a muscle slab that meets air), voxel spacing, contrast (T2/T1, fat suppression),
SNR, bias, rigid-motion bounds, positions (with the tilt of the tilted one), the truth physics
and the truth mesh size. :func:`draw_spec` draws a spec from a seed (deterministically; one
independent stream per seed); :func:`make_subject` writes the subject folder and its truth
folder, the truth deformation computed by FEBio (an FE code independent of ours) or by our
solver.

Sizes: ``"small"`` subjects are half-size anatomies in a small field of view with 1-2 mm
voxels and a truth mesh of a few thousand tets (a CI slice of a few subjects makes its truths
and runs the pipeline in minutes); ``"full"`` subjects are adult-size with the voxels of real
scans (1 mm, 0.5 x 0.5 x 0.6 mm, 0.7 x 0.7 x 1.5 mm).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.phantom.rendering import CONTRASTS
from breastmodel.phantom.subject_spec import (
    _SCALE,
    CUPS,
    FOV_KINDS,
    PHYSICS,
    SIZES,
    VOXEL_SPACINGS,
    SubjectSpec,
)
from breastmodel.phantom.truth_model import NU, TruthModel
from mechanics.mesh import BREAST_SIDE

__all__ = [
    "SubjectSpec", "draw_spec", "make_subject", "truth_model", "CUPS", "FOV_KINDS",
    "MODULUS_BANDS", "PHYSICS",
    "SIZES", "VOXEL_SPACINGS",
]

log = logging.getLogger("breastmodel.phantom")

#: Draw stream tag (keeps family draws independent of other uses of the same seed).
_STREAM = 0xFA11
#: Bands of the breast modulus an adult subject is drawn from, kPa (half-size subjects take
#: half: sag scales as rho g L^2 / E, so the half-size anatomy strains as much as the adult).
#: ``"standard"``, the suite's: adult breasts sag about 17-33 mm prone to supine (about 50 mm
#: at 1 kPa, :data:`~breastmodel.phantom.truth_model.E_BREAST`), the half-size ones 8-17 mm,
#: where the skin's fit hardly tells 10 % of the modulus from a voxel of segmentation (the
#: README's "Is the truth converged?"). ``"soft"``: the lower half of the moduli fitted to
#: prone-supine MRI in vivo (0.2-6 kPa; Mira et al. 0.2-0.3 kPa with a 4 kPa skin), twice
#: the sag: a half-size torso (seed 3) at 0.5 kPa sags 23 / 33 / 42 mm at most in prone /
#: supine / tilted (FEBio). The same draw maps into either band, so a seed keeps its place.
MODULUS_BANDS = {"standard": (1.5, 3.0), "soft": (0.7, 1.4)}


def truth_model(spec: SubjectSpec) -> TruthModel:
    """Truth physics of a spec: Neo-Hookean breast (``breast_E_kpa``) and muscle
    (``muscle_E_kpa``), nu 0.49, the posterior chest wall (node set ``fixed``) held, bonded
    breast-muscle interface (conforming mesh), no skin; then each ``+``-joined entry of
    ``spec.physics`` (:data:`PHYSICS`) applied in order."""
    nh = {"name": "neo_hookean", "nu": NU}
    mats: dict[int, dict] = {1: {**nh, "E": spec.breast_E_kpa}, 2: {**nh, "E": spec.muscle_E_kpa},
                             3: {**nh, "E": spec.breast_E_kpa}}
    effects: dict[str, dict] = {"fixed": {"node_set": "fixed"}}
    for part in spec.physics.split("+"):
        over, eff = PHYSICS[part]
        for code, o in over.items():
            m = dict(mats[code] if code in mats else mats[BREAST_SIDE[code]])
            o = dict(o)
            m["E"] = float(m["E"]) * float(o.pop("E_factor", 1.0))
            m.update(o)
            mats[code] = m
        effects.update({k: dict(v) for k, v in eff.items()})
    from breastmodel.phantom.truth_solvers import FEBIO_SOFT_BELOW_KPA, FEBIO_STEPS

    adult_E = spec.breast_E_kpa / _SCALE[spec.size]
    steps = (FEBIO_STEPS * math.ceil(FEBIO_SOFT_BELOW_KPA / adult_E)
             if adult_E < FEBIO_SOFT_BELOW_KPA else None)
    return TruthModel(materials=mats, effects=effects, mesh_size_mm=spec.truth_mesh_size_mm,
                      name=spec.physics, load_steps=steps)


def draw_spec(seed: int, *, size: str = "small", band: str = "standard",
              **overrides: Any) -> SubjectSpec:
    """Draw a varied subject from a seed.

    Every field is drawn in a fixed order from one stream of ``seed`` and ``size``, then
    ``overrides`` replace fields by name (the other fields do not change), so a seed always
    gives the same subject and an override changes only what it names.

    Parameters
    ----------
    seed
        Non-negative integer.
    size
        ``"small"`` or ``"full"``.
    band
        The breast modulus' band, a key of :data:`MODULUS_BANDS`.
    **overrides
        Fields of :class:`SubjectSpec` to set instead of drawing them.

    Returns
    -------
    SubjectSpec

    Notes
    -----
    Ranges: fov uniform over :data:`FOV_KINDS`; cup A-D; asymmetry +-0.15; ptosis 0-0.4;
    exponent 2-2.6; subcutaneous fat 4-16 mm (adult; scaled by size); gland scale 0.35-0.7;
    voxel spacing from :data:`VOXEL_SPACINGS`; T2 or T1, fat suppressed half the time;
    SNR 10-40; bias 10-40 %; rigid motion up to 15 deg / 30 mm (full) or 8 deg / 12 mm
    (small: the small field of view leaves less room); tilt 0-60 deg (whole degrees);
    breast modulus 1.5-3 kPa for full subjects and half that for small ones (sag scales as
    rho g L^2 / E: the half-size anatomy then strains as much as the adult); truth mesh 5 mm.
    """
    if size not in SIZES:
        raise ValueError(f"phantom: size must be one of {SIZES}, got {size!r}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"phantom: seed must be a non-negative integer, got {seed!r}")
    if band not in MODULUS_BANDS:
        raise ValueError(f"phantom: band must be one of {sorted(MODULUS_BANDS)}, got {band!r}")
    known = {f.name for f in fields(SubjectSpec)} - {"seed", "size"}
    extra = set(overrides) - known
    if extra:
        raise ValueError(f"phantom: draw_spec got unknown field(s) {sorted(extra)}; known "
                         f"{sorted(known)}")
    rng = np.random.default_rng([int(seed), _STREAM, SIZES.index(size)])
    s = _SCALE[size]
    full = size == "full"

    def u(lo, hi, nd=3):
        return round(float(rng.uniform(lo, hi)), nd)

    spacings = VOXEL_SPACINGS[size]
    e_lo, e_hi = MODULUS_BANDS[band]
    drawn = dict(
        fov=str(FOV_KINDS[rng.integers(len(FOV_KINDS))]),
        cup=str(sorted(CUPS)[rng.integers(len(CUPS))]),
        asymmetry=u(-0.15, 0.15),
        ptosis=u(0.0, 0.4),
        exponent=u(2.0, 2.6),
        subcutaneous_fat_mm=round(max(2.0, s * float(rng.uniform(4.0, 16.0))), 2),
        gland_scale=u(0.35, 0.7),
        voxel_size=tuple(spacings[rng.integers(len(spacings))]),
        contrast=str(sorted(CONTRASTS)[rng.integers(len(CONTRASTS))]),
        fat_suppressed=bool(rng.random() < 0.5),
        snr=u(10.0, 40.0, 2),
        bias=u(0.1, 0.4),
        max_rotation_deg=u(0.0, 15.0 if full else 8.0, 2),
        max_translation_mm=u(0.0, 30.0 if full else 12.0, 2),
        positions=("prone", "supine", f"supine_tilted_{int(rng.integers(0, 61))}"),
        breast_E_kpa=round(s * (e_lo + (e_hi - e_lo) * float(rng.random())), 2),
    )
    drawn.update(overrides)
    return SubjectSpec(seed=int(seed), size=size, **drawn)


def make_subject(spec: SubjectSpec, out: str | Path, *, truth_solver: str = "febio",
                 febio: str | Path | None = None, cache_dir: str | Path | None = None,
                 progress: bool = False) -> Path:
    """Write the subject folder ``out`` and its truth folder ``<out>_truth`` for a spec.

    The stress-free anatomy is meshed at ``spec.truth_mesh_size_mm`` (on a label map of at
    most a third of that voxel size), every position is solved under its gravity by
    ``truth_solver``, and each position's image is rendered from the deformed anatomy under
    its rigid motion (:func:`~breastmodel.phantom.simulated.make_simulated_phantom`).

    Parameters
    ----------
    spec
        The subject.
    out
        Subject folder to write.
    truth_solver
        ``"febio"`` (default) or ``"ours"``.
    febio
        FEBio executable (default ``$FEBIO`` or the known places).
    cache_dir
        Cache of truth meshes and solutions keyed by their inputs (None: no cache).
    progress
        Log the stages at INFO level and show progress bars.

    Returns
    -------
    Path
        The subject folder. The truth folder holds, beside :func:`make_phantom`'s files,
        ``spec.json`` (this spec), ``truth_model.json`` (physics and per-position solver
        statistics), ``stress_free_mesh.npz`` (the truth mesh), per position
        ``<position>_displacement.npy`` ((N, 3) mm at the truth mesh nodes) and
        ``timings.json`` (s per stage).
    """
    from breastmodel.config import write_atomic, write_json
    from breastmodel.phantom.simulated import make_simulated_phantom
    from breastmodel.phantom.writer import truth_folder

    if not isinstance(spec, SubjectSpec):
        raise TypeError(f"phantom: make_subject needs a SubjectSpec, got {type(spec).__name__}")
    timings: dict = {}
    t0 = time.perf_counter()
    make_simulated_phantom(
        out, seed=spec.seed, truth_model=spec.truth_model(), positions=spec.positions,
        anatomy=spec.anatomy(), progress=progress, timings=timings, truth_solver=truth_solver,
        febio=febio, cache_dir=cache_dir, voxel_size=spec.voxel_size, snr=spec.snr,
        bias=spec.bias, max_rotation_deg=spec.max_rotation_deg,
        max_translation_mm=spec.max_translation_mm, contrast=spec.contrast,
        fat_suppressed=spec.fat_suppressed,
    )
    timings["total"] = time.perf_counter() - t0
    truth = truth_folder(out)
    write_atomic(truth / "spec.json", spec.to_json() + "\n")
    write_json(truth / "timings.json", timings)
    log.info("phantom: subject %s made in %.1f s", spec.name, timings["total"])
    return Path(out)


def make_rigid_subject(spec: SubjectSpec, out: str | Path, *,
                       positions: tuple[str, ...] | None = None, snr: float | None = None,
                       bias: float | None = None) -> Path:
    """Write ``spec``'s subject folder ``out`` and ``<out>_truth`` with rigid motions only
    (:func:`~breastmodel.phantom.writer.make_phantom`: no FE truth, for scoring a
    segmentation), its truth folder holding ``spec.json``; every position of the spec, its
    SNR and bias unless given."""
    from breastmodel.config import write_atomic
    from breastmodel.phantom.writer import make_phantom, truth_folder

    make_phantom(out, seed=spec.seed, anatomy=spec.anatomy(), voxel_size=spec.voxel_size,
                 snr=spec.snr if snr is None else snr, bias=spec.bias if bias is None else bias,
                 positions=spec.positions if positions is None else positions,
                 contrast=spec.contrast, fat_suppressed=spec.fat_suppressed,
                 max_rotation_deg=spec.max_rotation_deg,
                 max_translation_mm=spec.max_translation_mm, progress=False)
    write_atomic(truth_folder(out) / "spec.json", spec.to_json() + "\n")
    return Path(out)
