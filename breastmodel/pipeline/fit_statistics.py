"""What a least-squares fit can tell about its parameters, from the Jacobian of the residuals
at the optimum (in log-parameter space): each one's linearised uncertainty
(:func:`lsq_uncertainty`) and which ones the data determine (:func:`identifiability`)."""

from __future__ import annotations

import numpy as np

__all__ = ["identifiability", "log_sd", "lsq_uncertainty"]


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
