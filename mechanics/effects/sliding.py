"""Sliding breast-muscle contact: no separation, Coulomb friction, large sliding.

Mesh layout (see :func:`mechanics.effects._interface.split_interface`): the interface nodes
are duplicated; face set ``interface`` holds the breast-side triangles (slave surface) and
``interface_muscle`` the muscle-side triangles (master surface), both oriented with the
normal from muscle into breast, on disjoint node sets. The two sides may be non-matching.

Contact points: 3 quadrature points per slave triangle (option ``points``: 1, 3, 7, or 0 for
one point per slave node, classic node-to-surface). Each point carries the reference area
w_p it stands for (mm^2).

Normal (penalty or augmented Lagrangian): every point is paired with its closest master
triangle, searched again at every evaluation (large sliding); its gap g is the signed
distance to that triangle's plane. The energy w_p (eps_N g^2 / 2 + lambda g) acts in both
directions, so the interface transmits pressure and tension and never separates; the
tangent is exact (gap Hessian included).

Edge of the muscle surface: the surface extends past its boundary edges by an extension zone
(option ``edge_extension``, in heights of the edge triangle, default 1), in which a point is
held by the extended plane of the edge triangle, standing in for the chest wall that goes on
past the muscle (measured: supine, 20k-tet phantom, 59 points end 0.17 heights past the
lateral slab edges; releasing them with a zone of 0.1 took the solve from 11 to 40 Newton
iterations). A point whose projection onto its closest triangle's plane falls further out
across a boundary edge (:func:`mechanics.effects._contact.past_boundary`) has slid off the
muscle (before, the whole extended plane held it, however far out) and is released: no
normal or friction force and no stiffness (its friction anchor is kept for when it slides
back).
:meth:`Sliding.released` lists them and :meth:`Sliding.begin_step` logs how many there are at
each converged state (logger ``mechanics.effects.sliding``, INFO).

Tangential (Coulomb, k = ``friction``): at the start of each load step every point keeps an
anchor, a material point of the master surface (facet, barycentric coordinates), and that
facet's normal n0. The elastic slip s = (I - n0 n0^T)(x_p - x_anchor) gives the trial force
t = eps_T w_p s (eps_T = ``tangential_penalty``, default 1 kPa/mm: the elastic slip while
sticking is k p / eps_T, 0.05 mm at 0.5 kPa, negligible against the mm-scale sliding; a
stiffer stick spring against 0.1-4 kPa tissue makes the stick/slip transition far narrower
than a Newton step and friction solves cycle: measured on the 3.5k-tet breast-like model,
supine at breast 0.1 / skin 20 / fascia 80 kPa converges with 1, not with 10 or 100 kPa/mm,
as the paper adapted ANSYS's tangential stiffness per case), capped at k times the
compressive normal force (zero in tension):
|t| <= k max(-f_N, 0) (return mapping), with the stick-slip corner rounded over a width
``smoothing`` (default 0.1) of the bound (:func:`friction_law`; the full-slip force stays
Coulomb's). The exact corner (smoothing 0) makes Newton stagnate, at any load since Coulomb
is scale-free: stick/slip states cycle between iterations (measured: supine breast-like model,
3.5k tets, no step converged even at load ~1/4000). An optional rounded bound at zero
pressure (``pressure_smoothing``, kPa, :func:`friction_bound`) is off by default. At the next
step a slipping point's anchor moves so that its trial force is the full-slip limit
(1 + smoothing) b: the carried force stays Coulomb's and a converged state stays in
equilibrium; the update happens once per converged state (cut-backs repeat it). The
tangent is exact for the frozen anchor and n0; it is unsymmetric while slipping (the effect
then sets ``symmetric = False``).
State (anchors, multipliers) is reset when a step starts from x == X (a new solve).

Zero pressure: where the friction bound is zero (no compression: the first iterate of every
solve, whose gaps are all zero) friction adds no tangential stiffness, so the sliding modes of
a breast held only by friction are free and the tangent is singular. :meth:`Sliding.regularization`
offers the stick stiffness of those points; the solver adds it to the Newton matrix (never the
residual) for the first correction from rest and whenever the tangent is singular, scaled by
the relative residual (``SolverOptions.singular_shift``), so the first correction sticks while
the pressure builds and the equilibrium is unchanged.
"""

