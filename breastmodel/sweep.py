"""Resumable parameter sweeps on a dask.distributed cluster.

Each point of a sweep is evaluated by ``fn(point) -> dict`` on a worker process; the client
writes each finished point to ``out_dir/points/<key>.json`` (atomically: write then rename)
as soon as it finishes, so a crash, a kill or Ctrl-C loses only the points still running,
and a rerun computes only the points without a file.

Failure handling:

* ``fn`` raises: the point is recorded with ``"status": "failed"``, ``"cause": "fn"`` and the
  exception text, and the sweep goes on. Such points are not recomputed on resume unless
  ``retry_failed=True`` (a non-converging simulation stays non-converging).
* The worker process dies (segfault, out of memory, ``os._exit``): its nanny restarts it and
  the scheduler gives the point to a worker again. The scheduler blames every point that was
  on the dead worker (running or queued there); a point blamed more than
  ``distributed.scheduler.allowed-failures`` times (default 3) is recorded as failed with a
  ``KilledWorker`` error and ``"cause": "worker"``. Errors raised outside ``fn`` (e.g.
  unpickling on the worker) are retried ``retries`` times (dask's ``retries=``), then recorded
  the same way. Since an innocent point can be blamed, ``"cause": "worker"`` failures ARE
  recomputed on resume.

``fn`` must be picklable: a module-level function of an importable module, a
``functools.partial`` of one, or a function of a script run as ``__main__`` (cloudpickle sends
those by value).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import numbers
import os
import socket
import time
import traceback
import uuid
from collections.abc import Callable, Mapping, Sequence
from decimal import Decimal
from pathlib import Path
from typing import Any

from .cache import canonical_json
from .config import _jsonable, package_versions, write_json

__all__ = ["axis", "grid", "load_results", "point_key", "run_sweep"]


# ---------------------------------------------------------------- points and grids


def _normalise_point(point: Mapping[str, Any]) -> dict[str, Any]:
    if not isinstance(point, Mapping) or not all(isinstance(k, str) for k in point):
        raise ValueError(f"sweep: a point must be a mapping with str keys, got {point!r}")
    out = {}
    for k, v in point.items():
        if isinstance(v, numbers.Real) and not isinstance(v, bool):
            v = float(v)  # 1 and 1.0 are the same point
            if not math.isfinite(v):
                raise ValueError(f"sweep: point {dict(point)} has a non-finite value for {k!r}")
        elif not isinstance(v, str | bool):
            raise ValueError(f"sweep: point value {k}={v!r} must be a number, str or bool")
        out[k] = v
    return out


def point_key(point: Mapping[str, Any]) -> str:
    """Stable 16-hex-digit name of a point (hash of its canonical JSON; ints count as floats).

    Parameters
    ----------
    point : mapping str -> float (or str, bool)

    Returns
    -------
    str
    """
    return hashlib.sha256(canonical_json(_normalise_point(point)).encode()).hexdigest()[:16]


def _decimals(x: float) -> int:
    return max(0, -Decimal(repr(float(x))).normalize().as_tuple().exponent)


def axis(start: float, stop: float, step: float) -> list[float]:
    """Evenly spaced values from ``start`` to ``stop`` INCLUSIVE, rounded to the step's digits.

    ``axis(0.1, 4, 0.1)`` gives 0.1, 0.2, ..., 4.0 (40 values, no 0.30000000000000004), so
    point keys stay readable and reproducible.

    Parameters
    ----------
    start, stop, step : float
        ``step > 0``; ``stop`` is included when it lies on the grid (to 1e-9 steps).

    Returns
    -------
    list of float
    """
    if not step > 0 or stop < start:
        raise ValueError(f"sweep: axis needs step > 0 and stop >= start, got "
                         f"({start}, {stop}, {step})")
    n = math.floor((stop - start) / step + 1e-9) + 1
    digits = max(_decimals(start), _decimals(step))
    return [float(round(start + i * step, digits)) for i in range(n)]


def grid(**axes: Sequence[float] | float | str) -> list[dict[str, Any]]:
    """Cartesian grid of points, the last axis varying fastest.

    Parameters
    ----------
    **axes
        ``name=values``: a sequence of values (see :func:`axis` for ranges) or one value.

    Returns
    -------
    list of dict

    Examples
    --------
    The paper's search grid (Young's moduli in kPa)::

        grid(E_breast=axis(0.1, 4.0, 0.1), E_skin=axis(1, 20, 1), E_fascia=axis(80, 250, 40))
    """
    names, values = [], []
    for name, vals in axes.items():
        if isinstance(vals, str | numbers.Number):
            vals = [vals]
        vals = list(vals)
        if not vals:
            raise ValueError(f"sweep: grid axis {name!r} has no values")
        names.append(name)
        values.append(vals)
    return [_normalise_point(dict(zip(names, combo))) for combo in itertools.product(*values)]


# ---------------------------------------------------------------- storage


def _points_dir(out_dir: Path) -> Path:
    return Path(out_dir) / "points"


def load_results(out_dir: str | Path) -> dict[str, dict]:
    """Stored point records of a sweep folder, by point key (unreadable files are skipped)."""
    found = {}
    folder = _points_dir(Path(out_dir))
    if not folder.is_dir():
        return found
    for p in folder.glob("*.json"):
        try:
            rec = json.loads(p.read_text())
        except (OSError, ValueError):
            continue  # not written by us (our writes are atomic): treat as missing
        if isinstance(rec, dict) and rec.get("key") == p.stem:
            found[p.stem] = rec
    return found


# ---------------------------------------------------------------- evaluation on a worker


def _evaluate(fn: Callable[[dict], Mapping], point: dict, key: str) -> dict:
    """Run fn on one point; never raises for errors of fn (they become a failed record)."""
    t0 = time.perf_counter()
    record = {"key": key, "point": point, "status": "ok", "result": None, "error": None}
    try:
        result = fn(dict(point))
        if not isinstance(result, Mapping):
            raise TypeError(f"fn returned {type(result).__name__}, expected a dict")
        # plain JSON types now: a result the client cannot store is this point's failure
        record["result"] = json.loads(json.dumps(dict(result), default=_jsonable))
    except Exception as exc:
        record.update(status="failed", cause="fn", error=f"{type(exc).__name__}: {exc}",
                      traceback=traceback.format_exc())
    record["wall_s"] = time.perf_counter() - t0
    record["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    return record


def _lost(key: str, point: dict, exc: BaseException) -> dict:
    return {"key": key, "point": point, "status": "failed", "cause": "worker", "result": None,
            "error": f"{type(exc).__name__}: {exc}", "wall_s": None, "worker": None}


# ---------------------------------------------------------------- the runner


def run_sweep(fn: Callable[[dict], Mapping], points: Sequence[Mapping[str, Any]],
              out_dir: str | Path, *, scheduler: str | None = None, n_workers: int = 2,
              threads_per_worker: int = 1, progress: bool = True, retries: int = 1,
              retry_failed: bool = False) -> list[dict]:
    """Evaluate ``fn`` on every point on a dask cluster, storing and resuming point by point.

    Parameters
    ----------
    fn : callable(dict) -> dict
        Picklable; gets a copy of the point, returns a JSON-able dict (numpy values allowed).
    points : sequence of mappings str -> float
        Duplicates (same :func:`point_key`) are evaluated once.
    out_dir : path
        ``points/<point_key>.json`` per finished point, and ``sweep.json`` (counts, wall time,
        versions) when the sweep ends.
    scheduler : str, optional
        Address of a running dask scheduler (``tcp://host:8786``); default: a
        :class:`distributed.LocalCluster` of processes, closed at the end.
    n_workers, threads_per_worker : int
        Size of the local cluster (ignored with ``scheduler``). The nannies pin BLAS/OpenMP to
        one thread per worker. ``n_workers=0``: no cluster, the points run one after the
        other in this process (same storage and resume; no protection from a crash of fn).
    progress : bool
        Show a tqdm progress bar on stderr.
    retries : int
        dask ``retries=`` for errors raised outside ``fn`` on the worker.
    retry_failed : bool
        Also recompute stored points where ``fn`` failed (``"cause": "fn"``); points lost to
        worker deaths (``"cause": "worker"``) are always recomputed.

    Returns
    -------
    list of dict, one per input point, in order
        ``{"key", "point", "status": "ok" | "failed", "result": dict | None, "error": str |
        None, "wall_s": s, "worker": "host:pid"}``; failures also have ``"cause"``
        (``"fn"`` or ``"worker"``), and ``"traceback"`` when fn raised.
    """
    import cloudpickle

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    norm = [_normalise_point(p) for p in points]
    keys = [point_key(p) for p in norm]
    stored = load_results(out_dir)
    todo = _to_compute(dict(zip(keys, norm)), stored, retry_failed=retry_failed)
    try:
        cloudpickle.dumps(fn)
    except Exception as exc:
        raise ValueError(f"sweep: fn {fn!r} cannot be sent to workers (not picklable): {exc}") \
            from None

    folder = _points_dir(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    n_now = 0
    if todo and scheduler is None and n_workers == 0:
        n_now = _run_here(fn, todo, folder, stored, progress=progress)
        todo = {}
    if todo:
        n_now += _run_on_cluster(fn, todo, folder, stored, n_total=len(set(keys)),
                                 scheduler=scheduler, n_workers=n_workers,
                                 threads_per_worker=threads_per_worker, retries=retries,
                                 progress=progress)

    results = [stored[k] for k in keys]
    statuses = [r["status"] for r in results]
    write_json(out_dir / "sweep.json", {
        "n_points": len(keys), "n_unique": len(set(keys)), "n_computed_now": n_now,
        "n_ok": statuses.count("ok"), "n_failed": statuses.count("failed"),
        "wall_s": time.perf_counter() - t0, "scheduler": scheduler or "LocalCluster",
        "n_workers": None if scheduler else n_workers, "versions": package_versions(),
    })
    return results


def _to_compute(todo: dict[str, dict], stored: Mapping[str, dict], *,
                retry_failed: bool) -> dict[str, dict]:
    """The points of ``todo`` (key -> point, unique keys in first-occurrence order) that no
    stored record answers: none stored, a worker lost it, or ``fn`` failed and
    ``retry_failed``."""
    for k, rec in stored.items():
        if k in todo and rec.get("point") == todo[k] and (
                rec.get("status") == "ok"
                or (rec.get("cause") == "fn" and not retry_failed)):
            del todo[k]
    return todo


def _run_here(fn: Callable[[dict], Mapping], todo: Mapping[str, dict], folder: Path,
              stored: dict[str, dict], *, progress: bool) -> int:
    """Evaluate the points one after the other in this process, storing each record; the
    number evaluated."""
    from tqdm.auto import tqdm

    n_now = 0
    for k, p in tqdm(todo.items(), desc="sweep", unit="point", disable=not progress):
        stored[k] = _evaluate(fn, p, k)
        write_json(folder / f"{k}.json", stored[k])
        n_now += 1
    return n_now


def _run_on_cluster(fn: Callable[[dict], Mapping], todo: Mapping[str, dict], folder: Path,
                    stored: dict[str, dict], *, n_total: int, scheduler: str | None,
                    n_workers: int, threads_per_worker: int, retries: int,
                    progress: bool) -> int:
    """Evaluate the points on the dask cluster at ``scheduler`` (default: a local cluster,
    closed at the end), storing each record as it arrives (a lost worker's point as failed);
    the number evaluated. ``n_total`` (unique points of the sweep) sizes the progress bar."""
    from distributed import Client, LocalCluster, as_completed
    from tqdm.auto import tqdm

    n_now = 0
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker,
                               processes=True, dashboard_address=":0")
    client = Client(scheduler if scheduler is not None else cluster)
    try:
        run = uuid.uuid4().hex[:8]  # dask keys unique per run: a shared scheduler would
        futures = {                  # otherwise hand back another sweep's same-key task
            client.submit(_evaluate, fn, p, k, key=f"sweep-{k}-{run}", retries=retries,
                          pure=False): k
            for k, p in todo.items()
        }
        bar = tqdm(total=n_total, initial=n_total - len(todo), desc="sweep",
                   unit="point", disable=not progress)
        with bar:
            for fut in as_completed(futures):
                k = futures[fut]
                try:
                    rec = fut.result()
                except Exception as exc:  # KilledWorker, or errors outside fn
                    rec = _lost(k, todo[k], exc)
                write_json(folder / f"{k}.json", rec)
                stored[k] = rec
                n_now += 1
                fut.release()
                bar.update(1)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return n_now
