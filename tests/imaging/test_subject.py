"""Subject folder reader: a valid folder reads back exactly; each bad input gets its clear error."""

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from imaging.subject import SubjectError, read_points_csv, read_subject

TOML = """\
subject = "s-01"
reference = "supine"

[positions.supine]
volume = "supine.nii.gz"
gravity = [0.0, 1.0, 0.0]
notes = "supine"

[positions.prone]
volume = "prone.nrrd"
gravity = [0.0, -1.0, 0.0]

[positions.supine_tilted]
volume = "tilted.mha"
gravity = [-0.7071067811865476, 0.7071067811865476, 0.0]
tilt_deg = 45.0
"""

FIDUCIALS = """\
position,label,x,y,z
supine,sternum_upper,0.0,-110.5,60.0
supine,imf_left,75.0,-95.0,-70.0
prone,sternum_upper,1.0,-108.0,61.0
prone,imf_left,74.0,-96.0,-71.0
"""


def _volume(path: Path, arr=None, spacing=(1.0, 1.0, 2.0)) -> None:
    arr = np.ones((4, 5, 6), np.float32) if arr is None else arr
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(spacing)
    sitk.WriteImage(img, str(path))


@pytest.fixture
def subject_dir(tmp_path) -> Path:
    d = tmp_path / "subj"
    d.mkdir()
    (d / "subject.toml").write_text(TOML)
    _volume(d / "supine.nii.gz")
    _volume(d / "prone.nrrd")
    _volume(d / "tilted.mha")
    (d / "fiducials.csv").write_text(FIDUCIALS)
    (d / "landmarks.csv").write_text(
        "position,label,x,y,z\nsupine,nipple_left,75,-160,-10\nprone,nipple_left,75,-170,-20\n"
    )
    return d


def test_valid_subject_reads_back(subject_dir):
    s = read_subject(subject_dir)
    assert s.id == "s-01"
    assert s.reference == "supine"
    assert list(s.positions) == ["supine", "prone", "supine_tilted"]
    tilted = s.positions["supine_tilted"]
    np.testing.assert_allclose(tilted.gravity, [-np.sqrt(0.5), np.sqrt(0.5), 0.0])
    assert tilted.tilt_deg == 45.0 and s.positions["prone"].tilt_deg is None
    assert s.positions["supine"].notes == "supine"
    assert tilted.volume_path == subject_dir / "tilted.mha"
    np.testing.assert_array_equal(s.fiducials["prone"]["imf_left"], [74.0, -96.0, -71.0])
    assert set(s.fiducials) == {"supine", "prone"}
    np.testing.assert_array_equal(s.landmarks["supine"]["nipple_left"], [75, -160, -10])
    img = s.load("prone")
    assert img.GetSize() == (6, 5, 4) and img.GetSpacing() == (1.0, 1.0, 2.0)
    with pytest.raises(ValueError):
        s.positions["supine"].gravity[0] = 1.0  # read-only


def test_reference_defaults_to_supine(subject_dir):
    text = TOML.replace('reference = "supine"\n', "")
    (subject_dir / "subject.toml").write_text(text)
    assert read_subject(subject_dir).reference == "supine"


def test_dicom_folder_position(subject_dir):
    d = subject_dir / "dicom_supine"
    d.mkdir()
    img = sitk.GetImageFromArray(np.arange(60, dtype=np.int16).reshape(3, 4, 5))
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    for k in range(3):
        sl = img[:, :, k]
        sl.SetMetaData("0020|000e", "1.2.826.0.1.3680043.2.1125.1.77")
        sl.SetMetaData("0020|0032", f"0\\0\\{k}")
        sl.SetMetaData("0020|0037", "1\\0\\0\\0\\1\\0")
        sl.SetMetaData("0020|0013", str(k + 1))
        writer.SetFileName(str(d / f"{k}.dcm"))
        writer.Execute(sl)
    text = TOML.replace('volume = "supine.nii.gz"', 'volume = "dicom_supine"')
    (subject_dir / "subject.toml").write_text(text)
    s = read_subject(subject_dir)
    assert np.array_equal(sitk.GetArrayFromImage(s.load("supine")), sitk.GetArrayFromImage(img))


def _edit_toml(old, new):
    def edit(d: Path):
        text = (d / "subject.toml").read_text()
        assert old in text
        (d / "subject.toml").write_text(text.replace(old, new))

    return edit


def _write(name, content):
    def edit(d: Path):
        (d / name).write_text(content)

    return edit


def _volume_edit(name, arr=None, spacing=(1.0, 1.0, 2.0)):
    def edit(d: Path):
        if arr is not None and arr.ndim == 4:
            imgs = [sitk.GetImageFromArray(a) for a in arr]
            sitk.WriteImage(sitk.JoinSeries(imgs), str(d / name))
        else:
            _volume(d / name, arr, spacing)

    return edit


def _zero_spacing(d: Path):
    header = (
        "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementSpacing = 1 1 0\n"
        "ElementType = MET_UCHAR\nElementDataFile = LOCAL\n"
    )
    (d / "tilted.mha").write_bytes(header.encode() + bytes(8))


