"""MRI-like T2- or T1-weighted intensities from tissue labels, with or without fat
suppression.

clean = partial-volume mix of tissue intensities -> Gaussian blur (point spread) ->
x smooth bias field (coil sensitivity, fixed to the scanner grid) -> Rician noise.
SNR is defined as the mean signal of the reference tissue (fat; gland when fat is
suppressed), after bias, divided by the noise sigma of each of the two Gaussian channels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from breastmodel.phantom.anatomy import AIR, FAT, GLAND, MARKER, MUSCLE, SKIN, THORAX
from breastmodel.phantom.voxelize import TissueVolume

__all__ = ["T2_INTENSITY", "T1_INTENSITY", "FAT_SUPPRESSION", "CONTRASTS", "Rendering",
           "render", "bias_field", "intensity_table"]

#: Relative T2-weighted intensity of each fine tissue code.
T2_INTENSITY = {
    AIR: 0.0, FAT: 1.0, MUSCLE: 0.25, GLAND: 0.6, SKIN: 0.7, MARKER: 1.6, THORAX: 0.1,
}
#: Relative T1-weighted intensity (fat bright, gland and muscle dark, fluid-free markers).
T1_INTENSITY = {
    AIR: 0.0, FAT: 1.0, MUSCLE: 0.35, GLAND: 0.3, SKIN: 0.45, MARKER: 0.9, THORAX: 0.15,
}
CONTRASTS = {"t2": T2_INTENSITY, "t1": T1_INTENSITY}
#: Fraction of the fat signal left by fat suppression (spectral fat saturation).
FAT_SUPPRESSION = 0.1


def intensity_table(contrast: str = "t2", *, fat_suppressed: bool = False) -> dict[int, float]:
    """Relative intensity of each fine tissue code for a contrast ("t2" or "t1"), with the fat
    signal scaled by :data:`FAT_SUPPRESSION` when ``fat_suppressed``."""
    if contrast not in CONTRASTS:
        raise ValueError(f"phantom: unknown contrast {contrast!r}; use one of {sorted(CONTRASTS)}")
    table = dict(CONTRASTS[contrast])
    if fat_suppressed:
        table[FAT] *= FAT_SUPPRESSION
    return table


@dataclass(frozen=True)
class Rendering:
    """A rendered volume and the numbers that define it.

    Attributes
    ----------
    image : (nz, ny, nx) float32
        Noisy magnitude image (fat ~ 1).
    noise_sigma : float
        Sigma of each Gaussian channel before the magnitude.
    mean_fat : float
        Mean noiseless signal over voxels fully inside fat.
    mean_reference : float
        Mean noiseless signal of the SNR's reference tissue (fat, or gland when fat is
        suppressed); ``noise_sigma = mean_reference / snr``.
    """

    image: np.ndarray
    noise_sigma: float
    mean_fat: float
    mean_reference: float = float("nan")


def bias_field(shape_zyx, rng: np.random.Generator, *, amplitude: float) -> np.ndarray:
    """Smooth multiplicative field 1 + amplitude * s, s a random quadratic in [-1, 1].

    Parameters
    ----------
    shape_zyx : tuple of 3 int
    rng
        Random generator (its state advances).
    amplitude
        Peak relative deviation (0.3 = +-30 %).

    Returns
    -------
    (nz, ny, nx) float32
    """
    nz, ny, nx = shape_zyx
    z = np.linspace(-1, 1, nz, dtype=np.float32)[:, None, None]
    y = np.linspace(-1, 1, ny, dtype=np.float32)[None, :, None]
    x = np.linspace(-1, 1, nx, dtype=np.float32)[None, None, :]
    c = rng.uniform(-1.0, 1.0, size=9).astype(np.float32)
    s = c[0] * x + c[1] * y + c[2] * z + c[3] * x * x + c[4] * y * y + c[5] * z * z
    s = s + c[6] * x * y + c[7] * x * z + c[8] * y * z
    s = s - 0.5 * (s.max() + s.min())
    peak = float(np.abs(s).max())
    if peak > 0:
        s *= np.float32(1.0 / peak)
    return (1.0 + np.float32(amplitude) * s).astype(np.float32)


def render(
    tissue: TissueVolume,
    rng: np.random.Generator,
    *,
    snr: float,
    bias: float,
    blur_sigma_voxels: float = 0.5,
    contrast: str = "t2",
    fat_suppressed: bool = False,
) -> Rendering:
    """Render an MRI-like magnitude image from a voxelised anatomy.

    Parameters
    ----------
    tissue
        Labels with partial-volume sub-sample counts.
    rng
        Random generator for the bias field and the noise.
    snr
        Mean reference-tissue signal / noise sigma (> 0); the reference is fat, or gland when
        fat is suppressed.
    bias
        Bias-field amplitude (0 disables it).
    blur_sigma_voxels
        Gaussian point-spread sigma in voxels (0 disables it).
    contrast
        Tissue intensities, ``"t2"`` or ``"t1"`` (:func:`intensity_table`).
    fat_suppressed
        Scale the fat signal by :data:`FAT_SUPPRESSION`.
    """
    if snr <= 0:
        raise ValueError(f"phantom: snr must be > 0, got {snr}")
    values = intensity_table(contrast, fat_suppressed=fat_suppressed)
    table = np.array([values[k] for k in range(len(values))], dtype=np.float32)
    clean = table[tissue.fine]
    flat = clean.reshape(-1)
    flat[tissue.boundary] = (tissue.counts.astype(np.float32) @ table) / tissue.samples
    if blur_sigma_voxels > 0:
        clean = ndimage.gaussian_filter(clean, blur_sigma_voxels, truncate=3.0)
    clean *= bias_field(clean.shape, rng, amplitude=bias)
    pure_fat = tissue.fine == FAT
    pure_fat.reshape(-1)[tissue.boundary] = False
    mean_fat = float(clean[pure_fat].mean()) if pure_fat.any() else 1.0
    mean_ref = mean_fat
    if fat_suppressed:
        pure_gland = tissue.fine == GLAND
        pure_gland.reshape(-1)[tissue.boundary] = False
        mean_ref = float(clean[pure_gland].mean()) if pure_gland.any() else values[GLAND]
    sigma = mean_ref / snr
    s = np.float32(sigma)
    re = rng.standard_normal(clean.shape, dtype=np.float32)
    re *= s
    re += clean
    im = rng.standard_normal(clean.shape, dtype=np.float32)
    im *= s
    re *= re
    im *= im
    re += im
    return Rendering(np.sqrt(re), float(sigma), mean_fat, mean_ref)
