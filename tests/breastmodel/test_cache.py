"""Stage cache: content keys, skip on rerun, recompute of dependants only, crash safety."""

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from breastmodel.cache import Cache, StageKey, content_hash, stage_key
from breastmodel.errors import StageError


def _pipeline(cache: Cache, image: Path, cfg: dict, calls: list) -> dict:
    """image -> A -> B -> C, and A -> D; each stage writes one file, and logs its call."""

    def stage(name, config, inputs):
        key = stage_key(name, config, inputs)

        def fn(out: Path):
            calls.append(name)
            upstream = "".join((cache.path(n, k) / "out.txt").read_text()
                               for n, k in config.get("_reads", []))
            (out / "out.txt").write_text(f"{name}{config['v']}({upstream})")

        cache.run(name, key, fn, config=config)
        return key

    a = stage("A", {"v": cfg["A"]}, [image])
    b = stage("B", {"v": cfg["B"], "_reads": [["A", a]]}, [a])
    c = stage("C", {"v": cfg["C"], "_reads": [["B", b]]}, [b])
    d = stage("D", {"v": cfg["D"], "_reads": [["A", a]]}, [a])
    return {"A": a, "B": b, "C": c, "D": d}


@pytest.fixture
def image(tmp_path):
    p = tmp_path / "image.bin"
    p.write_bytes(np.arange(1000, dtype=np.int16).tobytes())
    return p


CFG = {"A": 1, "B": 2, "C": 3, "D": 4}


def test_rerun_skips_and_records(tmp_path, image):
    cache, calls = Cache(tmp_path / "cache"), []
    keys = _pipeline(cache, image, CFG, calls)
    assert calls == ["A", "B", "C", "D"]
    assert (cache.path("C", keys["C"]) / "out.txt").read_text() == "C3(B2(A1()))"
    rec = cache.record("B", keys["B"])
    assert rec["name"] == "B" and rec["key"] == keys["B"] and rec["config"]["v"] == 2
    assert rec["wall_s"] >= 0 and "numpy" in rec["versions"]
    calls.clear()
    assert _pipeline(cache, image, CFG, calls) == keys
    assert calls == []


def test_config_change_recomputes_only_dependants(tmp_path, image):
    cache, calls = Cache(tmp_path / "cache"), []
    first = _pipeline(cache, image, CFG, calls)
    calls.clear()
    second = _pipeline(cache, image, {**CFG, "B": 20}, calls)
    assert calls == ["B", "C"]
    assert second["A"] == first["A"] and second["D"] == first["D"]
    assert second["C"] != first["C"]
    assert (cache.path("C", second["C"]) / "out.txt").read_text() == "C3(B20(A1()))"
    # the old results are still there: switching back costs nothing
    calls.clear()
    _pipeline(cache, image, CFG, calls)
    assert calls == []


def test_input_content_not_name_or_time_matters(tmp_path, image):
    cache, calls = Cache(tmp_path / "cache"), []
    first = _pipeline(cache, image, CFG, calls)
    calls.clear()
    os.utime(image, ns=(0, 0))  # new time, same bytes
    moved = image.with_name("renamed.bin")
    shutil.copy(image, moved)
    assert _pipeline(cache, moved, CFG, calls) == first and calls == []
    moved.write_bytes(b"other content")
    _pipeline(cache, moved, CFG, calls)
    assert calls == ["A", "B", "C", "D"]


def test_deleted_stage_is_redone_alone(tmp_path, image):
    cache, calls = Cache(tmp_path / "cache"), []
    keys = _pipeline(cache, image, CFG, calls)
    shutil.rmtree(cache.path("B", keys["B"]))
    calls.clear()
    _pipeline(cache, image, CFG, calls)
    assert calls == ["B"]


