"""Hyperelastic membrane triangles sharing nodes with the solid (skin, fascia).

Each triangle of a face set is a thin incompressible sheet of reference thickness H (mm).
With the in-plane right Cauchy-Green tensor C (2x2) and the thickness stretch fixed by
incompressibility (lambda_3^2 = 1 / det C), the first invariant is I1 = tr C + 1 / det C and

    Neo-Hookean: W = mu/2 (I1 - 3)
    Gent:        W = -mu Jm/2 ln(1 - (I1 - 3)/Jm)

per unit reference volume (kPa), mu = E / (2 (1 + nu)) with the project's nu = 0.49.
The energy of a triangle is H A0 W (A0 reference area, mm^2), so forces are mN.

Wrinkling (option ``wrinkling="tension_field"``, the skin's default): a membrane with a
free side has no bending stiffness, so it cannot carry compression; under it, it wrinkles.
Tension-field theory replaces W by its relaxed energy (Pipkin 1986, IMA J Appl Math 36:85;
Steigmann 1990, Proc R Soc A 429:141). With c1 >= c2 the eigenvalues of C, the minor
principal stress is compressive when c2 < c1^(-1/2) (narrower than the natural width in
uniaxial tension):

    taut      c2 c1^(1/2) >= 1:        I1 = c1 + c2 + 1 / (c1 c2)
    wrinkled  c1 > 1 > c2 c1^(1/2):    I1 = c1 + 2 c1^(-1/2)  (uniaxial tension along n1)
    slack     c1 <= 1, c2 < 1:         I1 = 3                 (no stress)

The relaxed energy is C1 across the three states. Without it (``wrinkling="none"``) a
compressed membrane has a negative geometric stiffness and the solid under it buckles: the
soft-breast prone points of the paper's search box failed that way. Taut triangles are
unchanged, so inflation and every tensile state agree with the plain law. The fascia keeps
the plain law by default: it lies between the breast, to which it is bonded, and the muscle,
from which it never separates, so it has no room to wrinkle (measured: relaxing it made the
soft-breast tilted solve stagnate at a relative residual of 4e-5; kept plain, it converges).

This module holds the kernel and the shared base class; ``skin`` and ``fascia`` register it
on their face sets.
"""

from __future__ import annotations

import numpy as np

from mechanics.effects.base import Contribution, Effect, Option, Param, Variant, bounds

#: Poisson ratio used to turn E into the shear modulus, as in the paper's bulk law.
NU_MEMBRANE = 0.49
LAWS = ("neo_hookean", "gent")
WRINKLING = ("tension_field", "none")
TAUT_MARGIN = 1e-10
#: Gent limit at which the diagnosis probes a membrane's strain stiffening.
JM_PROBE = 0.5
#: Why a membrane's thickness is not scored on its own.
THICKNESS_UNSCORED = "membrane stiffness depends on E x thickness; E is scored"
#: FEBio's shells stand for a membrane at this fraction of its thickness and this multiple of
#: its modulus (same E H). Measured, FEBio/ours share of the bare sag a 0.5 mm, 10 kPa skin
#: removes on the 20k-tet hemisphere (tip): 1.30 written at H, 1.052 at H/10, 1.025 at H/100,
#: 1.022 at H/1000; max |u_FEBio - u_ours| / max |u| 3.2 %, 1.4 %, 1.3 %, 1.3 %; on the 150k
#: mesh at H/100: 1.015 and 0.67 % (``bench/membrane_vs_febio.py``).
FEBIO_THINNING = 100.0


def membrane_options(wrinkling: str) -> tuple[Option, ...]:
    """The options of a membrane effect whose default wrinkling is ``wrinkling``."""
    return (Option("law", "neo_hookean", "membrane law", LAWS, (str,)),
            Option("wrinkling", wrinkling, "tension-field relaxation or the plain law",
                   WRINKLING, (str,)))


