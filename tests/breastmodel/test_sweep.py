"""Sweep runner on a real dask LocalCluster (2 processes, shared by the module's tests)."""

import functools
import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import cloudpickle
import numpy as np
import pytest

from breastmodel.sweep import axis, grid, load_results, point_key, run_sweep

# Workers are separate processes that may not have this test folder on their path: send the
# toy functions by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def toy(point):
    x = np.array([point["a"], point["b"]])
    return {"norm": np.linalg.norm(x), "vec": x * 2}  # numpy values: stored as plain JSON


def toy_logged(point, *, log_dir, die_at=None, fail_at=None):
    """toy, logging each call; dies (the whole worker process) the first time at ``die_at``,
    raises at ``fail_at``."""
    key = point_key(point)
    Path(log_dir, f"{key}-{uuid.uuid4().hex}").touch()
    if point["a"] == die_at:
        marker = Path(log_dir, "died")
        if not marker.exists():
            marker.touch()
            os._exit(1)
    if point["a"] == fail_at:
        raise ValueError(f"no convergence at a={point['a']}")
    return toy(point)


def double(point, *, log_dir):
    Path(log_dir, f"{point_key(point)}-{uuid.uuid4().hex}").touch()
    return {"y": 2 * point["a"]}


def returns_list(point):
    return [point["a"]]


def calls(log_dir: Path) -> dict[str, int]:
    out = {}
    for p in log_dir.iterdir():
        if p.name != "died":
            k = p.name.split("-")[0]
            out[k] = out.get(k, 0) + 1
    return out


@pytest.fixture(scope="module")
def scheduler():
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster:
        yield cluster.scheduler_address


@pytest.fixture
def log_dir(tmp_path):
    d = tmp_path / "log"
    d.mkdir()
    return d


def test_all_points_stored_in_order(tmp_path, scheduler):
    points = grid(a=axis(0, 1, 0.25), b=[1, 2])
    res = run_sweep(toy, points, tmp_path, scheduler=scheduler, progress=False)
    assert len(res) == 10 and [r["point"] for r in res] == points
    for r, p in zip(res, points):
        assert r["status"] == "ok"
        assert r["result"]["norm"] == pytest.approx(math.hypot(p["a"], p["b"]), rel=1e-15)
        assert r["result"]["vec"] == [2 * p["a"], 2 * p["b"]]
        stored = json.loads((tmp_path / "points" / f"{point_key(p)}.json").read_text())
        assert stored["result"] == r["result"]
    summary = json.loads((tmp_path / "sweep.json").read_text())
    assert summary["n_ok"] == 10 and summary["n_failed"] == 0 and summary["n_computed_now"] == 10


def test_rerun_after_deleting_half_recomputes_only_those(tmp_path, scheduler, log_dir):
    points = grid(a=axis(1, 8, 1), b=0.5)
    fn = functools.partial(toy_logged, log_dir=log_dir)
    first = run_sweep(fn, points, tmp_path / "out", scheduler=scheduler, progress=False)
    assert calls(log_dir) == {point_key(p): 1 for p in points}
    deleted = [point_key(p) for p in points[::2]]
    for k in deleted:
        (tmp_path / "out" / "points" / f"{k}.json").unlink()
    again = run_sweep(fn, points, tmp_path / "out", scheduler=scheduler, progress=False)
    counts = calls(log_dir)
    assert sorted(k for k, n in counts.items() if n == 2) == sorted(deleted)
    assert sum(counts.values()) == len(points) + len(deleted)
    assert [r["result"] for r in again] == [r["result"] for r in first]
    assert json.loads((tmp_path / "out" / "sweep.json").read_text())["n_computed_now"] == 4
    # a full rerun computes nothing, and duplicates are evaluated once
    run_sweep(fn, points + points[:2], tmp_path / "out", scheduler=scheduler, progress=False)
    assert sum(calls(log_dir).values()) == len(points) + len(deleted)


def test_killed_worker_loses_nothing(tmp_path, scheduler, log_dir):
    points = grid(a=axis(1, 6, 1), b=2.0)
    fn = functools.partial(toy_logged, log_dir=log_dir, die_at=3.0)
    res = run_sweep(fn, points, tmp_path, scheduler=scheduler, progress=False)
    assert (log_dir / "died").exists()  # a worker process really died
    assert [r["status"] for r in res] == ["ok"] * 6
    victim = point_key(points[2])
    assert calls(log_dir)[victim] == 2  # run again after the death
    assert res[2]["result"]["norm"] == pytest.approx(math.hypot(3.0, 2.0))
    assert len(load_results(tmp_path)) == 6


