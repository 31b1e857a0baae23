"""What a bulk material provides to the element kernels, and the registry of materials by name.

Every law is split into an isochoric (deviatoric) part evaluated per element from F, and a
volumetric part ``U(J) = K/2 (J - 1)^2`` (the paper's ``(1/d)(J - 1)^2`` with ``K = 2/d``)
that the formulation evaluates on the averaged nodal volume ratio (locking-free tets).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import numpy as np

from mechanics.effects.base import Param

MATERIALS: dict[str, type[Material]] = {}

#: Shared parameter declarations (E in kPa, nu dimensionless).
YOUNG = Param("E", "kPa", 1.0, 1e-3, 1e6, "Young's modulus (small-strain equivalent)")
POISSON = Param("nu", "-", 0.49, 0.0, 0.4999, "Poisson's ratio")


def register_material(cls: type[Material]) -> type[Material]:
    """Class decorator: make a material available by its ``name``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    if cls.name in MATERIALS and MATERIALS[cls.name] is not cls:
        raise ValueError(f"material name {cls.name!r} registered twice")
    MATERIALS[cls.name] = cls
    return cls


class Material:
    """A bulk material law with validated parameters.

    Subclasses set ``name`` and ``params`` and implement :meth:`deviatoric`.
    ``geometrically_linear`` materials use the small-strain volume change ``1 + tr(eps)``
    instead of ``det F`` in the volumetric term.
    """

    name: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = (YOUNG, POISSON)
    geometrically_linear: ClassVar[bool] = False

    def __init__(self, **values: float):
        known = {p.name: p for p in self.params}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ValueError(
                f"material {self.name!r}: unknown parameter(s) {unknown}; "
                f"allowed: {sorted(known)}"
            )
        self.values = {
            p.name: p.check(values.get(p.name, p.default), f"material {self.name!r}")
            for p in self.params
        }

    @classmethod
    def from_params(cls, params: Mapping[str, float]) -> Material:
        return cls(**dict(params))

    @property
    def mu(self) -> float:
        """Shear modulus mu = E / (2 (1 + nu)), kPa."""
        return self.values["E"] / (2.0 * (1.0 + self.values["nu"]))

    @property
    def bulk(self) -> float:
        """Bulk modulus K = 2/d = E / (3 (1 - 2 nu)), kPa (U(J) = K/2 (J-1)^2)."""
        return self.values["E"] / (3.0 * (1.0 - 2.0 * self.values["nu"]))

    def to_febio(self) -> tuple[str, dict]:
        """FEBio material type and parameters (kPa) of the same law (density is set by the
        writer). The default refuses: a law says itself how FEBio expresses it."""
        from mechanics.febio import unsupported

        raise unsupported(f"material {self.name!r}", "it does not say how (no to_febio hook)")

    def deviatoric(self, F: np.ndarray, *, tangent: bool = True):
        """Isochoric energy and its derivatives.

        Parameters
        ----------
        F : (M, 3, 3) deformation gradients

        Returns
        -------
        W : (M,) energy density, kPa
        P : (M, 3, 3) first Piola-Kirchhoff stress dW/dF, kPa
        A : (M, 3, 3, 3, 3) d2W/dF dF (kPa), or None when ``tangent`` is False.
            Entries are NaN where the law is undefined (e.g. beyond Gent's limit).
        """
        raise NotImplementedError


class IsochoricI1Material(Material):
    """A law whose isochoric energy is a function psi(I1bar) (Neo-Hookean, Gent, ...).

    Subclasses implement :meth:`psi`; the element kernels then use a fast closed-form
    stiffness instead of the general (3,3,3,3) tangent.
    """

    def psi(self, I1bar: np.ndarray):
        """Return (W, dW/dI1bar, d2W/dI1bar2), each (M,), kPa; NaN where undefined."""
        raise NotImplementedError

    def deviatoric(self, F: np.ndarray, *, tangent: bool = True):
        I1bar, dI, d2I, _ = isochoric_i1(F, tangent=tangent)
        W, d1, d2 = self.psi(I1bar)
        P = d1[:, None, None] * dI
        if not tangent:
            return W, P, None
        A = d1[:, None, None, None, None] * d2I + d2[:, None, None, None, None] * np.einsum(
            "miJ,mkL->miJkL", dI, dI
        )
        return W, P, A


def isochoric_i1(F: np.ndarray, *, tangent: bool = True):
    """I1bar = J^(-2/3) tr(F^T F) with its first and second derivatives with respect to F.

    Returns ``(I1bar (M,), dI (M,3,3), d2I (M,3,3,3,3) or None, J (M,))``.
    """
    J = np.linalg.det(F)
    H = np.linalg.inv(F).transpose(0, 2, 1)  # F^-T
    I1 = np.einsum("mij,mij->m", F, F)
    a = np.cbrt(J) ** -2
    I1bar = a * I1
    dI = a[:, None, None] * (2.0 * F - (2.0 / 3.0) * I1[:, None, None] * H)
    if not tangent:
        return I1bar, dI, None, J
    eye = np.eye(3)
    d2 = 2.0 * np.einsum("ik,JL->iJkL", eye, eye)[None]
    d2 = d2 - (4.0 / 3.0) * (
        np.einsum("mkL,miJ->miJkL", H, F) + np.einsum("mkL,miJ->miJkL", F, H)
    )
    d2 = d2 + (4.0 / 9.0) * I1[:, None, None, None, None] * np.einsum("miJ,mkL->miJkL", H, H)
    d2 = d2 + (2.0 / 3.0) * I1[:, None, None, None, None] * np.einsum("miL,mkJ->miJkL", H, H)
    d2 *= a[:, None, None, None, None]
    return I1bar, dI, d2, J
