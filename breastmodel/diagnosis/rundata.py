"""Read a finished ``breastmodel run`` folder back into plain arrays (what the diagnosis uses).

A run folder holds ``stages.json`` (stage name, label and cache key), ``config.toml`` (the
resolved run config), ``params.json`` (the model the predictions used) and ``metrics.json``;
the arrays live in the stage cache (``cache/``, or the one ``stages.json`` names when the
run shared another run's cache): ``cache/problem/<key>/`` (mesh and measured skins),
``cache/stress_free/<key>/X.npy`` and ``cache/predict/<key>/predicted.npz`` per position.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from breastmodel.errors import StageError

__all__ = ["RunData", "load_run"]


@dataclass(frozen=True, eq=False)
class RunData:
    """A finished run.

    out : the run folder
    config : resolved run config (``config.toml``)
    model : the ``[model]`` table the predictions used (``params.json["model"]``; fitted
        parameters included)
    problem_dir : the problem stage folder
    problem : :class:`breastmodel.pipeline.problem.Problem` (mesh, gravity, measured skins,
        landmarks, reference; reference frame, mm)
    X : (N, 3) stress-free node positions, mm
    x : position -> (N, 3) predicted node positions, mm
    metrics : ``metrics.json``
    subject : subject id
    """

    out: Path
    config: dict
    model: dict
    problem_dir: Path
    problem: Any
    X: np.ndarray
    x: dict
    metrics: dict
    subject: str

    @property
    def positions(self) -> list[str]:
        return list(self.x)


def _read_json(path: Path, out: Path) -> Any:
    if not path.is_file():
        raise StageError("diagnose", f"{path.name} is missing: not a finished `breastmodel run` "
                         "folder (run the pipeline first)", out)
    return json.loads(path.read_text())


def load_run(out: str | Path) -> RunData:
    """Load a finished run folder.

    Raises
    ------
    StageError
        The folder lacks a file of a finished run, or its cached stage folders are gone.
    """
    from breastmodel.pipeline.config import load_run_config
    from breastmodel.pipeline.problem import load_problem

    out = Path(out)
    if not out.is_dir():
        raise StageError("diagnose", "no such run folder", out)
    from breastmodel.pipeline.run import cache_of

    stages = _read_json(out / "stages.json", out)["stages"]
    cache = cache_of(out)
    params = _read_json(out / "params.json", out)
    metrics = _read_json(out / "metrics.json", out)
    if not (out / "config.toml").is_file():
        raise StageError("diagnose", "config.toml is missing: not a `breastmodel run` folder",
                         out)
    config = load_run_config(out / "config.toml", drop=("subject",))

    def stage_dir(name: str, label: str | None = None) -> Path:
        # the run's own stages, not those of its mesh-refinement check (same names)
        rows = [s for s in stages if s["name"] == name and (label is None or s["label"] == label)
                and not s["label"].startswith("refinement:")]
        if not rows:
            raise StageError("diagnose", f"stages.json lists no {label or name!r} stage", out)
        d = cache / name / rows[-1]["key"]
        if not d.is_dir():
            raise StageError("diagnose", f"the cached {label or name!r} stage is gone "
                             "(rerun `breastmodel run` with the same config)", d)
        return d

    problem_dir = stage_dir("problem")
    X = np.load(stage_dir("stress_free") / "X.npy")
    x = {}
    for pos in metrics["positions"]:
        with np.load(stage_dir("predict", f"predict {pos}") / "predicted.npz") as z:
            x[pos] = z["x"].copy()
    return RunData(out=out, config=config, model=params["model"], problem_dir=problem_dir,
                   problem=load_problem(problem_dir), X=X, x=x, metrics=metrics,
                   subject=str(metrics.get("subject", "")))
