"""Coulomb friction of the sliding interface (:class:`mechanics.effects.sliding.Sliding`, whose
module docstring states the model): the friction law with its rounded stick-slip corner, the
friction bound from the normal force, and the friction anchors (:class:`_FrictionAnchors`, a
mixin of the effect): the elastic slip from them, the friction state, their update at a
converged state, the friction force and tangent, and the stick stiffness the solver adds
where the tangent is singular."""

from __future__ import annotations

import logging

import numpy as np

from mechanics.effects._contact import closest_facets, facet_normals, node_dofs, summed_blocks

log = logging.getLogger("mechanics.effects.sliding")


def friction_law(r: np.ndarray, b: np.ndarray, sigma: float):
    """Magnitude of the friction force from the trial force r and the bound b (mN).

    sigma = 0: Coulomb return mapping, phi = min(r, b). sigma > 0: the corner is rounded by
    a parabola between r = (1 - sigma) b and (1 + sigma) b,
    phi = b - (r - (1 + sigma) b)^2 / (4 sigma b), continuous with its slope; below, phi = r
    exactly (stick: a linear spring), above, phi = b exactly (Coulomb slip). Exact on both
    branches is what makes the anchor update of :meth:`Sliding.begin_step` leave the force
    of a converged state unchanged (a law below r everywhere relaxed every friction force
    at every load step).

    Returns phi, d phi / dr, phi / r (its limit at r = 0) and d phi / db.
    """
    if sigma == 0.0:
        stick = r <= b
        phi = np.minimum(r, b)
        return (phi, stick.astype(float),
                np.where(stick, 1.0, b / np.where(r > 0, r, 1.0)), (~stick).astype(float))
    hi = (1.0 + sigma) * b
    stick = r <= (1.0 - sigma) * b
    slip = r >= hi
    den = np.where(b > 0, 4.0 * sigma * b, 1.0)
    d = r - hi  # < 0 in the blend
    phi = np.where(stick, r, np.where(slip, b, b - d * d / den))
    phi_r = np.where(stick, 1.0, np.where(slip, 0.0, -2.0 * d / den))
    phi_b = np.where(stick, 0.0, np.where(slip, 1.0,
                                          1.0 + 2.0 * (1.0 + sigma) * d / den
                                          + d * d / (den * np.where(b > 0, b, 1.0))))
    # r = b = 0 (the first iterate of a solve): no friction in the tangent, so the normal
    # pressure builds up first (measured: a stick tangent there makes supine solves stagnate)
    phi_over_r = np.where(r > 0, phi / np.where(r > 0, r, 1.0), np.where(b > 0, 1.0, 0.0))
    phi_r = np.where(b > 0, phi_r, 0.0)
    return phi, phi_r, phi_over_r, phi_b


def slip_limit(b: np.ndarray, sigma: float) -> np.ndarray:
    """(P,) trial force (mN) above which :func:`friction_law` is in full slip, (1 + sigma) b."""
    return (1.0 + sigma) * b


def friction_bound(fN: np.ndarray, w: np.ndarray, k: float, p_eps: float):
    """Friction bound b (P,) mN from the normal force fN (P,) mN (< 0 in compression) and
    its derivative d b / d fN.

    p_eps = 0: Coulomb, b = k max(-fN, 0), kinked at fN = 0. p_eps > 0 (kPa): a smooth
    ramp, b = k (-fN + sqrt(fN^2 + (w p_eps)^2)) / 2, which differs from the Coulomb bound
    by at most k w p_eps / 2 (at fN = 0) and by k w p_eps^2 / (4 p) at a pressure p, so it
    changes nothing where the pressure is well above p_eps but gives Newton a continuous
    tangent where the no-separation interface passes from compression to tension.
    """
    if p_eps == 0.0:
        comp = fN < 0.0
        return k * np.where(comp, -fN, 0.0), np.where(comp, -k, 0.0)
    h = np.sqrt(fN**2 + (w * p_eps) ** 2)
    return 0.5 * k * (h - fN), 0.5 * k * (fN / h - 1.0)


