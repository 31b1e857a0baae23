"""The one atomic writer: concurrent writers of one path never collide, a reader never sees a
mixed or partial file, and a failed write leaves nothing behind."""

import json
import multiprocessing as mp

import pytest

from breastmodel.config import write_atomic, write_json


def _writer(path: str, tag: int, n: int, errors) -> None:
    body = {"tag": tag, "payload": [tag] * 2000}
    for _ in range(n):
        try:
            write_json(path, body)
        except Exception as exc:  # counted, not raised: the parent asserts the count
            errors.put(repr(exc))


def test_two_writers_and_a_reader_never_collide(tmp_path):
    path = tmp_path / "result.json"
    write_json(path, {"tag": 0, "payload": [0] * 2000})
    ctx = mp.get_context("fork")
    errors = ctx.Queue()
    procs = [ctx.Process(target=_writer, args=(str(path), t, 300, errors)) for t in (1, 2)]
    for p in procs:
        p.start()
    reads = bad = 0
    while any(p.is_alive() for p in procs):
        doc = json.loads(path.read_text())  # raises on a partial file
        reads += 1
        if doc["payload"] != [doc["tag"]] * 2000:
            bad += 1
    for p in procs:
        p.join()
    assert all(p.exitcode == 0 for p in procs)
    failures = []
    while not errors.empty():
        failures.append(errors.get())
    assert failures == []
    assert reads > 0 and bad == 0
    assert sorted(q.name for q in tmp_path.iterdir()) == ["result.json"]  # no temp left


def test_failed_write_leaves_target_and_no_temp(tmp_path, monkeypatch):
    import os

    path = tmp_path / "a.txt"
    write_atomic(path, "old")

    def fail(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_atomic(path, "new")
    assert path.read_text() == "old"
    assert [q.name for q in tmp_path.iterdir()] == ["a.txt"]


def test_bytes_are_written_verbatim(tmp_path):
    path = tmp_path / "b.bin"
    write_atomic(path, b"\x00\x01\xff")
    assert path.read_bytes() == b"\x00\x01\xff"


def test_a_writer_that_wants_a_file_name_gets_the_suffix_it_asked_for(tmp_path):
    """SimpleITK, numpy and image libraries pick the format from the name: the temporary
    file ends in the given suffix; a writer that fails leaves the target and no temp."""
    import numpy as np

    from breastmodel.config import write_atomic_with

    seen = []

    def save(tmp):
        seen.append(tmp.name)
        np.savez(tmp, a=np.arange(3))

    path = write_atomic_with(tmp_path / "r.npz", save, suffix=".npz")
    assert seen[0].startswith(".r.npz.") and seen[0].endswith(".npz")
    assert np.load(path)["a"].tolist() == [0, 1, 2]

    def broken(tmp):
        tmp.write_bytes(b"half")
        raise RuntimeError("writer failed")

    with pytest.raises(RuntimeError, match="writer failed"):
        write_atomic_with(path, broken, suffix=".npz")
    assert np.load(path)["a"].tolist() == [0, 1, 2]
    assert [q.name for q in tmp_path.iterdir()] == ["r.npz"]
