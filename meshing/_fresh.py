"""A meshing module run in a fresh Python process (``python -m meshing.<name> ARGS``), with the
project's root on its path and its output file checked: fTetWild's reproducible runs
(:mod:`meshing._tetwild`) and the measured skins' workers (:mod:`meshing.surface`)."""

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
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    done = subprocess.run([sys.executable, "-m", module, *args], env=env, capture_output=True,
                          text=True, check=False)
    if done.returncode != 0 or not Path(out).is_file():
        tail = (done.stderr or done.stdout).strip().splitlines()[-5:]
        raise RuntimeError(f"{what} failed (exit code {done.returncode}): " + " | ".join(tail))
    return done
