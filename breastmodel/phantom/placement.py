"""Where a marker or landmark of the stress-free anatomy lies in a deformed position: the
root x of x = X + u(x) for a displacement field u sampled at current points (the contract of
:func:`breastmodel.phantom.writer.make_phantom`'s ``deformation``), or, where u jumps at the
root, where the image renders the marker's ball."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

__all__ = ["ROOT_TOL_MM", "JUMP_FRACTION", "deformed_point", "no_displacement"]

log = logging.getLogger("breastmodel.phantom")


def no_displacement(points: np.ndarray) -> np.ndarray:
    """The identity deformation (u = 0): a position that is only rigidly moved."""
    return np.zeros_like(points, dtype=float)


def deformed_point(material: np.ndarray, u: Callable[[np.ndarray], np.ndarray], *,
                   radius: float = 2.0) -> np.ndarray:
    """Current position x of material point X (3,) mm: solve x = X + u(x) by fixed point,
    then Newton; where u jumps at the root, where the image shows the ball of ``radius`` mm
    around X (:func:`_rendered_centre`)."""
    X = np.asarray(material, dtype=float)[None]
    if u is no_displacement:
        return X
    x = X.copy()
    best, best_r = X, np.inf
    for _ in range(100):
        x_new = X + u(x)
        r = float(np.max(np.abs(x_new - x)))
        if r < 1e-8:
            return x_new
        if r < best_r:
            best, best_r = x, r
        x = x_new
    x, r = _deformed_newton(X, u, best)
    if r < ROOT_TOL_MM:
        return x
    if 2.0 * r <= JUMP_FRACTION * radius:  # r: half the jump, at the best iterate
        centre = _rendered_centre(X, u, x, radius, off=r)
        if centre is not None:
            log.info("phantom: u jumps by about %.2g mm at the marker or landmark X = %s; placed "
                     "at the centre of its rendered ball, %.2g mm from the best root", 2.0 * r,
                     X[0].round(2), float(np.linalg.norm(centre - x)))
            return centre
    raise RuntimeError("phantom: deformation is not invertible near a marker or landmark "
                       f"(|x - X - u(x)| = {r:.2g} mm at X = {X[0].round(2)})")


#: Largest |x - X - u(x)| (mm) accepted for a marker or landmark where no exact root exists.
#: A simulated position's u(x) outside the mesh is its closest surface point's displacement,
#: continuous only up to which candidate triangle a search finds: on family seed 8 (gland
#: 10x) the upper sternum marker's u jumps by 0.002-0.005 mm, so that Newton and a damped fixed
#: point both stall at 0.0016-0.005 mm while I - grad u is near the identity. 0.01 mm is 50
#: times below the family's finest voxel (0.5 mm); a fold of the deformation leaves a
#: residual of its own size (millimetres).
ROOT_TOL_MM = 0.01
#: Largest jump of u at a marker, as a fraction of its radius, across which the marker is
#: placed where the image shows it. The closest-point extrapolation jumps where the closest
#: surface point switches from one surface to another, as in the concave corner where a
#: slab's breast meets its chest wall (family seed 5, tilted 49 deg: |x - X - u(x)| 0.23 mm
#: at the best iterate, which lies on the jump, so a jump of about 0.46 mm). The rendered
#: ball then has a slab of the jump's thickness cut out or doubled; up to half its radius it
#: stays one piece whose centre is where a reader of the image would put the marker.
JUMP_FRACTION = 0.5


def _deformed_newton(X: np.ndarray, u: Callable[[np.ndarray], np.ndarray], x: np.ndarray,
                     *, h: float = 1e-4) -> tuple[np.ndarray, float]:
    """x = X + u(x) by Newton's method from ``x`` (1, 3; the fixed point's best iterate), with
    u's gradient by central differences (step ``h`` mm) and a halving line search on
    |x - X - u(x)|: where |grad u| >= 1 the plain fixed point diverges or cycles, Newton
    converges wherever u is smooth near the root. Returns the best iterate and its residual
    max |x - X - u(x)| mm (nonzero where u jumps at the root)."""
    def residual(y):
        return y - X - u(y)

    r = residual(x)
    for _ in range(50):
        if np.max(np.abs(r)) < 1e-8:
            break
        pts = np.concatenate([x + h * np.eye(3), x - h * np.eye(3)])
        du = u(pts)
        J = np.eye(3) - (du[:3] - du[3:]).T / (2.0 * h)
        try:
            step = -np.linalg.solve(J, r[0])
        except np.linalg.LinAlgError:
            break
        for _ in range(30):
            x_new = x + step[None]
            r_new = residual(x_new)
            if np.linalg.norm(r_new) < np.linalg.norm(r):
                x, r = x_new, r_new
                break
            step = 0.5 * step
        else:
            break
    return x, float(np.max(np.abs(r)))


def _rendered_centre(X: np.ndarray, u: Callable[[np.ndarray], np.ndarray], x: np.ndarray,
                     radius: float, *, off: float, per_radius: int = 12) -> np.ndarray | None:
    """Centroid (1, 3) mm of the current points whose material point x - u(x) lies in the
    ball of ``radius`` around X: where the image renders that ball. Sampled on a cube around
    ``x`` (the best root, |x - X - u(x)| = ``off`` mm) at ``radius / per_radius``; None where the
    rendered ball is not one piece within the cube (a fold, or a stretch the cube misses)."""
    from scipy import ndimage

    h = radius / per_radius
    n = int(np.ceil((2.0 * radius + 4.0 * off) / h))
    t = np.arange(-n, n + 1) * h
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), axis=-1).reshape(-1, 3) + x
    inside = np.sum((g - u(g) - X) ** 2, axis=1) <= radius**2
    mask = inside.reshape((len(t),) * 3)
    edges = np.concatenate([mask[[0, -1]].ravel(), mask[:, [0, -1]].ravel(),
                            mask[:, :, [0, -1]].ravel()])
    if not inside.any() or edges.any() or ndimage.label(mask)[1] != 1:
        return None
    return g[inside].mean(axis=0)[None]
