"""TOML configuration: loading with clear errors, key validation, and provenance of outputs."""

from __future__ import annotations

import json
import platform
import sys
import tomllib
from collections.abc import Iterable, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import tomli_w

from imaging.atomic import write_atomic, write_atomic_with  # noqa: F401 - the writer

_TRACKED_PACKAGES = (
    "breastmodel", "numpy", "scipy", "SimpleITK", "scikit-image", "opencv-python-headless",
    "pymeshlab", "pytetwild", "open3d-cpu", "meshio", "dask", "pypardiso",
)


class ConfigError(ValueError):
    """A configuration file is unreadable or invalid; the message names the file and key."""


def load_toml(path: str | Path, *, stage: str = "config") -> dict[str, Any]:
    """Read a TOML file, failing with one message naming the stage, file and problem."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{stage}: config file {path} does not exist")
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{stage}: {path} is not valid TOML: {exc}") from None


def check_keys(table: Mapping[str, Any], allowed: Iterable[str], *, where: str) -> None:
    """Reject unknown keys (typos would otherwise be silently ignored)."""
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def package_versions() -> dict[str, str]:
    """Versions of the packages that shape results, plus Python and platform."""
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in _TRACKED_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def write_json(path: str | Path, data: Any) -> None:
    write_atomic(path, json.dumps(data, indent=2, default=_jsonable) + "\n")


def _jsonable(obj):
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-serialisable: {type(obj).__name__}")


def write_provenance(out_dir: str | Path, config: Mapping[str, Any], *, command: str) -> None:
    """Put the resolved config (``config.toml``) and package versions beside the outputs."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    clean = json.loads(json.dumps(dict(config), default=_jsonable))
    write_atomic(out_dir / "config.toml", tomli_w.dumps(_drop_none(clean)))
    write_json(out_dir / "provenance.json", {"command": command, "versions": package_versions()})


def _drop_none(d):
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, list):
        return [_drop_none(v) for v in d]
    return d
