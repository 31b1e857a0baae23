"""Sentences of the report on what a fit can tell about its parameters: what the data cannot
determine (:func:`identifiability_notes`) and how far a segmentation bias moves them
(:func:`offset_notes`). Each returns HTML-escaped sentences for ``<p>`` elements."""

from __future__ import annotations

import html
from collections.abc import Mapping

__all__ = ["identifiability_notes", "offset_notes"]


def identifiability_notes(ident: dict | None) -> list[str]:
    """What the data cannot determine (see ``pipeline.fit_statistics.identifiability``)."""
    if not ident:
        return []
    notes = [f"The data do not separate {html.escape(a)} and {html.escape(b)} (correlation "
             f"{r:+.2f}): their combination is fitted, not each one."
             for a, b, r in ident.get("not_separable", [])]
    notes += [f"The data hardly see {html.escape(k)}: its value is the starting point."
              for k in ident.get("unseen", [])]
    if ident.get("condition") is not None:
        notes.append(f"Condition number of the fit's Jacobian: {ident['condition']:.3g}.")
    if not ident.get("not_separable") and not ident.get("unseen"):
        notes.insert(0, "Every fitted parameter is determined by the data (no pair of "
                        "estimates correlated beyond 0.95).")
    return notes


def offset_notes(values: Mapping[str, float], units: Mapping[str, str],
                 sens: Mapping[str, float] | None) -> list[str]:
    """How far a measured skin 1 mm outside the true one moves each fitted parameter
    (``sens``: change per mm, ``pipeline.fit_statistics.offset_sensitivity``; ``values``
    and ``units`` by parameter path)."""
    moves = [f"{html.escape(k)} by {100.0 * d / values[k]:+.1f} % ({d:+.3g} "
             f"{html.escape(units.get(k, ''))})"
             for k, d in (sens or {}).items() if values.get(k)]
    if not moves:
        return []
    return [f"A measured skin 1 mm outside the true one (a segmentation bias) would move "
            f"{', '.join(moves)}; 1 mm inside, the opposite. This is a bias, which the "
            f"uncertainty column (the skin's noise) does not include."]
