"""The chest-wall refinement repeated over sampling seeds: the transform the repeats agree on
(:func:`mean_transform`) and how far they scatter (:func:`seed_spread`, :func:`point_errors`).

The correlation samples a random share of the mask's voxels (``[register] sampling``), and
along the directions a chest wall pins weakly its optimum is flat: each sampling seed stops
the optimiser (50 iterations a level, which it reaches) somewhere else along them. Measured
on the validation suite (``python bench/register_suite.py --arms truth_labels,pipeline
--seed-study 5``: 12 small subjects, 48 registrations, each once per seed 20211-20215;
``bench/results/register_seed_study_2026-12-07.json``): one seed's chest-wall TRE (max) ranged
over 0.24-0.54 mm on small-000's prone position (own segmentation), 0.69-2.32 mm on
small-002's tilted one, 0.75-2.16 mm on small-007's prone one; over the 48 the mean of one
seed's max TRE is 0.560 mm, that of the mean transform of the first 3 seeds 0.470 and of
all 5 0.470, and the mean of 5 is no worse than the seeds' average on every one. More
samples in one run do as much (one run with ``sampling = 0.5``: 0.461 mm on one seed), but
say nothing of the scatter: the repeats' scatter is the registration's own measure of how
well the images pin it (small-002, 2 mm voxels at SNR 13, is the one subject whose repeats'
standard error passes 0.25 mm).
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from registration.initialise import _to_euler
from registration.refine import _check_seed
from registration.transforms import STAGE, matrix_to_transform, transform_to_matrix

#: Refinements whose mean is the registration (``[register] repeats``): 3 did as well as 5
#: on the suite (above) at 3/5 of the time.
REPEATS = 3
#: A registration warns where the mean of its repeats is uncertain by more than this from
#: the sampling alone (their standard error on the chest wall, mm): two standard errors, what
#: the sampling leaves 1 time in 20, are then past issue 14's 0.5 mm.
SPREAD_WARN_MM = 0.25
#: Seeds are at most this (SimpleITK's sampling seed is a positive 32-bit integer).
_SEED_MAX = 2**31 - 1


def repeat_seeds(seed: int, repeats: int) -> list[int]:
    """``repeats`` distinct sampling seeds from ``seed`` (itself checked): ``seed, seed + 1,
    ...`` (wrapping below 2^31, never 0, which SimpleITK reads as "seed from the wall clock")."""
    _check_seed(seed)
    if isinstance(repeats, bool) or not isinstance(repeats, int | np.integer) or repeats < 1:
        raise ValueError(f"{STAGE}: repeats must be a positive integer, got {repeats!r}")
    return [(int(seed) - 1 + k) % _SEED_MAX + 1 for k in range(int(repeats))]


def mean_transform(tfms: list[sitk.Transform], centre: np.ndarray) -> sitk.Euler3DTransform:
    """The rigid transform the ``tfms`` agree on: the chordal mean of their rotations
    (:meth:`scipy.spatial.transform.Rotation.mean`) and the mean of their translations, about
    ``centre`` (rigid transforms that differ by fractions of a degree)."""
    mats = np.array([transform_to_matrix(t) for t in tfms])
    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(mats[:, :3, :3]).mean().as_matrix()
    out[:3, 3] = mats[:, :3, 3].mean(axis=0)
    return _to_euler(matrix_to_transform(out), np.asarray(centre, float))


def seed_spread(tfms: list[sitk.Transform], mean: sitk.Transform,
                points: np.ndarray) -> dict[str, float]:
    """How far the repeats scatter about their ``mean`` at ``points`` (N, 3) mm: ``rms`` over
    repeats and points of ``|T_k(x) - mean(x)|``, ``max`` the largest, and ``standard_error``
    the mean's own error from the sampling alone, ``rms / sqrt(K - 1)`` (0 with one repeat)."""
    p = np.c_[np.asarray(points, float), np.ones(len(points))]
    at_mean = p @ transform_to_matrix(mean).T
    d = np.array([np.linalg.norm((p @ transform_to_matrix(t).T - at_mean)[:, :3], axis=1)
                  for t in tfms])
    rms = float(np.sqrt(np.mean(d ** 2))) if d.size else 0.0
    k = len(tfms)
    return {"rms": rms, "max": float(d.max()) if d.size else 0.0,
            "standard_error": rms / np.sqrt(k - 1) if k > 1 else 0.0, "repeats": k}


def point_errors(tfms: list[sitk.Transform], mean: sitk.Transform,
                 points: np.ndarray) -> np.ndarray:
    """(N,) the ``mean`` transform's standard error at each of ``points`` (mm) from the
    repeats' scatter there, ``sqrt(mean_k |T_k(x) - mean(x)|^2 / (K - 1))`` (0 with one)."""
    k = len(tfms)
    p = np.c_[np.asarray(points, float).reshape(-1, 3), np.ones(len(points))]
    if k < 2 or not len(p):
        return np.zeros(len(p))
    at_mean = p @ transform_to_matrix(mean).T
    d2 = np.array([np.sum((p @ transform_to_matrix(t).T - at_mean)[:, :3] ** 2, axis=1)
                   for t in tfms])
    return np.sqrt(d2.mean(axis=0) / (k - 1))
