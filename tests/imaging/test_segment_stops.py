"""A segmentation that does not hold up stops the segment stage with a clear error, after
its label map and QA picture are written (issue 14: no stage degrades silently).

On the validation suite the 2 mm, SNR 13 coil subject's muscle agreed to 0.23-0.37 with its
threshold start (muscle Dice 0.24-0.40) and its pipeline went on to fail three stages later
in the fit; here the mechanism is tried on the numpy slab by asking for more agreement than
any segmentation reaches.
"""

import pytest
from mri_synth import Slab, render, write_subject

from breastmodel.errors import StageError
from breastmodel.pipeline.segment import segment_subject


@pytest.fixture(scope="module")
def slab_subject(tmp_path_factory):
    img, _ = render(Slab(), seed=3)
    return write_subject(tmp_path_factory.mktemp("slab") / "subject",
                         {"supine": (img, (0.0, 1.0, 0.0))})


def _config(tmp_path, stop):
    path = tmp_path / "seg.toml"
    path.write_text(f"[segment]\nstop_below_agreement = {stop}\n", encoding="utf-8")
    return path


def test_a_segmentation_below_the_agreement_floor_stops_naming_volume_and_reason(
        slab_subject, tmp_path):
    out = tmp_path / "seg"
    with pytest.raises(StageError) as err:
        segment_subject(slab_subject, out, config=_config(tmp_path, 0.9999))
    msg = str(err.value)
    assert msg.startswith("segment [") and "supine.nii.gz" in msg
    assert "does not hold up" in msg and "agree only to Dice" in msg
    assert "stop_below_agreement" in msg
    # the label map and the QA picture are there for a look
    assert (out / "supine_labels.nii.gz").is_file() and (out / "supine_qa.png").is_file()


def test_the_default_floor_passes_a_good_segmentation_and_zero_never_stops(
        slab_subject, tmp_path):
    res = segment_subject(slab_subject, tmp_path / "a")
    assert res["supine"]["confidence"]["agreement"]["muscle"] >= 0.5
    res = segment_subject(slab_subject, tmp_path / "b", config=_config(tmp_path, 0))
    assert "supine" in res
