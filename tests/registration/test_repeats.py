"""The chest-wall refinement repeated over sampling seeds: their mean, their scatter, and the
registration that uses them."""

import numpy as np
import pytest
import SimpleITK as sitk

from imaging.fiducials import find_fiducials
from imaging.io import read_volume
from imaging.preprocess import preprocess
from imaging.subject import read_subject
from registration.repeats import mean_transform, repeat_seeds, seed_spread
from registration.rigid import chest_wall_mask, register_rigid
from registration.transforms import matrix_to_transform, transform_to_matrix


def _euler(angles_deg, shift, centre=(10.0, -5.0, 30.0)):
    t = sitk.Euler3DTransform()
    t.SetCenter(tuple(float(c) for c in centre))
    t.SetRotation(*np.radians(angles_deg))
    t.SetTranslation(tuple(float(v) for v in shift))
    return t


def test_the_mean_of_transforms_symmetric_about_one_is_that_one():
    middle = transform_to_matrix(_euler((2.0, -1.0, 3.0), (4.0, -2.0, 1.0)))
    step = transform_to_matrix(_euler((0.3, -0.2, 0.5), (0.4, 0.1, -0.3)))  # a small motion
    back = np.eye(4)
    back[:3, :3], back[:3, 3] = step[:3, :3].T, -step[:3, 3]  # rotation undone, shift reversed
    a, b = middle @ step, middle @ back
    mean = mean_transform([matrix_to_transform(a), matrix_to_transform(b)], np.zeros(3))
    # Their rotations are M R and M R^T, their shifts M s + t and -M s + t: the chordal mean
    # of the rotations is M and the mean shift t, exactly.
    assert np.abs(transform_to_matrix(mean) - middle).max() < 1e-12


def test_the_spread_of_repeats_is_their_distance_from_the_mean():
    centre = np.zeros(3)
    base = _euler((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), centre)
    tfms = [_euler((0.0, 0.0, 0.0), (d, 0.0, 0.0), centre) for d in (-0.3, 0.0, 0.3)]
    pts = np.random.default_rng(1).normal(0.0, 50.0, (40, 3))
    s = seed_spread(tfms, base, pts)
    # Shifts of -0.3, 0 and 0.3 mm about their mean: RMS sqrt(0.06) mm, largest 0.3 mm,
    # and the mean's standard error RMS / sqrt(K - 1).
    assert s["rms"] == pytest.approx(np.sqrt(0.06))
    assert s["max"] == pytest.approx(0.3)
    assert s["standard_error"] == pytest.approx(np.sqrt(0.06) / np.sqrt(2))
    assert s["repeats"] == 3
    one = seed_spread(tfms[:1], tfms[0], pts)
    assert one["rms"] == 0.0 and one["standard_error"] == 0.0


def test_repeat_seeds_are_distinct_positive_and_wrap_below_2_31():
    assert repeat_seeds(20211, 3) == [20211, 20212, 20213]
    top = repeat_seeds(2**31 - 2, 3)
    assert top == [2**31 - 2, 2**31 - 1, 1]  # never 0: SimpleITK reads 0 as the wall clock
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="repeats must be a positive integer"):
            repeat_seeds(20211, bad)


@pytest.fixture(scope="module")
def prone_pair(mri_phantom):
    subject_dir, truth_dir = mri_phantom
    subject = read_subject(subject_dir)
    fixed = preprocess(subject.load("supine"), denoise_iterations=0)
    moving = preprocess(subject.load("prone"), denoise_iterations=0)
    mask = chest_wall_mask(read_volume(truth_dir / "supine_labels.nii.gz"))
    return dict(fixed=fixed, moving=moving, fixed_points=find_fiducials(fixed),
                moving_points=find_fiducials(moving), fixed_mask=mask)


def test_a_repeated_registration_is_the_mean_of_its_single_seed_runs(prone_pair):
    """The registration with three repeats is the mean of the three registrations with one
    repeat each at seeds s, s + 1, s + 2: each repeat is the whole single-seed refinement
    (its loose directions set too), from the same start."""
    seed = 777
    res = register_rigid(**prone_pair, seed=seed, repeats=3)
    singles = [register_rigid(**prone_pair, seed=s, repeats=1).refined_transform
               for s in (seed, seed + 1, seed + 2)]
    mats = np.array([transform_to_matrix(t) for t in singles])
    assert np.abs(mats - mats[0]).max() > 1e-6  # the seeds do land apart
    mean = mean_transform(singles, np.asarray(singles[0].GetCenter()))
    assert np.abs(transform_to_matrix(res.refined_transform)
                  - transform_to_matrix(mean)).max() < 1e-9
    assert res.spread["repeats"] == 3 and res.spread["rms"] > 0.0
    assert res.spread["standard_error"] == pytest.approx(res.spread["rms"] / np.sqrt(2))
    again = register_rigid(**prone_pair, seed=seed, repeats=3)  # same input, same transform
    assert np.array_equal(transform_to_matrix(again.transform), transform_to_matrix(res.transform))


def test_repeats_that_scatter_more_than_the_limit_are_named_in_a_warning(prone_pair):
    quiet = register_rigid(**prone_pair, repeats=3, spread_warn_mm=10.0)
    assert not any("sampling seeds disagree" in w for w in quiet.warnings)
    se = quiet.spread["standard_error"]
    loud = register_rigid(**prone_pair, repeats=3, spread_warn_mm=se / 2)
    said = [w for w in loud.warnings if "sampling seeds disagree" in w]
    assert len(said) == 1 and f"{se:.2f} mm from the sampling alone" in said[0]


def test_the_thread_count_set_is_the_one_the_metric_runs_on(prone_pair):
    """``threads`` decides the transform, whatever SimpleITK's global count: the metric
    splits its sums over the global count (the method's own setting alone did not hold it),
    so the refinement sets it for the call and puts it back."""
    runs = {}
    was = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    try:
        for global_count in (1, 3):
            sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(global_count)
            for threads in (1, 2):
                res = register_rigid(**prone_pair, repeats=1, threads=threads)
                runs[global_count, threads] = transform_to_matrix(res.refined_transform)
            assert sitk.ProcessObject.GetGlobalDefaultNumberOfThreads() == global_count
    finally:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(was)
    assert np.array_equal(runs[1, 1], runs[3, 1]) and np.array_equal(runs[1, 2], runs[3, 2])
    # and the count does reach the sums: another count, other last bits
    assert not np.array_equal(runs[1, 1], runs[1, 2])
