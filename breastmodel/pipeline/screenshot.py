"""A picture of the report page: headless Chromium renders ``report.html`` into a PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from breastmodel.config import write_atomic_with

__all__ = ["CHROMIUM_FLAGS", "find_chromium", "screenshot"]


#: Flags for a headless Chromium that touches nothing outside the page.
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu",
                  "--disable-background-networking", "--no-first-run", "--hide-scrollbars")


def find_chromium() -> str | None:
    """Path of a Chromium (or Chrome) executable on PATH, or None."""
    import shutil

    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(html_path: str | Path, png_path: str | Path, *, width: int = 1200,
               height: int = 16000, timeout_s: float = 120.0) -> Path:
    """Render a report page with headless Chromium into a PNG, trimmed of the blank page
    below the content.

    Parameters
    ----------
    html_path : the page (``report.html``)
    png_path : output PNG
    width, height : browser window in CSS pixels (height: at least the page's)
    timeout_s : wall-clock limit for Chromium, s

    Raises
    ------
    RuntimeError
        No Chromium on PATH (Debian: ``apt-get install chromium``), or it wrote no picture.
    """
    import subprocess
    import tempfile

    from PIL import Image

    exe = find_chromium()
    if exe is None:
        raise RuntimeError("report: no chromium on PATH to render the report (Debian: "
                           "apt-get install -y chromium)")
    png_path = Path(png_path)
    with tempfile.TemporaryDirectory() as profile:
        shot = Path(profile) / "page.png"
        proc = subprocess.run(
            [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
             f"--window-size={width},{height}", f"--screenshot={shot}",
             Path(html_path).resolve().as_uri()],
            capture_output=True, text=True, timeout=timeout_s, check=False)
        if not shot.is_file():
            raise RuntimeError(f"report: chromium wrote no screenshot of {html_path} (exit "
                               f"{proc.returncode}): {proc.stderr.strip()[-500:]}")
        img = Image.open(shot).convert("RGB")
        a = np.asarray(img)
        rows = np.flatnonzero((a < 250).any(axis=(1, 2)))
        bottom = int(rows[-1]) + 20 if len(rows) else a.shape[0]
        cropped = img.crop((0, 0, a.shape[1], min(bottom, a.shape[0])))
        write_atomic_with(png_path, cropped.save, suffix=".png")
    return png_path
