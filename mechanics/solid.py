"""The bulk solid: per-region materials on linear tets with averaged nodal pressure.

Formulation ``"anp"`` (default, locking-free): the isochoric energy is evaluated per element
from F, the volumetric energy ``K/2 (Jbar - 1)^2`` on the nodal volume ratio
``Jbar_a = v_a / V_a`` where ``v_a`` sums a quarter of the current volume of each tet around
node a (Bonet & Burton 1998). Nodes then carry one volume constraint each instead of every
tet, which removes volumetric locking of linear tets at nu -> 0.5. The discrete energy is
exact, so the tangent is symmetric and consistent. Formulation ``"standard"`` evaluates the
volumetric term per element (plain displacement tets, locks; kept for comparison).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from mechanics.effects.base import MaterialSpec
from mechanics.kernels import (
    IU,
    JU,
    deformation_gradient,
    det_inv,
    element_force,
    element_stiffness,
    full_from_upper78,
    reference_geometry,
    upper_outer,
)
from mechanics.materials import MATERIALS
from mechanics.materials.base import IsochoricI1Material

FORMULATIONS = ("anp", "standard")
_CHUNK = 8192  # elements per block of the stiffness kernel


class InvalidConfiguration(ValueError):
    """An element inverted (J <= 0) or left the domain of its material law."""


@dataclass(frozen=True)
class SolidEval:
    """Solid response at one configuration (see :meth:`Solid.evaluate`)."""

    force: np.ndarray  # (N, 3) internal nodal forces, mN
    Kup: np.ndarray | None  # (M, 78) upper triangle of the element stiffness, mN/mm
    dv: np.ndarray  # (M, 4, 3) dv_e/dx, mm^2
    p_node: np.ndarray  # (N,) nodal pressure, kPa ("anp"), else empty
    p_elem: np.ndarray  # (M,) element pressure, kPa
    F: np.ndarray  # (M, 3, 3)
    P_dev: np.ndarray  # (M, 3, 3) isochoric first Piola-Kirchhoff stress, kPa
    energy: float  # stored energy, mN mm (= uJ)


class Solid:
    """Bulk material response of a tet mesh in a given reference configuration.

    Parameters
    ----------
    tets : (M, 4) int node indices
    region : (M,) int region codes
    materials : region code -> MaterialSpec (every region present must have one)
    X : (N, 3) reference (stress-free) node positions, mm
    formulation : "anp" or "standard"
    """

    def __init__(self, tets, region, materials: Mapping[int, MaterialSpec], X, *,
                 formulation: str = "anp"):
        if formulation not in FORMULATIONS:
            raise ValueError(f"mechanics: unknown formulation {formulation!r}; "
                             f"choose one of {FORMULATIONS}")
        self.formulation = formulation
        self.tets = np.asarray(tets, dtype=np.int64)
        self.X = np.asarray(X, dtype=np.float64)
        self.n_nodes = len(self.X)
        self.dN, self.V0 = reference_geometry(self.X, self.tets)
        bad = np.flatnonzero(~(self.V0 > 0.0))
        if len(bad):
            raise ValueError(
                f"mechanics: inverted or degenerate mesh: {len(bad)} of {len(self.V0)} tets have "
                f"reference volume <= 0 (first: tet {bad[0]}, volume {self.V0[bad[0]]:.3g} mm^3)"
            )
        region = np.asarray(region)
        self.groups = []
        bulk = np.empty(len(self.tets))
        self.linear_mask = np.zeros(len(self.tets), bool)
        for code in np.unique(region):
            spec = materials.get(int(code))
            if spec is None:
                raise ValueError(f"mechanics: region {int(code)} has no material "
                                 f"(materials given for regions {sorted(materials)})")
            if spec.name not in MATERIALS:
                raise ValueError(f"mechanics: unknown material {spec.name!r} for region "
                                 f"{int(code)}; known: {sorted(MATERIALS)}")
            law = MATERIALS[spec.name].from_params(spec.params)
            idx = np.flatnonzero(region == code)
            self.groups.append((law, idx))
            bulk[idx] = law.bulk
            self.linear_mask[idx] = law.geometrically_linear
        self.bulk_elem = bulk
        w = np.repeat(self.V0 / 4.0, 4)
        flat = self.tets.ravel()
        self.V_node = np.bincount(flat, weights=w, minlength=self.n_nodes)
        kv = np.bincount(flat, weights=w * np.repeat(bulk, 4), minlength=self.n_nodes)
        with np.errstate(invalid="ignore", divide="ignore"):
            self.bulk_node = np.where(self.V_node > 0, kv / self.V_node, 0.0)
        self.used_nodes = self.V_node > 0

    # ------------------------------------------------------------------------------------
    def evaluate(self, x: np.ndarray, *, tangent: bool = True) -> SolidEval:
        """Internal forces (and element stiffness) at current positions x (N, 3) mm.

        Raises :class:`InvalidConfiguration` if an element is inverted or a law is undefined.
        """
        dN, V0, lin = self.dN, self.V0, self.linear_mask
        F = deformation_gradient(x, self.tets, dN)
        M = len(F)
        J, Finv = det_inv(F)
        bad = ~(J > 0.0) & ~lin
        if np.any(bad):
            raise InvalidConfiguration(f"{int(bad.sum())} element(s) inverted (J <= 0)")
        g = np.einsum("maJ,mJi->mai", dN, Finv)  # spatial shape-function gradients, 1/mm
        v = V0 * J
        dv = v[:, None, None] * g
        any_lin = bool(lin.any())
        if any_lin:
            v = np.where(lin, V0 * (np.trace(F, axis1=1, axis2=2) - 2.0), v)
            dv = np.where(lin[:, None, None], V0[:, None, None] * dN, dv)
        fe = np.empty((M, 4, 3))
        P = np.empty((M, 3, 3))
        coef = None
        if tangent:
            coef = {k: np.zeros(M) for k in ("gg", "sw", "fg", "dd", "qq")}
            coef["f"] = np.zeros((M, 4, 3))
            coef["q"] = np.zeros((M, 4, 3))
        generic = []
        energy = 0.0
        for law, idx in self.groups:
            if isinstance(law, IsochoricI1Material):
                energy += self._i1_group(law, idx, F, J, Finv, g, fe, P, coef)
            else:
                W, P[idx], A = law.deviatoric(F[idx], tangent=tangent)
                energy += float(np.dot(W, V0[idx]))
                fe[idx] = element_force(P[idx], dN[idx], V0[idx])
                if tangent:
                    generic.append((idx, element_stiffness(A, dN[idx], V0[idx])))
        if not np.all(np.isfinite(fe)):
            raise InvalidConfiguration("a material law is undefined at this strain "
                                       "(e.g. beyond the Gent limit)")
        if self.formulation == "anp":
            v_node = np.bincount(self.tets.ravel(), weights=np.repeat(v / 4.0, 4),
                                 minlength=self.n_nodes)
            Jbar = np.ones(self.n_nodes)
            u = self.used_nodes
            Jbar[u] = v_node[u] / self.V_node[u]
            p_node = self.bulk_node * (Jbar - 1.0)
            p_elem = p_node[self.tets].mean(axis=1)
            energy += float(0.5 * np.dot(self.bulk_node * self.V_node, (Jbar - 1.0) ** 2))
        else:
            p_node = np.zeros(0)
            p_elem = self.bulk_elem * (v / V0 - 1.0)
            energy += float(0.5 * np.dot(self.bulk_elem * V0, (v / V0 - 1.0) ** 2))
        fe += p_elem[:, None, None] * dv
        force = np.zeros((self.n_nodes, 3))
        _scatter(force, self.tets, fe)
        Kup = None
        if tangent:
            # Geometric stiffness of the volume: p d2v/dx2 = p v (g_ai g_bk - g_ak g_bi).
            pv = p_elem * v * ~lin if any_lin else p_elem * v
            coef["gg"] += pv
            coef["sw"] -= pv
            if self.formulation == "standard":
                coef["gg"] += self.bulk_elem * V0 * J * J * ~lin
            Kup = np.empty((M, 78))
            for s in range(0, M, _CHUNK):  # bounded temporaries (M x 144) and cache reuse
                e = min(M, s + _CHUNK)
                Kup[s:e] = _stiffness_upper(g[s:e], {k: c[s:e] for k, c in coef.items()},
                                            dN[s:e])
            for idx, K12 in generic:
                Kup[idx] += K12[:, IU, JU]
            if lin.any() and self.formulation == "standard":
                Kup[lin] += (self.bulk_elem / V0)[lin, None] * upper_outer(dv, dv)[lin]
            if not np.all(np.isfinite(Kup)):
                raise InvalidConfiguration("the tangent is not finite")
        return SolidEval(force, Kup, dv, p_node, p_elem, F, P, energy)

    def _i1_group(self, law, idx, F, J, Finv, g, fe, P, coef) -> float:
        """Closed-form force of a psi(I1bar) law on elements ``idx``; stores the stiffness
        coefficients (of g g, the index-swapped g g, f g + g f, D I and q q) in ``coef``."""
        Fi, dNi, V0 = F[idx], self.dN[idx], self.V0[idx]
        gi = g[idx]
        I1 = np.einsum("mij,mij->m", Fi, Fi)
        a = np.cbrt(J[idx]) ** -2
        W, d1, d2 = law.psi(a * I1)
        f = np.einsum("miJ,maJ->mai", Fi, dNi)  # F dN_a
        q = a[:, None, None] * (2.0 * f - (2.0 / 3.0) * I1[:, None, None] * gi)  # dI1bar.dN_a
        fe[idx] = (V0 * d1)[:, None, None] * q
        H = Finv[idx].transpose(0, 2, 1)
        P[idx] = (d1 * a)[:, None, None] * (2.0 * Fi - (2.0 / 3.0) * I1[:, None, None] * H)
        if coef is not None:
            al = V0 * d1 * a
            coef["gg"][idx] = 4.0 / 9.0 * al * I1
            coef["sw"][idx] = 2.0 / 3.0 * al * I1
            coef["fg"][idx] = -4.0 / 3.0 * al
            coef["dd"][idx] = 2.0 * al
            coef["f"][idx] = f
            if np.any(d2):
                coef["qq"][idx] = V0 * d2
                coef["q"][idx] = q
        return float(np.dot(W, V0))

    def cauchy_stress(self, ev: SolidEval) -> np.ndarray:
        """Cauchy stress (M, 3, 3) kPa per element: (1/J) P_dev F^T + p I."""
        J = det_inv(ev.F)[0]
        J = np.where(self.linear_mask, 1.0, J)
        F = np.where(self.linear_mask[:, None, None], np.eye(3), ev.F)
        sig = np.einsum("miJ,mkJ->mik", ev.P_dev, F) / J[:, None, None]
        return sig + ev.p_elem[:, None, None] * np.eye(3)

    # ------------------------------------------------------------------------------------
    def condensed_tangent(self, ev: SolidEval) -> sp.csr_matrix:
        """The full (3N, 3N) tangent dR/dx of the solid (pressure eliminated), for checks."""
        n = 3 * self.n_nodes
        dofs = (3 * self.tets[:, :, None] + np.arange(3)).reshape(-1, 12)
        rows = np.repeat(dofs, 12, axis=1).ravel()
        cols = np.tile(dofs, (1, 12)).ravel()
        Ke = full_from_upper78(ev.Kup)
        K = sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()
        if self.formulation == "anp":
            G = self.pressure_coupling(ev)
            w = np.where(self.used_nodes, self.bulk_node / np.where(self.used_nodes,
                                                                     self.V_node, 1.0), 0.0)
            K = K + (G @ sp.diags(w) @ G.T).tocsr()
        return K

    def pressure_coupling(self, ev: SolidEval) -> sp.csr_matrix:
        """G (3N, N): dv_a/dx, with v_a the nodal share of current volume (mm^2)."""
        M = len(self.tets)
        dofs = (3 * self.tets[:, :, None] + np.arange(3)).reshape(M, 12)
        rows = np.repeat(dofs, 4, axis=1).ravel()
        cols = np.tile(self.tets, (1, 12)).ravel()
        vals = np.repeat(ev.dv.reshape(M, 12) / 4.0, 4, axis=1).ravel()
        return sp.coo_matrix((vals, (rows, cols)), shape=(3 * self.n_nodes, self.n_nodes)).tocsr()


def _stiffness_upper(g, c, dN) -> np.ndarray:
    """(M, 78) upper triangles of sum of the closed-form stiffness terms.

    K[(a,i),(b,k)] = c_gg g_ai g_bk + c_sw g_bi g_ak + c_fg (f_ai g_bk + g_ai f_bk)
                     + c_dd (dN_a . dN_b) delta_ik + c_qq q_ai q_bk
    """
    M = len(g)
    gg = g[:, :, :, None, None] * g[:, None, None, :, :]  # (M, 4, 3, 4, 3)
    K = c["gg"][:, None, None, None, None] * gg
    K += c["sw"][:, None, None, None, None] * gg.transpose(0, 1, 4, 3, 2)
    fg = c["f"][:, :, :, None, None] * g[:, None, None, :, :]
    fg += fg.transpose(0, 3, 4, 1, 2)
    K += c["fg"][:, None, None, None, None] * fg
    D = np.einsum("maJ,mbJ->mab", dN, dN) * c["dd"][:, None, None]
    for i in range(3):
        K[:, :, i, :, i] += D
    if np.any(c["qq"]):
        q = c["q"]
        K += c["qq"][:, None, None, None, None] * (q[:, :, :, None, None] * q[:, None, None, :, :])
    return K.reshape(M, 144)[:, IU * 12 + JU]


def _scatter(force: np.ndarray, tets: np.ndarray, fe: np.ndarray) -> None:
    """force[tets] += fe with bincount (much faster than np.add.at)."""
    n = len(force)
    idx = tets.ravel()
    for i in range(3):
        force[:, i] += np.bincount(idx, weights=fe[:, :, i].ravel(), minlength=n)
