"""A subject of the phantom family as plain data: :class:`SubjectSpec` and its ranges.

A spec is frozen, JSON-serialisable and validated on construction; it makes its own
:class:`~breastmodel.phantom.anatomy.Anatomy` (size, cup, left/right difference, ptosis, fat,
gland, field of view) and names its truth physics (:data:`PHYSICS`). Drawing specs from seeds
and making subjects from them is :mod:`breastmodel.phantom.family`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from breastmodel.phantom.anatomy import Anatomy, Breast
from breastmodel.phantom.motion import patient_gravity
from breastmodel.phantom.rendering import CONTRASTS

if TYPE_CHECKING:
    from breastmodel.phantom.truth_model import TruthModel

__all__ = ["SubjectSpec", "CUPS", "FOV_KINDS", "PHYSICS", "SIZES", "VOXEL_SPACINGS"]


SIZES = ("small", "full")
#: ``torso``: the whole torso width, cut behind the breasts' base; ``coil``: a dedicated breast
#: coil's box, the body cut by the image boundary at the sides and behind (the body, and its
#: truth, go on past every cut: :data:`BODY_BEYOND_MM`); ``slab``: a muscle
#: slab fixed at its posterior face and free at its sides, meeting air.
FOV_KINDS = ("torso", "coil", "slab")
#: Adult (``"full"``) breast base half-width (x), half-height (z) and projection, mm, per cup.
CUPS = {"A": (46.0, 42.0, 28.0), "B": (52.0, 48.0, 38.0), "C": (60.0, 55.0, 48.0),
        "D": (66.0, 60.0, 58.0)}
#: Voxel spacings (x, y, z) mm drawn per size: 1 mm isotropic, the paper's 0.5 x 0.5 x 0.6 mm
#: and a clinical 0.7 x 0.7 x 1.5 mm for full subjects; 1-2 mm for small ones (1 mm only
#: in-plane: rendering a deformed position costs about 0.3 ms per voxel on one core).
VOXEL_SPACINGS = {
    "small": ((1.5, 1.5, 1.5), (2.0, 2.0, 2.0), (1.0, 1.0, 2.0)),
    "full": ((1.0, 1.0, 1.0), (0.5, 0.5, 0.6), (0.7, 0.7, 1.5)),
}
#: Truth physics: the bulk control (Neo-Hookean breast and muscle, posterior chest wall fixed,
#: bonded = conforming mesh, no skin) and variants that each add one hidden effect. Values:
#: ``(material overrides as multiples of the breast modulus per region code, effects)``.
PHYSICS: dict[str, tuple[dict[int, dict], dict[str, dict]]] = {
    "bulk": ({}, {}),
    # left breast softer, right breast stiffer than the fitted single modulus
    "asymmetric": ({1: {"E_factor": 0.7}, 3: {"E_factor": 1.4}}, {}),
    # glandular tissue three times stiffer than fat (near the noise floor of the small
    # subjects' diagnosis), and ten times (visible)
    "gland": ({4: {"E_factor": 3.0}, 5: {"E_factor": 3.0}}, {}),
    "gland_10x": ({4: {"E_factor": 10.0}, 5: {"E_factor": 10.0}}, {}),
    # strain-stiffening (Gent) breast tissue, Jm 1 (the skin moves 0.7-1.6 mm p95 against
    # the bulk truth on small-003) and near the noise floor (Jm 3). Stronger limits make
    # FEBio slow: with 25 Newton iterations a step it had not finished seed 3 with Jm 0.3
    # (prone, 13 min) or 0.5 (tilted, 23 min); with 60 (FEBIO_MAX_REFS) Jm 0.5 took 22 min.
    "gent_breast": ({1: {"name": "gent", "Jm": 1.0}, 3: {"name": "gent", "Jm": 1.0}}, {}),
    "gent_breast_weak": ({1: {"name": "gent", "Jm": 3.0}, 3: {"name": "gent", "Jm": 3.0}}, {}),
    # FEBio approximates the skin membrane by a shell (recorded with the truth). Written at the
    # skin's 2 mm, FEBio's initialisation of that shell domain stops with "negative jacobian"
    # on small subjects (slab; torso seed 3, prone); written 100x thinner (the writer's
    # default) seed 3's prone truth converges and its supine stops at load 0.06 with negative
    # Jacobians (the error names the position and FEBio's message)
    "skin": ({}, {"skin": {"E": 4.0, "thickness": 2.0}}),
    # the skin as a solid layer: the breast tets that own a skin face (region codes
    # skin_layer_left/right; their volume over the skin's area is 1.4 mm on small-003's
    # 5 mm truth mesh) ten times stiffer than the breast, about a 2 mm membrane of 8 kPa
    # (the paper's box: 1-20 kPa); three times near the noise floor. FEBio's UT4 solids
    # carry it where its shells fail (above)
    "skin_layer": ({6: {"E_factor": 10.0}, 7: {"E_factor": 10.0}}, {}),
    "skin_layer_weak": ({6: {"E_factor": 3.0}, 7: {"E_factor": 3.0}}, {}),
    # the sliding interface as the loose tissue the breast slides on: the breast tets with a
    # node on the breast-muscle interface (interface_layer_left/right, one element thick,
    # ``mechanics.mesh.with_layer``) twice as soft as the breast (visible: against the bulk
    # truth the skin moves p95 1.7 / 2.3 / 3.3 mm prone / supine / tilted on small-003, 1.0
    # / 1.7 / 1.8 on small-008, 1.1 / 1.7 / 3.0 on small-000) and 1.25 times (weak: 0.4 /
    # 0.5 / 0.8 on small-003, 0.3 / 0.4 / 0.4-0.7 on the others). FEBio's sliding-elastic
    # fails on these subjects (a singular contact at zero gap); its solids carry the layer.
    # Ten times softer, FEBio retried through negative Jacobians in prone and supine and was
    # stopped at load 0.49 of the tilted position after 13 minutes (small-003)
    "sliding_layer": ({8: {"E_factor": 0.5}, 9: {"E_factor": 0.5}}, {}),
    "sliding_layer_weak": ({8: {"E_factor": 0.8}, 9: {"E_factor": 0.8}}, {}),
    "fascia": ({}, {"fascia": {"E": 120.0, "thickness": 0.1}}),
    "ligaments": ({}, {"ligaments": {"E": 100.0}}),
}
#: How far the body (and the truth's mesh) goes on past the scan's cuts behind, above and
#: below the breasts, mm for the adult anatomy (scaled by the size).
BODY_BEYOND_MM = 40.0
#: Scale of a size's anatomy relative to the adult one.
_SCALE = {"small": 0.5, "full": 1.0}


@dataclass(frozen=True)
class SubjectSpec:
    """Every choice that makes one synthetic subject (lengths mm, moduli kPa, angles deg).

    Attributes
    ----------
    seed
        Seed of the noise, bias field and rigid motions (and the draw that made the spec).
    size
        ``"small"`` (half-size anatomy) or ``"full"`` (adult).
    fov
        Field of view kind, one of :data:`FOV_KINDS`.
    cup
        Cup size "A" to "D" (:data:`CUPS`, scaled by the size).
    asymmetry
        Left/right difference: the left breast's semi-axes are scaled by ``1 + asymmetry/2``
        and the right's by ``1 - asymmetry/2`` (dimensionless, |asymmetry| < 0.5).
    ptosis
        Drop of each breast's tip below its base centre as a fraction of its projection.
    exponent
        Superellipsoid exponent of the breasts (2: ellipsoid; larger: fuller).
    subcutaneous_fat_mm
        Thickness of the fat layer between skin and muscle on the torso, mm.
    gland_scale
        Gland semi-axes as fractions of the breast's (x and z; y is 0.8 of it); the glandular
        fraction of the breast grows as its cube.
    voxel_size
        Voxel spacing (x, y, z), mm.
    contrast
        ``"t2"`` or ``"t1"``.
    fat_suppressed
        Fat signal suppressed (SNR then refers to the gland signal).
    snr
        Reference-tissue signal / noise sigma.
    bias
        Bias-field amplitude (0.3 = +-30 %).
    max_rotation_deg, max_translation_mm
        Bounds of the random rigid motion of each position, deg and mm.
    positions
        Position names (``"supine_tilted_<deg>"`` carries its tilt).
    physics
        Truth physics, keys of :data:`PHYSICS` joined by ``+``.
    breast_E_kpa, muscle_E_kpa
        Young's moduli of breast tissue and muscle in the truth, kPa (nu 0.49).
    truth_mesh_size_mm
        Target tet edge of the truth mesh, mm (finer than a fit's 8 mm).
    """

    seed: int
    size: str = "small"
    fov: str = "torso"
    cup: str = "C"
    asymmetry: float = 0.0
    ptosis: float = 0.0
    exponent: float = 2.0
    subcutaneous_fat_mm: float = 5.0
    gland_scale: float = 0.5
    voxel_size: tuple[float, float, float] = (1.5, 1.5, 1.5)
    contrast: str = "t2"
    fat_suppressed: bool = False
    snr: float = 20.0
    bias: float = 0.3
    max_rotation_deg: float = 5.0
    max_translation_mm: float = 10.0
    positions: tuple[str, ...] = ("prone", "supine", "supine_tilted_45")
    physics: str = "bulk"
    breast_E_kpa: float = 2.0
    muscle_E_kpa: float = 10.0
    truth_mesh_size_mm: float = 5.0

    def __post_init__(self):
        vs = tuple(float(v) for v in np.broadcast_to(np.asarray(self.voxel_size, float), (3,)))
        object.__setattr__(self, "voxel_size", vs)
        object.__setattr__(self, "positions", tuple(str(p) for p in self.positions))
        bad = []
        if int(self.seed) != self.seed or self.seed < 0:
            bad.append(f"seed must be a non-negative integer, got {self.seed!r}")
        if self.size not in SIZES:
            bad.append(f"size must be one of {SIZES}, got {self.size!r}")
        if self.fov not in FOV_KINDS:
            bad.append(f"fov must be one of {FOV_KINDS}, got {self.fov!r}")
        if self.cup not in CUPS:
            bad.append(f"cup must be one of {sorted(CUPS)}, got {self.cup!r}")
        if not abs(self.asymmetry) < 0.5:
            bad.append(f"asymmetry must lie in (-0.5, 0.5), got {self.asymmetry}")
        if not 0.0 <= self.ptosis <= 0.8:
            bad.append(f"ptosis must lie in [0, 0.8], got {self.ptosis}")
        if not 1.5 <= self.exponent <= 4.0:
            bad.append(f"exponent must lie in [1.5, 4], got {self.exponent}")
        if not self.subcutaneous_fat_mm > 0:
            bad.append(f"subcutaneous_fat_mm must be > 0, got {self.subcutaneous_fat_mm}")
        if not 0.1 <= self.gland_scale <= 0.8:
            bad.append(f"gland_scale must lie in [0.1, 0.8], got {self.gland_scale}")
        if not all(v > 0 for v in vs):
            bad.append(f"voxel_size must be > 0 mm, got {vs}")
        if self.contrast not in CONTRASTS:
            bad.append(f"contrast must be one of {sorted(CONTRASTS)}, got {self.contrast!r}")
        if not self.snr > 0 or not self.bias >= 0:
            bad.append(f"snr must be > 0 and bias >= 0, got {self.snr}, {self.bias}")
        if self.max_rotation_deg < 0 or self.max_translation_mm < 0:
            bad.append("motion bounds must be >= 0")
        if not self.positions or len(set(self.positions)) != len(self.positions):
            bad.append(f"positions must be distinct and at least one, got {self.positions}")
        for part in self.physics.split("+"):
            if part not in PHYSICS:
                bad.append(f"unknown physics {part!r}; known {sorted(PHYSICS)}")
        if not (self.breast_E_kpa > 0 and self.muscle_E_kpa > 0 and self.truth_mesh_size_mm > 0):
            bad.append("moduli and the truth mesh size must be > 0")
        if bad:
            raise ValueError("phantom: bad subject spec: " + "; ".join(bad))
        for p in self.positions:
            patient_gravity(p)  # unknown position names fail here

    # --- serialisation ------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (tuples as lists)."""
        d = asdict(self)
        d["voxel_size"] = list(self.voxel_size)
        d["positions"] = list(self.positions)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SubjectSpec:
        """Inverse of :meth:`to_dict`; unknown keys are an error (names them)."""
        known = {f.name for f in fields(cls)}
        extra = set(d) - known
        if extra:
            raise ValueError(f"phantom: unknown subject spec key(s) {sorted(extra)}; known "
                             f"{sorted(known)}")
        d = dict(d)
        if "voxel_size" in d:
            d["voxel_size"] = tuple(np.broadcast_to(np.asarray(d["voxel_size"], float), (3,)))
        if "positions" in d:
            d["positions"] = tuple(d["positions"])
        return cls(**d)

    @classmethod
    def from_json(cls, text: str) -> SubjectSpec:
        return cls.from_dict(json.loads(text))

    # --- what the spec makes ------------------------------------------------------------------

    @property
    def name(self) -> str:
        """Short identifier, e.g. ``small-0007``."""
        return f"{self.size}-{self.seed:04d}"

    def anatomy(self) -> Anatomy:
        """The :class:`Anatomy` of this spec (patient frame, mm)."""
        s = _SCALE[self.size]
        rx, rz, proj = (s * v for v in CUPS[self.cup])
        width, depth = 150.0 * s, 110.0 * s
        nipple = 3.0 if self.size == "small" else 4.0
        imf_gap = 8.0 * s + 2.0
        g = float(self.gland_scale)

        def breast(side: int) -> Breast:
            f = 1.0 + side * 0.5 * float(self.asymmetry)
            return Breast(
                center_x=0.0, center_z=0.0, radius_x=rx * f, radius_z=rz * f,
                projection=proj * f, exponent=float(self.exponent),
                gland_scale=(g, 0.8 * g, g), nipple_radius=nipple,
                ptosis=float(self.ptosis) * proj * f,
            )

        left, right = breast(+1), breast(-1)
        rx_max = max(left.radius_x, right.radius_x)
        cx = max(0.52 * width, rx_max + 6.0 * s)
        left, right = replace(left, center_x=cx), replace(right, center_x=-cx)
        rz_max = max(left.radius_z, right.radius_z)
        drop = max(left.ptosis, right.ptosis)
        slab = self.fov == "slab"
        muscle = (15.0 if slab else 12.0) * s
        marker = 2.0
        margin = 10.0 * s + 0.5 * float(self.max_translation_mm)
        z_lo = rz_max + drop + imf_gap + 2 * marker + 2.5
        z_half = max(z_lo, rz_max) + margin
        base = dict(
            torso_half_width=width, torso_half_depth=depth, skin=2.0 if s == 1.0 else 1.5,
            subcutaneous_fat=float(self.subcutaneous_fat_mm), muscle=muscle,
            left=left, right=right, marker_radius=marker, marker_gap=0.5,
            sternum_z=(0.6 * rz_max, -0.4 * rz_max), imf_gap=imf_gap,
            chest_wall="slab" if slab else "torso",
            slab_half_width=cx + rx_max + 12.0 * s, slab_half_height=z_lo + 4.0 * s,
        )
        an = Anatomy(**base)
        tips = [an.nipple_tip(b)[1] - b.nipple_radius for b in (left, right)]
        y_lo = min(tips) - margin
        if slab:
            x_half = an.slab_half_width + margin
            y_hi = margin
            z_half = an.slab_half_height + margin
        else:
            x_half, y_hi = width + margin, -0.1 * depth
        body = {}
        if not slab:
            # The body goes on past the scan's cuts (behind, above and below; a coil's box
            # also at the sides): the truth spans the torso's width and BODY_BEYOND_MM * s
            # more behind, above and below, the scans see the field of view. Until
            # 2026-12-02 the truth was cut to the field of view, so it had free faces where
            # the model has them too: the model's own truncation, hidden from the suite.
            beyond = BODY_BEYOND_MM * s
            body = {"body_min": (-float(x_half), float(y_lo), -float(z_half + beyond)),
                    "body_max": (float(x_half), float(y_hi + beyond), float(z_half + beyond))}
        if self.fov == "coil":
            x_half, y_hi = 0.8 * width, -0.45 * depth
        y_mid = float(np.mean([an.chest_surface_y(cx) - 0.5 * b.projection
                               for b in (left, right)]))
        return replace(an, fov_min=(-float(x_half), float(y_lo), -float(z_half)),
                       fov_max=(float(x_half), float(y_hi), float(z_half)),
                       rotation_center=(0.0, y_mid, 0.0), **body)

    def truth_model(self) -> TruthModel:
        """The truth physics (:func:`breastmodel.phantom.family.truth_model`)."""
        from breastmodel.phantom.family import truth_model

        return truth_model(self)
