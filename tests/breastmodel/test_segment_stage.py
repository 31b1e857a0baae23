"""The pipeline's segment stage keeps the segmentation's own confidence, says when it doubts
itself, and a registration that then fails names that doubt (issue 14: no stage degrades
silently). Before, `breastmodel run` dropped the confidence: on the validation suite's
small-005 (slab, T2) the tilted scan's muscle (Dice 0.024) went on unreported until the
registration stopped with a message about the fiducials alone."""

from __future__ import annotations

import logging

import pytest
from mri_synth import render_family_supine

from breastmodel.errors import StageError
from breastmodel.pipeline.segment import read_confidence, update_summary
from breastmodel.pipeline.subject_stages import (
    doubtful_segmentations,
    register_stage,
    segment_stage,
)


def test_the_segment_stage_keeps_the_confidence_and_the_run_says_its_doubts(tmp_path, caplog):
    from breastmodel.pipeline.run import _say_doubts
    from imaging.subject import read_subject

    pos = "supine_tilted_49"
    render_family_supine(5, tmp_path, position=pos)
    subject = read_subject(tmp_path / "subject")
    d = tmp_path / "stage"
    d.mkdir()
    segment_stage(subject, pos, {"preprocess": {}, "segment": {}})(d)
    conf = read_confidence(d, pos)
    assert set(conf["agreement"]) == {"body", "muscle"}
    assert all(0.0 <= v <= 1.0 for v in conf["agreement"].values())
    assert conf["confident"] == (not conf["warnings"])
    # the run warns from the stage's final folder (a cached stage's doubts are said again)
    doubt = {"agreement": {"body": 0.61}, "confident": False,
             "warnings": ["low confidence: the body's active contour ... Dice 0.610"]}
    for folder, c in ((d, conf), (tmp_path / "doubting", doubt)):
        folder.mkdir(exist_ok=True)
        update_summary(folder, pos, {"confidence": c})
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="breastmodel.pipeline"):
            _say_doubts(folder, pos)
        said = [r.getMessage() for r in caplog.records]
        assert len(said) == (1 if c["warnings"] else 0)
        if said:
            assert all(w in said[0] for w in c["warnings"])
            assert said[0].endswith(f"(look at {folder / f'{pos}_qa.png'})")


def test_a_registration_that_stops_names_the_segmentation_that_doubted_itself(tmp_path,
                                                                               monkeypatch):
    import breastmodel.pipeline.register as register

    seg_dirs = {}
    for pos, confident in (("supine", True), ("prone", False)):
        seg_dirs[pos] = tmp_path / pos
        seg_dirs[pos].mkdir()
        (seg_dirs[pos] / f"{pos}_labels.nii.gz").write_bytes(b"")
        warnings = [] if confident else ["low confidence: the muscle's active contour and "
                                         "its threshold start agree only to Dice 0.610"]
        update_summary(seg_dirs[pos], pos, {"confidence": {
            "agreement": {"body": 0.99, "muscle": 0.61}, "warnings": warnings,
            "confident": confident}})
    assert doubtful_segmentations(seg_dirs) == f"'prone' ({warnings[0]})"

    def stops(*args, **kwargs):
        raise StageError("register", "position 'prone': the registration is flagged", "r.json")

    monkeypatch.setattr(register, "register_subject", stops)
    d = tmp_path / "register"
    d.mkdir()
    with pytest.raises(StageError) as exc:
        register_stage(object(), seg_dirs, {"register": {}})(d)
    msg = str(exc.value)
    assert msg.startswith("register [r.json]: position 'prone': the registration is flagged.")
    assert "doubted itself: 'prone' (low confidence: the muscle's" in msg
    assert "'supine'" not in msg
    # without a doubtful segmentation the registration's own error goes out as it was
    update_summary(seg_dirs["prone"], "prone", {"confidence": {"warnings": [],
                                                               "confident": True}})
    d2 = tmp_path / "register2"
    d2.mkdir()
    with pytest.raises(StageError, match=r"flagged$"):
        register_stage(object(), seg_dirs, {"register": {}})(d2)


def test_scans_of_one_subject_that_read_different_contrasts_are_each_doubted(tmp_path,
                                                                             monkeypatch,
                                                                             caplog):
    """On the phantom family (60 subjects, one protocol each) every subject whose scans read
    different contrasts held a misread (small-040: prone and tilted read fat suppressed, its
    T1 supine fat bright; the two misreads were confident): each position of such a subject
    is doubted, by the run, the `segment` command and a registration that stops."""
    import SimpleITK as sitk
    from mri_synth import write_subject

    import breastmodel.pipeline.segment as segment
    from imaging.segment_contrast import contrast_disagreement

    assert contrast_disagreement({"prone": "fat_bright", "supine": "fat_bright"}) == ""
    said = contrast_disagreement({"prone": "fat_suppressed", "supine": "fat_bright",
                                  "supine_tilted_15": "fat_suppressed"})
    assert "(fat_bright: supine; fat_suppressed: prone, supine_tilted_15)" in said
    assert "declare [segment] contrast" in said

    read = {"prone": "fat_suppressed", "supine": "fat_bright"}
    img = sitk.Image(8, 8, 8, sitk.sitkFloat32)
    subject = write_subject(tmp_path / "subject", {p: (img, (0.0, 0.0, -1.0)) for p in read})

    def segmented(subject, position, out, **kwargs):
        return {"contrast": read[position], "notes": [],
                "confidence": {"agreement": {"body": 0.99, "muscle": 0.98}, "warnings": [],
                               "confident": True}}

    monkeypatch.setattr(segment, "segment_position", segmented)
    out = tmp_path / "seg"
    with caplog.at_level(logging.WARNING, logger="breastmodel.segment"):
        results = segment.segment_subject(subject, out)
    assert [r.getMessage() for r in caplog.records] == [
        "segment: the subject's scans read different contrasts (fat_bright: supine; "
        "fat_suppressed: prone): one is misread unless they were acquired so; if they were "
        "acquired alike, declare [segment] contrast"]
    for pos in read:  # the command's segmentation.json says it of every position, once
        conf = segment.read_confidence(out, pos)
        assert results[pos]["confidence"] == conf
        assert conf["confident"] is False and conf["warnings"][-1].startswith("the subject's")
        assert segment.read_confidences({p: out for p in read})[pos] == conf
    # the run's stage folders, one per position: each position doubted, as a stopping
    # registration would name them
    seg_dirs = {}
    for pos in read:
        seg_dirs[pos] = tmp_path / f"stage_{pos}"
        seg_dirs[pos].mkdir()
        update_summary(seg_dirs[pos], pos, segmented(None, pos, None))
    doubt = doubtful_segmentations(seg_dirs)
    assert doubt.startswith("'prone' (the subject's scans") and "; 'supine' (" in doubt
    update_summary(seg_dirs["prone"], "prone", {**segmented(None, "prone", None),
                                                "contrast": "fat_bright"})
    assert doubtful_segmentations(seg_dirs) == ""