NAN = np.ones((4, 5, 6), np.float32)
NAN[2, 2, 2] = np.nan

BAD_CASES = {
    # name: (edit, file named in the error, phrase in the error)
    "no toml": (lambda d: (d / "subject.toml").unlink(), "subject.toml", "missing"),
    "bad toml": (_write("subject.toml", "subject = [\n"), "subject.toml", "not valid TOML"),
    "unknown key": (_edit_toml("notes =", "note ="), "subject.toml", "unknown key(s) ['note']"),
    "no subject id": (_edit_toml('subject = "s-01"', 'subject = ""'), "subject.toml", "'subject'"),
    "reference missing": (
        _edit_toml('reference = "supine"', 'reference = "upright"'),
        "subject.toml",
        "reference position 'upright' is not among",
    ),
    "missing volume": (
        lambda d: (d / "prone.nrrd").unlink(), "prone.nrrd", "does not exist"
    ),
    "no volume key": (
        _edit_toml('volume = "prone.nrrd"\n', ""), "positions.prone", "'volume'"
    ),
    "2-D volume": (
        _volume_edit("supine.nii.gz", np.ones((5, 6), np.float32), (1.0, 1.0)),
        "supine.nii.gz",
        "expected a 3-D image, got 2-D",
    ),
    "4-D volume": (
        _volume_edit("supine.nii.gz", np.ones((2, 4, 5, 6), np.float32)),
        "supine.nii.gz",
        "got 4-D",
    ),
    "NaN voxel": (_volume_edit("prone.nrrd", NAN), "prone.nrrd", "NaN or infinite"),
    "zero spacing": (_zero_spacing, "tilted.mha", "spacing must be > 0"),
    "non-unit gravity": (
        _edit_toml("gravity = [0.0, -1.0, 0.0]", "gravity = [0.0, -0.9, 0.0]"),
        "positions.prone",
        "must be a unit vector",
    ),
    "short gravity": (
        _edit_toml("gravity = [0.0, -1.0, 0.0]", "gravity = [0.0, -1.0]"),
        "positions.prone",
        "list of 3 numbers",
    ),
    "text tilt": (
        _edit_toml("tilt_deg = 45.0", 'tilt_deg = "45"'), "positions.supine_tilted", "tilt_deg"
    ),
    "inconsistent fiducials": (
        _write("fiducials.csv", FIDUCIALS.replace("prone,imf_left", "prone,imf_right")),
        "fiducials.csv",
        "labels differ between positions",
    ),
    "csv header": (
        _write("fiducials.csv", FIDUCIALS.replace("position,label", "pos,label")),
        "fiducials.csv",
        "header must be position,label,x,y,z",
    ),
    "csv not a number": (
        _write("fiducials.csv", FIDUCIALS.replace("-110.5", "abc")),
        "fiducials.csv line 2",
        "coordinates must be numbers",
    ),
    "csv columns": (
        _write("landmarks.csv", "position,label,x,y,z\nsupine,nipple_left,75,-160\n"),
        "landmarks.csv line 2",
        "expected 5 columns, got 4",
    ),
    "csv unknown position": (
        _write("fiducials.csv", FIDUCIALS + "upright,sternum_upper,0,0,0\n"),
        "fiducials.csv line 6",
        "unknown position 'upright'",
    ),
    "csv duplicate": (
        _write("fiducials.csv", FIDUCIALS + "prone,imf_left,0,0,0\n"),
        "fiducials.csv line 6",
        "duplicate label 'imf_left'",
    ),
    "csv not finite": (
        _write("fiducials.csv", FIDUCIALS.replace("-110.5", "nan")),
        "fiducials.csv line 2",
        "must be finite",
    ),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_subject_gets_one_clear_error(subject_dir, case):
    edit, where, phrase = BAD_CASES[case]
    edit(subject_dir)
    with pytest.raises(SubjectError) as info:
        read_subject(subject_dir)
    message = str(info.value)
    assert where in message, message
    assert phrase in message, message
    assert "\n" not in message


def test_metadata_only_read_skips_voxels(subject_dir):
    _volume_edit("prone.nrrd", NAN)(subject_dir)
    s = read_subject(subject_dir, check_volumes=False)  # NaNs are only seen when loading
    with pytest.raises(SubjectError, match="NaN"):
        s.load("prone")
    with pytest.raises(SubjectError, match="no position 'upright'"):
        s.load("upright")


def test_points_csv_without_subject(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("position,label,x,y,z\n\na,m1,1,2,3\nb,m1,4,5,6\n")
    pts = read_points_csv(path)
    np.testing.assert_array_equal(pts["b"]["m1"], [4.0, 5.0, 6.0])


def test_subject_pickles(subject_dir):
    """Subjects travel to dask workers: they must pickle and come back equal."""
    import pickle

    s = read_subject(subject_dir)
    back = pickle.loads(pickle.dumps(s))
    assert back.reference == s.reference and list(back.positions) == list(s.positions)
    np.testing.assert_array_equal(back.fiducials["prone"]["imf_left"], [74.0, -96.0, -71.0])
