"""The least squares' Jacobian by forward differences and its stopping rules (used by
:func:`breastmodel.pipeline.fit.least_squares`)."""

from __future__ import annotations

import numpy as np

from breastmodel.pipeline.fit_statistics import log_sd

__all__ = ["LSQ_STEP", "PENALTY_MM", "STOP_SD", "STOP_STEP", "Jacobian"]

PENALTY_MM = 1e3  # objective of a failed evaluation as the optimiser sees it
LSQ_STEP = 0.05  # log-parameter step of the least-squares Jacobian (5 %)
#: least squares stops once an accepted step moved every parameter by less than this many of
#: its own standard deviations (``lsq_uncertainty`` at the new point): further steps refine
#: the estimate below what the data determine
STOP_SD = 0.5
#: ... or once the accepted step, or the next Gauss-Newton step from the Jacobian just
#: computed, moves every parameter by less than this in ln p (1 %): the modulus is wanted to
#: 10 %, and an uncertainty from ~10k skin nodes taken as independent is far below 1 %, so the
#: rule above seldom stops a large subject (the suite's full-000: 12 -> 9 simulations, the
#: three left out moving the modulus by 0.4 % and the calibrated MHD by less than 0.1 %)
STOP_STEP = 0.01


class Jacobian:
    """The least-squares Jacobian by forward differences in w (an absolute log step: scipy's
    relative steps would be rounded away by the 6 digits that key the stored evaluations),
    and the stop once the steps fall below the fit's precision or the parameters'
    uncertainty (``settled``, the callback trf calls after each iteration, with the Jacobian
    at an accepted point just computed here; a rejected step leaves x where it was)."""

    def __init__(self, fun, shift: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 w0: np.ndarray):
        self.fun, self.shift, self.lo, self.hi = fun, shift, lo, hi
        self.x, self.J, self.stop, self.failed = np.asarray(w0, float), None, None, False

    def __call__(self, w) -> np.ndarray:
        f0 = self.fun(w)
        cols, self.failed = [], False
        for i in range(len(w)):
            up = w[i] + self.shift[i] + LSQ_STEP <= self.hi[i]
            h = LSQ_STEP if up else -LSQ_STEP
            wi = np.array(w, float)
            wi[i] += h
            fi = self.fun(wi)
            self.failed |= bool(np.all(fi == PENALTY_MM))
            cols.append((fi - f0) / h)
        self.J = np.column_stack(cols)
        return self.J

    def _ahead(self, x: np.ndarray, r: np.ndarray) -> np.ndarray | None:
        """|ln p| moved by the next Gauss-Newton step from x (within the bounds); None where a
        probe of the Jacobian failed (its column is the penalty's, not a slope)."""
        if self.failed:
            return None
        z = x + self.shift
        d = np.linalg.lstsq(self.J, -r, rcond=None)[0]
        return np.abs(np.clip(z + d, self.lo, self.hi) - z)

    def settled(self, intermediate_result) -> None:
        x = np.asarray(intermediate_result.x, float)
        step, self.x = np.abs(x - self.x), x
        if not step.any():
            return
        r = np.asarray(intermediate_result.fun, float)
        ahead = self._ahead(x, r)
        if np.all(step < STOP_STEP):
            self.stop = (f"the last step moved every parameter by less than "
                         f"{100 * STOP_STEP:g} % (at most {100 * step.max():.2f} %)")
        elif ahead is not None and np.all(ahead < STOP_STEP):
            self.stop = (f"the next Gauss-Newton step would move every parameter by less than "
                         f"{100 * STOP_STEP:g} % (at most {100 * ahead.max():.2f} %)")
        else:
            sd = log_sd(self.J, r)
            if sd is None or not np.all(step < STOP_SD * sd):
                return
            self.stop = (f"the last step moved every parameter by less than {STOP_SD} of its "
                         f"standard deviation (at most {(step / sd).max():.2f})")
        raise StopIteration
