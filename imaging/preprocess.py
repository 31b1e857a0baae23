"""MRI preprocessing: input checks, N4 bias correction, isotropic resampling, denoising and
intensity normalisation. Every step is optional and returns a new image (inputs are never
modified); geometry (origin, spacing, direction) survives each step except resampling.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

STAGE = "preprocess"


def check_volume(img: sitk.Image, *, name: str = "volume", stage: str = STAGE) -> None:
    """Fail with one clear message unless ``img`` is a finite scalar 3-D volume.

    Parameters
    ----------
    img : SimpleITK.Image
        The volume to check.
    name : str
        What to call it in the message (usually the file path).
    stage : str
        Stage named in the message.

    Raises
    ------
    ValueError
        Wrong dimension, vector pixels, zero/negative/non-finite spacing, NaN or Inf voxels.
    """
    if not isinstance(img, sitk.Image):
        raise ValueError(f"{stage}: {name} is a {type(img).__name__}, not a SimpleITK image")
    dim = img.GetDimension()
    if dim != 3:
        raise ValueError(f"{stage}: {name} is {dim}-D; a 3-D volume is required")
    if img.GetNumberOfComponentsPerPixel() != 1:
        raise ValueError(
            f"{stage}: {name} has {img.GetNumberOfComponentsPerPixel()} components per voxel "
            "(4-D or vector image); a scalar 3-D volume is required"
        )
    if min(img.GetSize()) < 2:
        raise ValueError(f"{stage}: {name} has size {img.GetSize()}; every axis needs >= 2 voxels")
    spacing = np.asarray(img.GetSpacing(), float)
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise ValueError(f"{stage}: {name} has invalid voxel spacing {tuple(spacing)} mm")
    if img.GetPixelID() in (sitk.sitkFloat32, sitk.sitkFloat64):
        a = sitk.GetArrayViewFromImage(img)
        bad = int(np.count_nonzero(~np.isfinite(a)))
        if bad:
            raise ValueError(f"{stage}: {name} contains {bad} NaN/Inf voxels")


def foreground_mask(img: sitk.Image) -> sitk.Image:
    """Foreground (uint8 0/1): voxels above the Otsu threshold of a 2x bin-shrunk copy.

    Shrinking averages the noise away for the threshold estimate and costs 1/8 of the
    volume; the threshold is then applied to the full grid (isolated noise voxels do not
    matter to the callers: N4 fitting, normalisation and marker detection).
    """
    f = sitk.Cast(img, sitk.sitkFloat32)
    small = sitk.BinShrink(f, [2 if n >= 8 else 1 for n in f.GetSize()])
    otsu = sitk.OtsuThresholdImageFilter()
    otsu.SetInsideValue(0)
    otsu.SetOutsideValue(1)
    otsu.Execute(small)
    return sitk.Cast(f > otsu.GetThreshold(), sitk.sitkUInt8)


def n4_correct(
    img: sitk.Image,
    *,
    shrink: int = 4,
    iterations: tuple[int, ...] = (50, 40, 30),
    mask: sitk.Image | None = None,
) -> sitk.Image:
    """N4 bias-field correction, fitted on a shrunken copy and applied at full resolution.

    Parameters
    ----------
    img : SimpleITK.Image
        Scalar 3-D volume with positive intensities in the body.
    shrink : int
        Shrink factor of the fit (the field is smooth, so 4 loses nothing and saves ~60x time).
    iterations : tuple of int
        Maximum iterations per fitting level (one level per entry).
    mask : SimpleITK.Image, optional
        Where to fit the field (default: Otsu foreground).

    Returns
    -------
    SimpleITK.Image
        Float32 corrected volume on the input grid.
    """
    f = sitk.Cast(img, sitk.sitkFloat32)
    # N4 works on log intensities: keep them strictly positive.
    f = sitk.Maximum(f, 1e-3)
    mask = foreground_mask(f) if mask is None else sitk.Cast(mask > 0, sitk.sitkUInt8)
    small = sitk.Shrink(f, [shrink] * 3)
    small_mask = sitk.Shrink(mask, [shrink] * 3)
    n4 = sitk.N4BiasFieldCorrectionImageFilter()
    n4.SetMaximumNumberOfIterations(list(iterations))
    n4.Execute(small, small_mask)
    # The field is smooth: evaluate it on the shrunken grid and interpolate linearly to the
    # full grid (evaluating the B-spline at every voxel costs ~10x more for no gain).
    log_bias = sitk.Resample(n4.GetLogBiasFieldAsImage(small), f, sitk.Transform(),
                             sitk.sitkLinear, 0.0, sitk.sitkFloat32, True)
    return sitk.Cast(f / sitk.Exp(log_bias), sitk.sitkFloat32)


def resample_isotropic(
    img: sitk.Image, *, spacing_mm: float | None = None, labels: bool = False
) -> sitk.Image:
    """Resample to cubic voxels of ``spacing_mm`` (default: the finest input spacing).

    Linear interpolation for intensities, nearest neighbour when ``labels`` is true.
    """
    old = np.asarray(img.GetSpacing(), float)
    s = float(old.min() if spacing_mm is None else spacing_mm)
    if s <= 0:
        raise ValueError(f"{STAGE}: isotropic spacing must be > 0 mm, got {s}")
    size = [max(1, int(round(n * o / s))) for n, o in zip(img.GetSize(), old)]
    interp = sitk.sitkNearestNeighbor if labels else sitk.sitkLinear
    return sitk.Resample(
        img, size, sitk.Transform(), interp, img.GetOrigin(), (s, s, s), img.GetDirection(),
        0, img.GetPixelID(),
    )


def denoise(
    img: sitk.Image, *, iterations: int = 3, conductance: float = 1.0, method: str = "gradient"
) -> sitk.Image:
    """Edge-preserving denoising by anisotropic diffusion (float32 output).

    Parameters
    ----------
    img : SimpleITK.Image
        Scalar volume.
    iterations : int
        Diffusion iterations.
    conductance : float
        Edge threshold relative to the image's mean gradient magnitude (lower keeps more
        edges).
    method : {"gradient", "curvature"}
        Perona-Malik gradient diffusion (default; about 4x cheaper per volume: 2 s against
        8 s for 3 iterations on 256^3) or curvature-driven diffusion (keeps thin bright
        lines slightly better).

    Notes
    -----
    The time step is 0.06 * min spacing, below the 3-D stability limit of spacing / 16.
    """
    f = sitk.Cast(img, sitk.sitkFloat32)
    step = 0.06 * min(img.GetSpacing())
    filters = {"gradient": sitk.GradientAnisotropicDiffusion,
               "curvature": sitk.CurvatureAnisotropicDiffusion}
    if method not in filters:
        raise ValueError(f"{STAGE}: denoising method must be one of {sorted(filters)}, "
                         f"got {method!r}")
    return filters[method](f, timeStep=step, conductanceParameter=conductance,
                           numberOfIterations=int(iterations))


def bright_mode(values: np.ndarray) -> float:
    """Mode of the bright class of ``values`` (above their Otsu threshold): the fat level of a
    T2/T1-weighted breast MRI, robust to bright outliers such as markers."""
    from skimage.filters import threshold_otsu

    v = np.asarray(values, float).ravel()
    if v.size > 2_000_000:  # a strided sample is plenty for a histogram
        v = v[:: v.size // 2_000_000]
    upper = v[v > threshold_otsu(v)]
    if upper.size == 0:
        return float(v.max())
    hist, edges = np.histogram(upper, bins=128)
    hist = np.convolve(hist, np.ones(5) / 5, mode="same")
    k = int(hist.argmax())
    return float(0.5 * (edges[k] + edges[k + 1]))


def normalise(img: sitk.Image) -> sitk.Image:
    """Map the background level to 0 and the bright-tissue (fat) mode to 1 (float32).

    Background = median outside the Otsu foreground, so the scale ignores the amount of air;
    the fat mode ignores small bright objects (markers) that a percentile would catch.
    """
    f = sitk.Cast(img, sitk.sitkFloat32)
    a = sitk.GetArrayViewFromImage(f)
    fg = sitk.GetArrayFromImage(foreground_mask(f)).astype(bool)
    if not fg.any() or fg.all():
        raise ValueError(f"{STAGE}: cannot normalise a volume without foreground and background")
    lo = float(np.median(a[~fg]))
    hi = bright_mode(a[fg])
    if hi <= lo:
        raise ValueError(f"{STAGE}: volume has no contrast (foreground {hi} <= background {lo})")
    return sitk.Cast((f - lo) / (hi - lo), sitk.sitkFloat32)


def preprocess(
    img: sitk.Image,
    *,
    n4: bool = True,
    n4_shrink: int = 4,
    isotropic_mm: float | None = None,
    denoise_iterations: int = 3,
    denoise_method: str = "gradient",
    normalise_intensity: bool = True,
    name: str = "volume",
) -> sitk.Image:
    """Run the enabled steps in order: check, N4, resample, denoise, normalise.

    Parameters
    ----------
    img : SimpleITK.Image
        Raw scalar 3-D volume.
    n4 : bool
        Bias-field correction on/off.
    n4_shrink : int
        Shrink factor for the N4 fit.
    isotropic_mm : float, optional
        Resample to this cubic voxel size in mm (None: keep the grid).
    denoise_iterations : int
        Anisotropic diffusion iterations (0: off).
    denoise_method : {"gradient", "curvature"}
        Diffusion flavour (see :func:`denoise`).
    normalise_intensity : bool
        Background -> 0, fat mode -> 1.
    name : str
        Name used in error messages.

    Returns
    -------
    SimpleITK.Image
        Float32 volume (on the input grid unless ``isotropic_mm`` is set).
    """
    check_volume(img, name=name)
    out = sitk.Cast(img, sitk.sitkFloat32)
    if n4:
        out = n4_correct(out, shrink=n4_shrink)
    if isotropic_mm is not None:
        out = resample_isotropic(out, spacing_mm=isotropic_mm)
    if denoise_iterations > 0:
        out = denoise(out, iterations=denoise_iterations, method=denoise_method)
    if normalise_intensity:
        try:
            out = normalise(out)
        except ValueError as exc:  # name the file: "empty volume" alone is not actionable
            raise ValueError(f"{exc} ({name})") from None
    return out
