"""TOML configuration: loading with clear errors, key validation, and provenance of outputs."""

from __future__ import annotations

import contextlib
import json
import platform
import sys
import tomllib
from collections.abc import Callable, Iterable, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import tomli_w

_TRACKED_PACKAGES = (
    "breastmodel", "numpy", "scipy", "SimpleITK", "scikit-image", "opencv-python-headless",
    "pymeshlab", "pytetwild", "open3d-cpu", "meshio", "dask", "pypardiso",
)


def _umask() -> int:
    import os

    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()


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


def write_atomic(path: str | Path, data: str | bytes) -> Path:
    """Write text or bytes so that a reader never sees a half-written file.

    The data goes to a uniquely named temporary file in the target folder (two writers of
    one path never share it), is flushed to disk, and replaces ``path`` in one rename; on any
    failure the temporary file is removed and ``path`` is left as it was.
    """
    raw = data.encode() if isinstance(data, str) else bytes(data)
    return write_atomic_with(path, lambda tmp: tmp.write_bytes(raw))


def write_atomic_with(path: str | Path, write: Callable[[Path], Any], *,
                      suffix: str = ".tmp") -> Path:
    """:func:`write_atomic` for writers that want a file name (SimpleITK, numpy, an image
    library): ``write(tmp)`` fills a uniquely named temporary file beside ``path`` whose
    name ends in ``suffix`` (the writer may choose its format by it: ``".seg.nrrd"``,
    ``".png"``, ``".npz"``), which is then flushed to disk and renamed onto ``path``; on
    any failure it is removed and ``path`` is left as it was."""
    import os
    import tempfile

    path = Path(path)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    tmp = Path(name)
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes 0600; give what open() would
        os.close(fd)
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


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
