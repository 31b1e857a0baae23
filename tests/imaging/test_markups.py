"""3D Slicer markups: LPS and RAS files read back in LPS; a subject folder may hold markups
instead of fiducials.csv and reads to the same fiducials."""

import json

import numpy as np
import pytest
from test_subject import FIDUCIALS, subject_dir  # noqa: F401 - the fixture

from imaging.markups import MarkupsError, read_markups, write_markups
from imaging.subject import SubjectError, read_subject

POINTS = {"supine": {"sternum_upper": np.array([0.0, -110.5, 60.0]),
                     "imf_left": np.array([75.0, -95.0, -70.0])},
          "prone": {"sternum_upper": np.array([1.0, -108.0, 61.0]),
                    "imf_left": np.array([74.0, -96.0, -71.0])}}


@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_markups_round_trip_in_lps(tmp_path, system):
    path = write_markups(tmp_path / "f.mrk.json", POINTS, coordinate_system=system)
    doc = json.loads(path.read_text())
    assert [m["coordinateSystem"] for m in doc["markups"]] == [system, system]
    first = doc["markups"][0]["controlPoints"][0]["position"]
    sign = np.array([-1, -1, 1]) if system == "RAS" else np.ones(3)
    assert first == pytest.approx(POINTS["supine"]["sternum_upper"] * sign)
    back = read_markups(path)
    assert set(back) == set(POINTS)
    for pos, pts in POINTS.items():
        for k, v in pts.items():
            np.testing.assert_allclose(back[pos][k], v)


def test_slicer_file_in_ras_converts_to_lps(tmp_path):
    """A file as Slicer writes it: one unnamed list, RAS, a point not placed yet."""
    doc = {"@schema": "x", "markups": [{"type": "Fiducial", "coordinateSystem": "RAS",
                                        "controlPoints": [
        {"label": "a", "position": [10.0, 20.0, 30.0], "positionStatus": "defined"},
        {"label": "b", "position": [0.0, 0.0, 0.0], "positionStatus": "undefined"}]}]}
    path = tmp_path / "supine_fiducials.mrk.json"
    path.write_text(json.dumps(doc))
    back = read_markups(path)
    assert list(back) == ["supine_fiducials"]
    assert list(back["supine_fiducials"]) == ["a"]
    np.testing.assert_allclose(back["supine_fiducials"]["a"], [-10.0, -20.0, 30.0])


@pytest.mark.parametrize("edit, match", [
    (lambda m: m.update(coordinateSystem="IJK"), "neither LPS nor RAS"),
    (lambda m: m["controlPoints"][0].update(position=[1.0, "x", 2.0]), "3 finite numbers"),
    (lambda m: m["controlPoints"][1].update(label="sternum_upper"), "used twice"),
    (lambda m: m.update(coordinateUnits="um"), "only mm"),
])
def test_bad_markups_get_one_clear_error(tmp_path, edit, match):
    path = write_markups(tmp_path / "f.mrk.json", {"supine": POINTS["supine"]})
    doc = json.loads(path.read_text())
    edit(doc["markups"][0])
    path.write_text(json.dumps(doc))
    with pytest.raises(MarkupsError, match=match):
        read_markups(path)


def test_subject_reads_markups_instead_of_csv(subject_dir):  # noqa: F811
    csv = read_subject(subject_dir).fiducials
    assert "sternum_upper" in FIDUCIALS and set(csv) == {"supine", "prone"}
    (subject_dir / "fiducials.csv").unlink()
    write_markups(subject_dir / "fiducials.mrk.json", {"supine": csv["supine"]},
                  coordinate_system="RAS")
    write_markups(subject_dir / "prone_fiducials.mrk.json", {"anything": csv["prone"]})
    got = read_subject(subject_dir).fiducials
    assert set(got) == set(csv)
    for pos in csv:
        assert set(got[pos]) == set(csv[pos])
        for k in csv[pos]:
            np.testing.assert_allclose(got[pos][k], csv[pos][k], atol=1e-12)


def test_subject_markups_named_after_no_position_fail(subject_dir):  # noqa: F811
    (subject_dir / "fiducials.csv").unlink()
    write_markups(subject_dir / "fiducials.mrk.json", {"standing": POINTS["supine"]})
    with pytest.raises(SubjectError, match="standing.*named after no position"):
        read_subject(subject_dir)
