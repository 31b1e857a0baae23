"""Shared fixtures. A zoo of tiny meshes lives in tests/zoo.py."""

import matplotlib
import pytest

matplotlib.use("Agg")


@pytest.fixture(scope="session")
def mri_phantom(tmp_path_factory):
    """Small 1 mm phantom with 15 deg / 30 mm motions, shared by the MRI tests:
    (subject folder, truth folder)."""
    from breastmodel.phantom import make_phantom

    root = tmp_path_factory.mktemp("mri_phantom_small")
    subject = root / "subject"
    make_phantom(subject, seed=3, small=True, positions=("supine", "prone"),
                 max_rotation_deg=15.0, max_translation_mm=30.0, progress=False)
    return subject, root / "subject_truth"


@pytest.fixture(scope="module")
def febio():
    """The FEBio 4 executable (../shared/febio/febio4 or $FEBIO); the test is skipped, saying
    why, where there is none (a user's machine)."""
    from breastmodel.febio import FebioError, find_febio

    try:
        return find_febio()
    except FebioError as exc:
        pytest.skip(f"FEBio not available: {exc}")
