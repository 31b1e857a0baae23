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
    DIAG_PAIR,
    DIAG_ROWS,
    IU,
    JU,
    SW1,
    SW2,
    det_inv,
    element_force,
    element_stiffness,
    full_from_upper78,
    pair_dots,
    reference_geometry,
    upper_outer,
)
from mechanics.materials import MATERIALS
from mechanics.materials.base import IsochoricI1Material
from mechanics.system import blocks  # the whole mesh, or blocks of system.STREAM

FORMULATIONS = ("anp", "standard")
_CHUNK = 2048  # elements per block of the stiffness kernel (78 x 2048 doubles: in L2)


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


@dataclass(frozen=True)
class _Block:
    """Elements [start, stop) of one block an evaluation streams through, with its laws in
    block-local indices and the nodal sums of its (element, node) values."""

    sl: slice
    i1_all: bool  # every element of the block has a closed-form psi(I1bar) law
    i1_sel: object  # those elements: slice(None), or block-local indices
    i1_groups: list  # (law, positions in i1_sel)
    generic_groups: list  # (law, block-local indices) of the other laws
    node_sum: sp.csr_matrix  # (N, 4k) ones: a CSR product is several times faster than
    # np.add.at or three bincounts

    @classmethod
    def make(cls, solid, start: int, stop: int, law_of: np.ndarray, closed: list) -> _Block:
        group = law_of[start:stop]
        k = stop - start
        sel = np.flatnonzero(np.asarray(closed)[group])
        local = np.full(k, -1, np.int64)
        local[sel] = np.arange(len(sel))
        i1, generic = [], []
        for n, (law, _) in enumerate(solid.groups):
            idx = np.flatnonzero(group == n)
            if len(idx):
                (i1 if closed[n] else generic).append((law, local[idx] if closed[n] else idx))
        tets = solid.tets[start:stop]
        node_sum = sp.csr_matrix((np.ones(4 * k), (tets.ravel(), np.arange(4 * k))),
                                 shape=(solid.n_nodes, 4 * k))
        all_ = len(sel) == k
        return cls(slice(start, stop), all_, slice(None) if all_ else sel, i1, generic,
                   node_sum)


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
        self._prepare_fast_paths()

    # ------------------------------------------------------------------------------------
    def _prepare_fast_paths(self) -> None:
        """Constant data of the vectorised kernels (built once per reference configuration):
        the element blocks an evaluation streams through (:class:`_Block`: their laws and
        node-element incidence) and, on a mesh of one block, every element's dN_a . dN_b."""
        M = len(self.tets)
        law_of = np.empty(M, np.int64)  # each element's group
        for n, (_, idx) in enumerate(self.groups):
            law_of[idx] = n
        closed = [isinstance(law, IsochoricI1Material) for law, _ in self.groups]
        self.blocks = [_Block.make(self, sl.start, sl.stop, law_of, closed)
                       for sl in blocks(M)]
        # dN_a . dN_b of the 10 node pairs, the constant part of the isochoric stiffness of
        # psi(I1bar) laws: kept for one block, else made per block (150k tets: 12 MB).
        self.dndn = pair_dots(self.dN) if len(self.blocks) == 1 else None

    def evaluate(self, x: np.ndarray, *, tangent: bool = True, sink=None,
                 tensile_pressure_stiffness: bool = True) -> SolidEval:
        """Internal forces (and element stiffness) at current positions x (N, 3) mm.

        With ``sink`` (e.g. :meth:`mechanics.system.Assembly.add_stiffness`), the element
        stiffness goes to ``sink(elements, KT)`` block by block, KT (78, k) the upper
        triangles of the elements ``elements`` (a slice or indices, element-last), and
        ``Kup`` stays None: no mesh-sized array of element matrices is made.
        ``tensile_pressure_stiffness=False`` leaves the geometric stiffness p d2v/dx2 of
        the elements in volumetric tension (p > 0) out of the element stiffness, not out
        of the forces (see ``SolverOptions.tensile_pressure_stiffness_below``).
        Raises :class:`InvalidConfiguration` if an element is inverted or a law is undefined.

        Two passes over the element blocks: F and the volumes (the nodal pressure needs
        every element's), then forces and stiffness; only F, the stress, the volumes and
        dv/dx are mesh-sized (150k tets: the rest of an evaluation's arrays are a block's).
        """
        x = np.asarray(x, dtype=np.float64)
        M, lin = len(self.V0), self.linear_mask
        F, J = np.empty((M, 3, 3)), np.empty(M)
        Finv = None
        for b in self.blocks:
            xe = x[self.tets[b.sl]].transpose(0, 2, 1)
            np.matmul(xe, self.dN[b.sl], out=F[b.sl])  # F_iJ = x_ai dN_aJ
            J[b.sl], Finv = det_inv(F[b.sl])  # the inverse kept for a single block
        any_lin = bool(lin.any())
        bad = ~(J > 0.0) & ~lin if any_lin else ~(J > 0.0)
        if np.any(bad):
            raise InvalidConfiguration(f"{int(bad.sum())} element(s) inverted (J <= 0)")
        v = self.V0 * J
        if any_lin:  # geometrically linear elements: their linearised volume
            v = np.where(lin, self.V0 * (np.trace(F, axis1=1, axis2=2) - 2.0), v)
        p_node, p_elem, energy = self._volumetric(v)
        force, P, dv = np.zeros((self.n_nodes, 3)), np.empty((M, 3, 3)), np.empty((M, 4, 3))
        # without a sink, one block's stiffness is the whole (no copy), more are gathered
        Kup = np.empty((78, M)) if tangent and sink is None and len(self.blocks) > 1 else None
        p_k = p_elem if tensile_pressure_stiffness else np.minimum(p_elem, 0.0)
        for b in self.blocks:
            sl = b.sl
            if len(self.blocks) > 1:
                Finv = det_inv(F[sl])[1]
            g = np.matmul(self.dN[sl], Finv)  # spatial gradients g_ai = dN_aJ Finv_Ji, 1/mm
            np.multiply(v[sl, None, None], g, out=dv[sl])
            if any_lin:
                dv[sl] = np.where(lin[sl, None, None], self.V0[sl, None, None] * self.dN[sl],
                                  dv[sl])
            fe, P[sl], e_dev, co, generic = self._deviatoric(b, F[sl], J[sl], Finv, g, tangent)
            energy += e_dev
            fe += p_elem[sl, None, None] * dv[sl]
            force += b.node_sum @ fe.reshape(-1, 3)
            Finv = fe = None  # the stiffness does not need them
            if tangent:
                gT = np.ascontiguousarray(g.reshape(-1, 12).T)
                del g
                KT, extra = self._element_stiffness(b, J[sl], gT, v[sl], dv[sl], p_k[sl], co,
                                                    generic)
                if sink is not None:
                    sink(sl, KT)
                    for idx, Ke in extra:
                        sink(sl.start + idx, Ke.T)
                    continue
                for idx, Ke in extra:
                    KT[:, idx] += Ke.T
                if Kup is None:
                    Kup = KT
                else:
                    Kup[:, sl] = KT
        return SolidEval(force, None if Kup is None else Kup.T, dv, p_node, p_elem, F, P,
                         energy)

    def _deviatoric(self, b: _Block, F, J, Finv, g, tangent: bool):
        """The isochoric part of every law on block ``b``'s elements (F, J, Finv, g theirs):
        element forces fe (k, 4, 3) mN, stress P (k, 3, 3) kPa, energy mN mm, the
        closed-form laws' stiffness coefficients (or None) and the other laws' element
        stiffness [(block-local elements, (n, 12, 12))]. Raises
        :class:`InvalidConfiguration` where a law is undefined."""
        dN, V0 = self.dN[b.sl], self.V0[b.sl]
        k = len(V0)
        fe = np.zeros((k, 4, 3))
        P = np.zeros((k, 3, 3))
        energy = 0.0
        co = None
        if len(b.i1_groups):
            e_i1, co = self._i1_laws(b, F, J, Finv, g, fe, P, tangent)
            energy += e_i1
        generic = []
        for law, idx in b.generic_groups:
            W, P[idx], A = law.deviatoric(F[idx], tangent=tangent)
            energy += float(np.dot(W, V0[idx]))
            fe[idx] = element_force(P[idx], dN[idx], V0[idx])
            if tangent:
                generic.append((idx, element_stiffness(A, dN[idx], V0[idx])))
        if not np.isfinite(fe.sum()):
            raise InvalidConfiguration("a material law is undefined at this strain "
                                       "(e.g. beyond the Gent limit)")
        return fe, P, energy, co, generic

    def _volumetric(self, v: np.ndarray):
        """Nodal pressure (N,) kPa ("anp", else empty), element pressure (M,) kPa and the
        volumetric energy, mN mm, at the current volumes v (M,) mm^3."""
        V0 = self.V0
        if self.formulation == "anp":
            v_node = sum(b.node_sum @ np.repeat(0.25 * v[b.sl], 4) for b in self.blocks)
            Jbar = np.ones(self.n_nodes)
            u = self.used_nodes
            Jbar[u] = v_node[u] / self.V_node[u]
            p_node = self.bulk_node * (Jbar - 1.0)
            p_elem = p_node[self.tets].mean(axis=1)
            energy = float(0.5 * np.dot(self.bulk_node * self.V_node, (Jbar - 1.0) ** 2))
        else:
            p_node = np.zeros(0)
            p_elem = self.bulk_elem * (v / V0 - 1.0)
            energy = float(0.5 * np.dot(self.bulk_elem * V0, (v / V0 - 1.0) ** 2))
        return p_node, p_elem, energy

    def _element_stiffness(self, b: _Block, J, gT, v, dv, p_elem, co, generic):
        """Upper triangles of block ``b``'s element stiffness, mN/mm (arrays: the block's;
        gT (12, k) the spatial gradients g, element-last): the closed-form laws' kernel and
        the volume's geometric stiffness in chunks, then the other laws' stiffness and the
        volumetric term of geometrically linear elements. Returns KT (78, k) and
        [(block-local elements, their (n, 78))] to add to it."""
        V0, lin = self.V0[b.sl], self.linear_mask[b.sl]
        M = len(V0)
        any_lin = bool(lin.any())
        # Geometric stiffness of the volume: p d2v/dx2 = p v (g_ai g_bk - g_ak g_bi).
        pv = p_elem * v * ~lin if any_lin else p_elem * v
        c_gg, c_sw = pv.copy(), -pv
        if self.formulation == "standard":
            c_gg += self.bulk_elem[b.sl] * V0 * J * J * ~lin
        sel = b.i1_sel
        fT = qT = None
        if co is not None:
            c_gg[sel] += co["gg"]
            c_sw[sel] += co["sw"]
            fT = np.zeros((12, M))
            fT[:, sel] = co.pop("f").reshape(-1, 12).T
            c_fg, c_dd = np.zeros(M), np.zeros(M)
            c_fg[sel], c_dd[sel] = co["fg"], co["dd"]
            if co["qq"] is not None:
                qT, c_qq = np.zeros((12, M)), np.zeros(M)
                qT[:, sel] = co["q"].reshape(-1, 12).T
                c_qq[sel] = co["qq"]
            del co["q"]
        dndn = self.dndn[:, b.sl] if self.dndn is not None else pair_dots(self.dN[b.sl])
        KT = np.empty((78, M))  # element index last: fast gathers
        for s in range(0, M, _CHUNK):  # bounded temporaries, cache reuse
            e = min(M, s + _CHUNK)
            gc = gT[:, s:e]
            h = c_gg[s:e] * gc
            if fT is not None:
                fc = fT[:, s:e]
                h += c_fg[s:e] * fc
            K = gc[IU] * h[JU]
            K += (c_sw[s:e] * gc)[SW1] * gc[SW2]
            if fT is not None:
                K += fc[IU] * (c_fg[s:e] * gc)[JU]
                K[DIAG_ROWS] += (c_dd[s:e] * dndn[:, s:e])[DIAG_PAIR]
            if qT is not None:
                qc = qT[:, s:e]
                K += qc[IU] * (c_qq[s:e] * qc)[JU]
            KT[:, s:e] = K
        if not np.isfinite(KT.sum()):
            raise InvalidConfiguration("the tangent is not finite")
        extra = [(idx, K12[:, IU, JU]) for idx, K12 in generic]
        if any_lin and self.formulation == "standard":
            extra.append((np.flatnonzero(lin), ((self.bulk_elem[b.sl] / V0)[lin, None]
                                               * upper_outer(dv[lin], dv[lin]))))
        for _, Ke in extra:
            if not np.isfinite(Ke.sum()):
                raise InvalidConfiguration("the tangent is not finite")
        return KT, extra

    def _i1_laws(self, b: _Block, F, J, Finv, g, fe, P, tangent: bool):
        """Closed-form force of the psi(I1bar) laws on block ``b`` (arrays: the block's,
        filled in fe and P at its closed-form elements ``b.i1_sel``). Returns their energy
        and, with ``tangent``, the stiffness coefficients (of g g, the index-swapped g g,
        f g + g f, D I and q q), else None."""
        sel = b.i1_sel
        if not b.i1_all:
            F, J, Finv, g = F[sel], J[sel], Finv[sel], g[sel]
        dNi, V0 = self.dN[b.sl][sel], self.V0[b.sl][sel]
        I1 = np.einsum("mij,mij->m", F, F)
        a = np.cbrt(J) ** -2
        I1bar = a * I1
        W, d1, d2 = np.empty_like(I1), np.empty_like(I1), np.empty_like(I1)
        for law, idx in b.i1_groups:
            W[idx], d1[idx], d2[idx] = law.psi(I1bar[idx])
        f = np.matmul(dNi, F.transpose(0, 2, 1))  # f_ai = F_iJ dN_aJ
        q = a[:, None, None] * (2.0 * f - (2.0 / 3.0) * I1[:, None, None] * g)  # dI1bar/dx_ai
        fe[sel] = (V0 * d1)[:, None, None] * q
        P[sel] = (d1 * a)[:, None, None] * (2.0 * F - (2.0 / 3.0) * I1[:, None, None]
                                            * Finv.transpose(0, 2, 1))
        co = None
        if tangent:
            al = V0 * d1 * a
            has_qq = bool(np.any(d2))
            co = {"gg": 4.0 / 9.0 * al * I1, "sw": 2.0 / 3.0 * al * I1, "fg": -4.0 / 3.0 * al,
                  "dd": 2.0 * al, "f": f, "qq": V0 * d2 if has_qq else None, "q": q}
        return float(np.dot(W, V0)), co

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
