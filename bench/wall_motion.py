"""How far the "rigid" chest wall moves in a validation truth: the best rigid motion of the
muscle's surface nodes (off the fixed posterior wall) from the reference position to each
other, in FEBio's truth, and what that rigid motion leaves.

A registration on the chest wall can be no better than the wall is rigid: where the breasts
pull the muscle, the wall the scans show turns and shifts against the thorax that carries
the true rigid motion (README, "The coil's tilted registration").

    python bench/wall_motion.py W/subjects/small-soft-000_truth W/subjects/small-000_truth

Prints a table and writes ``--json`` (default ``bench/results/wall_motion.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if sys.path and Path(sys.path[0]).resolve() == ROOT / "bench":
    sys.path[0] = str(ROOT)


def _rigid(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation and translation taking points P onto Q (Kabsch)."""
    pc, qc = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - pc).T @ (Q - qc))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, qc - R @ pc


def wall_motion(truth: Path) -> dict:
    """Per position other than the reference: the wall's rigid turn (deg), the shift of its
    centroid (mm), its nodes' mean motion and the mean residual of the rigid fit (mm)."""
    from mechanics.mesh import REGIONS, Mesh
    from meshing.sets import tet_faces

    spec = json.loads((truth / "truth.json").read_text())
    ref = spec["reference"]
    mesh = Mesh.load_npz(truth / "stress_free_mesh.npz")
    faces, owner, _, _ = tet_faces(mesh.tets)
    wall = np.setdiff1d(np.unique(faces[mesh.region[owner] == REGIONS["muscle"]]),
                        mesh.node_sets["fixed"])
    at_ref = mesh.nodes[wall] + np.load(truth / f"{ref}_displacement.npy")[wall]
    out = {"truth": str(truth), "reference": ref, "wall_nodes": int(len(wall)), "positions": {}}
    for pos in spec["positions"]:
        if pos == ref:
            continue
        at = mesh.nodes[wall] + np.load(truth / f"{pos}_displacement.npy")[wall]
        R, t = _rigid(at_ref, at)
        centre = at_ref.mean(0)
        out["positions"][pos] = {
            "turn_deg": round(float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2,
                                                                 -1, 1)))), 3),
            "shift_mm": round(float(np.linalg.norm(R @ centre + t - centre)), 3),
            "moves_mean_mm": round(float(np.linalg.norm(at - at_ref, axis=1).mean()), 3),
            "residual_mean_mm": round(float(np.linalg.norm(at_ref @ R.T + t - at, axis=1)
                                            .mean()), 3)}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("truths", nargs="+", type=Path, help="<subject>_truth folders")
    ap.add_argument("--json", type=Path, default=ROOT / "bench/results/wall_motion.json")
    args = ap.parse_args(argv)
    from breastmodel.config import write_json

    rows = [wall_motion(t) for t in args.truths]
    print(f"{'truth':22} {'position':18} {'turn deg':>9} {'shift mm':>9} {'moves mm':>9} "
          f"{'non-rigid mm':>13}")
    for r in rows:
        for pos, p in r["positions"].items():
            print(f"{Path(r['truth']).name:22} {pos:18} {p['turn_deg']:9.2f} "
                  f"{p['shift_mm']:9.2f} {p['moves_mean_mm']:9.2f} {p['residual_mean_mm']:13.2f}")
    write_json(args.json, {"rows": rows})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
