"""Primitives of the phantom anatomy's constructive description (patient frame, mm).

Each primitive tests point membership (for voxelisation) and gives the exact chord interval
of a line parallel to y (for reference volumes that do not depend on any voxel grid): an
elliptic cylinder along z (the torso layers), an axis-aligned box (the chest-wall slab) and a
sheared superellipsoid (breasts, glands, nipples, markers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["EllipticCylinderZ", "Box", "Superellipsoid"]


@dataclass(frozen=True)
class EllipticCylinderZ:
    """Infinite elliptic cylinder along z: ((x-cx)/a)^2 + ((y-cy)/b)^2 <= 1 (mm)."""

    center: tuple[float, float]
    radii: tuple[float, float]

    def contains(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Membership of points given by coordinate arrays (mm)."""
        u = (x - float(self.center[0])) * (1.0 / self.radii[0])
        v = (y - float(self.center[1])) * (1.0 / self.radii[1])
        u *= u
        v *= v
        u += v
        return u <= 1.0

    @property
    def z_range(self) -> tuple[float, float]:
        return (-np.inf, np.inf)

    def chord_y(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interval [lo, hi] of y inside the shape on the line (x, ., z); NaN where empty."""
        u = (x - self.center[0]) / self.radii[0]
        r = 1.0 - u * u
        h = np.where(r >= 0, self.radii[1] * np.sqrt(np.clip(r, 0, None)), np.nan)
        return self.center[1] - h, self.center[1] + h

    @property
    def volume_per_mm(self) -> float:
        """Cross-section area, mm^2 (volume per mm of length)."""
        return float(np.pi * self.radii[0] * self.radii[1])


@dataclass(frozen=True)
class Box:
    """Axis-aligned box [lo, hi] (mm)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def contains(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Membership of points given by coordinate arrays (mm)."""
        lo, hi = [float(v) for v in self.lo], [float(v) for v in self.hi]
        return (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (
            z <= hi[2])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box (lo, hi), (3,) mm each."""
        return np.asarray(self.lo, float), np.asarray(self.hi, float)

    def chord_y(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interval [lo, hi] of y inside the shape on the line (x, ., z); NaN where empty."""
        ok = (x >= self.lo[0]) & (x <= self.hi[0]) & (z >= self.lo[2]) & (z <= self.hi[2])
        return (np.where(ok, self.lo[1], np.nan), np.where(ok, self.hi[1], np.nan))


@dataclass(frozen=True)
class Superellipsoid:
    """|u|^e + |v|^e + |w|^e <= 1 with u = (x - cx)/rx, v = (y - cy)/ry and
    w = (z - cz - shear (y - cy))/rz (mm); e = 2 is an ellipsoid.

    ``shear`` (dimensionless, mm of z per mm of y) tilts the shape's axis in the y-z plane: a
    breast with ptosis has ``shear > 0``, so its anterior part (y < cy) hangs lower.
    """

    center: tuple[float, float, float]
    radii: tuple[float, float, float]
    exponent: float = 2.0
    shear: float = 0.0

    def _power(self, t: np.ndarray) -> np.ndarray:
        if self.exponent == 2.0:
            return t * t
        t = np.abs(t)
        return t ** t.dtype.type(self.exponent) if isinstance(t, np.ndarray) else t**self.exponent

    def contains(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Membership of points given by coordinate arrays (mm)."""
        c, r = [float(v) for v in self.center], [float(v) for v in self.radii]
        s = self._power((x - c[0]) * (1.0 / r[0]))
        s += self._power((y - c[1]) * (1.0 / r[1]))
        if self.shear:
            s += self._power((z - c[2] - float(self.shear) * (y - c[1])) * (1.0 / r[2]))
        else:
            s += self._power((z - c[2]) * (1.0 / r[2]))
        return s <= 1.0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box (lo, hi), (3,) mm each (the shear widens its z extent)."""
        c, r = np.asarray(self.center, float), np.asarray(self.radii, float)
        h = r.copy()
        h[2] += abs(float(self.shear)) * r[1]
        return c - h, c + h

    @property
    def z_range(self) -> tuple[float, float]:
        lo, hi = self.bounds()
        return (float(lo[2]), float(hi[2]))

    def chord_y(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interval [lo, hi] of y inside the shape on the line (x, ., z); NaN where empty.

        Closed form without shear; with shear, the level function along the line is convex in
        y, so its minimum is found by golden-section search and the two crossings of 1 by
        bisection (to ~1e-10 of the semi-axis).
        """
        c, r = self.center, self.radii
        x, z = np.asarray(x, float), np.asarray(z, float)
        if not self.shear:
            rest = 1.0 - self._power((x - c[0]) / r[0]) - self._power((z - c[2]) / r[2])
            h = np.where(rest >= 0, r[1] * np.clip(rest, 0, None) ** (1.0 / self.exponent),
                         np.nan)
            return c[1] - h, c[1] + h
        e, sh = float(self.exponent), float(self.shear)
        a = np.abs((x - c[0]) / r[0]) ** e

        def f(t):  # level along the line at y = cy + t
            return a + np.abs(t / r[1]) ** e + np.abs((z - c[2] - sh * t) / r[2]) ** e

        lo, hi = np.full(x.shape, -float(r[1])), np.full(x.shape, float(r[1]))
        g = (np.sqrt(5.0) - 1.0) / 2.0
        for _ in range(50):
            m1, m2 = hi - g * (hi - lo), lo + g * (hi - lo)
            left = f(m1) < f(m2)
            hi, lo = np.where(left, m2, hi), np.where(left, lo, m1)
        tmin = 0.5 * (lo + hi)
        hit = f(tmin) <= 1.0

        def crossing(inside, outside):
            for _ in range(45):
                mid = 0.5 * (inside + outside)
                ok = f(mid) <= 1.0
                inside, outside = np.where(ok, mid, inside), np.where(ok, outside, mid)
            return 0.5 * (inside + outside)

        t_lo = crossing(tmin.copy(), np.full(x.shape, -float(r[1])))
        t_hi = crossing(tmin.copy(), np.full(x.shape, float(r[1])))
        return (np.where(hit, c[1] + t_lo, np.nan), np.where(hit, c[1] + t_hi, np.nan))

    @property
    def volume(self) -> float:
        """Closed-form volume, mm^3: 8 rx ry rz Gamma(1+1/e)^3 / Gamma(1+3/e)."""
        from math import gamma

        e = self.exponent
        return float(8 * np.prod(self.radii) * gamma(1 + 1 / e) ** 3 / gamma(1 + 3 / e))
