"""The pipeline's stage log: :class:`Runner` runs (or skips) each cached stage and records
it; :class:`Prepared` is what the stages up to the problem folder hand on, :class:`RunResult`
what a run returns."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from breastmodel.cache import Cache, StageKey, stage_key

__all__ = ["Prepared", "RunResult", "Runner"]


class RunResult(dict):
    """``{"stages": [{"name", "key", "status": "ran" | "skipped", "wall_s"}], "metrics",
    "params", "out"}``."""


@dataclass(frozen=True, eq=False)
class Prepared:
    """subject, positions (names), runner (stage log), problem_dir, problem_key, and the
    stage folders and keys of the images (``register_dir``, ``segment_dirs`` and
    ``segment_keys`` {position: folder or key}; None for a given problem)."""

    subject: Any
    positions: list[str]
    runner: Any
    problem_dir: Path
    problem_key: str
    register_dir: Path | None = None
    segment_dirs: Mapping[str, Path] | None = None
    problem_inputs: tuple = ()  # the problem's inputs but the mesh (registration, skins, ...)
    segment_keys: Mapping[str, str] | None = None


class Runner:
    """Runs the stages of one run in the cache under ``cache`` (default ``out/cache``),
    printing one line per stage with ``progress``; ``stages`` lists each one's name, label,
    key, status (ran / skipped) and wall time."""

    def __init__(self, out: Path, progress: bool, cache: Path | None = None):
        self.cache_root = Path(cache).resolve() if cache else (out / "cache").resolve()
        self.cache = Cache(self.cache_root)
        self.stages: list[dict] = []
        self.progress = progress

    def done(self, name: str, config: Mapping[str, Any], inputs) -> bool:
        """Whether the stage ``name`` keyed by ``config`` and ``inputs`` is in the cache."""
        return self.cache.done(name, stage_key(name, config, inputs))

    def stage(self, name: str, config: Mapping[str, Any], inputs, fn: Callable[[Path], None],
              *, label: str | None = None) -> tuple[Path, StageKey]:
        """Run ``fn`` into the stage folder of ``name`` keyed by ``config`` and ``inputs``,
        unless it is done; the folder and key. A failure carries the stages so far
        (``exc.stages``)."""
        key = stage_key(name, config, inputs)
        label = label or name
        done = self.cache.done(name, key)
        t0 = time.perf_counter()
        if self.progress:
            print(f"[{len(self.stages) + 1:2d}] {label:<26s} "
                  f"{'cached' if done else 'running...'}", flush=True)
        try:
            path = self.cache.run(name, key, fn, config=config)
        except Exception as exc:
            # the stages so far travel with the error, so a caller can report what ran
            failed = {"name": name, "label": label, "key": str(key), "status": "failed",
                      "wall_s": round(time.perf_counter() - t0, 3)}
            exc.stages = [*self.stages, failed]
            raise
        wall = time.perf_counter() - t0
        if self.progress and not done:
            print(f"     {label:<26s} done in {wall:.1f} s", flush=True)
        self.stages.append({"name": name, "label": label, "key": str(key),
                            "status": "skipped" if done else "ran", "wall_s": round(wall, 3)})
        return path, key