from __future__ import annotations

import logging

import numpy as np

from mechanics.effects._contact import (
    boundary_edges,
    closest_facets,
    facet_normals,
    nodal_areas,
    node_dofs,
    past_boundary,
    signed_gap,
    summed_blocks,
)
from mechanics.effects.base import Contribution, Effect, Option, Param, Variant, register_effect

log = logging.getLogger("mechanics.effects.sliding")

METHODS = ("penalty", "augmented")
#: Triangles whose normals differ by more than this angle (cos) make a crease (0.5 degree).
HOLD_COS = float(np.cos(np.radians(0.5)))

#: Quadrature rules on the slave triangles: barycentric points and weights (sum 1).
_A1, _B1 = 0.0597158717897698, 0.4701420641051151
_A2, _B2 = 0.7974269853530873, 0.1012865073234563
RULES = {
    1: (np.full((1, 3), 1 / 3), np.ones(1)),
    3: (np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]]),
        np.full(3, 1 / 3)),
    7: (np.array([[1 / 3, 1 / 3, 1 / 3], [_A1, _B1, _B1], [_B1, _A1, _B1], [_B1, _B1, _A1],
                  [_A2, _B2, _B2], [_B2, _A2, _B2], [_B2, _B2, _A2]]),
        np.array([0.225] + [0.1323941527885062] * 3 + [0.1259391805448271] * 3)),
}


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


class _InterfaceContact(Effect):
    """Shared set-up of the split-interface effects: slave faces, master faces."""

    requires = ("face_sets:interface", "face_sets:interface_muscle")

    def _setup(self):
        mesh = self.mesh
        self.slave_faces = np.asarray(mesh.face_sets["interface"], np.int64)
        self.master = np.asarray(mesh.face_sets["interface_muscle"], np.int64)
        self.slaves = np.unique(self.slave_faces)
        if np.intersect1d(self.slaves, np.unique(self.master)).size:
            raise ValueError(
                f"effect {self.name!r}: the 'interface' and 'interface_muscle' face sets share "
                "nodes; split the interface first (mechanics.effects._interface."
                "split_interface)")


