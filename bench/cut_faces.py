"""What holding the reference scan's cut buys: the validation suite's bulk fit of made subjects
with the model's faces on the cut left free, the muscle's held (``cut_faces``, the pipeline's
default) and the breast's held along the cut's normal too.

Each subject folder (``WORK/subjects/<subject>`` of ``bench/validate.py``, its truth beside it
as ``<subject>_truth``) is run through the whole pipeline with the suite's config of ``--arm``
(``breastmodel.validation.suite.suite_config``), once per variant of ``cut_faces``, into
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
VARIANTS = {"free": None, "muscle": {}, "muscle+normal": {"breast": "normal"}}


def run_variant(subject: Path, arm: str, table: dict | None, out: Path) -> dict:
    """One run of ``subject`` with the suite's config of ``arm`` and ``cut_faces`` as
    ``table``: fitted modulus, the truth's, MHD and overlap MHD per position."""
    from breastmodel.pipeline.config import resolve_config
    from breastmodel.pipeline.run import run_subject
    from breastmodel.validation.figures import truth_breast_E
    from breastmodel.validation.suite import suite_config
    from imaging.subject import read_subject

    truth = subject.parent / f"{subject.name}_truth"
    sub = read_subject(subject)
    cfg = json.loads(json.dumps(suite_config(arm, truth, list(sub.positions), sub.reference)))
    cfg["model"]["effects"].pop("cut_faces", None)
    if table is not None:
        cfg["model"]["effects"]["cut_faces"] = table
    run_subject(subject, resolve_config(cfg, where="bench cut_faces"), out)
    params = json.loads((out / "params.json").read_text())
    metrics = json.loads((out / "metrics.json").read_text())["positions"]
    return {"E_fit": params["parameters"]["materials.breast_left.E"],
            "E_truth": truth_breast_E(truth).get("left"),
            "mhd_mm": {p: round(m["mhd_mm"], 3) for p, m in metrics.items()},
            "mhd_overlap_mm": {p: round(m["mhd_overlap_mm"], 3) for p, m in metrics.items()}}


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
