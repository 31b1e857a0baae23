"""The fit's evaluations of the objective: memoised, stored atomically one record per
parameter vector (``<key>.json``), replayed on resume, and optionally warm-started from the
nearest earlier evaluation's stress-free geometry (``<key>.X.npy``) and displacements
(``<key>.u.npz``, one array per position solved)."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("breastmodel.pipeline")

__all__ = ["Evaluator", "stored_solution"]


class Evaluator:
    """Memoised, stored evaluations of the objective (keys: rounded parameter values).

    With ``warm`` (a list, shared by the evaluators of one fit), each new evaluation starts
    its stress-free inverse from the stress-free geometry of the nearest earlier evaluation
    (in log-parameter space), and each forward solve from that evaluation's displacement of
    the same position; both are stored beside its record (``<key>.X.npy``, ``<key>.u.npz``)
    so that a resumed fit starts each evaluation exactly where the uninterrupted one did. A
    warm start that fails is retried from the reference geometry.
    """

    def __init__(self, problem_dir: Path, settings: Mapping[str, Any], folder: Path,
                 progress: bool, *, residuals: bool = False, warm: list | None = None):
        self.problem_dir, self.settings, self.folder = problem_dir, settings, folder
        self.residuals = residuals
        self.warm = warm
        self.folder.mkdir(parents=True, exist_ok=True)
        self.history: list[dict] = []
        self.seen: dict[str, dict] = {}  # key -> record, this evaluator's so far
        self.progress = progress
        self.n_new = 0

    def stored(self, params: Mapping[str, float]) -> dict | None:
        """The record this evaluator already has for ``params`` (None: not evaluated)."""
        from breastmodel.sweep import point_key

        return self.seen.get(point_key({k: float(f"{v:.6g}") for k, v in params.items()}))

    def __call__(self, params: Mapping[str, float]) -> dict:
        from breastmodel.config import write_json
        from breastmodel.sweep import point_key

        params = {k: float(f"{v:.6g}") for k, v in params.items()}
        key = point_key(params)
        if key in self.seen:  # a search asks again (the Jacobian's base point): no disk
            return self.seen[key]
        path = self.folder / f"{key}.json"
        rec = None
        if path.is_file():
            try:
                rec = json.loads(path.read_text())
            except ValueError:
                rec = None
        if rec is None:
            rec = {"params": params, **self._evaluate(params, key)}
            write_json(path, rec)
            self.n_new += 1
        elif self.warm is not None and (stored := stored_solution(self.folder, key)):
            self._remember(params, *stored, key)
        self.seen[key] = rec
        self.history.append({"key": key, **rec})
        if self.progress:
            vals = ", ".join(f"{k.split('.', 1)[1]}={v:.4g}" for k, v in params.items())
            print(f"     fit #{len(self.history):3d}: {vals} -> MHD "
                  f"{rec['objective']:.4f} mm", flush=True)
        return rec

    def _evaluate(self, params: dict, key: str) -> dict:
        from breastmodel.pipeline.problem import evaluate_params

        kw: dict[str, Any] = {"residuals": True} if self.residuals else {}
        if self.warm is None:
            return evaluate_params(params, self.problem_dir, self.settings, **kw)
        start = self._nearest(params)
        out = None
        if start is not None:
            # a record stored without displacements starts from X alone
            u_kw = {"u_start": start[2]} if start[2] else {}
            out = evaluate_params(params, self.problem_dir, self.settings, start=start[1],
                                  keep_X=True, **kw, **u_kw)
            out["warm_start"] = start[0]
            if out.get("error"):
                log.info("fit: the evaluation started from %s failed (%s); retrying from the "
                         "reference geometry", start[0], out["error"])
                out = None
        if out is None:
            out = evaluate_params(params, self.problem_dir, self.settings, keep_X=True, **kw)
        X, u = out.pop("X", None), out.pop("u", None) or {}
        if X is not None and not out.get("error"):
            # each written under a temporary name, then renamed (atomic); X last, as the
            # record that the evaluation has a start to give
            if u:
                np.savez(self.folder / f"{key}.u.tmp.npz", **u)
                (self.folder / f"{key}.u.tmp.npz").replace(self.folder / f"{key}.u.npz")
            np.save(self.folder / f"{key}.X.tmp.npy", X)
            (self.folder / f"{key}.X.tmp.npy").replace(self.folder / f"{key}.X.npy")
            self._remember(params, X, u, key)
        return out

    def _remember(self, params: dict, X: np.ndarray, u: dict, key: str) -> None:
        if not any(k == key for k, *_ in self.warm):
            self.warm.append((key, dict(params), X, u))

    def _nearest(self, params: dict) -> tuple[str, np.ndarray, dict] | None:
        """(key, X, u) of the stored evaluation nearest to ``params`` in log space."""
        best, dist = None, math.inf
        for key, p, X, u in self.warm:
            if set(p) != set(params):
                continue
            d = sum(math.log(params[n] / p[n]) ** 2 for n in params)
            if d < dist:
                best, dist = (key, X, u), d
        return best


def stored_solution(folder: Path, key: str) -> tuple[np.ndarray, dict] | None:
    """(X, u {position: displacement}) an evaluation stored beside its record in ``folder``
    (u empty for a record stored without displacements), or None."""
    if not (folder / f"{key}.X.npy").is_file():
        return None
    u = {}
    if (folder / f"{key}.u.npz").is_file():
        with np.load(folder / f"{key}.u.npz") as z:
            u = {p: z[p] for p in z.files}
    return np.load(folder / f"{key}.X.npy"), u