@register_effect
class Sliding(_InterfaceContact):
    """No-separation breast-muscle contact with Coulomb friction (see the module docstring).

    Options: ``method`` "penalty" (default) or "augmented" (the normal multipliers are
    updated, Uzawa-style, at the start of every load step); ``points`` 0 (node-to-surface:
    one contact point per slave node) or 1, 3, 7 quadrature points per slave triangle
    (default 3: Gauss-point-to-surface, which passes the non-matching patch test);
    ``search_candidates`` (int, 8); ``edge_extension`` (float >= 0, 1.0: how far the muscle
    surface extends past its boundary edges, in heights of the edge triangle);
    ``hold_flipping`` (bool, True): a point whose pairing flips back, within one solver step,
    to the muscle triangle it had two evaluations before, across a crease (normals more than
    0.5 degree apart), keeps its current triangle until the step ends. The faceted muscle
    surface makes the normal force jump when a point crosses a creased triangle edge (across
    a flat edge it is continuous); points near such edges flipped back and
    forth and Newton stalled (measured: 20k-tet meshed phantom, tilted, stalled at load 0.81
    after 94 s). Points that do not flip are paired afresh at every evaluation, so a solve
    without flips is unchanged (freezing every pairing after a fixed number of evaluations
    instead made converged states depend on the path, and a fit could no longer reproduce
    its own synthetic measurements); ``path_steps`` (int, 1): the loading path of the
    friction history, see below. The converged state is in equilibrium for its
    pairing; in that tilted solve (36 iterations at the time) 3 of 3822 points ended held, and their
    gaps to the held and to the closest triangle differed by at most 0.041 mm, the size of
    the penalty gaps themselves (up to 0.061 mm).

    Loading path: friction makes the equilibrium depend on the path. The friction anchors
    (and the augmented multipliers) are updated only at the path points, loads k /
    ``path_steps``, where the solver always converges a step (:meth:`path_points`); the
    solver's own sub-steps (cut-backs, growth) leave them alone. The solution is then a
    function of the model and ``path_steps`` alone, not of how the Newton steps fell: a fit's
    parameter perturbations, a truth phantom and its model follow the same path (exactly
    without held pairings; a held pairing ends its solver step in equilibrium for the held
    triangle, which left up to 0.05 mm of step-dependence on the tilted two-mound model;
    path 1 against 4 differs by 0.13 mm there, 0.19 mm on the 20k-tet phantom). Before,
    anchors moved at every converged step, and a change in the stagnation cut-back that
    solved a tilted two-mound model in one step instead of two doubled its fitted tilted error
    (0.17 -> 0.34 mm) and moved the diagnosis from the truth's Gent fascia to friction.
    The default, 1, is the proportional-loading solution: slip measured from the stress-free
    state.
    """

    name = "sliding"
    doc = "breast slides on the muscle with Coulomb friction and never separates from it"
    params = (
        Param("friction", "-", 0.1, 0.0, 2.0, "Coulomb friction coefficient k"),
        Param("penalty", "kPa/mm", 100.0, 1e-3, 1e7, "normal penalty stiffness per area",
              numerical=True),
        Param("tangential_penalty", "kPa/mm", 1.0, 1e-3, 1e7,
              "tangential (stick) penalty stiffness per area", numerical=True),
        Param("smoothing", "-", 0.1, 0.0, 1.0,
              "width of the rounded stick-slip transition, fraction of the friction bound",
              numerical=True),
        Param("pressure_smoothing", "kPa", 0.0, 0.0, 10.0,
              "width of the rounded friction bound at zero contact pressure", numerical=True),
    )
    option_specs = (
        Option("method", "penalty", "normal enforcement", METHODS, (str,)),
        Option("search_candidates", 8, "muscle triangles searched per point", types=(int,)),
        Option("points", 3, "contact points per slave triangle (0: nodes)", types=(int,)),
        Option("edge_extension", 1.0, "extension of the muscle surface past its edges",
               types=(int, float)),
        Option("hold_flipping", True, "hold pairings that flip back across a crease",
               types=(bool,)),
        Option("path_steps", 1, "load steps of the friction history", types=(int,)),
    )
    split_interface = True
    excludes = ("tied",)

    @classmethod
    def variants(cls, view):
        """Sliding switched on (an on/off change), replacing the effects it excludes."""
        change = {cls.name: {}, **{view.keys[n]: None for n in cls.excluded_by(view.used)}}
        return [Variant(cls.name, cls.doc or cls.name, change)]

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        opts = self.options
        self.method = str(opts["method"])
        self.k_search = int(opts["search_candidates"])
        self.points = int(opts["points"])
        self.edge_extension = float(opts["edge_extension"])
        self.hold_flipping = bool(opts["hold_flipping"])
        self.path_steps = int(opts["path_steps"])
        if self.path_steps < 1:
            raise ValueError(f"effect 'sliding': path_steps must be >= 1, got {self.path_steps}")
        if not self.edge_extension >= 0.0:
            raise ValueError("effect 'sliding': edge_extension must be >= 0")
        if self.points not in (0, *RULES):
            raise ValueError(f"effect 'sliding': points must be 0, 1, 3 or 7, got {self.points}")
        self._setup()
        self._boundary_edges = boundary_edges(self.master)
        if self.points == 0:
            self.sconn = self.slaves[:, None]
            self.sN = np.ones((len(self.slaves), 1))
        else:
            eta, _ = RULES[self.points]
            self.sconn = np.repeat(self.slave_faces, len(eta), axis=0)
            self.sN = np.tile(eta, (len(self.slave_faces), 1))
        P, m = self.sN.shape
        # C maps the local dofs (m slave nodes, 3 master nodes) to (x_p, x1, x2, x3).
        C = np.zeros((P, 12, 3 * m + 9))
        for b in range(m):
            C[:, 0:3, 3 * b:3 * b + 3] = self.sN[:, b, None, None] * np.eye(3)
        C[:, 3:, 3 * m:] = np.eye(9)
        self._C = C
        self._w = None
        self.symmetric = self.values["friction"] == 0.0
        self.multiplier = np.zeros(P)  # mN, augmented Lagrangian normal force
        self.anchor_facet: np.ndarray | None = None
        self.anchor_bary = np.zeros((P, 3))
        self.anchor_normal = np.zeros((P, 3))
        self._begun = None  # (x, state before the update) of the last begin_step
        self._history = self._held = None  # pairings of the last two evaluations; held

    def weights(self, X: np.ndarray) -> np.ndarray:
        """(P,) reference area of each contact point, mm^2."""
        if self._w is None or self._w[0] is not X:
            if self.points == 0:
                w = nodal_areas(X, self.slave_faces, self.slaves)
            else:
                Xt = X[self.slave_faces]
                A = 0.5 * np.linalg.norm(np.cross(Xt[:, 1] - Xt[:, 0], Xt[:, 2] - Xt[:, 0]),
                                         axis=1)
                w = np.outer(A, RULES[self.points][1]).ravel()
            self._w = (X, w)
        return self._w[1]

    def contact_points(self, x: np.ndarray) -> np.ndarray:
        """(P, 3) current positions of the contact points on the breast side, mm."""
        return np.einsum("pm,pmi->pi", self.sN, x[self.sconn])

    def point_normals(self, x: np.ndarray) -> np.ndarray | None:
        """(P, 3) unit normals of the breast-side triangles the contact points lie on (the
        pairing ignores muscle triangles facing away from them); None for node points."""
        if self.points == 0:
            return None
        xt = x[self.sconn]
        n = np.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]

    # -- normal part -------------------------------------------------------------------
    def _normal(self, X, x, *, hessian=True):
        """Pairing, gap (with derivatives), normal force fN (P,) mN, weights w (P,) mm^2 and
        ``on`` (P,) 1.0 for points over the muscle surface, 0.0 for released ones.

        ``hessian`` (the residual and tangent of :meth:`contribute`): a point whose pairing
        flips back to the triangle it had two evaluations before keeps its current triangle
        for the rest of the load step (see the class docstring)."""
        xp = self.contact_points(x)
        facet, _, _ = closest_facets(xp, x, self.master, k=self.k_search,
                                     normals=self.point_normals(x))
        if hessian and self.hold_flipping:
            if self._held is None:
                self._held = np.full(len(facet), -1)
            if self._history is not None and self._history[1] is not None:
                prev1, prev2 = self._history
                flip = (facet == prev2) & (facet != prev1) & (self._held < 0)
                if flip.any():  # across a crease only: between coplanar triangles the
                    n = facet_normals(x, self.master)  # force is continuous at the edge
                    crease = np.einsum("pi,pi->p", n[facet], n[prev1]) < HOLD_COS
                    flip &= crease
                self._held[flip] = prev1[flip]
            facet = np.where(self._held >= 0, self._held, facet)
            self._history = (facet, None if self._history is None else self._history[0])
        xm = x[self.master[facet]]
        nodes = np.concatenate([self.sconn, self.master[facet]], axis=1)
        g, dg, d2g = signed_gap(xp, xm, hessian=hessian)
        w = self.weights(X)
        on = 1.0 - past_boundary(xp, xm, self._boundary_edges[facet], tol=self.edge_extension)
        # mN, < 0 in compression; zero off the muscle surface
        fN = on * (self.values["penalty"] * w * g + self.multiplier)
        return nodes, g, dg, d2g, fN, w, on

    def released(self, X: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(P,) bool: contact points past the edge of the muscle surface, which carry no
        contact force (see :func:`past_boundary`)."""
        return self._normal(X, x, hessian=False)[6] == 0.0

    def gaps(self, X: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(P,) signed normal gaps at the contact points, mm (positive: separated)."""
        return self._normal(X, x, hessian=False)[1]

    def pressure(self, X: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(P,) contact pressure at the contact points, kPa (positive in compression)."""
        _, _, _, _, fN, w, _ = self._normal(X, x, hessian=False)
        return -fN / w

    def nodal_pressure(self, X: np.ndarray, x: np.ndarray) -> np.ndarray:
        """(S,) contact pressure lumped to the slave nodes ``self.slaves``, kPa: the normal
        contact force each node receives over its tributary area (compression positive)."""
        fN = self._normal(X, x, hessian=False)[4]
        f = np.bincount(self.sconn.ravel(), weights=(self.sN * -fN[:, None]).ravel(),
                        minlength=len(x))
        return f[self.slaves] / nodal_areas(X, self.slave_faces, self.slaves)

    # -- friction anchors --------------------------------------------------------------
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

    def to_febio(self, feb):
        """FEBio ``sliding-elastic`` contact between the breast side (primary, faces flipped so
        that the normal points out of the breast) and the muscle side: penalty per area
        without automatic scaling (or augmented Lagrangian), Coulomb ``fric_coeff``; without
        friction ``tension`` is on (no separation, as ours); FEBio cannot combine it with
        friction, so with friction its interface may separate. An approximation, refused
        unless allowed: FEBio's contact points are its own (not our quadrature), its surface
        ends at the muscle's boundary edges (no extension zone), and its friction sticks with
        the normal penalty, has a sharp stick-slip corner and follows FEBio's time steps (ours:
        ``tangential_penalty``, ``smoothing``, ``path_steps``)."""
        friction = self.values["friction"] > 0
        why = ("FEBio's sliding-elastic differs in contact points, surface edges"
               + (", stick stiffness, stick-slip corner and friction path, and it may "
                  "separate (FEBio cannot combine tension with friction)" if friction else ""))
        feb.approximate(f"effect {self.name!r}", why)
        owner = f"effect {self.name!r}"
        primary = feb.surface(f"{self.name}_breast", self.slave_faces[:, ::-1], owner=owner)
        secondary = feb.surface(f"{self.name}_muscle", self.master, owner=owner)
        pair = feb.surface_pair(self.name, primary, secondary)
        feb.contact("sliding-elastic", pair, {
            "laugon": "AUGLAG" if self.method == "augmented" else "PENALTY",
            "penalty": self.values["penalty"], "auto_penalty": "0", "two_pass": "0",
            "tension": "0" if friction else "1", "symmetric_stiffness": "0" if friction else "1",
            "fric_coeff": self.values["friction"], "tolerance": 0.1, "search_tol": 0.01})

    def path_points(self) -> tuple[float, ...]:
        return tuple(k / self.path_steps for k in range(1, self.path_steps))

    def begin_step(self, X, x, load=None):
        self._history = self._held = None
        if np.array_equal(x, X):  # first step of a new solve: forget the last solve's state
            self.reset()
        elif load is not None and abs(load * self.path_steps
                                      - round(load * self.path_steps)) > 1e-9:
            return  # between path points the history stays (cut-back sub-steps)
        # A cut-back starts the step again from the same converged x: update from the state
        # the first call at this x started from, so that the update happens once per
        # converged state (each repeated update relaxed the friction forces further, and the
        # augmented multipliers grew by the penalty force at every retry).
        if self._begun is not None and np.array_equal(self._begun[0], x):
            (self.multiplier, self.anchor_facet, self.anchor_bary,
             self.anchor_normal) = (None if a is None else a.copy() for a in self._begun[1])
        else:
            self._begun = (x.copy(), tuple(None if a is None else a.copy() for a in (
                self.multiplier, self.anchor_facet, self.anchor_bary, self.anchor_normal)))
        if self.method == "augmented":
            self.multiplier = self._normal(X, x, hessian=False)[4].copy()
        if self.values["friction"] == 0.0:
            return
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

    def reset(self) -> None:
        """Forget friction anchors and multipliers (start of a new solve from scratch)."""
        self.anchor_facet = None
        self.multiplier = np.zeros(len(self.sN))
        self._begun = None

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
        xi = self.anchor_bary[free]
        C = self._C[free]
        B = np.zeros((int(free.sum()), 3, 12))
        B[:, :, 0:3] = np.eye(3)
        for a in range(3):
            B[:, :, 3 + 3 * a:6 + 3 * a] = -xi[:, a, None, None] * np.eye(3)
        B = B @ C
        n0 = self.anchor_normal[free]
        P0 = np.eye(3) - np.einsum("si,sj->sij", n0, n0)
        epsT = self.values["tangential_penalty"] * w[free]
        K = epsT[:, None, None] * (B.transpose(0, 2, 1) @ P0 @ B)
        dof = node_dofs(np.concatenate([self.sconn[free], mnodes], axis=1))
        return summed_blocks(dof, dof, K, 3 * len(x))

    # -- residual and tangent ----------------------------------------------------------
    def contribute(self, X, x, load):
        n = len(x)
        C = self._C
        nodes, g, dg, d2g, fN, w, on = self._normal(X, x)
        eps = self.values["penalty"]
        dgf = (dg[:, None, :] @ C)[:, 0]  # gradient on the local dofs
        K = (eps * w * on)[:, None, None] * np.einsum("pi,pj->pij", dgf, dgf) \
            + fN[:, None, None] * (C.transpose(0, 2, 1) @ d2g @ C)
        dofN = node_dofs(nodes)
        fq = fN[:, None] * dgf  # (P, L) force on the local dofs
        rows, cols, Ks = [dofN], [dofN], [K]
        k_fric = self.values["friction"]
        if k_fric > 0.0:
            if self.anchor_facet is None:  # contribute() before any begin_step
                self._set_anchors(x, self.contact_points(x))
            s, t, mnodes = self._trial(X, x)
            xi = self.anchor_bary
            P = len(s)
            B = np.zeros((P, 3, 12))
            B[:, :, 0:3] = np.eye(3)
            for a in range(3):
                B[:, :, 3 + 3 * a:6 + 3 * a] = -xi[:, a, None, None] * np.eye(3)
            B = B @ C  # d(x_p - x_anchor)/d(local dofs)
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
            rows.append(dofT)
            cols.append(dofT)
            Ks.append(B.transpose(0, 2, 1) @ (Dt @ dtt))
            comp = (bound_f != 0.0) & (phi_b != 0.0)
            if np.any(comp):
                db = (bound_f * eps * w)[:, None] * dgf  # d bound / dq on the normal dofs
                dt_n = phi_b[:, None, None] * np.einsum("si,sj->sij", sh, db)
                rows.append(dofT[comp])
                cols.append(dofN[comp])
                Ks.append(B[comp].transpose(0, 2, 1) @ dt_n[comp])
            fT = np.einsum("sij,si->sj", B, force_t)  # (P, L) on the anchor's local dofs
            force = np.bincount(np.concatenate([dofN.ravel(), dofT.ravel()]),
                                weights=np.concatenate([fq.ravel(), fT.ravel()]),
                                minlength=3 * n)
        else:
            force = np.bincount(dofN.ravel(), weights=fq.ravel(), minlength=3 * n)
        # one block kind per row of (rows, cols, Ks), all (S, L, L): summed in one product
        rows, cols, vals = summed_blocks(np.concatenate(rows), np.concatenate(cols),
                                         np.concatenate(Ks), 3 * n)
        return Contribution(force.reshape(n, 3), rows, cols, vals)
