"""Small synthetic MRI volumes built with numpy, for the segmentation and registration tests.

The anatomy the project's phantom does not make (yet): a muscle slab meeting air (no thorax
shell) with two breasts on it, optionally cut by the field of view, with a breast swing
between positions. Patient frame: LPS mm, x left, y posterior (the breasts point to -y),
z superior; the slab's anterior face is the plane y = 0.

Intensities are fractions of fat: air 0, muscle 0.25, gland 0.6, skin 0.7, fat 1 (T2-like,
fat bright); ``contrast="t1"`` is T1-like (muscle 0.35, gland 0.45, skin 0.6) and
``"t1_fatsat"`` a fat-suppressed look (fat 0.35, muscle 0.55, gland 1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from registration.transforms import rigid_matrix

AIR, BREAST, MUSCLE, GLAND = 0, 1, 2, 3
#: Intensity per fine class: air, fat, muscle, gland, skin, marker.
LEVELS = {"t2": (0.0, 1.0, 0.25, 0.6, 0.7, 1.3), "t1": (0.0, 1.0, 0.35, 0.45, 0.6, 1.3),
          "t1_fatsat": (0.0, 0.35, 0.55, 1.0, 0.8, 1.3)}


@dataclass(frozen=True)
class Slab:
    """Muscle slab with two ellipsoidal breasts on its anterior face (mm)."""

    half_width: float = 58.0      # slab x half-extent
    half_height: float = 45.0     # slab z half-extent
    thickness: float = 15.0       # slab y extent (posterior of y = 0)
    breast_x: float = 29.0        # |x| of the breast centres
    breast_radius: float = 22.0   # x and z semi-axes
    projection: float = 26.0      # y semi-axis (anterior)
    skin: float = 2.0
    gland_scale: float = 0.4
    marker_radius: float = 2.0
    fov_min: tuple = (-70.0, -40.0, -55.0)
    fov_max: tuple = (70.0, 30.0, 55.0)

    def markers(self) -> dict[str, np.ndarray]:
        """Fiducial positions on the slab face (patient frame, mm): rigid with the slab."""
        return {"sternum_upper": np.array([0.0, -2.5, 36.0]),
                "sternum_lower": np.array([0.0, -2.5, -36.0]),
                "lateral_left": np.array([52.0, -2.5, 30.0]),
                "lateral_right": np.array([-52.0, -2.5, -30.0])}

    def classify(self, x, y, z, *, swing_mm: float = 0.0):
        """Fine class (0 air, 1 fat, 2 muscle, 3 gland, 4 skin, 5 marker) and the label of
        each point (markers are background).

        ``swing_mm`` shears the breasts sideways (+x) in proportion to their height over the
        slab (a tilted position's swing), the slab staying put.
        """
        h = np.clip(-y, 0.0, None)
        xs = x - swing_mm * h / self.projection
        fine = np.zeros(x.shape, np.uint8)
        slab = ((y >= 0) & (y <= self.thickness) & (np.abs(x) <= self.half_width)
                & (np.abs(z) <= self.half_height))
        for cx in (-self.breast_x, self.breast_x):
            u = ((xs - cx) / self.breast_radius) ** 2 + (z / self.breast_radius) ** 2
            outer = (y < 0) & (u + (y / self.projection) ** 2 <= 1.0)
            r, p, s = self.breast_radius, self.projection, self.skin
            inner = (y < 0) & (((xs - cx) / (r - s)) ** 2 + (z / (r - s)) ** 2
                               + (y / (p - s)) ** 2 <= 1.0)
            g = self.gland_scale
            gland = (((xs - cx) / (g * r)) ** 2 + (z / (g * r)) ** 2
                     + ((y + 0.5 * p) / (g * p)) ** 2 <= 1.0)
            fine[outer] = 4
            fine[inner] = 1
            fine[inner & gland] = 3
        fine[slab] = 2
        for c in self.markers().values():
            fine[(x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2
                 <= self.marker_radius ** 2] = 5
        labels = np.array([AIR, BREAST, MUSCLE, GLAND, BREAST, AIR], np.uint8)[fine]
        return fine, labels


def euler(rot_deg=(0.0, 0.0, 0.0), shift_mm=(0.0, 0.0, 0.0), center=(0.0, -10.0, 0.0)):
    """Rigid patient -> image transform (SimpleITK Euler3D, degrees and mm)."""
    return sitk.Euler3DTransform(tuple(map(float, center)), *np.radians(rot_deg),
                                 tuple(map(float, shift_mm)))


def render(anatomy: Slab, *, motion: sitk.Transform | None = None, swing_mm: float = 0.0,
           spacing=(1.5, 1.5, 1.5), noise: float = 0.04, contrast: str = "t2",
           seed: int = 0, fov_min=None, fov_max=None) -> tuple[sitk.Image, sitk.Image]:
    """Image and label map of ``anatomy`` seen through ``motion`` (patient -> image).

    The image grid covers the field of view in the image frame; each voxel's 27 sub-voxel
    samples are taken back to the patient frame through the inverse motion and averaged
    (partial volume); noise is Gaussian (``noise`` of fat), the image its magnitude.
    """
    lo = np.asarray(anatomy.fov_min if fov_min is None else fov_min, float)
    hi = np.asarray(anatomy.fov_max if fov_max is None else fov_max, float)
    sp = np.asarray(spacing, float)
    n = np.floor((hi - lo) / sp).astype(int) + 1
    r, t = rigid_matrix(motion.GetInverse()) if motion is not None else (np.eye(3), np.zeros(3))
    # Partial volume: the mean of 3 x 3 x 3 sub-voxel samples (box filter).
    k = 3
    sub = (np.arange(k) - (k - 1) / 2) / k
    val = np.zeros(n[::-1], np.float32)
    levels = np.asarray(LEVELS[contrast], np.float32)
    axes = [lo[i] + sp[i] * np.arange(n[i]) for i in range(3)]
    for dz in sub:
        z, y, x = np.meshgrid(axes[2] + dz * sp[2], axes[1], axes[0], indexing="ij")
        for dy in sub:
            for dx in sub:
                p = np.stack([(x + dx * sp[0]).ravel(), (y + dy * sp[1]).ravel(),
                              z.ravel()], axis=1) @ r.T + t
                fine, _ = anatomy.classify(p[:, 0], p[:, 1], p[:, 2], swing_mm=swing_mm)
                val += levels[fine].reshape(val.shape)
    val /= k ** 3
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    p = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1) @ r.T + t
    _, lab = anatomy.classify(p[:, 0], p[:, 1], p[:, 2], swing_mm=swing_mm)
    img = sitk.GetImageFromArray(val)
    img.SetSpacing(tuple(sp))
    img.SetOrigin(tuple(lo))
    a = sitk.GetArrayFromImage(img)
    a += np.random.default_rng(seed).normal(0.0, noise, a.shape).astype(np.float32)
    out = sitk.GetImageFromArray(np.abs(a) * 400.0)  # magnitude image, scanner units
    out.CopyInformation(img)
    labels = sitk.GetImageFromArray(lab.reshape(z.shape))
    labels.CopyInformation(img)
    return out, labels


def chest_points(labels: sitk.Image, step: int = 7) -> np.ndarray:
    """(N,3) physical points (mm) of every ``step``-th muscle voxel of a label map."""
    idx = np.argwhere(sitk.GetArrayViewFromImage(labels) == MUSCLE)[::step][:, ::-1]
    d = np.asarray(labels.GetDirection()).reshape(3, 3)
    return (idx * np.asarray(labels.GetSpacing())) @ d.T + np.asarray(labels.GetOrigin())


def write_subject(folder, images: dict, *, fiducials: dict | None = None,
                  reference: str = "supine") -> Path:
    """Write a subject folder: ``images`` position -> (image, gravity); ``fiducials``
    position -> label -> (3,) mm (optional). Returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lines = ['subject = "synthetic"', f'reference = "{reference}"']
    for name, (img, g) in images.items():
        sitk.WriteImage(img, str(folder / f"{name}.nii.gz"))
        lines += [f"[positions.{name}]", f'volume = "{name}.nii.gz"',
                  f"gravity = [{', '.join(f'{float(v):.6f}' for v in g)}]"]
    (folder / "subject.toml").write_text("\n".join(lines) + "\n")
    if fiducials:
        rows = ["position,label,x,y,z"] + [
            f"{p},{k},{v[0]:.4f},{v[1]:.4f},{v[2]:.4f}"
            for p, pts in fiducials.items() for k, v in pts.items()]
        (folder / "fiducials.csv").write_text("\n".join(rows) + "\n")
    return folder


def render_family_supine(seed: int, root, *, snr: float | None = None,
                         bias: float | None = None, position: str = "supine"):
    """(spec, scan, its truth labels) of the validation suite's small subject ``seed``
    (``draw_spec(seed, size="small")``) in ``position`` (supine unless given), rendered under
    ``root`` by the renderer ``make_subject`` uses, with rigid motion only (no FE truth is
    needed to score a segmentation); at the drawn SNR and bias unless given."""
    from breastmodel.phantom.family import draw_spec, make_rigid_subject
    from imaging.io import read_volume

    spec = draw_spec(seed, size="small")
    out = Path(root) / "subject"
    make_rigid_subject(spec, out, positions=(position,), snr=snr or None, bias=bias)
    return (spec, read_volume(out / f"{position}.nii.gz"),
            read_volume(Path(root) / "subject_truth" / f"{position}_labels.nii.gz"))
