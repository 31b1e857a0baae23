"""The held-out check of the diagnosis on a synthetic linearisation: a candidate fitted on the
calibration position is judged by the held-out one only where it moves that position's
prediction enough to show an improvement (:data:`HELD_OUT_MIN_CHANGE_MM`)."""

from __future__ import annotations

import numpy as np
import pytest

from breastmodel.diagnosis.candidates import Candidate
from breastmodel.diagnosis.residual import Baseline, Linearisation, rms
from breastmodel.diagnosis.scoring import HELD_OUT_MIN_CHANGE_MM, score_candidates

N = 400


def _problem(held_out_column):
    """prone (calibrated) carries a residual of RMS 1 mm that the candidate's column removes
    exactly; supine_tilted (held out) a residual of RMS 0.3 mm, where the candidate's column
    is ``held_out_column(r_tilted)``. Nothing else is fitted."""
    rng = np.random.default_rng(1)
    r_p = rng.normal(size=N)
    r_p /= rms(r_p)
    r_t = rng.normal(size=N)
    r_t *= 0.3 / rms(r_t)
    r0 = np.concatenate([r_p, r_t])
    col = np.concatenate([-r_p, held_out_column(r_t, rng)])
    slices = {"prone": slice(0, N), "supine_tilted": slice(N, 2 * N)}
    records = {"cand|x": {"status": "ok", "result": {"residual": {
        "prone": r0[:N] + col[:N], "supine_tilted": r0[N:] + col[N:]}}}}
    lin = Linearisation(records, np.ones(N, bool), ["prone", "supine_tilted"], slices, {},
                        r0, [], [], [], [])
    cal = np.zeros(2 * N, bool)
    cal[:N] = True
    base = Baseline(0.05, "given", ["prone"], ["supine_tilted"], cal, r0.copy(), {},
                    float(r0 @ r0), rms(r0), rms(r0), float(N), r0.copy(), {})
    cand = Candidate("x", "effect", "a synthetic effect", effects={"x": {}}, amplitude=(0.0, 2.0))
    (entry,), failed, _ = score_candidates([cand], lin, base, None, {})
    assert not failed
    return entry


def _random(scale):
    def column(r_t, rng):
        w = rng.normal(size=N)
        w -= (w @ r_t) / (r_t @ r_t) * r_t  # orthogonal to the held-out residual
        return scale * w / rms(w)
    return column


@pytest.mark.parametrize("scale", [0.01, 0.3])
def test_a_held_out_position_judges_only_the_candidates_that_move_it(scale):
    """A candidate that removes the calibration residual and moves the held-out position
    along nothing that is there: by 0.01 mm RMS that position cannot test it (it stays
    significant: a position tilted a few degrees from the reference, which the stress-free
    inverse reproduces whatever the model, tells nothing), by 0.3 mm it does, and the
    candidate, making it worse, is not significant."""
    e = _problem(_random(scale))
    (h,) = e["held_out"].values()
    assert h["change_rms_mm"] == pytest.approx(scale, rel=0.02)
    assert h["rms_after_mm"] > h["rms_before_mm"]  # worse, however little
    assert e["explained"] > 0.8 and e["delta_bic"] < -6.0
    testable = scale >= HELD_OUT_MIN_CHANGE_MM
    assert e["held_out_tests"] is testable
    assert e["held_out_improves"] is False
    assert e["significant"] is (not testable)


def test_a_candidate_that_also_corrects_the_held_out_position_passes_its_test():
    e = _problem(lambda r_t, rng: -r_t)
    (h,) = e["held_out"].values()
    assert e["held_out_tests"] and e["held_out_improves"] and e["significant"]
    assert h["rms_after_mm"] == pytest.approx(0.0, abs=1e-9)
