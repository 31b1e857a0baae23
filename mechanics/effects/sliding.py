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

import numpy as np

from mechanics.effects._contact import (
    boundary_edges,
    closest_facets,
    facet_normals,
    nodal_areas,
    node_dofs,
    past_boundary,
    signed_gap_edges,
    summed_blocks,
)
from mechanics.effects._contact_points import RULES, _InterfaceContact
from mechanics.effects._friction import (
    _FrictionAnchors,
    friction_bound,
    friction_law,
    slip_limit,
)
from mechanics.effects.base import Contribution, Option, Param, Variant, register_effect

__all__ = ["HOLD_COS", "METHODS", "RULES", "Sliding", "friction_bound", "friction_law",
           "slip_limit"]

METHODS = ("penalty", "augmented")
#: Triangles whose normals differ by more than this angle (cos) make a crease (0.5 degree).
HOLD_COS = float(np.cos(np.radians(0.5)))


@register_effect
class Sliding(_FrictionAnchors, _InterfaceContact):
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
        self._setup_points()
        P = len(self.sN)
        self.symmetric = self.values["friction"] == 0.0
        self.multiplier = np.zeros(P)  # mN, augmented Lagrangian normal force
        self.anchor_facet: np.ndarray | None = None
        self.anchor_bary = np.zeros((P, 3))
        self.anchor_normal = np.zeros((P, 3))
        self._begun = None  # (x, state before the update) of the last begin_step
        self._history = self._held = None  # pairings of the last two evaluations; held

    # -- normal part -------------------------------------------------------------------
    def _normal(self, X, x, *, hessian=True):
        """Pairing, gap (with derivatives on (d, e1, e2), see
        :func:`mechanics.effects._contact.signed_gap_edges`), normal force fN (P,) mN,
        weights w (P,) mm^2 and ``on`` (P,) 1.0 for points over the muscle surface, 0.0 for
        released ones.

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
        g, dg, d2g = signed_gap_edges(xp, xm, hessian=hessian)  # on (d, e1, e2)
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
        self._update_anchors(X, x)

    def reset(self) -> None:
        """Forget friction anchors and multipliers (start of a new solve from scratch)."""
        self.anchor_facet = None
        self.multiplier = np.zeros(len(self.sN))
        self._begun = None

    # -- residual and tangent ----------------------------------------------------------
    def contribute(self, X, x, load):
        n = len(x)
        C9 = self._C9
        nodes, g, dg, d2g, fN, w, on = self._normal(X, x)
        eps = self.values["penalty"]
        dgf = (dg[:, None, :] @ C9)[:, 0]  # gradient on the local dofs
        # the 9 x 9 matrix on (d, e1, e2) first, then one product with the map to the dofs
        K9 = (eps * w * on)[:, None, None] * (dg[:, :, None] * dg[:, None, :]) \
            + fN[:, None, None] * d2g
        K = C9.transpose(0, 2, 1) @ K9 @ C9
        dofN = node_dofs(nodes)
        fq = fN[:, None] * dgf  # (P, L) force on the local dofs
        rows, cols, Ks = [dofN], [dofN], [K]
        if self.values["friction"] > 0.0:
            dofT, fT, blocks = self._friction_terms(X, x, dgf, dofN, fN, w, on)
            # a point still on its anchor's triangle has its friction blocks on the dofs of
            # its normal block: added to it, not scattered as blocks of their own (20k-tet
            # phantom, supine: 7.7k blocks of 18 x 18 -> 4k)
            same = np.all(dofT == dofN, axis=1)
            for pts, r, c, k in blocks:
                on_n = same[pts]
                if len(pts) == len(K):  # every point: one pass, no gather and scatter
                    K += np.where(on_n[:, None, None], k, 0.0)
                else:
                    K[pts[on_n]] += k[on_n]
                rows.append(r[~on_n])
                cols.append(c[~on_n])
                Ks.append(k[~on_n])
            force = np.bincount(np.concatenate([dofN.ravel(), dofT.ravel()]),
                                weights=np.concatenate([fq.ravel(), fT.ravel()]),
                                minlength=3 * n)
        else:
            force = np.bincount(dofN.ravel(), weights=fq.ravel(), minlength=3 * n)
        # one block kind per row of (rows, cols, Ks), all (S, L, L): summed in one product
        rows, cols, vals = summed_blocks(np.concatenate(rows), np.concatenate(cols),
                                         np.concatenate(Ks), 3 * n)
        return Contribution(force.reshape(n, 3), rows, cols, vals)
