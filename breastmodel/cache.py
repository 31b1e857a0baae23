"""Content-hash keyed cache of pipeline stages: a rerun redoes only what changed or is missing.

A stage's key hashes its name, the canonical JSON of its config and the CONTENT of its inputs
(files, folders, raw bytes) or the keys of the upstream stages it reads. A change anywhere
upstream therefore changes every dependant key, and nothing else.

A stage runs in a temporary folder next to its final place and is renamed into place (one
atomic ``rename`` on the same file system) only when it returns: a crash or a kill leaves no
half result under the final name, and the next run redoes that stage only.

Layout::

    root/<name>/<key>/            finished stage (its files + stage.json)
    root/<name>/.tmp-<key>-<host>-<pid>-<random>/   a stage being computed (or left by a kill)
    root/<name>/failed-<key>/     what the last failed run of that stage wrote, for inspection

A stage that fails leaves its files under ``failed-<key>`` (never read back by the cache) and
its error names that folder, not the temporary one.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import socket
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from .config import _jsonable, package_versions, write_json

__all__ = ["Cache", "StageKey", "canonical_json", "content_hash", "stage_key"]

_KEY_RE = re.compile(r"^[0-9a-f]{64}$")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_CHUNK = 1 << 20
_FILE_HASHES: dict[tuple, str] = {}  # (path, size, mtime_ns, inode) -> sha256, per process


class StageKey(str):
    """A stage key (64 hex digits); as an input of another stage it stands for that stage."""


def canonical_json(value: Any) -> str:
    """JSON with sorted keys, no whitespace, numpy scalars/arrays and paths made plain.

    Equal configs give equal strings whatever their key order; ``1`` and ``1.0`` differ
    (as they do in TOML), so write numbers the same way every time.
    """
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                      allow_nan=False, default=_jsonable)


def _file_hash(path: Path) -> str:
    st = path.stat()
    memo = (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino)
    if memo not in _FILE_HASHES:
        h = hashlib.sha256()
        with path.open("rb") as f:
            while chunk := f.read(_CHUNK):
                h.update(chunk)
        _FILE_HASHES[memo] = h.hexdigest()
    return _FILE_HASHES[memo]


def content_hash(path: str | Path) -> str:
    """SHA-256 of a file's bytes, or of a folder's relative file names and file contents.

    Names and times of the top path itself do not count: a copied or moved input keeps its
    hash. Hidden files (``.name``) inside folders are skipped (editor and OS litter).

    Raises
    ------
    FileNotFoundError
        If the path does not exist.
    """
    path = Path(path)
    if path.is_file():
        return _file_hash(path)
    if not path.is_dir():
        raise FileNotFoundError(f"cache: input {path} does not exist")
    h = hashlib.sha256(b"folder\0")
    files = sorted(
        p for p in path.rglob("*")
        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(path).parts)
    )
    for p in files:
        h.update(p.relative_to(path).as_posix().encode() + b"\0")
        h.update(_file_hash(p).encode() + b"\0")
    return h.hexdigest()


def stage_key(name: str, config: Mapping[str, Any],
              inputs: Sequence[Path | str | bytes] = ()) -> StageKey:
    """Key of a stage: hash of its name, config and inputs.

    Parameters
    ----------
    name : str
        Stage name (letters, digits, ``_.-``).
    config : mapping
        The stage's own resolved settings (JSON-able: numbers, strings, lists, dicts, numpy
        scalars/arrays, paths as strings).
    inputs : sequence
        In order, each one of: a :class:`StageKey` or a 64-hex-digit ``str`` (an upstream
        stage's key); a :class:`~pathlib.Path` or any other ``str`` (a file or folder, hashed
        by content); ``bytes`` (hashed as given, e.g. a serialised array).

    Returns
    -------
    StageKey
        64 hex digits.

    Raises
    ------
    ValueError
        Bad stage name, non-JSON config, or an input that is neither (message names it).
    FileNotFoundError
        An input path that does not exist.
    """
    _check_name(name)
    try:
        cfg = canonical_json(dict(config))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"cache: config of stage {name!r} is not JSON-serialisable: {exc}") \
            from None
    h = hashlib.sha256(b"breastmodel-stage-v1\0")
    h.update(name.encode() + b"\0" + cfg.encode() + b"\0")
    for item in inputs:
        if isinstance(item, StageKey) or (isinstance(item, str) and _KEY_RE.match(item)):
            h.update(b"key\0" + item.encode())
        elif isinstance(item, str | os.PathLike):
            h.update(b"path\0" + content_hash(Path(item)).encode())
        elif isinstance(item, bytes | bytearray | memoryview):
            h.update(b"bytes\0" + hashlib.sha256(bytes(item)).hexdigest().encode())
        else:
            raise ValueError(f"cache: input {item!r} of stage {name!r} is not a key, path or "
                             "bytes")
        h.update(b"\0")
    return StageKey(h.hexdigest())


def _check_name(name: str) -> None:
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ValueError(f"cache: bad stage name {name!r} (letters, digits, '_', '.', '-')")


def _check_key(key: str) -> None:
    if not isinstance(key, str) or not _KEY_RE.match(key):
        raise ValueError(f"cache: bad stage key {key!r} (expected 64 hex digits from stage_key)")


class Cache:
    """Finished stages under ``root``, one folder per (stage name, key).

    Parameters
    ----------
    root : path
        Cache folder (created on first use).

    Examples
    --------
    >>> key = stage_key("mesh", {"edge_mm": 4.0}, [segmentation_key])   # doctest: +SKIP
    >>> out = cache.run("mesh", key, lambda d: build_mesh(d / "mesh.npz"),
    ...                 config={"edge_mm": 4.0})                          # doctest: +SKIP
    """

    def __init__(self, root: str | Path):
        self.root = Path(root)

    def path(self, name: str, key: str) -> Path:
        """Final folder of a stage (whether it exists or not)."""
        _check_name(name)
        _check_key(key)
        return self.root / name / key

    def done(self, name: str, key: str) -> bool:
        """Whether the stage finished (its folder and its ``stage.json`` exist)."""
        return (self.path(name, key) / "stage.json").is_file()

    def record(self, name: str, key: str) -> dict:
        """The ``stage.json`` of a finished stage."""
        return json.loads((self.path(name, key) / "stage.json").read_text())

    @contextlib.contextmanager
    def staging(self, name: str, key: str, *,
                config: Mapping[str, Any] | None = None) -> Iterator[Path]:
        """Context manager: yields an empty temporary folder; on normal exit writes
        ``stage.json`` and renames the folder to :meth:`path`; on an exception moves it to
        ``failed-<key>`` beside it and rewrites the exception's message (and a ``path``
        attribute) to name that folder.

        Check :meth:`done` first; a stage that finished meanwhile (a concurrent run) is kept
        and this run's copy is discarded.
        """
        final = self.path(name, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        self._remove_orphans(final.parent, key)
        tmp = final.parent / f".tmp-{key}-{socket.gethostname()}-{os.getpid()}-" \
                              f"{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        t0, started = time.perf_counter(), datetime.now(UTC).isoformat(timespec="seconds")
        try:
            yield tmp
            write_json(tmp / "stage.json", {
                "name": name, "key": str(key),
                "config": json.loads(canonical_json(dict(config or {}))),
                "started": started, "wall_s": round(time.perf_counter() - t0, 6),
                "versions": package_versions(),
            })
            try:
                os.rename(tmp, final)
            except OSError:
                if not (final / "stage.json").is_file():
                    raise
                # another run finished the same stage first; its result is equivalent
            shutil.rmtree(final.parent / f"failed-{key}", ignore_errors=True)
        except BaseException as exc:
            _keep_failed(tmp, final.parent / f"failed-{key}", exc)
            raise
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def run(self, name: str, key: str, fn: Callable[[Path], None], *,
            config: Mapping[str, Any] | None = None) -> Path:
        """Run a stage unless it is done; return its final folder.

        Parameters
        ----------
        name, key : str
            Stage name and its :func:`stage_key`.
        fn : callable(Path) -> None
            Writes the stage's outputs into the folder it is given (a temporary one).
        config : mapping, optional
            Recorded in ``stage.json`` (with name, key, start time, wall time in s, package
            versions).

        Returns
        -------
        Path
            :meth:`path` ``(name, key)``, complete.

        Any exception of ``fn`` propagates and leaves nothing behind.
        """
        if not self.done(name, key):
            with self.staging(name, key, config=config) as tmp:
                fn(tmp)
        return self.path(name, key)

    @staticmethod
    def _remove_orphans(folder: Path, key: str) -> None:
        """Remove temporary folders of this key left by killed processes on this host."""
        host = socket.gethostname()
        prefix = f".tmp-{key}-"
        for p in folder.glob(prefix + "*"):
            parts = p.name[len(prefix):].rsplit("-", 2)  # host, pid, random
            if len(parts) != 3 or parts[0] != host or not parts[1].isdigit():
                continue
            if not _pid_alive(int(parts[1])):
                shutil.rmtree(p, ignore_errors=True)


def _keep_failed(tmp: Path, kept: Path, exc: BaseException) -> None:
    """Move a failed stage's temporary folder to ``kept`` and point ``exc`` at it."""
    if not tmp.exists():
        return
    shutil.rmtree(kept, ignore_errors=True)
    try:
        os.rename(tmp, kept)
    except OSError:
        return
    old, new = str(tmp), str(kept)
    exc.args = tuple(a.replace(old, new) if isinstance(a, str) else a for a in exc.args)
    path = getattr(exc, "path", None)
    if isinstance(path, str | Path) and old in str(path):
        exc.path = type(path)(str(path).replace(old, new))


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
