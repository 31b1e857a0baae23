"""What holding the reference scan's cut buys: the validation suite's bulk fit of made subjects
with the model's faces on the cut left free, the muscle's held (``cut_faces``, the pipeline's
default), the breast's held along the cut's normal too, or the muscle's held along its
normal only.

Each subject folder (``WORK/subjects/<subject>`` of ``bench/validate.py``, its truth beside it
as ``<subject>_truth``) is run through the whole pipeline with the suite's config of ``--arm``
(``breastmodel.validation.suite.run_arm``), once per variant of ``cut_faces``, into
``--work/<subject>/<arm>/<variant>``; the table gives the fitted breast modulus against the
truth's and the MHD of every position. Prints a table and writes ``--json`` (default
``bench/results/cut_faces.json``).

    python bench/cut_faces.py W/subjects/small-000 W/subjects/small-003 --work C
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)

#: variant -> the ``cut_faces`` table (None: the effect left out of the model).
VARIANTS = {"free": None, "muscle": {}, "muscle+normal": {"breast": "normal"},
            "muscle_normal": {"muscle": "normal"}}


def run_variant(subject: Path, arm: str, table: dict | None, out: Path) -> dict:
    """One run of ``subject`` with the suite's config of ``arm`` and ``cut_faces`` as
    ``table`` (:func:`breastmodel.validation.suite.run_arm`): fitted modulus, the truth's,
    MHD and overlap MHD per position."""
    from breastmodel.validation.suite import run_arm

    r = run_arm(subject, subject.parent / f"{subject.name}_truth", out, arm,
                effects={"cut_faces": table})
    if r["error"]:
        raise SystemExit(f"bench cut_faces: {subject.name} [{arm}]: {r['error']}")
    return {"E_fit": r["fitted"]["breast_E"], "E_truth": r["truth_E"].get("left"),
            **{k: {p: round(v, 3) for p, v in r[k].items()}
               for k in ("mhd_mm", "mhd_overlap_mm")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("subjects", nargs="+", type=Path, help="WORK/subjects/<subject> folders")
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--arm", default="truth_labels", help="truth_labels or pipeline")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--json", type=Path, default=ROOT / "bench/results/cut_faces.json")
    args = ap.parse_args()
    rows = []
    print(f"{'subject':<14}{'variant':<15}{'E fit/truth kPa':<22}MHD per position mm")
    for subject in args.subjects:
        for name in args.variants.split(","):
            r = run_variant(subject, args.arm, VARIANTS[name],
                            args.work / subject.name / args.arm / name)
            rows.append({"subject": subject.name, "arm": args.arm, "variant": name, **r})
            err = 100 * (r["E_fit"] / r["E_truth"] - 1)
            print(f"{subject.name:<14}{name:<15}{r['E_fit']:.3f}/{r['E_truth']:.2f} "
                  f"({err:+.1f} %)   " + " ".join(f"{p} {v:.2f}" for p, v in r["mhd_mm"].items()))
    args.json.write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
