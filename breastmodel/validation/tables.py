"""The suite's table: one row per subject and arm."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np


def _fmt(v, digits=2) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def _abbr(position: str) -> str:
    """Short position name for tables: initials of its words plus any number
    (``supine_tilted_30`` -> ``st30``, ``prone`` -> ``p``)."""
    parts = position.split("_")
    return "".join(p if p.isdigit() else p[0] for p in parts if p)


def _short_error(error: str | None, width: int = 110) -> str:
    """An arm's error without the file path a stage names (the JSON keeps it whole)."""
    import re

    return re.sub(r" \[[^\]]*\]", "", error or "")[:width]


def summary_rows(res: Mapping[str, Any]) -> dict[str, str]:
    """One table row per subject and arm: the figures, per position where they differ."""
    rows = []
    info = res.get("info") or {}
    for arm, a in (res.get("arms") or {}).items():
        dice = a.get("dice") or {}
        reg = a.get("registration") or {}
        mhd = a.get("mhd_mm") or {}
        ovl = a.get("mhd_overlap_mm") or {}
        times = {}
        for st in a.get("stages") or []:
            times[st["name"]] = times.get(st["name"], 0.0) + float(st["wall_s"])
        E = (a.get("fitted") or {}).get("breast_E")
        truth = a.get("truth_E") or {}
        rows.append({
            "subject": res["subject"], "kind": str(info.get("label", "")), "arm": arm,
            "dice b/m": " ".join(f"{v.get('breast', np.nan):.3f}/{v.get('muscle', np.nan):.3f}"
                                 for v in dice.values()) or "-",
            "TRE mm": " ".join(f"{_abbr(p)} {v['tre_max_mm']:.2f}" for p, v in reg.items()) or "-",
            "rot deg": " ".join(f"{v['rotation_error_deg']:.2f}" for v in reg.values()) or "-",
            "E fit/truth kPa": (f"{E:.3f}/" if E is not None else "-/")
                               + "/".join(f"{v:.2f}" for v in truth.values()),
            "MHD cal mm": " ".join(f"{_abbr(p)} {mhd[p]:.2f}" for p in a.get("calibrate", [])
                                   if mhd.get(p) is not None) or "-",
            "MHD held mm": " ".join(f"{_abbr(p)} {mhd[p]:.2f}" for p in a.get("held_out", [])
                                    if mhd.get(p) is not None) or "-",
            "MHD shared cal mm": " ".join(f"{_abbr(p)} {ovl[p]:.2f}"
                                          for p in a.get("calibrate", [])
                                          if ovl.get(p) is not None) or "-",
            "time s": " ".join(f"{k[:4]} {v:.0f}" for k, v in times.items()),
            "error": _short_error(a.get("error")),
        })
    if res.get("error"):
        rows.append({"subject": res["subject"], "kind": "", "arm": "-",
                     "error": res["error"][:90]})
    return rows


def format_table(results: Sequence[Mapping[str, Any]], *, markdown: bool = False) -> str:
    """The suite's table: one row per subject and arm."""
    rows = [r for res in results for r in summary_rows(res)]
    if not rows:
        return "(no results)"
    cols = ["subject", "kind", "arm", "dice b/m", "TRE mm", "rot deg", "E fit/truth kPa",
            "MHD cal mm", "MHD held mm", "MHD shared cal mm", "time s", "error"]
    cells = [[_fmt(r.get(c, "")) for c in cols] for r in rows]
    if markdown:
        lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        lines += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in cells]
        return "\n".join(lines)
    width = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
    fmt = "  ".join(f"{{:<{w}}}" for w in width)
    return "\n".join([fmt.format(*cols)] + [fmt.format(*row) for row in cells])
