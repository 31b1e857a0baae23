"""The tet mesh of a label-map file, made in a fresh process started at once, so that the
caller's own work runs beside it: the pipeline meshes the reference position while it
segments and registers the others (:func:`breastmodel.pipeline.run.prepare_subject`).

On an adult volume (320 x 180 x 200 voxels of 1 mm) the mesh takes about two minutes, most
of it on one core (fTetWild's one thread, pymeshlab's remeshing), while the segmentation and
registration of the other positions use about 1.3 of two cores. A process, not a thread:
pymeshlab and ITK's readers are not known to be thread-safe (see :mod:`meshing.surface`).
Below :data:`meshing.surface.PARALLEL_VOXELS` voxels, or with ``background=False``, the mesh
is made in this process when :meth:`mesh_in_background.result` is called: a worker's start
(about 2 s of imports) would cost more than it saves.
"""

from __future__ import annotations

import json
import logging
import tempfile
import warnings
from pathlib import Path

import SimpleITK as sitk

from mechanics.mesh import Mesh
from meshing._fresh import check_done, start_module

__all__ = ["mesh_in_background", "mesh_label_file"]

log = logging.getLogger("meshing")


def mesh_label_file(path: str | Path, *, size_mm, keep_gland: bool = False,
                    threads: int = 1) -> tuple[Mesh, float, str]:
    """:func:`meshing.mesh_labels` of the label map in ``path`` at the element size of the
    setting ``size_mm`` (a number or "auto", :func:`meshing.sizing.mesh_size`); the mesh, the
    size (mm) and how it was chosen."""
    from meshing import mesh_labels
    from meshing.sizing import mesh_size

    labels = sitk.ReadImage(str(path))
    size, why = mesh_size(size_mm, labels)
    log.info("mesh: %g mm (%s)", size, why)
    return mesh_labels(labels, size_mm=size, keep_gland=bool(keep_gland),
                       threads=int(threads)), size, why


class mesh_in_background:
    """:func:`mesh_label_file` of ``path``, started now in a ``python -m meshing.background``
    process when ``background`` (and the map has at least ``PARALLEL_VOXELS`` voxels);
    :meth:`result` waits for it. The worker's repair warnings and logged warnings are
    repeated here when the result is taken, and its ValueError or RuntimeError raised then.
    A context manager: leaving it stops a worker still running and removes its files."""

    def __init__(self, path: str | Path, *, size_mm, keep_gland: bool = False,
                 threads: int = 1, background: bool = True):
        from meshing.surface import worth_a_worker

        self.path = str(path)
        self.options = {"size_mm": size_mm, "keep_gland": bool(keep_gland),
                        "threads": int(threads)}
        self.proc = None
        if background and worth_a_worker(self.path):
            self.tmp = tempfile.TemporaryDirectory(prefix="mesh_labels_")
            self.out = Path(self.tmp.name) / "result.json"
            self.proc = start_module("meshing.background",
                                     [self.path, json.dumps(self.options), str(self.out)],
                                     Path(self.tmp.name) / "worker.log")

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def result(self) -> tuple[Mesh, float, str]:
        """The mesh, its size (mm) and how the size was chosen (see :func:`mesh_label_file`).

        Raises
        ------
        ValueError, RuntimeError
            As :func:`meshing.mesh_labels` (bad label map, surfaces that cannot be repaired);
            RuntimeError when the worker itself dies.
        """
        if self.proc is None:
            return mesh_label_file(self.path, **self.options)
        from meshing.labels import repaired

        code = self.proc.wait()
        said = (Path(self.tmp.name) / "worker.log").read_text(errors="replace")
        check_done(code, said, self.out, what=f"meshing {self.path}")
        got = json.loads(self.out.read_text())
        for message in got["repaired"]:
            repaired(message)
        for message in got["logged"]:
            log.warning("%s", message)
        for message in got["warned"]:
            warnings.warn(message, RuntimeWarning, stacklevel=2)
        if "error" in got:
            raise (ValueError if got["kind"] == "ValueError" else RuntimeError)(got["error"])
        return Mesh.load_npz(Path(self.tmp.name) / "mesh.npz"), got["size_mm"], got["why"]

    def close(self) -> None:
        """Stop the worker if it still runs; remove its files."""
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.terminate()
                self.proc.wait()
            self.tmp.cleanup()
            self.proc = None


class _Said(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def _main(path: str, options: str, out: str) -> None:
    """The worker: the mesh of ``path`` (``mesh.npz`` beside ``out``) or its error, and what
    it warned, to ``out`` (JSON, written last)."""
    from imaging.atomic import write_atomic_with
    from meshing.labels import MeshingWarning

    said = _Said()
    log.addHandler(said)
    log.propagate = False  # the caller repeats the warnings
    result: dict = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            mesh, size, why = mesh_label_file(path, **json.loads(options))
            mesh.save_npz(Path(out).with_name("mesh.npz"))
            result = {"size_mm": size, "why": why}
        except (ValueError, RuntimeError) as exc:
            result = {"error": str(exc), "kind": type(exc).__name__}
    repairs = [str(w.message) for w in caught if issubclass(w.category, MeshingWarning)]
    result.update(repaired=repairs, logged=[m for m in said.messages if m not in repairs],
                  warned=[str(w.message) for w in caught
                          if issubclass(w.category, RuntimeWarning)])

    def write(tmp: Path) -> None:
        tmp.write_text(json.dumps(result))
    write_atomic_with(out, write, suffix=".json")


if __name__ == "__main__":
    import sys

    _main(*sys.argv[1:4])