def reference_triangles(X: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shape-function gradients and areas of triangles in their own plane.

    Parameters
    ----------
    X : (N, 3) reference positions, mm
    tri : (T, 3) node indices

    Returns
    -------
    G : (T, 3, 2) gradients of the three linear shape functions along two orthonormal
        in-plane axes, 1/mm (F = x^T G is the 3x2 deformation gradient)
    A0 : (T,) reference areas, mm^2
    """
    Xe = X[tri]
    e1 = Xe[:, 1] - Xe[:, 0]
    e2 = Xe[:, 2] - Xe[:, 0]
    n = np.cross(e1, e2)
    twice = np.linalg.norm(n, axis=1)
    if np.any(twice <= 0.0):
        raise ValueError("membrane: degenerate (zero-area) triangle in the face set")
    t1 = e1 / np.linalg.norm(e1, axis=1)[:, None]
    t2 = np.cross(n / twice[:, None], t1)
    D = np.stack([np.stack([np.einsum("ti,ti->t", e, t) for t in (t1, t2)], axis=1)
                  for e in (e1, e2)], axis=2)  # (T, 2, 2): columns = local edge coordinates
    Dinv = np.linalg.inv(D)
    ref = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
    G = np.einsum("ab,tbc->tac", ref, Dinv)
    return G, 0.5 * twice


def _law_derivatives(I1: np.ndarray, mu: float, law: str, Jm: float):
    """W(I1), dW/dI1, d2W/dI1^2 for the membrane law (kPa)."""
    if law == "neo_hookean":
        return 0.5 * mu * (I1 - 3.0), np.full_like(I1, 0.5 * mu), np.zeros_like(I1)
    s = 1.0 - (I1 - 3.0) / Jm
    s = np.where(s > 0.0, s, np.nan)  # beyond Gent's limit stretch: undefined
    return -0.5 * mu * Jm * np.log(s), 0.5 * mu / s, 0.5 * mu / (Jm * s * s)


def _sym_outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(T, 2, 2) symmetric part of a b^T for (T, 2) vectors."""
    ab = a[:, :, None] * b[:, None, :]
    return 0.5 * (ab + ab.transpose(0, 2, 1))


def _relax(C: np.ndarray, c: np.ndarray, I1: np.ndarray, dI: np.ndarray,
           d2I: np.ndarray | None):
    """Replace I1 and its C-derivatives by the tension-field values where the membrane is
    wrinkled or slack (see the module docstring); taut triangles are returned unchanged.
    ``d2I`` None: no second derivatives (no tangent wanted)."""
    tr = C[:, 0, 0] + C[:, 1, 1]
    disc = np.sqrt(np.maximum(0.25 * (C[:, 0, 0] - C[:, 1, 1]) ** 2 + C[:, 0, 1] ** 2, 0.0))
    c1, c2 = 0.5 * tr + disc, 0.5 * tr - disc
    # Taut first, with a round-off margin: the stress-free state (c1 = c2 = 1) keeps the
    # plain law's stiffness (a compressive stress of 1e-10 mu there is immaterial).
    taut = c2 * np.sqrt(np.maximum(c1, 1.0)) >= 1.0 - TAUT_MARGIN
    slack = ~taut & (c1 <= 1.0)
    wrinkled = ~taut & ~slack  # also collapsed triangles (c <= 0)
    if not np.any(slack | wrinkled):
        return I1, dI, d2I
    I1, dI = I1.copy(), dI.copy()
    I1[slack], dI[slack] = 3.0, 0.0
    if d2I is not None:
        d2I = d2I.copy()
        d2I[slack] = 0.0
    w = np.flatnonzero(wrinkled)
    if len(w):
        Cw, a1, a2 = C[w], c1[w], c2[w]
        # eigenvector n1 of c1: (C01, c1 - C00) or (c1 - C11, C01), the better conditioned
        v1 = np.stack([Cw[:, 0, 1], a1 - Cw[:, 0, 0]], axis=1)
        v2 = np.stack([a1 - Cw[:, 1, 1], Cw[:, 0, 1]], axis=1)
        n1 = np.where((np.einsum("ti,ti->t", v1, v1) >= np.einsum("ti,ti->t", v2, v2))[:, None],
                      v1, v2)
        norm = np.linalg.norm(n1, axis=1)
        n1 = np.where(norm[:, None] > 0.0, n1 / np.where(norm > 0, norm, 1.0)[:, None],
                      np.array([1.0, 0.0]))  # C isotropic: any direction
        n2 = np.stack([-n1[:, 1], n1[:, 0]], axis=1)
        N11, M12 = _sym_outer(n1, n1), _sym_outer(n1, n2)
        g = 1.0 - a1**-1.5  # dI1/dc1 of the uniaxial invariant c1 + 2 c1^(-1/2)
        I1[w] = a1 + 2.0 / np.sqrt(a1)
        dI[w] = g[:, None, None] * N11
        if d2I is None:
            return I1, dI, d2I
        # d2c1/dC2 = 2 M12 x M12 / (c1 - c2) (first-order eigenvalue perturbation)
        d2I[w] = (1.5 * a1**-2.5)[:, None, None, None, None] * np.einsum("tAB,tCD->tABCD",
                                                                           N11, N11) \
            + (2.0 * g / (a1 - a2))[:, None, None, None, None] * np.einsum("tAB,tCD->tABCD",
                                                                            M12, M12)
    return I1, dI, d2I


def membrane_energy_terms(x: np.ndarray, tri: np.ndarray, G: np.ndarray, A0: np.ndarray,
                          H: float | np.ndarray, E: float, *, law: str = "neo_hookean",
                          Jm: float = np.inf, wrinkling: str = "tension_field",
                          tangent: bool = True):
    """Energy, nodal forces and element stiffness of membrane triangles.

    Parameters
    ----------
    x : (N, 3) current positions, mm
    tri, G, A0 : from :func:`reference_triangles`
    H : thickness, mm (scalar or (T,))
    E : Young's modulus, kPa
    law : "neo_hookean" or "gent" (with ``Jm`` = limit of I1 - 3)
    wrinkling : "tension_field" (relaxed energy: no compressive stress) or "none"

    Returns
    -------
    energy : (T,) mN mm
    fe : (T, 3, 3) internal force on each triangle node, mN
    Ke : (T, 9, 9) stiffness d fe / d x in local dof order 3 * a + i, mN/mm (None without
        ``tangent``)
    """
    mu = E / (2.0 * (1.0 + NU_MEMBRANE))
    F = np.einsum("tai,taA->tiA", x[tri], G)  # (T, 3, 2)
    C = np.einsum("tiA,tiB->tAB", F, F)
    c = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    relax = wrinkling == "tension_field"
    if np.any(c <= 0.0) and not relax:
        c = np.where(c > 0.0, c, np.nan)  # collapsed triangle: undefined, solver cuts back
    with np.errstate(divide="ignore", invalid="ignore"):  # c <= 0 only where relaxed away
        Ci = np.empty_like(C)
        Ci[:, 0, 0], Ci[:, 1, 1] = C[:, 1, 1] / c, C[:, 0, 0] / c
        Ci[:, 0, 1] = Ci[:, 1, 0] = -C[:, 0, 1] / c
        I1 = C[:, 0, 0] + C[:, 1, 1] + 1.0 / c
        eye = np.eye(2)
        dI = eye[None] - Ci / c[:, None, None]  # dI1/dC (symmetric)
        # d2I1/dC dC, minor and major symmetric (only for the tangent)
        d2I = None if not tangent else (
            0.5 * (np.einsum("tAC,tBD->tABCD", Ci, Ci) + np.einsum("tAD,tBC->tABCD", Ci, Ci))
            + np.einsum("tAB,tCD->tABCD", Ci, Ci)) / c[:, None, None, None, None]
    if relax:
        I1, dI, d2I = _relax(C, c, I1, dI, d2I)
    W, d1, d2 = _law_derivatives(I1, mu, law, Jm)
    vol = np.broadcast_to(np.asarray(H, float), A0.shape) * A0  # mm^3
    S = d1[:, None, None] * dI  # dW/dC
    # dE/dx_a = 2 V F S G_a
    fe = 2.0 * vol[:, None, None] * (G @ S @ F.transpose(0, 2, 1))
    if not tangent:
        return vol * W, fe, None
    K4 = (d1[:, None, None, None, None] * d2I
          + d2[:, None, None, None, None] * np.einsum("tAB,tCD->tABCD", dI, dI))
    # geometric: 2 V (G_a S G_b) delta_ij; material: 4 V K_ABCD G_aA F_iB G_bC F_jD
    geo = 2.0 * (G @ S @ G.transpose(0, 2, 1))
    T = len(tri)
    FG = np.einsum("taA,tiB->taiAB", G, F).reshape(T, 9, 4)  # G_aA F_iB
    mat = 4.0 * FG @ K4.reshape(T, 4, 4) @ FG.transpose(0, 2, 1)
    Ke = mat.reshape(T, 3, 3, 3, 3) + geo[:, :, None, :, None] * np.eye(3)[None, None, :, None, :]
    Ke = vol[:, None, None, None, None] * Ke
    return vol * W, fe, Ke.reshape(T, 9, 9)


def scatter(n_nodes: int, conn: np.ndarray, fe: np.ndarray, Ke: np.ndarray | None
            ) -> Contribution:
    """Assemble element forces (T, k, 3) and stiffness (T, 3k, 3k) into a Contribution."""
    k = conn.shape[1]
    force = np.zeros((n_nodes, 3))
    np.add.at(force, conn.ravel(), fe.reshape(-1, 3))
    if Ke is None:
        return Contribution(force)
    dofs = (3 * conn[:, :, None] + np.arange(3)).reshape(len(conn), 3 * k)
    rows = np.repeat(dofs, 3 * k, axis=1).ravel()
    cols = np.tile(dofs, (1, 3 * k)).ravel()
    return Contribution(force, rows, cols, Ke.ravel())


class MembraneEffect(Effect):
    """Base of the membrane effects: a face set, a thickness, a modulus and a law.

    Subclasses set ``name``, ``face_set``, ``params`` (``E`` kPa, ``thickness`` mm, ``Jm``)
    and ``option_specs`` (:func:`membrane_options`: ``law`` "neo_hookean" or "gent";
    ``wrinkling`` "tension_field" (no compressive stress) or "none").
    """

    face_set: str = ""
    option_specs = membrane_options("tension_field")

    def __init__(self, mesh, **values):
        super().__init__(mesh, **values)
        self.law = str(self.options["law"])
        self.wrinkling = str(self.options["wrinkling"])
        self.tri = np.asarray(mesh.face_sets[self.face_set], np.int64)
        self._ref = None

    @classmethod
    def inert_params(cls, table):
        """``Jm`` unless the law is Gent."""
        return frozenset() if table.get("law", "neo_hookean") == "gent" else frozenset({"Jm"})

    @classmethod
    def option_variants(cls, key, table, view):
        """Gent strain stiffening of a Neo-Hookean membrane, probed at ``JM_PROBE``."""
        if table.get("law", "neo_hookean") == "gent":
            return []
        jm = next(p for p in cls.params if p.name == "Jm")
        path = f"effects.{key}.Jm"
        return [Variant(f"strain_stiffening:{cls.name}",
                        f"Gent strain stiffening of the {cls.name} membrane",
                        {key: {**table, "law": "gent", "Jm": JM_PROBE}}, {path: bounds(jm)},
                        (0.0, 2.0), start={path: JM_PROBE}, kind="option")]

    def _reference(self, X):
        if self._ref is None or self._ref[0] is not X:
            self._ref = (X, *reference_triangles(X, self.tri))
        return self._ref[1], self._ref[2]

    def energy(self, X: np.ndarray, x: np.ndarray) -> float:
        """Stored energy of the membrane, mN mm."""
        G, A0 = self._reference(X)
        W, _, _ = membrane_energy_terms(x, self.tri, G, A0, self.values["thickness"],
                                        self.values["E"], law=self.law, Jm=self.values["Jm"],
                                        wrinkling=self.wrinkling, tangent=False)
        return float(W.sum())

    def contribute(self, X, x, load):
        G, A0 = self._reference(X)
        _, fe, Ke = membrane_energy_terms(x, self.tri, G, A0, self.values["thickness"],
                                          self.values["E"], law=self.law, Jm=self.values["Jm"],
                                          wrinkling=self.wrinkling)
        return scatter(len(x), self.tri, fe, Ke)

    def to_febio(self, feb):
        """FEBio tri3 shells (``elastic-shell``) on the face set, sharing nodes with the solid,
        with the same law as a nearly incompressible solid (uncoupled Mooney-Rivlin c1 = mu/2
        or Gent G = mu, k = E / (3 (1 - 2 nu)), nu = 0.49) and no weight, written
        :data:`FEBIO_THINNING` times thinner and stiffer than H and E: a membrane's stiffness
        is E H alone, while a shell's bending (E H^3 / 12) vanishes with the thickness at equal
        E H. What remains is FEBio's own: its thickness follows the 3D law instead of exact
        incompressibility, and its tri3 shells keep a transverse shear stiffness (G H) at the
        folds. Tension-field wrinkling has no counterpart (an approximation, refused unless
        allowed)."""
        if self.wrinkling == "tension_field":
            feb.approximate(f"effect {self.name!r}", "tension-field wrinkling (no compressive "
                            "membrane stress) has no FEBio counterpart: the shell carries "
                            "compression")
        s, H = FEBIO_THINNING, self.values["thickness"]
        E, nu = self.values["E"] * s, NU_MEMBRANE
        mu, k = E / (2.0 * (1.0 + nu)), E / (3.0 * (1.0 - 2.0 * nu))
        if self.law == "gent":
            params = {"density": 0.0, "G": mu, "Jm": self.values["Jm"], "k": k,
                      "pressure_model": "Abaqus"}
            mat = feb.material(self.name, "Gent", params)
        else:
            mat = feb.material(self.name, "Mooney-Rivlin", {
                "density": 0.0, "c1": 0.5 * mu, "c2": 0.0, "k": k, "pressure_model": "Abaqus"})
        feb.shell_domain(self.name, self.tri, mat, H / s, owner=f"effect {self.name!r}")
        feb.note(f"effect {self.name!r}", f"a membrane of E {self.values['E']:g} kPa and "
                 f"thickness {H:g} mm, written as shells {s:g} times thinner and stiffer (same "
                 "E x thickness, so that the shells' bending vanishes)")


#: Locking parameter of the Gent membrane (used only with ``law="gent"``).
JM_MEMBRANE = Param("Jm", "-", 10.0, 0.05, 1e4, "Gent limit of I1 - 3 (law='gent' only)")