def _slip_map(xi: np.ndarray, C: np.ndarray) -> np.ndarray:
    """(P, 3, L) d(x_p - x_anchor)/d(local dofs): the contact point minus the anchor at
    barycentric coordinates ``xi`` (P, 3) of its master triangle, through ``C`` (P, 12, L)."""
    B = np.zeros((len(xi), 3, 12))
    B[:, :, 0:3] = np.eye(3)
    for a in range(3):
        B[:, :, 3 + 3 * a:6 + 3 * a] = -xi[:, a, None, None] * np.eye(3)
    return B @ C


class _FrictionAnchors:
    """The friction anchors of :class:`mechanics.effects.sliding.Sliding` and what follows
    from them. Reads the effect's contact points, normal part (``_normal``), options and
    ``values``; keeps ``anchor_facet``, ``anchor_bary`` and ``anchor_normal``."""

    def _trial(self, X, x):
        """Elastic slip s (P, 3) mm from the anchors, trial force (P, 3) mN, anchor nodes."""
        nodes = self.master[self.anchor_facet]
        xa = np.einsum("sa,sai->si", self.anchor_bary, x[nodes])
        n0 = self.anchor_normal
        r = self.contact_points(x) - xa
        s = r - np.einsum("si,si->s", r, n0)[:, None] * n0
        return s, self.values["tangential_penalty"] * self.weights(X)[:, None] * s, nodes

    def tangential_state(self, X: np.ndarray, x: np.ndarray):
        """Friction state of the contact points at x against the current anchors.

        Returns ``slip`` (P, 3) mm (elastic slip since the last anchor update), ``force``
        (P, 3) mN (tangential force carried) and ``stick`` (P,) bool.
        """
        if self.anchor_facet is None:
            self._set_anchors(x, self.contact_points(x))
        s, t, _ = self._trial(X, x)
        _, _, _, _, fN, w, on = self._normal(X, x, hessian=False)
        bound = self._bound(fN, w, on)[0]
        r = np.linalg.norm(t, axis=1)
        _, _, phi_over_r, _ = friction_law(r, bound, self.values["smoothing"])
        return s, t * phi_over_r[:, None], r <= bound

    def _bound(self, fN, w, on):
        """Friction bound and its derivative by fN, zero at released points (``on`` 0)."""
        b, db = friction_bound(fN, w, self.values["friction"], self.values["pressure_smoothing"])
        return b * on, db * on

    def _set_anchors(self, x, points):
        facet, bary, _ = closest_facets(points, x, self.master, k=self.k_search,
                                        normals=self.point_normals(x))
        self.anchor_facet, self.anchor_bary = facet, bary
        self.anchor_normal = facet_normals(x, self.master)[facet]

    def _update_anchors(self, X, x):
        """At a converged state x: set the anchors (first step), or move those of slipping
        points to the full-slip limit; freeze every anchor facet's normal."""
        xp = self.contact_points(x)
        if self.anchor_facet is None:
            self._set_anchors(x, xp)
            return
        _, _, _, _, fN, w, on = self._normal(X, x, hessian=False)
        released = int(np.sum(on == 0.0))
        if released:
            log.info("sliding: %d of %d contact points are past the edge of the muscle surface "
                     "and carry no contact force", released, len(on))
        s, t, _ = self._trial(X, x)
        bound = self._bound(fN, w, on)[0]
        r = np.linalg.norm(t, axis=1)
        hi = slip_limit(bound, self.values["smoothing"])
        slip = r > hi
        if np.any(slip):
            # Move the anchor of a slipping point so that its elastic slip is the full-slip
            # limit, |t_new| = (1 + sigma) b (the rest of the slip is permanent): its force
            # stays Coulomb's b, so the converged state stays in equilibrium.
            keep = np.where(slip, hi / np.where(slip, r, 1.0), 1.0)
            old = self.anchor_facet.copy(), self.anchor_bary.copy()
            self._set_anchors(x, xp - keep[:, None] * s)
            self.anchor_facet = np.where(slip, self.anchor_facet, old[0])
            self.anchor_bary = np.where(slip[:, None], self.anchor_bary, old[1])
        # Freeze the normal of every anchor facet at the converged configuration.
        self.anchor_normal = facet_normals(x, self.master)[self.anchor_facet]

    def regularization(self, X: np.ndarray, x: np.ndarray):
        """COO triplets (dof numbering, mN/mm) of the stick stiffness eps_T w B^T P0 B of the
        contact points whose friction bound is zero (no compressive pressure).

        Not part of the tangent: the solver adds it, scaled down with the residual, only when
        the tangent is singular (:class:`mechanics.solver.SolverOptions` ``singular_shift``).
        At zero contact pressure (the first iterate of a solve) friction gives no tangential
        stiffness and the sliding modes are free; this stiffness makes the first Newton
        correction a sticking one while the pressure builds. It never enters the residual,
        so the equilibrium is unchanged.
        """
        none = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        if self.values["friction"] == 0.0:
            return none
        if self.anchor_facet is None:
            self._set_anchors(x, self.contact_points(x))
        _, _, _, _, fN, w, on = self._normal(X, x, hessian=False)
        free = (self._bound(fN, w, on)[0] <= 0.0) & (on > 0.0)
        if not free.any():
            return none
        mnodes = self.master[self.anchor_facet[free]]
        B = _slip_map(self.anchor_bary[free], self._C[free])
        n0 = self.anchor_normal[free]
        P0 = np.eye(3) - np.einsum("si,sj->sij", n0, n0)
        epsT = self.values["tangential_penalty"] * w[free]
        K = epsT[:, None, None] * (B.transpose(0, 2, 1) @ P0 @ B)
        dof = node_dofs(np.concatenate([self.sconn[free], mnodes], axis=1))
        return summed_blocks(dof, dof, K, 3 * len(x))

    def _friction_terms(self, X, x, dgf, dofN, fN, w, on):
        """The friction part of :meth:`Sliding.contribute`: the anchors' dofs ``dofT`` (P, L),
        the friction force on them ``fT`` (P, L) mN, and the tangent blocks as (points, rows,
        cols, K): the friction law along the slip (all points), and where the bound follows
        the normal force, its coupling to the normal dofs ``dofN`` (``dgf``: the gap's
        gradient); the points as index arrays."""
        eps = self.values["penalty"]
        if self.anchor_facet is None:  # contribute() before any begin_step
            self._set_anchors(x, self.contact_points(x))
        s, t, mnodes = self._trial(X, x)
        B = _slip_map(self.anchor_bary, self._C)  # d(x_p - x_anchor)/d(local dofs)
        n0 = self.anchor_normal
        P0 = np.eye(3) - np.einsum("si,sj->sij", n0, n0)
        epsT = self.values["tangential_penalty"] * w
        dtt = epsT[:, None, None] * (P0 @ B)  # d t_trial / dq
        bound, bound_f = self._bound(fN, w, on)
        r = np.linalg.norm(t, axis=1)
        sh = t / np.where(r > 0, r, 1.0)[:, None]
        phi, phi_r, phi_over_r, phi_b = friction_law(r, bound, self.values["smoothing"])
        dofT = node_dofs(np.concatenate([self.sconn, mnodes], axis=1))
        force_t = phi[:, None] * sh
        ss = np.einsum("si,sj->sij", sh, sh)
        Dt = phi_r[:, None, None] * ss + phi_over_r[:, None, None] * (np.eye(3) - ss)
        blocks = [(np.arange(len(w)), dofT, dofT, B.transpose(0, 2, 1) @ (Dt @ dtt))]
        comp = np.flatnonzero((bound_f != 0.0) & (phi_b != 0.0))
        if len(comp):
            db = (bound_f * eps * w)[:, None] * dgf  # d bound / dq on the normal dofs
            dt_n = phi_b[:, None, None] * np.einsum("si,sj->sij", sh, db)
            blocks.append((comp, dofT[comp], dofN[comp],
                           B[comp].transpose(0, 2, 1) @ dt_n[comp]))
        fT = np.einsum("sij,si->sj", B, force_t)  # (P, L) on the anchor's local dofs
        return dofT, fT, blocks