def test_failures_recorded_and_not_retried_unless_asked(tmp_path, scheduler, log_dir):
    points = grid(a=axis(1, 4, 1), b=1.0)
    fn = functools.partial(toy_logged, log_dir=log_dir, fail_at=2.0)
    res = run_sweep(fn, points, tmp_path, scheduler=scheduler, progress=False)
    assert [r["status"] for r in res] == ["ok", "failed", "ok", "ok"]
    assert res[1]["error"] == "ValueError: no convergence at a=2.0" and res[1]["cause"] == "fn"
    assert "toy_logged" in res[1]["traceback"] and res[1]["result"] is None
    stored = json.loads((tmp_path / "points" / f"{point_key(points[1])}.json").read_text())
    assert stored["status"] == "failed"
    assert json.loads((tmp_path / "sweep.json").read_text())["n_failed"] == 1
    run_sweep(fn, points, tmp_path, scheduler=scheduler, progress=False)
    assert sum(calls(log_dir).values()) == 4
    run_sweep(fn, points, tmp_path, scheduler=scheduler, progress=False, retry_failed=True)
    assert calls(log_dir)[point_key(points[1])] == 2 and sum(calls(log_dir).values()) == 5
    bad = run_sweep(returns_list, points[:1], tmp_path / "bad", scheduler=scheduler,
                    progress=False)
    assert bad[0]["status"] == "failed" and "expected a dict" in bad[0]["error"]


DRIVER = """
import sys, time
from breastmodel.sweep import grid, run_sweep

def slow_double(point):
    time.sleep(0.3)
    return {"y": 2 * point["a"]}

if __name__ == "__main__":
    run_sweep(slow_double, grid(a=list(range(12))), sys.argv[1], n_workers=2, progress=False)
"""


def test_killed_driver_loses_nothing_and_resume_completes(tmp_path, scheduler, log_dir):
    script, out = tmp_path / "driver.py", tmp_path / "out"
    script.write_text(DRIVER)
    proc = subprocess.Popen([sys.executable, str(script), str(out)], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while len(list((out / "points").glob("*.json"))) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and its cluster, mid-sweep
        proc.wait()
    done = load_results(out)
    assert 3 <= len(done) < 12  # every file that exists is a complete record
    assert all(r["result"]["y"] == 2 * r["point"]["a"] for r in done.values())
    points = grid(a=list(range(12)))
    res = run_sweep(functools.partial(double, log_dir=log_dir), points, out,
                    scheduler=scheduler, progress=False)
    assert [r["result"]["y"] for r in res] == [2.0 * i for i in range(12)]
    assert set(calls(log_dir)) == {point_key(p) for p in points} - set(done)


def always_dies(point):
    if point["a"] < 0:
        os._exit(1)
    return toy(point)


def test_default_local_cluster_and_point_that_keeps_killing_workers(tmp_path, scheduler):
    import dask

    # The scheduler gives up on a point after `allowed-failures` worker deaths (default 3);
    # 0 keeps the test short. It blames every point queued on the dead worker, so the
    # killer runs alone first.
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        res = run_sweep(always_dies, [{"a": -1.0, "b": 4.0}], tmp_path, n_workers=1)
    assert res[0]["status"] == "failed" and res[0]["cause"] == "worker"
    assert res[0]["error"].startswith("KilledWorker")
    # a point lost to worker deaths is recomputed on resume (here by a fn that survives it)
    res = run_sweep(toy, grid(a=[3.0, -1.0], b=4.0), tmp_path, scheduler=scheduler,
                    progress=False)
    assert [r["status"] for r in res] == ["ok", "ok"]
    assert [r["result"]["norm"] for r in res] == pytest.approx([5.0, math.hypot(1.0, 4.0)])
    assert len(load_results(tmp_path)) == 2


def test_unpicklable_fn_is_refused(tmp_path):
    lock = threading.Lock()

    def fn(point):
        with lock:
            return {}

    with pytest.raises(ValueError, match=r"sweep: fn .* \(not picklable\)"):
        run_sweep(fn, [{"a": 1.0}], tmp_path, progress=False)


def test_grid_and_axis():
    a = axis(0.1, 4.0, 0.1)
    assert len(a) == 40 and a[2] == 0.3 and a[-1] == 4.0  # no 0.30000000000000004
    assert axis(80, 250, 40) == [80.0, 120.0, 160.0, 200.0, 240.0]
    g = grid(E_breast=a, E_skin=axis(1, 20, 1), E_fascia=axis(80, 250, 40))
    assert len(g) == 40 * 20 * 5
    assert g[0] == {"E_breast": 0.1, "E_skin": 1.0, "E_fascia": 80.0}
    assert g[1] == {"E_breast": 0.1, "E_skin": 1.0, "E_fascia": 120.0}  # last axis fastest
    assert len({point_key(p) for p in g}) == len(g)
    assert point_key({"a": 1, "b": 2.0}) == point_key({"b": 2, "a": 1.0})
    with pytest.raises(ValueError, match="step > 0"):
        axis(0, 1, 0)
    with pytest.raises(ValueError, match="number, str or bool"):
        point_key({"a": [1, 2]})
