"""The project's one atomic file writer (standard library only, so every layer above imaging
may use it: imaging, meshing and the application; registration, which imports no other
stage, keeps the same steps in :func:`registration.transforms.write_transform`).

A reader never sees a half-written file and two writers of one path never collide: the data
go to a uniquely named temporary file in the target folder, are flushed to disk, and replace
the target in one rename; on any failure the temporary file is removed and the target is left
as it was.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()


def write_atomic_with(path: str | Path, write: Callable[[Path], Any], *,
                      suffix: str = ".tmp") -> Path:
    """``write(tmp)`` fills a uniquely named temporary file beside ``path`` whose name ends
    in ``suffix`` (a writer that picks its format from the name gets the one it needs:
    ``".nii.gz"``, ``".seg.nrrd"``, ``".png"``, ``".npz"``); it is then flushed to disk and
    renamed onto ``path``. The folder must exist. Returns ``path``."""
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


def write_atomic(path: str | Path, data: str | bytes) -> Path:
    """Write text (UTF-8) or bytes atomically (:func:`write_atomic_with`)."""
    raw = data.encode() if isinstance(data, str) else bytes(data)
    return write_atomic_with(path, lambda tmp: tmp.write_bytes(raw))
