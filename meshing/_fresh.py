"""A meshing module run in a fresh Python process (``python -m meshing.<name> ARGS``), with the
project's root on its path and its output file checked: fTetWild's reproducible runs
(:mod:`meshing._tetwild`), the measured skins' workers (:mod:`meshing.surface`) and the tet
mesh made beside the pipeline's other stages (:mod:`meshing.background`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def run_module(module: str, args: list[str], out: str | Path, *,
               what: str) -> subprocess.CompletedProcess:
    """Run ``python -m module *args``; its completed process (stderr kept for the caller).
    RuntimeError "``what`` failed (exit code N): <last lines>" when it fails or leaves no
    ``out``."""
    done = subprocess.run([sys.executable, "-m", module, *args], env=_env(), capture_output=True,
                          text=True, check=False)
    check_done(done.returncode, done.stderr or done.stdout, out, what=what)
    return done


def start_module(module: str, args: list[str], log_file: str | Path) -> subprocess.Popen:
    """Start ``python -m module *args`` and return at once; its stdout and stderr go to
    ``log_file`` (a pipe nobody reads would block it). Wait with ``proc.wait()``, then
    :func:`check_done`."""
    with open(log_file, "w") as f:
        return subprocess.Popen([sys.executable, "-m", module, *args], env=_env(), stdout=f,
                                stderr=subprocess.STDOUT)


def check_done(returncode: int, said: str, out: str | Path, *, what: str) -> None:
    """RuntimeError "``what`` failed (exit code N): <last lines of ``said``>" when the
    process failed or left no ``out``."""
    if returncode != 0 or not Path(out).is_file():
        tail = said.strip().splitlines()[-5:]
        raise RuntimeError(f"{what} failed (exit code {returncode}): " + " | ".join(tail))


def _env() -> dict:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    return env
