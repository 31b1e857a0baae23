"""Can ``compliant_interface`` express the sliding class's truth? On each FEBio truth of the
suite's ``sliding_layer`` family (the breast's base layer softer, solid elements), on the
truth's own mesh (no segmentation, registration or meshing of ours):

1. forward, from the truth's stress-free geometry: the skin's change that FEBio's layer makes
   against our bulk model (the layer given the breast's modulus), and the share of its square
   that the bulk model plus ``compliant_interface`` reproduces at each shear (with its
   cosine); our own solve of the layer beside it (FEBio against us, same physics);
2. inverse, as the diagnosis sees it: from the truth's reference position (the measured mesh),
   our stress-free inverse and the other positions' skin residual against FEBio's, for the bulk
   model at each breast modulus and for the candidate at each (modulus, shear).

The truths are the suite's subject folders' ``<subject>_truth`` (made with FEBio by
``python bench/diagnosis_matrix.py --suite febio --cases sliding --seeds 3 --out O`` as
``O/sliding-3/subject_truth``). Prints tables and writes ``--json`` (default
``bench/results/sliding_candidate.json``); a subject takes a few minutes on 2 cores.

    python bench/sliding_candidate.py O/sliding-{3,8,0}/subject_truth --shears 0.2,0.1,0.05
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)

from breastmodel.config import write_json  # noqa: E402
from breastmodel.phantom.simulated import _position_effects  # noqa: E402
from breastmodel.phantom.truth_model import TruthModel  # noqa: E402
from mechanics.effects._interface import split_interface  # noqa: E402
from mechanics.mesh import BREAST_SIDE, LAYER_REGIONS, Mesh  # noqa: E402
from mechanics.model import build_model  # noqa: E402
from mechanics.solver import SolverError, SolverOptions, solve  # noqa: E402
from mechanics.stress_free import inverse_fixed_point  # noqa: E402

LAYER = LAYER_REGIONS["interface"]


def _truth(folder: Path):
    doc = json.loads((folder / "truth_model.json").read_text())
    tj = json.loads((folder / "truth.json").read_text())
    mesh = Mesh.load_npz(folder / "stress_free_mesh.npz")
    u = {p: np.load(folder / f"{p}_displacement.npy") for p in doc["solves"]}
    mats = {int(k): dict(v) for k, v in doc["materials"].items()}
    if not any(c in mats for c in LAYER):
        raise SystemExit(f"sliding_candidate: {folder} is not a sliding_layer truth "
                         f"(no region {LAYER} in its materials)")
    return doc, tj["reference"], mesh, u, mats


def _bulk(mats: dict, E: float | None = None) -> dict:
    """The truth's materials with the layer given its side's breast material (modulus E)."""
    out = {k: dict(v) for k, v in mats.items()}
    for k in LAYER:
        out[k] = dict(mats[BREAST_SIDE[k]])
    if E is not None:
        for k in BREAST_SIDE:
            if k in out:
                out[k]["E"] = E
    return out


def _effects(doc: dict, pos: str, extra: dict | None = None) -> dict:
    """The truth's effects and gravity in position ``pos`` (as the truth was solved), plus
    ``extra``."""
    return {**_position_effects(TruthModel.from_dict(doc), pos), **(extra or {})}


def _cand(shear: float) -> dict:
    return {"compliant_interface": {"shear": shear}}


def _share(d_truth: np.ndarray, d_model: np.ndarray) -> tuple[float, float]:
    """(share of |d_truth|^2 that d_model reproduces, cosine of the two)."""
    ss = float((d_truth ** 2).sum())
    cos = float((d_truth * d_model).sum() / np.sqrt(ss * (d_model ** 2).sum()))
    return 1.0 - float(((d_truth - d_model) ** 2).sum()) / ss, cos


def forward(doc, mesh, u, mats, shears, opts) -> dict:
    skin = np.unique(mesh.face_sets["skin"])
    split = split_interface(mesh)
    p95 = lambda d: float(np.percentile(np.linalg.norm(d, axis=1), 95))  # noqa: E731
    out = {}
    for pos in doc["solves"]:
        ub = solve(build_model(mesh, _bulk(mats), _effects(doc, pos)), options=opts).u
        ul = solve(build_model(mesh, mats, _effects(doc, pos)), options=opts).u
        dF = (u[pos] - ub)[skin]
        row = {"febio_layer_vs_bulk_p95_mm": p95(dF),
               "ours_layer_vs_bulk_p95_mm": p95((ul - ub)[skin]),
               "febio_vs_ours_layer_p95_mm": p95((u[pos] - ul)[skin]), "shears": {}}
        for s in shears:
            uc = solve(build_model(split, _bulk(mats), _effects(doc, pos, _cand(s))),
                       options=opts).u[:mesh.n_nodes]
            share, cos = _share(dF, (uc - ub)[skin])
            row["shears"][str(s)] = {"share": share, "cosine": cos}
        out[pos] = row
    return out


def inverse(doc, ref, mesh, u, mats, moduli, cand_moduli, shears, opts) -> list[dict]:
    """Skin RMS of the non-reference positions predicted from the reference's inverse."""
    skin = np.unique(mesh.face_sets["skin"])
    x = {p: mesh.nodes + u[p] for p in doc["solves"]}
    measured = Mesh(x[ref], mesh.tets, mesh.region, node_sets=mesh.node_sets,
                    face_sets=mesh.face_sets)
    split = split_interface(measured)
    rows = []
    points = [(E, None) for E in moduli] + [(E, s) for E in cand_moduli for s in shears]
    for E, s in points:
        msh, extra = (measured, None) if s is None else (split, _cand(s))
        t = time.perf_counter()
        row = {"E": E, "shear": s}
        try:
            res = inverse_fixed_point(build_model(msh, _bulk(mats, E), _effects(doc, ref, extra)),
                                      msh.nodes, tol=0.01, max_iter=30, options=opts)
            for p in doc["solves"]:
                if p != ref:
                    xp = solve(build_model(msh, _bulk(mats, E), _effects(doc, p, extra)),
                               X=res.X, options=opts).x[:mesh.n_nodes]
                    row[p] = float(np.sqrt(((x[p] - xp)[skin] ** 2).sum(1).mean()))
            row["converged"] = bool(res.converged)
        except SolverError as exc:
            row["error"] = str(exc)[:200]
        row["seconds"] = time.perf_counter() - t
        rows.append(row)
        rms = "  ".join(f"{p} {row[p]:.3f}" for p in doc["solves"] if p in row)
        print(f"  E {E:<6.3g} shear {s if s is not None else '-':<6} {rms or row['error']}",
              flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("truths", type=Path, nargs="+", help="<subject>_truth folders")
    ap.add_argument("--shears", default="0.2,0.1,0.05")
    ap.add_argument("--moduli", default="0.7,0.75,0.8,0.9",
                    help="bulk breast moduli of the inverse, fractions of the truth's")
    ap.add_argument("--cand-moduli", default="0.9,1.0",
                    help="breast moduli with the candidate, fractions of the truth's")
    ap.add_argument("--json", type=Path, default=ROOT / "bench/results/sliding_candidate.json")
    args = ap.parse_args(argv)
    floats = lambda s: [float(v) for v in s.split(",") if v]  # noqa: E731
    shears = floats(args.shears)
    opts = SolverOptions()
    results = {}
    for folder in args.truths:
        doc, ref, mesh, u, mats = _truth(folder)
        name = json.loads((folder / "truth.json").read_text())["subject"]
        print(f"{name} ({folder}): forward from the stress-free geometry, skin nodes")
        fw = forward(doc, mesh, u, mats, shears, opts)
        for pos, r in fw.items():
            print(f"  {pos:<18} FEBio layer - bulk p95 {r['febio_layer_vs_bulk_p95_mm']:.2f} mm,"
                  f" FEBio - our layer p95 {r['febio_vs_ours_layer_p95_mm']:.2f} mm; "
                  + ", ".join(f"shear {s}: {v['share']:.2f} (cos {v['cosine']:.2f})"
                              for s, v in r["shears"].items()))
        print(f"  inverse from {ref}, skin RMS mm of the other positions against FEBio's:")
        E = mats[1]["E"]
        inv = inverse(doc, ref, mesh, u, mats, [f * E for f in floats(args.moduli)],
                      [f * E for f in floats(args.cand_moduli)], shears, opts)
        results[name] = {"truth": str(folder), "reference": ref, "forward": fw,
                         "inverse": inv, "truth_breast_E": mats[1]["E"]}
    write_json(args.json, {"shears": shears, "subjects": results})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
