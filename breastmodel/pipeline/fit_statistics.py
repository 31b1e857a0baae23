"""What a least-squares fit can tell about its parameters, from the Jacobian of the residuals
at the optimum (in log-parameter space): each one's linearised uncertainty
(:func:`lsq_uncertainty`), which ones the data determine (:func:`identifiability`) and how
far a bias of the measured skin moves them (:func:`offset_sensitivity`)."""

from __future__ import annotations

import numpy as np

__all__ = ["identifiability", "log_sd", "lsq_uncertainty", "offset_sensitivity"]


def lsq_uncertainty(J: np.ndarray, r: np.ndarray, p: np.ndarray,
                    names: list[str]) -> dict[str, float]:
    """Linearised 1-sd uncertainty of least-squares parameters fitted in log space.

    cov(ln p) = s^2 (J^T J)^-1 with s^2 = |r|^2 / (m - n), as if the m residuals were
    independent with equal variance (neighbouring skin nodes are correlated, so this is a
    lower bound); sd(p) = p sd(ln p).

    Parameters
    ----------
    J : (m, n) Jacobian of the residuals (mm) with respect to ln p
    r : (m,) residuals at the solution, mm
    p : (n,) parameters at the solution (their own units)
    names : the n parameter paths

    Returns
    -------
    dict
        path -> sd in the parameter's unit; empty when m <= n or J^T J is singular.
    """
    sd = log_sd(J, r)
    if sd is None:
        return {}
    return {k: float(v) for k, v in zip(names, np.asarray(p, float) * sd)}


def log_sd(J: np.ndarray, r: np.ndarray) -> np.ndarray | None:
    """The (n,) 1-sd uncertainties of ln p of :func:`lsq_uncertainty`; None when m <= n or
    J^T J is singular."""
    J, r = np.asarray(J, float), np.asarray(r, float)
    m, n = J.shape
    if m <= n:
        return None
    try:
        cov = float(r @ r) / (m - n) * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


def identifiability(J: np.ndarray, names: list[str], *, separable: float = 0.95,
                    seen: float = 1e-6) -> dict:
    """Which fitted parameters the data determine, from the Jacobian at the optimum.

    The correlation of two parameters' estimates (from (J^T J)^-1, in log space) near +-1
    means the data move them together: their ratio is fitted, not each one. A column that is
    tiny next to the largest means the data hardly see that parameter.

    Parameters
    ----------
    J : (m, n) Jacobian of the residuals (mm) with respect to ln p
    names : the n parameter paths
    separable : |correlation| at or above which a pair is reported as not separable
    seen : column norm, relative to the largest, below which a parameter is unseen

    Returns
    -------
    dict
        ``correlation`` ({"a | b": r} for every pair), ``not_separable`` ([a, b, r] for
        pairs with |r| >= ``separable``), ``unseen`` (names), ``condition`` (of J; None
        when J^T J is singular).
    """
    J = np.asarray(J, float)
    norms = np.linalg.norm(J, axis=0)
    unseen = [k for k, c in zip(names, norms) if c <= seen * max(norms.max(initial=0.0), 1e-300)]
    out = {"correlation": {}, "not_separable": [], "unseen": unseen, "condition": None}
    sv = np.linalg.svd(J, compute_uv=False) if J.size else np.zeros(0)
    if len(sv) < len(names) or len(sv) == 0 or sv.min() <= 1e-12 * sv.max():
        return out
    cov = np.linalg.inv(J.T @ J)
    d = np.sqrt(np.diag(cov))
    corr = cov / np.outer(d, d)
    out["condition"] = float(sv.max() / sv.min())
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            r = float(corr[i, j])
            out["correlation"][f"{names[i]} | {names[j]}"] = r
            if abs(r) >= separable:
                out["not_separable"].append([names[i], names[j], r])
    return out


def offset_sensitivity(J: np.ndarray, g: np.ndarray, p: np.ndarray,
                       names: list[str]) -> dict[str, float]:
    """How far each fitted parameter moves when the measured skin is offset outward by 1 mm
    (a segmentation that puts the skin outside the body; inward: the opposite sign).

    The offset changes the residuals by ``g`` (per mm) and the linearised least squares
    absorbs it by d ln p = -(J^T J)^-1 J^T g; dp = p d ln p. Unlike :func:`lsq_uncertainty`
    this is a bias, not noise: it does not shrink with more skin nodes.

    Parameters
    ----------
    J : (m, n) Jacobian of the residuals (mm) with respect to ln p
    g : (m,) derivative of the residuals with respect to the offset (per mm)
    p : (n,) parameters at the solution (their own units)
    names : the n parameter paths

    Returns
    -------
    dict
        path -> change per mm of outward offset in the parameter's unit; empty when the
        lengths differ or J^T J is singular.
    """
    J, g = np.asarray(J, float), np.asarray(g, float)
    if J.ndim != 2 or g.shape != (J.shape[0],) or J.shape[0] <= J.shape[1]:
        return {}
    sv = np.linalg.svd(J, compute_uv=False)
    if sv.size == 0 or sv.min() <= 1e-12 * sv.max():
        return {}
    dz = np.linalg.lstsq(J, -g, rcond=None)[0]
    return {k: float(v) for k, v in zip(names, np.asarray(p, float) * dz)}
