"""What the diagnosis answers with the skin near the field-of-view cut left out or kept: a
finished run diagnosed with several widths of the rim (``rank_candidates(rim_mm=...)``, the
skin within that distance of its open edge left out of the residual; default 15 mm).

The evaluations of the candidates do not depend on the rim: they are made once per run and
stored in ``--work/<run name>`` (a rerun reuses them), so each further rim costs only the
scoring and the held-out re-fits. Per run and rim the table gives the answer (the first
significant candidate, or "none"), its explained fraction, and the row of every candidate
whose name starts with ``--watch`` (default ``cut_faces``).

    python bench/validate.py --seeds 0 --arms truth_labels --work W
    python bench/cut_faces.py W/subjects/small-000 --work C --variants free
    python bench/diagnosis_rim.py W/runs/small-000/truth_labels C/small-000/truth_labels/free \\
        --rims 15,10,5 --work D

Prints a table and writes ``--json`` (default ``bench/results/diagnosis_rim.json``). A
diagnosis of a small suite subject takes one to two minutes on 2 cores the first time.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)


def _row(r: dict) -> dict:
    held = {p: round(v["rms_after_mm"], 3) for p, v in (r.get("held_out") or {}).items()}
    return {"name": r["name"], "significant": r["significant"],
            "explained": round(r["explained"], 3), "predicted_rms_mm": round(
                r["predicted_rms_mm"], 3), "estimate": r.get("estimate"),
            "held_out_rms_mm": held}


def diagnose_at(run: Path, work: Path, rim_mm: float, watch: str) -> dict:
    """The diagnosis of ``run`` with a rim of ``rim_mm``: answer, verdict, the watched rows."""
    from breastmodel.diagnosis import answer, load_run, rank_candidates

    d = rank_candidates(load_run(run), progress=False, verify_top=0, work_dir=work,
                        rim_mm=rim_mm)
    best = answer(d["ranking"])
    return {"rim_mm": rim_mm, "answer": best["name"] if best else "none",
            "answer_explained": round(best["explained"], 3) if best else None,
            "residual_rms_mm": round(d["baseline"]["rms_mm"], 3),
            "verdict": d["verdict"], "ranking": [_row(r) for r in d["ranking"][:5]],
            "watched": [_row(r) for r in d["ranking"] if r["name"].startswith(watch)]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders")
    ap.add_argument("--rims", default="15,10,5", help="comma-separated rim widths, mm")
    ap.add_argument("--work", type=Path, required=True, help="where evaluations are stored")
    ap.add_argument("--watch", default="cut_faces", help="candidates shown by name prefix")
    ap.add_argument("--json", type=Path, default=ROOT / "bench/results/diagnosis_rim.json")
    args = ap.parse_args()
    rows = []
    print(f"{'run':<44}{'rim mm':>7}  {'answer (explained)':<36}watched (explained)")
    for run in args.runs:
        name = "-".join(run.resolve().parts[-3:])
        for rim in (float(r) for r in args.rims.split(",")):
            r = diagnose_at(run, args.work / name, rim, args.watch)
            rows.append({"run": str(run), **r})
            ans = (f"{r['answer']} ({r['answer_explained']:.2f})" if r["answer_explained"]
                   is not None else "none")
            watched = ", ".join(f"{w['name']} ({w['explained']:+.2f}"
                                f"{', significant' if w['significant'] else ''})"
                                for w in r["watched"])
            print(f"{name:<44}{rim:>7.1f}  {ans:<36}{watched}", flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"rows": rows}, indent=1, default=str) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
