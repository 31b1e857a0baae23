"""Fuzz: malformed subject folders end with the project's own errors, naming the file.

Each case starts from a small valid subject folder and breaks one thing (a truncated or
corrupt volume, NaN voxels, a bad spacing, noise only, a bad position name or path, bad TOML
or CSV) or mutates subject.toml at random (seeded). The reader, ``info`` and ``segment`` run
in-process: every case must end with a SubjectError / VolumeError / SegmentationError /
ConfigError / StageError, never another exception, a signal or a silent success. The
non-UTF-8 path (ITK aborts the process on one) runs in a child process.
"""

from __future__ import annotations

import gzip
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from mri_synth import Slab, render

from breastmodel.config import ConfigError
from breastmodel.errors import StageError
from imaging.io import VolumeError
from imaging.segment import SegmentationError
from imaging.subject import SubjectError, read_subject

OWN_ERRORS = (SubjectError, VolumeError, SegmentationError, ConfigError, StageError)
TOML = """subject = "fuzz"
reference = "supine"

[positions.supine]
volume = "supine.nii.gz"
gravity = [0.0, 1.0, 0.0]

[positions.prone]
volume = "prone.nii.gz"
gravity = [0.0, -1.0, 0.0]
"""
CSV = "position,label,x,y,z\n" + "".join(
    f"{p},m{i},{i}.0,{-i}.0,{2 * i}.0\n" for p in ("supine", "prone") for i in range(4))


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A valid small subject folder (3 mm voxels)."""
    root = tmp_path_factory.mktemp("fuzz_base") / "subject"
    root.mkdir()
    img, _ = render(Slab(), spacing=(3.0, 3.0, 3.0), seed=5)
    img = sitk.Cast(img, sitk.sitkFloat32)
    sitk.WriteImage(img, str(root / "supine.nii.gz"))
    sitk.WriteImage(img, str(root / "prone.nii.gz"))
    (root / "subject.toml").write_text(TOML)
    (root / "fiducials.csv").write_text(CSV)
    read_subject(root)  # the base is valid
    return root


def _nifti_bytes(path: Path) -> bytearray:
    return bytearray(gzip.decompress(path.read_bytes()))


def _put_nifti(folder: Path, raw: bytes, name="supine.nii.gz") -> None:
    (folder / name).write_bytes(gzip.compress(bytes(raw)) if name.endswith(".gz") else raw)
    if not name.startswith("supine.nii.gz"):
        (folder / "subject.toml").write_text(TOML.replace('"supine.nii.gz"', f'"{name}"'))


def _volume_cases():
    def truncated(frac, gz=True):
        def f(d):
            data = (d / "supine.nii.gz").read_bytes() if gz else bytes(
                _nifti_bytes(d / "supine.nii.gz"))
            name = "supine.nii.gz" if gz else "supine.nii"
            cut = data[: max(1, int(len(data) * frac))]
            (d / "supine.nii.gz").unlink()
            _put_nifti(d, cut, name) if not gz else (d / name).write_bytes(cut)
        return f

    def corrupt(seed):
        def f(d):
            data = bytearray((d / "supine.nii.gz").read_bytes())
            rng = np.random.default_rng(seed)
            for i in rng.integers(10, len(data), 8):
                data[i] ^= 0xFF
            (d / "supine.nii.gz").write_bytes(bytes(data))
        return f

    def header(offset, fmt, value, name="supine.nii.gz"):
        def f(d):
            raw = _nifti_bytes(d / "supine.nii.gz")
            raw[offset:offset + struct.calcsize(fmt)] = struct.pack(fmt, value)
            (d / "supine.nii.gz").unlink()
            _put_nifti(d, raw, name)
        return f

    def array(a, ext=".nii.gz", spacing=None):
        def f(d):
            img = sitk.GetImageFromArray(a() if callable(a) else a)
            if spacing is not None:
                img.SetSpacing(spacing)
            (d / "supine.nii.gz").unlink()
            sitk.WriteImage(img, str(d / f"supine{ext}"))
            if ext != ".nii.gz":
                (d / "subject.toml").write_text(TOML.replace('"supine.nii.gz"',
                                                             f'"supine{ext}"'))
        return f

    def with_nan(ext, value=np.nan):
        def a():
            img, _ = render(Slab(), spacing=(3.0, 3.0, 3.0), seed=5)
            arr = sitk.GetArrayFromImage(sitk.Cast(img, sitk.sitkFloat32))
            arr[3, 4, 5] = value
            return arr
        return array(a, ext)

    def noise(seed, kind):
        def a():
            rng = np.random.default_rng(seed)
            shape = (24, 20, 30)
            if kind == "normal":
                return np.abs(rng.normal(100, 30, shape)).astype(np.float32)
            if kind == "uniform":
                return rng.uniform(0, 1000, shape).astype(np.float32)
            return rng.rayleigh(50, shape).astype(np.float32)
        return array(a)

    cases = {}
    for frac in (0.05, 0.2, 0.5, 0.8, 0.95, 0.99):
        cases[f"truncated-gz-{frac}"] = truncated(frac)
    for frac in (0.001, 0.1, 0.3, 0.5, 0.9, 0.999):
        cases[f"truncated-nii-{frac}"] = truncated(frac, gz=False)
    for seed in range(8):
        cases[f"corrupt-{seed}"] = corrupt(seed)
    for ext in (".nii.gz", ".nii", ".mha", ".nrrd"):
        cases[f"nan{ext}"] = with_nan(ext)
        cases[f"inf{ext}"] = with_nan(ext, np.inf)
    for v in (0.0, -1.0, float("nan"), float("inf"), 1e6, 1e-9):
        cases[f"pixdim-x-{v}"] = header(80, "<f", v)
        cases[f"pixdim-z-{v}-nii"] = header(88, "<f", v, "supine.nii")
    cases["scl-slope-nan"] = header(112, "<f", float("nan"))
    cases["dim0-0"] = header(40, "<h", 0)
    cases["dim0-9"] = header(40, "<h", 9)
    cases["dim-negative"] = header(44, "<h", -5)
    cases["dim-huge"] = header(42, "<h", 32000)
    cases["datatype-rgb"] = header(70, "<h", 128)
    cases["datatype-bogus"] = header(70, "<h", 77)
    cases["vox-offset-inside-header"] = header(108, "<f", 10.0)
    cases["vox-offset-past-end"] = header(108, "<f", 1e7)
    cases["magic"] = header(344, "4s", b"xxxx")
    cases["sizeof-hdr"] = header(0, "<i", 123)
    for seed, kind in enumerate(("normal", "uniform", "rayleigh", "normal", "uniform")):
        cases[f"noise-{kind}-{seed}"] = noise(seed, kind)
    cases["constant"] = array(np.full((10, 12, 14), 7.0, np.float32))
    cases["2-D"] = array(np.zeros((12, 14), np.float32))
    cases["4-D"] = array(np.zeros((3, 4, 5, 6), np.float32), ext=".nii")
    cases["vector"] = array(lambda: sitk.GetArrayFromImage(
        sitk.Compose([sitk.Image(5, 6, 7, sitk.sitkFloat32)] * 3)), ext=".mha")
    cases["one-slice"] = array(np.ones((1, 30, 30), np.float32))
    cases["mha-spacing-huge"] = array(np.ones((8, 8, 8), np.float32), ".mha", (1e6, 1, 1))
    cases["empty-file"] = lambda d: (d / "supine.nii.gz").write_bytes(b"")
    cases["text-file"] = lambda d: (d / "supine.nii.gz").write_text("hello")
    cases["volume-is-folder"] = lambda d: ((d / "supine.nii.gz").unlink(),
                                           (d / "supine.nii.gz").mkdir())
    return cases


def _toml_cases():
    def toml(text):
        return lambda d: (d / "subject.toml").write_text(text, encoding="utf-8")

    def replace(old, new):
        assert old in TOML
        return toml(TOML.replace(old, new))

    cases = {}
    for bad in ("../../escaped", "a/b", "..", ".hidden", "with space", "", "x" * 80,
                "né", "1prone", "a\\\\b"):
        cases[f"position-name-{bad[:12]!r}"] = replace("[positions.prone]",
                                                       f'[positions."{bad}"]')
    cases["reference-list"] = replace('reference = "supine"', 'reference = ["supine"]')
    cases["reference-int"] = replace('reference = "supine"', "reference = 3")
    cases["reference-unknown"] = replace('reference = "supine"', 'reference = "side"')
    cases["gravity-strings"] = replace("[0.0, -1.0, 0.0]", '["0", "-1", "0"]')
    cases["gravity-short"] = replace("[0.0, -1.0, 0.0]", "[0.0, -1.0]")
    cases["gravity-not-unit"] = replace("[0.0, -1.0, 0.0]", "[0.0, -2.0, 0.0]")
    cases["gravity-nan"] = replace("[0.0, -1.0, 0.0]", "[nan, -1.0, 0.0]")
    cases["gravity-inf"] = replace("[0.0, -1.0, 0.0]", "[inf, -1.0, 0.0]")
    cases["gravity-bool"] = replace("[0.0, -1.0, 0.0]", "[true, false, false]")
    cases["volume-missing"] = replace('"prone.nii.gz"', '"absent.nii.gz"')
    cases["volume-int"] = replace('"prone.nii.gz"', "5")
    cases["volume-nul"] = replace('"prone.nii.gz"', '"pro\\u0000ne.nii.gz"')
    cases["volume-absolute-missing"] = replace('"prone.nii.gz"', '"/nonexistent/x.nii.gz"')
    cases["volume-subject-folder"] = replace('"prone.nii.gz"', '"."')
    cases["tilt-string"] = replace("gravity = [0.0, -1.0, 0.0]",
                                   'gravity = [0.0, -1.0, 0.0]\ntilt_deg = "45"')
    cases["unknown-key"] = replace('subject = "fuzz"', 'subject = "fuzz"\ncolour = 1')
    cases["subject-empty"] = replace('subject = "fuzz"', 'subject = ""')
    cases["no-positions"] = toml('subject = "fuzz"\n')
    cases["positions-not-table"] = toml('subject = "fuzz"\npositions = 3\n')
    cases["syntax"] = toml(TOML + "\n[positions.supine\n")
    cases["duplicate-table"] = toml(TOML + "\n[positions.prone]\nvolume = 'x'\n")
    cases["empty-toml"] = toml("")
    cases["binary-toml"] = lambda d: (d / "subject.toml").write_bytes(b"\xff\xfe\x00bad")
    cases["latin1-toml"] = lambda d: (d / "subject.toml").write_bytes(
        TOML.replace("fuzz", "fu\xdf").encode("latin-1"))
    cases["toml-missing"] = lambda d: (d / "subject.toml").unlink()
    cases["toml-is-folder"] = lambda d: ((d / "subject.toml").unlink(),
                                         (d / "subject.toml").mkdir())
    return cases


def _csv_cases():
    def csv(text):
        return lambda d: (d / "fiducials.csv").write_text(text)

    cases = {
        "csv-header": csv(CSV.replace("position,label", "pos,lab")),
        "csv-columns": csv(CSV + "supine,m9,1,2\n"),
        "csv-text": csv(CSV + "supine,m9,a,b,c\n"),
        "csv-nan": csv(CSV.replace("prone,m1,1.0", "prone,m1,nan")),
        "csv-inf": csv(CSV.replace("prone,m1,1.0", "prone,m1,inf")),
        "csv-duplicate": csv(CSV + "prone,m1,1,2,3\n"),
        "csv-unknown-position": csv(CSV + "side,m1,1,2,3\n"),
        "csv-labels-differ": csv(CSV.replace("prone,m3", "prone,m7")),
        "csv-empty": csv(""),
        "csv-empty-label": csv(CSV.replace("prone,m2", "prone,")),
        "csv-quote": csv(CSV + 'prone,"m9,1,2,3\n'),
        "csv-binary": lambda d: (d / "fiducials.csv").write_bytes(b"\x00\xff\xfe" * 30),
        "landmarks-bad": lambda d: (d / "landmarks.csv").write_text("a,b\n1,2\n"),
        "csv-is-folder": lambda d: ((d / "fiducials.csv").unlink(),
                                    (d / "fiducials.csv").mkdir()),
    }
    return cases


def _random_toml_cases(n=20):
    def mutate(seed):
        def f(d):
            rng = np.random.default_rng(seed)
            text = bytearray(TOML.encode())
            for _ in range(int(rng.integers(1, 4))):
                i = int(rng.integers(0, len(text)))
                op = rng.integers(0, 3)
                if op == 0:
                    del text[i]
                elif op == 1:
                    text.insert(i, int(rng.choice(list(b'[]"=.,/\\\n#\x00\xff'))))
                else:
                    text[i] = int(rng.integers(0, 256))
            (d / "subject.toml").write_bytes(bytes(text))
        return f
    return {f"toml-mutation-{s}": mutate(s) for s in range(n)}


CASES = {**_volume_cases(), **_toml_cases(), **_csv_cases(), **_random_toml_cases()}


def test_enough_cases():
    assert len(CASES) >= 100


def _fresh(base: Path, tmp_path: Path, case: str) -> Path:
    d = tmp_path / "subject"
    shutil.copytree(base, d)
    CASES[case](d)
    return d


def _names_the_file(message: str, d: Path) -> bool:
    return str(d) in message or d.name in message


@pytest.mark.parametrize("case", sorted(CASES))
def test_malformed_subject_ends_with_a_clear_error(base, tmp_path, case, capsys):
    from breastmodel.commands.info import main_info
    from breastmodel.commands.segment import segment_subject

    d = _fresh(base, tmp_path, case)
    try:
        read_subject(d)
    except OWN_ERRORS as exc:
        message = str(exc)
        assert _names_the_file(message, d), message
        assert "\n" not in message.strip()
        assert main_info(d) == 1
        assert "invalid:" in capsys.readouterr().err
        return
    # The reader accepted it: only a random mutation may leave a valid folder, or the
    # volume may be readable but meaningless (noise, constant), which segmentation refuses.
    if case.startswith("toml-mutation"):
        assert main_info(d) == 0
        return
    assert case.startswith(("noise", "constant")), f"{case}: accepted silently"
    with pytest.raises(OWN_ERRORS) as info:
        segment_subject(d, tmp_path / "seg", positions=["supine"])
    assert _names_the_file(str(info.value), d), str(info.value)


def test_non_utf8_path_is_refused_before_itk(base, tmp_path):
    """ITK aborts the process (SIGABRT) on a path that is not valid UTF-8: the reader must
    refuse it first. In a child process, so that an abort fails this test, not the run."""
    code = f"""
import os, shutil, sys
sys.path[:0] = {[str(Path.cwd()), str(Path(__file__).parents[1])]!r}
from imaging.subject import SubjectError, read_subject
from imaging.io import VolumeError, read_volume
from breastmodel.commands.info import main_info
d = os.fsdecode(os.path.join({str(tmp_path).encode()!r}, b"bad\\xffname"))
shutil.copytree({str(base)!r}, d)
try:
    read_subject(d)
    sys.exit(3)
except SubjectError as exc:
    assert "not valid UTF-8" in str(exc), exc
try:
    read_volume(os.path.join(d, "supine.nii.gz"))
    sys.exit(4)
except VolumeError as exc:
    assert "not valid UTF-8" in str(exc), exc
sys.exit(0 if main_info(d) == 1 else 5)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**os.environ, "PYTHONIOENCODING": "utf-8"}, timeout=120)
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
    assert "invalid:" in proc.stderr