def test_exception_inside_stage_leaves_no_result_and_rerun_completes(tmp_path):
    cache = Cache(tmp_path / "cache")
    key = stage_key("solve", {"E": 0.3})

    def crash(out: Path):
        (out / "half.npy").write_bytes(b"partial")
        raise StageError("solve", "Newton diverged", path=out / "solve.json")

    with pytest.raises(StageError, match="Newton diverged") as info:
        cache.run("solve", key, crash)
    assert not cache.done("solve", key)
    assert not cache.path("solve", key).exists()
    # no temporary left; what the stage wrote is kept for inspection, and the error names it
    failed = tmp_path / "cache" / "solve" / f"failed-{key}"
    assert list((tmp_path / "cache" / "solve").iterdir()) == [failed]
    assert (failed / "half.npy").read_bytes() == b"partial"
    assert str(failed / "solve.json") in str(info.value) and ".tmp-" not in str(info.value)
    assert info.value.path == failed / "solve.json"
    out = cache.run("solve", key, lambda d: (d / "u.txt").write_text("ok"))
    assert (out / "u.txt").read_text() == "ok" and cache.done("solve", key)
    assert not (out / "half.npy").exists()
    assert not failed.exists()  # a success clears the failed run's files


def test_killed_process_leaves_no_result_and_rerun_cleans_up(tmp_path):
    root = tmp_path / "cache"
    key = stage_key("mesh", {"edge": 4})
    script = textwrap.dedent(f"""
        import os, signal
        from pathlib import Path
        from breastmodel.cache import Cache
        def fn(out):
            (out / "half.txt").write_text("partial")
            os.kill(os.getpid(), signal.SIGKILL)
        Cache({str(root)!r}).run("mesh", {str(key)!r}, fn)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=60)
    assert proc.returncode == -9
    cache = Cache(root)
    assert not cache.done("mesh", key) and not cache.path("mesh", key).exists()
    orphans = list((root / "mesh").glob(".tmp-*"))
    assert len(orphans) == 1 and (orphans[0] / "half.txt").exists()
    out = cache.run("mesh", key, lambda d: (d / "mesh.txt").write_text("full"))
    assert (out / "mesh.txt").read_text() == "full"
    assert list((root / "mesh").glob(".tmp-*")) == []  # the dead process's folder is gone


def test_staging_context_manager(tmp_path):
    cache = Cache(tmp_path)
    key = stage_key("fit", {"x": [1, 2]})
    with cache.staging("fit", key, config={"x": np.array([1, 2])}) as tmp:
        (tmp / "p.json").write_text("{}")
        assert not cache.done("fit", key)
    assert cache.done("fit", key)
    assert json.loads((cache.path("fit", key) / "stage.json").read_text())["config"] == {
        "x": [1, 2]}


def test_stage_key_rules(tmp_path):
    k1 = stage_key("s", {"a": 1, "b": {"c": 2.5, "d": "x"}})
    k2 = stage_key("s", {"b": {"d": "x", "c": 2.5}, "a": 1})
    assert k1 == k2 and isinstance(k1, StageKey) and len(k1) == 64
    assert stage_key("s", {"a": 1.0, "b": {"c": 2.5, "d": "x"}}) != k1  # 1 and 1.0 differ
    assert stage_key("t", {"a": 1, "b": {"c": 2.5, "d": "x"}}) != k1
    # upstream keys: a plain str of 64 hex digits counts as a key, so order matters
    assert stage_key("s", {}, [k1, str(k2)]) == stage_key("s", {}, [str(k1), k2])
    assert stage_key("s", {}, [b"ab", b"c"]) != stage_key("s", {}, [b"a", b"bc"])
    # folders hash by content and relative names, not by their own name
    for name in ("one", "two"):
        (tmp_path / name / "sub").mkdir(parents=True)
        (tmp_path / name / "sub" / "f.txt").write_text("data")
        (tmp_path / name / ".DS_Store").write_text(name)  # hidden: ignored
    assert content_hash(tmp_path / "one") == content_hash(str(tmp_path / "two"))
    (tmp_path / "two" / "sub" / "f.txt").write_text("Data")
    assert content_hash(tmp_path / "one") != content_hash(tmp_path / "two")
    with pytest.raises(FileNotFoundError, match="missing"):
        stage_key("s", {}, [tmp_path / "missing"])
    with pytest.raises(ValueError, match="not a key, path or bytes"):
        stage_key("s", {}, [3.0])
    with pytest.raises(ValueError, match="not JSON"):
        stage_key("s", {"f": object()})
    with pytest.raises(ValueError, match="bad stage name"):
        stage_key("../up", {})
    with pytest.raises(ValueError, match="bad stage key"):
        Cache(tmp_path).path("s", "../../etc")
