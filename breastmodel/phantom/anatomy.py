"""Parametric torso-and-breasts anatomy for synthetic MRI subjects (phantoms).

All coordinates are in the *patient frame*: LPS millimetres, x toward the patient's left,
y posterior, z superior, origin on the torso axis. The torso is an elliptic cylinder along z
made of nested layers (skin, subcutaneous fat, muscle, thorax interior); each breast is a
superellipsoid centred on the chest surface (its anterior part protrudes, the rest lies inside
the torso where the layers take priority), with an inner glandular superellipsoid and a nipple.
Skin markers are small spheres just outside the skin on stiff zones (sternum, inframammary
folds), as in the paper. With ``chest_wall="slab"`` the torso is replaced by a flat muscle slab
(posterior face at y = 0, free sides, air behind and around it) carrying the two breasts, with
no skin outside the breasts: a chest wall whose muscle meets air, as in a dedicated breast coil
whose field of view ends at the pectoralis.

The anatomy is a small constructive description made of primitives that can both test point
membership (for voxelisation) and give exact chord intervals along y (for reference volumes
that do not depend on any voxel grid), see :func:`reference_volumes`. The primitives are in
:mod:`breastmodel.phantom.shapes`, the grid-free volumes in :mod:`breastmodel.phantom.volumes`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from breastmodel.phantom.shapes import Box, EllipticCylinderZ, Superellipsoid
from breastmodel.phantom.volumes import reference_volumes

__all__ = [
    "AIR", "FAT", "MUSCLE", "GLAND", "SKIN", "MARKER", "THORAX", "TISSUE_NAMES",
    "Breast", "Anatomy", "EllipticCylinderZ", "Superellipsoid", "Box",
    "reference_volumes", "segmentation_codes",
]

#: Fine tissue codes of the truth label volumes.
AIR, FAT, MUSCLE, GLAND, SKIN, MARKER, THORAX = range(7)
TISSUE_NAMES = ("air", "fat", "muscle", "gland", "skin", "marker", "thorax")


@dataclass(frozen=True)
class Breast:
    """One breast: a superellipsoid protrusion centred on the chest surface (mm).

    Attributes
    ----------
    center_x, center_z
        Position of the breast centre on the chest surface (x > 0 is the patient's left).
    radius_x, radius_z
        Half-width (L-R) and half-height (S-I) of the base, mm.
    projection
        How far the breast projects anterior of the chest surface at its centre, mm.
    exponent
        Superellipsoid exponent (2: ellipsoid; larger: fuller, boxier shape).
    gland_scale
        Gland semi-axes as fractions of the breast semi-axes (x, y, z).
    gland_offset
        Gland centre anterior shift from the breast centre, as a fraction of ``projection``.
    nipple_radius
        Radius of the spherical nipple centred on the breast tip, mm.
    ptosis
        How far the tip hangs below the base centre, mm (the breast's axis is sheared in the
        y-z plane; 0: the tip is level with the base centre).
    """

    center_x: float
    center_z: float
    radius_x: float
    radius_z: float
    projection: float
    exponent: float = 2.0
    gland_scale: tuple[float, float, float] = (0.55, 0.45, 0.55)
    gland_offset: float = 0.35
    nipple_radius: float = 4.0
    ptosis: float = 0.0

    @property
    def shear(self) -> float:
        """z drop per mm of anterior projection (dimensionless)."""
        return float(self.ptosis) / float(self.projection)


@dataclass(frozen=True)
class Anatomy:
    """Parameters of the phantom torso (mm). Defaults: an adult breast-MRI field of view.

    Attributes
    ----------
    torso_half_width, torso_half_depth
        Semi-axes (x, y) of the outer skin ellipse of the torso, centred on the patient-frame
        origin; the anterior chest surface is at y = -torso_half_depth.
    skin, subcutaneous_fat, muscle
        Layer thicknesses along the ellipse axes, mm (layers are concentric ellipses).
    left, right
        The two breasts (left at x > 0).
    marker_radius, marker_gap
        Skin marker sphere radius and its gap to the skin surface, mm.
    sternum_z
        z of the upper and lower sternal markers, mm.
    imf_gap
        Distance below each breast's lower edge of its inframammary-fold marker, mm.
    fov_min, fov_max
        Field-of-view box (patient frame = image frame before motion), mm.
    body_min, body_max
        Box the body is cut to for the truth's mesh (patient frame, mm; None: the field of
        view). A breast coil's field of view cuts a body that goes on past it: its truth
        spans the torso while its scans see the coil's box (:attr:`body_box`).
    rotation_center
        Centre of the random rigid rotations, mm (the middle of the breast region keeps
        motions from pushing the breasts out of the field of view).
    chest_wall
        ``"torso"`` (the layered elliptic torso) or ``"slab"``: a flat muscle slab of
        ``muscle`` mm between y = -muscle and y = 0 and of half-extent ``slab_half_width``
        (x) by ``slab_half_height`` (z), air behind and around it, no skin outside the
        breasts; the torso semi-axes, skin-free layers and subcutaneous fat are then unused
        (the breast skin keeps ``skin``).
    slab_half_width, slab_half_height
        Half-extent of the slab, mm.
    """

    torso_half_width: float = 150.0
    torso_half_depth: float = 110.0
    skin: float = 2.0
    subcutaneous_fat: float = 8.0
    muscle: float = 12.0
    left: Breast = field(
        default_factory=lambda: Breast(
            center_x=78.0, center_z=-10.0, radius_x=66.0, radius_z=60.0, projection=55.0
        )
    )
    right: Breast = field(
        default_factory=lambda: Breast(
            center_x=-78.0, center_z=-8.0, radius_x=62.0, radius_z=57.0, projection=48.0,
            exponent=2.4, gland_scale=(0.5, 0.4, 0.5),
        )
    )
    marker_radius: float = 2.0
    marker_gap: float = 0.5
    sternum_z: tuple[float, float] = (60.0, -40.0)
    imf_gap: float = 8.0
    fov_min: tuple[float, float, float] = (-160.0, -185.0, -100.0)
    fov_max: tuple[float, float, float] = (160.0, -5.0, 100.0)
    body_min: tuple[float, float, float] | None = None
    body_max: tuple[float, float, float] | None = None
    rotation_center: tuple[float, float, float] = (0.0, -100.0, -10.0)
    chest_wall: str = "torso"
    slab_half_width: float = 140.0
    slab_half_height: float = 90.0

    def __post_init__(self):
        if self.chest_wall not in ("torso", "slab"):
            raise ValueError(f"phantom: chest_wall must be 'torso' or 'slab', got "
                             f"{self.chest_wall!r}")

    @classmethod
    def small(cls) -> Anatomy:
        """A half-size torso in a 170 x 90 x 100 mm field of view (for fast tests and demos)."""
        return cls(
            torso_half_width=75.0,
            torso_half_depth=55.0,
            skin=2.0,
            subcutaneous_fat=5.0,
            muscle=8.0,
            left=Breast(
                center_x=38.0, center_z=0.0, radius_x=28.0, radius_z=26.0, projection=28.0,
                nipple_radius=3.0,
            ),
            right=Breast(
                center_x=-38.0, center_z=1.0, radius_x=25.0, radius_z=24.0, projection=24.0,
                exponent=2.4, gland_scale=(0.5, 0.4, 0.5), nipple_radius=3.0,
            ),
            sternum_z=(32.0, -20.0),
            imf_gap=6.0,
            fov_min=(-85.0, -100.0, -50.0),
            fov_max=(85.0, -10.0, 50.0),
            rotation_center=(0.0, -55.0, 0.0),
        )

    @property
    def body_box(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(lo, hi) of the box the truth's mesh spans: the body box and the field of view."""
        lo = tuple(map(min, self.body_min or self.fov_min, self.fov_min))
        hi = tuple(map(max, self.body_max or self.fov_max, self.fov_max))
        return lo, hi

    def with_fov(self, fov_min, fov_max) -> Anatomy:
        """Copy with another field of view (e.g. a crop around one breast)."""
        return replace(self, fov_min=tuple(map(float, fov_min)), fov_max=tuple(map(float, fov_max)))

    # --- derived geometry -------------------------------------------------------------------

    def torso_layer(self, depth: float) -> EllipticCylinderZ:
        """Torso ellipse shrunk by ``depth`` mm along both axes."""
        return EllipticCylinderZ(
            (0.0, 0.0), (self.torso_half_width - depth, self.torso_half_depth - depth)
        )

    def chest_surface_y(self, x: float) -> float:
        """y of the outer (skin) torso surface at lateral position x, mm (anterior side); the
        slab's anterior face for ``chest_wall="slab"``."""
        if self.chest_wall == "slab":
            return -float(self.muscle)
        a, b = self.torso_half_width, self.torso_half_depth
        return float(-b * np.sqrt(max(0.0, 1.0 - (x / a) ** 2)))

    def breast_shape(self, breast: Breast, *, shrink: float = 0.0) -> Superellipsoid:
        """The breast superellipsoid, optionally shrunk by ``shrink`` mm (skin inner side)."""
        cy = self.chest_surface_y(breast.center_x)
        return Superellipsoid(
            (breast.center_x, cy, breast.center_z),
            (breast.radius_x - shrink, breast.projection - shrink, breast.radius_z - shrink),
            breast.exponent,
            breast.shear,
        )

    def gland_shape(self, breast: Breast) -> Superellipsoid:
        dy = breast.gland_offset * breast.projection
        cy = self.chest_surface_y(breast.center_x) - dy
        sx, sy, sz = breast.gland_scale
        return Superellipsoid(
            (breast.center_x, cy, breast.center_z - breast.shear * dy),
            (sx * breast.radius_x, sy * breast.projection, sz * breast.radius_z),
            breast.exponent,
            breast.shear,
        )

    def nipple_tip(self, breast: Breast) -> np.ndarray:
        """Most anterior point of the breast superellipsoid (nipple centre), mm."""
        cy = self.chest_surface_y(breast.center_x)
        return np.array([breast.center_x, cy - breast.projection,
                         breast.center_z - float(breast.ptosis)])

    def nipple_shape(self, breast: Breast) -> Superellipsoid:
        r = breast.nipple_radius
        return Superellipsoid(tuple(self.nipple_tip(breast)), (r, r, r))

    def markers(self) -> dict[str, np.ndarray]:
        """Skin-marker centres (patient frame, mm), on the outward normal of the torso skin."""
        out = {}
        a, b = self.torso_half_width, self.torso_half_depth
        d = self.marker_radius + self.marker_gap

        def on_skin(x: float, z: float) -> np.ndarray:
            y = self.chest_surface_y(x)
            if self.chest_wall == "slab":
                return np.array([x, y - d, z])
            n = np.array([x / a**2, y / b**2, 0.0])
            return np.array([x, y, z]) + d * n / np.linalg.norm(n)

        out["sternum_upper"] = on_skin(0.0, self.sternum_z[0])
        out["sternum_lower"] = on_skin(0.0, self.sternum_z[1])
        for side, br in (("left", self.left), ("right", self.right)):
            out[f"imf_{side}"] = on_skin(br.center_x, br.center_z - br.radius_z - self.imf_gap)
        return out

    def landmarks(self) -> dict[str, np.ndarray]:
        """Internal/anatomical landmarks (patient frame, mm): nipple tips and gland centres."""
        out = {}
        for side, br in (("left", self.left), ("right", self.right)):
            out[f"nipple_{side}"] = self.nipple_tip(br)
            out[f"gland_center_{side}"] = np.asarray(self.gland_shape(br).center, dtype=float)
        return out

    def primitives(self) -> dict[str, EllipticCylinderZ | Superellipsoid]:
        """Every primitive of the constructive description, by name."""
        s, f, m = self.skin, self.subcutaneous_fat, self.muscle
        prims: dict[str, EllipticCylinderZ | Superellipsoid | Box]
        if self.chest_wall == "slab":
            w, h = self.slab_half_width, self.slab_half_height
            prims = {"slab": Box((-w, -m, -h), (w, 0.0, h))}
        else:
            prims = {
                "torso_outer": self.torso_layer(0.0),
                "torso_inner": self.torso_layer(s),
                "muscle_outer": self.torso_layer(s + f),
                "muscle_inner": self.torso_layer(s + f + m),
            }
        for side, br in (("left", self.left), ("right", self.right)):
            prims[f"breast_{side}_outer"] = self.breast_shape(br)
            prims[f"breast_{side}_inner"] = self.breast_shape(br, shrink=s)
            prims[f"gland_{side}"] = self.gland_shape(br)
            prims[f"nipple_{side}"] = self.nipple_shape(br)
        r = self.marker_radius
        for name, c in self.markers().items():
            prims[f"marker_{name}"] = Superellipsoid(tuple(c), (r, r, r))
        return prims

    # --- classification ---------------------------------------------------------------------

    def classify(self, points: np.ndarray) -> np.ndarray:
        """Fine tissue code of each point.

        Parameters
        ----------
        points : (n, 3) float
            Patient-frame points, mm.

        Returns
        -------
        (n,) uint8
            Codes AIR 0, FAT 1, MUSCLE 2, GLAND 3, SKIN 4, MARKER 5, THORAX 6.
        """
        p = np.asarray(points)
        x, y, z = (np.ascontiguousarray(p[:, i]) for i in range(3))
        return self.classify_xyz(x, y, z)

    def classify_xyz(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Like :meth:`classify` for coordinate arrays x, y, z (n,) mm (float32 is fine)."""
        n = len(x)
        if n == 0:
            return np.zeros(0, dtype=np.uint8)
        inside = {}
        prims = self.primitives()
        zlo, zhi = float(z.min()), float(z.max())
        for names in self._groups(prims):
            shapes = [prims[k] for k in names]
            if isinstance(shapes[0], EllipticCylinderZ):
                for k, pr in zip(names, shapes):
                    inside[k] = pr.contains(x, y, z)
                continue
            # Local shapes: test only the points inside the group's bounding box.
            lo = np.min([sh.bounds()[0] for sh in shapes], 0)
            hi = np.max([sh.bounds()[1] for sh in shapes], 0)
            if hi[2] < zlo or lo[2] > zhi:
                continue
            sel = (x >= lo[0]) & (x <= hi[0])
            sel &= (y >= lo[1]) & (y <= hi[1])
            sel &= (z >= lo[2]) & (z <= hi[2])
            idx = np.flatnonzero(sel)
            if len(idx) == 0:
                continue
            xs, ys, zs = x[idx], y[idx], z[idx]
            for k, sh in zip(names, shapes):
                inside[k] = np.zeros(n, dtype=bool)
                inside[k][idx] = sh.contains(xs, ys, zs)
        none = np.zeros(n, dtype=bool)

        def any_of(*names: str) -> np.ndarray:
            out = none.copy()
            for k in names:
                if k in inside:
                    out |= inside[k]
            return out

        outer = any_of(
            "torso_outer", "breast_left_outer", "breast_right_outer", "nipple_left",
            "nipple_right", "slab",
        )
        inner = any_of("torso_inner", "breast_left_inner", "breast_right_inner", "slab")
        code = np.full(n, FAT, dtype=np.uint8)
        # Later assignments win: gland < muscle < thorax < skin < air < marker.
        code[any_of("gland_left", "gland_right")] = GLAND
        code[any_of("muscle_outer", "slab")] = MUSCLE
        code[any_of("muscle_inner")] = THORAX
        code[~inner] = SKIN
        code[~outer] = AIR
        if self.chest_wall == "slab":  # nothing of the breasts lies behind the chest wall
            code[(y > -float(self.muscle)) & ~any_of("slab")] = AIR
        code[any_of(*(k for k in inside if k.startswith("marker_")))] = MARKER
        return code

    @staticmethod
    def _groups(prims: dict) -> list[list[str]]:
        """Primitives tested together: each torso layer alone, each breast with its inner
        surface, gland and nipple (one bounding box), each marker alone."""
        groups = [[k] for k in prims if k.startswith(("torso_", "muscle_", "marker_", "slab"))]
        for side in ("left", "right"):
            groups.append(
                [k for k in prims if not k.startswith("marker_") and side in k.split("_")]
            )
        return groups

    def is_anterior(self, points: np.ndarray) -> np.ndarray:
        """True for points anterior of the coronal plane through the torso axis (y < 0)."""
        return np.asarray(points)[:, 1] < 0.0


def segmentation_codes(fine: np.ndarray, anterior: np.ndarray) -> np.ndarray:
    """Map fine codes to the segmentation convention.

    0 background (air, thorax interior, markers, and tissue posterior of the torso axis),
    1 breast tissue (fat, gland and skin anterior of the torso axis), 2 muscle, 3 gland.
    """
    lut = np.array([0, 1, 2, 3, 1, 0, 0], dtype=np.uint8)
    seg = lut[fine]
    seg[(~anterior) & ((fine == FAT) | (fine == SKIN) | (fine == GLAND))] = 0
    return seg
