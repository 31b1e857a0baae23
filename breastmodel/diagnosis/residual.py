"""The diagnosis' residual vector and its linearisation around the fitted model.

The residual is the signed node-to-surface error of the scored skin nodes (the rim left out,
:func:`away_from_rim`), the scored positions one after another. :func:`linearise` turns the
evaluated model variants into the baseline every candidate is compared with: the fitted
model's residual ``r0``, the derivatives ``J_theta`` with respect to the fitted parameters
(log scale), the noise floor, and the bounded linear re-fit without any candidate
(:meth:`Linearisation.solve`). Also here: the effective number of independent residuals and
the BIC difference that charges a candidate for its columns, and the measured skin's geometry
that the non-physical candidates' columns are built from.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from breastmodel.diagnosis.evaluations import fit_bounds

log = logging.getLogger("breastmodel.diagnosis")

def rms(v) -> float:
    """Root mean square of ``v``; NaN when empty."""
    return float(np.sqrt(np.mean(np.square(v)))) if len(v) else math.nan


def variant_residual(records: Mapping[str, dict], name: str, keep: np.ndarray,
                     positions: Sequence[str]) -> np.ndarray | None:
    """The residual of variant ``name`` over the scored nodes ``keep`` of ``positions``, one
    position after another, mm (None when its evaluation failed)."""
    r = records[name]
    if r["status"] != "ok":
        return None
    return np.concatenate([np.asarray(r["result"]["residual"][p], float)[keep]
                           for p in positions])


@dataclass
class Linearisation:
    """The evaluated variants, linearised around the fitted model.

    ``records`` {variant: sweep record}; ``keep`` (n_skin,) bool, the scored skin nodes;
    ``obj_pos`` the scored positions; ``slices`` {position: slice of the residual vector};
    ``region_masks`` {region: (n_scored,) bool}; ``r0`` the fitted model's residual, mm;
    ``J_theta`` its derivatives by the log of each fitted parameter in ``th_names``, whose
    log bounds are ``th_lo`` / ``th_hi``.
    """

    records: Mapping[str, dict]
    keep: np.ndarray
    obj_pos: Sequence[str]
    slices: dict[str, slice]
    region_masks: dict[str, np.ndarray]
    r0: np.ndarray
    J_theta: list[np.ndarray]
    th_lo: list[float]
    th_hi: list[float]
    th_names: list[str]

    def vec(self, name: str) -> np.ndarray | None:
        """The residual of variant ``name`` (None when its evaluation failed)."""
        return variant_residual(self.records, name, self.keep, self.obj_pos)

    def solve(self, extra_cols, lo, hi, inert=(), rows=None):
        """Bounded linear re-fit (on ``rows`` of the residual, default all); fitted
        parameters in ``inert`` (made inert by the candidate, e.g. moduli that the regions
        effect overrides) are left out. Returns the whole predicted residual, the fitted
        parameters' log changes and the extra columns' coefficients."""
        from scipy.optimize import lsq_linear

        use = [i for i, q in enumerate(self.th_names) if not set(q.split("|")) & set(inert)]
        cols = [self.J_theta[i] for i in use] + list(extra_cols)
        if not cols:
            return self.r0.copy(), {}, np.zeros(0)
        A = np.column_stack(cols)
        lb = np.array([self.th_lo[i] for i in use] + list(lo), float)
        ub = np.array([self.th_hi[i] for i in use] + list(hi), float)
        ub = np.maximum(ub, lb + 1e-12)
        m = slice(None) if rows is None else rows
        sol = lsq_linear(A[m], -self.r0[m], bounds=(lb, ub), method="bvls")
        z_th = {self.th_names[i]: float(z) for i, z in zip(use, sol.x)}
        return self.r0 + A @ sol.x, z_th, sol.x[len(use):]

    def per_position(self, r: np.ndarray) -> dict:
        """RMS and mean |e| of ``r`` per position, mm."""
        return {p: {"rms_mm": rms(r[s]), "mean_abs_mm": float(np.mean(np.abs(r[s])))}
                for p, s in self.slices.items()}

    def per_region(self, r: np.ndarray) -> dict[str, float]:
        """RMS of ``r`` per ``position.region``, mm."""
        out = {}
        for p, s in self.slices.items():
            for name, m in self.region_masks.items():
                if m.any():
                    out[f"{p}.{name}"] = rms(r[s][m])
        return out


@dataclass
class Baseline:
    """The fitted model re-fitted alone: the yardstick of every candidate.

    ``floor`` the noise floor, mm, and where it comes from; ``calibrate`` / ``held_out`` the
    scored positions of the run's fit and the others, ``cal_rows`` the former's rows;
    ``r_base`` the residual after the linear re-fit, ``z_base`` its log parameter changes,
    ``ss_base`` its squared sum, ``rms_now`` / ``rms_base`` the RMS before and after, mm;
    ``n_eff`` the effective number of residuals; ``r_base_cal`` the re-fit on the calibration
    rows alone (None without held-out positions); ``regions`` the RMS per region.
    """

    floor: float
    floor_from: str
    calibrate: list
    held_out: list
    cal_rows: np.ndarray
    r_base: np.ndarray
    z_base: dict
    ss_base: float
    rms_now: float
    rms_base: float
    n_eff: float
    r_base_cal: np.ndarray | None
    regions: dict[str, float]


def linearise(run, records: Mapping[str, dict], *, keep: np.ndarray, nodes: np.ndarray,
              obj_pos: Sequence[str], fitted: Sequence[str], steps: Mapping[str, float],
              theta0: Mapping[str, float], floor_min_mm: float,
              ) -> tuple[Linearisation, Baseline]:
    """The residual of every variant in ``records`` linearised around the fitted model, and
    the baseline (the fitted parameters re-fitted alone); the noise floor is at least
    ``floor_min_mm``."""
    from breastmodel.pipeline.problem import skin_node_regions

    cfg, problem = run.config, run.problem
    mesh = problem.mesh
    positions = list(run.positions)
    inverse = cfg["stress_free"]["method"] == "inverse"
    n_skin = int(keep.sum())
    region_masks = {k: m[keep] for k, m in regions(problem, nodes, run.X[:mesh.n_nodes],
                                                   skin_node_regions(mesh)).items()}
    slices = {p: slice(i * n_skin, (i + 1) * n_skin) for i, p in enumerate(obj_pos)}

    all_base = {p: np.asarray(records["base"]["result"]["residual"][p])[keep]
                for p in positions}
    if inverse and problem.reference in all_base:
        floor = rms(all_base[problem.reference])
        floor_from = f"reference position {problem.reference!r} (reproduced by construction)"
    else:
        floor = min(rms(v) for v in all_base.values())
        floor_from = "the best-fitting position (no position is reproduced by construction)"
    floor = max(floor, floor_min_mm)

    r0 = variant_residual(records, "base", keep, obj_pos)
    J_theta, th_lo, th_hi, th_names = [], [], [], []
    for q in fitted:
        rq = variant_residual(records, f"theta|{q}", keep, obj_pos)
        if rq is None:
            continue
        h = steps[f"theta|{q}"]
        J_theta.append((rq - r0) / h)
        lo, hi = fit_bounds(cfg, q)
        th_lo.append(math.log(lo / theta0[q]))
        th_hi.append(math.log(hi / theta0[q]))
        th_names.append(q)
    lin = Linearisation(records, keep, obj_pos, slices, region_masks, r0, J_theta, th_lo,
                        th_hi, th_names)

    # rows of the calibration positions (the run's fit) and of the held-out ones
    calibrate = [p for p in (cfg["fit"].get("calibrate") or []) if p in obj_pos]
    held_out = [p for p in obj_pos if p not in calibrate] if calibrate else []
    cal_rows = np.zeros(len(r0), bool)
    for p in calibrate:
        cal_rows[slices[p]] = True

    r_base, z_base, _ = lin.solve([], [], [])
    base = Baseline(
        floor=floor, floor_from=floor_from, calibrate=calibrate, held_out=held_out,
        cal_rows=cal_rows, r_base=r_base, z_base=z_base, ss_base=float(r_base @ r_base),
        rms_now=rms(r0), rms_base=rms(r_base),
        n_eff=effective_n(mesh, nodes, keep, r_base, slices),
        r_base_cal=lin.solve([], [], [], rows=cal_rows)[0] if held_out else None,
        regions=lin.per_region(r_base))
    return lin, base


def away_from_rim(mesh, nodes: np.ndarray, X: np.ndarray, rim_mm: float) -> np.ndarray:
    """(n_skin,) bool: skin nodes farther than ``rim_mm`` from the skin's open edge (edges
    of one skin triangle only). All True when the skin is closed or ``rim_mm`` <= 0."""
    from scipy.spatial import cKDTree

    faces = np.asarray(mesh.face_sets["skin"])
    e = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    edge_nodes = np.unique(uniq[count == 1])
    if rim_mm <= 0 or not len(edge_nodes):
        return np.ones(len(nodes), bool)
    d, _ = cKDTree(X[edge_nodes]).query(X[nodes])
    keep = d > rim_mm
    if keep.sum() < 0.2 * len(nodes):
        raise ValueError(f"diagnose: a {rim_mm} mm rim leaves {int(keep.sum())} of "
                         f"{len(nodes)} skin nodes; use a smaller rim_mm")
    return keep


def regions(problem, nodes: np.ndarray, X: np.ndarray, node_region: np.ndarray,
            ) -> dict[str, np.ndarray]:
    """Boolean masks over the canonical skin nodes: the skin regions of the maps module
    where it is available, else left / right breast."""
    try:
        from breastmodel.diagnosis.maps import skin_regions
    except ImportError:
        skin_regions = None
    if skin_regions is not None:
        try:
            return {k: np.asarray(v, bool) for k, v in skin_regions(problem.mesh, X).items()}
        except Exception as exc:  # noqa: BLE001 - regions are evidence, not the ranking
            log.warning("diagnose: skin regions unavailable (%s); using left/right", exc)
    from mechanics.mesh import REGIONS

    reg = node_region[nodes]
    return {"left": np.isin(reg, (REGIONS["breast_left"], REGIONS["gland_left"])),
            "right": np.isin(reg, (REGIONS["breast_right"], REGIONS["gland_right"]))}


def effective_n(mesh, nodes: np.ndarray, keep: np.ndarray, r: np.ndarray,
                slices: Mapping[str, slice]) -> float:
    """Effective number of independent entries of the residual ``r``.

    Neighbouring skin nodes carry nearly the same error wherever the residual is a smooth
    field, so the node count overstates the evidence. With rho the correlation of the
    residual across skin edges (pooled over positions), n_eff = n (1 - rho) / (1 + rho), the
    count of an AR(1) sequence of the same lag-one correlation; white noise keeps n.
    """
    idx = np.full(mesh.n_nodes, -1, np.int64)
    idx[nodes[keep]] = np.arange(int(keep.sum()))
    faces = np.asarray(mesh.face_sets["skin"])
    e = np.unique(np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1), axis=0)
    e = idx[e]
    e = e[(e >= 0).all(axis=1)]
    num = den = 0.0
    for s in slices.values():
        v = r[s] - r[s].mean()
        num += float(np.sum(v[e[:, 0]] * v[e[:, 1]])) / max(len(e), 1)
        den += float(np.mean(v * v))
    rho = min(max(num / den, 0.0), 0.999) if den > 0 else 0.0
    return float(max(len(r) * (1 - rho) / (1 + rho), 2.0))


def delta_bic(ss: float, ss_base: float, n_eff: float, k: int) -> float:
    """BIC of the re-fit with the candidate minus that of the re-fit without it (Gaussian
    residual of unknown variance): n_eff ln(ss / ss_base) + k ln(n_eff); negative favours
    the candidate, and every added parameter costs ln(n_eff)."""
    tiny = 1e-30
    return float(n_eff * math.log(max(ss, tiny) / max(ss_base, tiny)) + k * math.log(n_eff))


def measured_geometry(problem, state: Mapping[str, Any], nodes: np.ndarray, keep: np.ndarray,
                      positions: Sequence[str]) -> dict:
    """Per position, the closest points ``y`` on the measured skin of the fitted model's
    scored skin nodes and the outward directions ``g`` (the non-physical candidates'
    columns)."""
    from breastmodel.diagnosis.measurement import _directions
    from breastmodel.evaluation import point_to_surface

    out = {}
    X = np.asarray(state["X"])
    for p in positions:
        x = (X + np.asarray(state["u"][p]))[nodes[keep]]
        v, t = problem.skins[p]
        d, y = point_to_surface(x, v, t, signed=True)
        out[p] = {"y": np.asarray(y), "g": _directions(x, np.asarray(d), np.asarray(y), v, t)}
    return out
