"""The Newton iterations of one load step and their tests: convergence by the residual,
divergence, stagnation (with a retry on exact linear solves), acceptance by FEBio's
displacement and energy norms; the Newton direction with its fall-backs for a singular
tangent, and the line search along it."""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from mechanics.linear_solvers import SingularSystem
from mechanics.newton.options import SolverError, SolverOptions
from mechanics.solid import InvalidConfiguration

if TYPE_CHECKING:
    from mechanics.newton.workspace import _Newton

log = logging.getLogger("mechanics.solver")

#: a step from rest whose relative residual lies between ``stagnate_above`` and this is
#: given twice ``stagnate_after`` iterations before the stagnation check: with sliding
#: contact and friction such steps fall slowly through 1e-2 to 1e-3 as the contact settles
#: and converge at iterations 12-19; cut back at 8-10 they failed again at every smaller load
#: (the suite's small-000, breast 0.1 / skin 20 / fascia 80 kPa, prone: loads 1 down to 1/16
#: from rest stagnated at 3e-3 to 1.6e-2, 110 Newton iterations in 14 steps; with this rule
#: one step of 19). Far from equilibrium a step that stalls stays cut back at
#: ``stagnate_after`` (the 17k-tet suite mesh's softest corner: its step to full load from
#: 0.75 stalls at 0.3-0.5; given 12 or 16 iterations it took 66 or 74 in all against 62), and
#: so do later steps: given the rule too, the 17k mesh's soft corners, where friction holds a
#: sliding breast near the end of its reach, spent 16 iterations on each of the cut-backs
#: that end in a "no equilibrium" verdict (12 solves: 1458 iterations against 1334 without the
#: rule and 1269 with it from rest only; one solve that converged ended in the verdict).
_NEAR = 0.1

#: a direction from a reused factorisation must cut the relative residual at least this much,
#: else the next direction is factorised anew
_REUSE_PROGRESS = 0.5


def _progressing(res: list[float]) -> bool:
    """True when a Newton step's relative residuals show progress that the stagnation check
    must not cut short: the last iteration halved the best residual so far, or the last
    three each fell, by a quarter in all (a damped, line-searched approach to a large
    deformation).

    Measured on the 20k-tet phantom with every effect on: 45 deg tilted went 0.97 -> 0.13 at
    iteration 8 and supine fell steadily from 2.3 to 0.91 over iterations 1-8; both were cut
    back there and took 27-36 iterations in two load steps; left alone they converged at
    iterations 15 and 18."""
    last = res[-1]
    if last <= 0.5 * min(res[:-1]):
        return True
    tail = res[-4:]
    return len(tail) == 4 and all(b < a for a, b in zip(tail, tail[1:])) \
        and last <= 0.75 * tail[0]


def _accepted_by_norms(opt: SolverOptions, entry: dict) -> bool:
    """FEBio's displacement and energy tests on the last iteration, with the relative
    residual below ``accept_residual`` (see :class:`SolverOptions`)."""
    d, e = entry["displacement_norms"], entry["energy_norms"]
    return bool(opt.accept_residual > 0.0 and d and entry["residuals"][-1] <= opt.accept_residual
                and d[-1] <= opt.dtol and e[-1] <= opt.etol)


def _stop_early(opt: SolverOptions, entry: dict, u, ev, reason: str):
    """A step that stalls: accepted when FEBio's norms say it converged. Returns
    :func:`_newton`'s (ok, u, ev, reason)."""
    if _accepted_by_norms(opt, entry):
        entry["converged_by"] = "norms"
        return True, u, ev, None
    return False, u, ev, reason


def _stagnating(opt: SolverOptions, res: list[float], it: int, rel: float,
                exact_from: int | None, from_rest: bool) -> bool:
    """True when a step has stopped making progress (``SolverOptions.stagnate_after``): at
    least ``stagnate_after`` iterations (and 4 since its linear solves became exact), the
    relative residual ``rel`` of iteration ``it`` fell less than 10x over the last 3
    iterations and shows no other progress (:func:`_progressing`), and it is still above
    ``stagnate_above`` or the best residual has not halved in the last 5 iterations
    (friction states cycling: 20k-tet prone ran 20 iterations at 1e-4). A step from rest
    (``from_rest``) between ``stagnate_above`` and ``_NEAR`` has twice ``stagnate_after``
    iterations."""
    near = from_rest and opt.stagnate_above < rel <= _NEAR
    after = opt.stagnate_after * (2 if near else 1)
    return bool(opt.stagnate_after and it >= after
                and (exact_from is None or it >= exact_from + 4)
                and rel > 0.1 * res[max(it - 3, 0)] and not _progressing(res)
                and (rel > opt.stagnate_above
                     or min(res[it - 4:]) > 0.5 * min(res[:max(it - 4, 1)])))


def _direction(nw: _Newton, A, R, u, rel: float, entry: dict, *, first_from_rest: bool,
               fresh: bool = False):
    """The Newton correction at ``u``: (du, None), or (None, why) when the tangent is
    singular and no regularised matrix (:meth:`_Newton.regularized`) gives a direction.
    ``first_from_rest``: the first iteration of a step from rest (no free displacement);
    ``fresh``: factorise A anew (no reuse). Counts the shifted solves in ``entry``."""
    opt = nw.opt
    try:
        A_first = None
        if first_from_rest and opt.singular_shift > 0.0:
            # From rest every contact gap is zero: frictional sliding gives no tangential
            # stiffness and a body held by friction alone has an exactly singular but
            # consistent tangent, which some factorisations solve without complaint,
            # adding an arbitrary rigid slide (measured: 107 mm with scipy on the
            # two-mound model, diverged). The first correction from rest therefore always
            # uses the effects' regularisation (what a detected singular tangent gets).
            A_first = nw.effect_shift(A, u, 1.0)
        du = nw.direction(A if A_first is None else A_first, R, rel,
                          fresh=fresh or A_first is not None)
        if A_first is not None:
            entry["shifted"] = entry.get("shifted", 0) + 1
    except SingularSystem as exc:
        du = None
        if opt.singular_shift > 0.0:
            for A_reg in nw.regularized(A, u, rel):
                try:
                    du = nw.direction(A_reg, R, rel, fresh=True)
                except SingularSystem:
                    continue
                entry["shifted"] = entry.get("shifted", 0) + 1
                break
        if du is None:
            return None, f"singular tangent ({exc}); is the model constrained?"
    return du, None


def _line_search(nw: _Newton, u, du, lam: float, R):
    """Crisfield-type line search on R . du along the direction ``du`` from ``u`` (halving
    the step while an element inverts; one secant step when R . du does not fall by 10 %).
    Returns ((eta, ev, R, A) of the accepted point, or None when every trial inverts; the
    first trial length that inverted nothing, 0 when none)."""
    opt = nw.opt
    s0 = float(R @ du)
    eta, accepted, valid = 1.0, None, 0.0
    for _ls in range(8):
        try:
            ev1, R1, A1 = nw.evaluate(u + eta * du, lam, tangent=True)
        except InvalidConfiguration:
            eta *= 0.5
            continue
        valid = eta  # every path below ends the search
        if not opt.line_search or s0 >= 0.0:
            accepted = (eta, ev1, R1, A1)
            break
        s1 = float(R1 @ du)
        if abs(s1) <= 0.9 * abs(s0) or accepted is not None:
            accepted = (eta, ev1, R1, A1)
            break
        accepted = (eta, ev1, R1, A1)  # keep as fallback, try one secant step
        r = s0 / (s0 - s1)  # root of the linear interpolation of s(eta) / eta
        if not (0.0 < r < 1.0) or abs(r - 1.0) < 0.05:
            break
        new_eta = max(0.1, min(1.0, r)) * eta
        try:
            ev2, R2, A2 = nw.evaluate(u + new_eta * du, lam, tangent=True)
        except InvalidConfiguration:
            break
        if np.linalg.norm(R2[nw.free]) < np.linalg.norm(R1[nw.free]) or \
                abs(float(R2 @ du)) < abs(s1):
            accepted = (new_eta, ev2, R2, A2)
        break
    return accepted, valid


def _modified_raised(nw: _Newton, R, r0: float, rel: float, entry: dict, it: int) -> bool:
    """True when a direction from a matrix without the tensile pressure stiffness raised the
    relative residual (as the next iteration sees it, R the line search's accepted point)
    above ``rel``: the step is kept and the rest of the step uses the exact tangent, from
    this point's Newton matrix on (20k-tet phantom, 45 deg tilted: 0.77 -> 2.8, then 12
    iterations in all against 13 without the option; undoing the step instead took 18)."""
    rf, rc = nw.norms(R)
    if rf / max(rc, r0, 1e-300) <= rel:
        return False
    nw.exact_tangent, nw.no_pressure_stiffness = True, False
    entry["exact_tangent_from"] = it
    return True


def _record_norms(nw: _Newton, entry: dict, step, u, u_start, R, energy0: float) -> None:
    """FEBio's displacement and energy norms of an accepted Newton step (``step`` on the
    free dofs; R the residual there, ``energy0`` the step's |du_0 . R_0|)."""
    total = float(np.linalg.norm((u - u_start)[nw.free]))
    entry["displacement_norms"].append(float(np.linalg.norm(step)) / max(total, 1e-300))
    entry["energy_norms"].append(abs(float(step @ R[nw.free])) / max(energy0, 1e-300))


def _newton(nw: _Newton, u, lam, start: list, entry, u_start):
    """Newton iterations of one load step from ``u`` (the predictor; ``start`` its [ev, R,
    A], emptied here: the caller keeps no evaluation through the step; ``u_start`` the
    step's converged start). Returns (ok, u, ev, reason); a failed step's ev may be None."""
    opt = nw.opt
    ev, R, A = start
    start.clear()
    rf, rc = nw.norms(R)
    r0 = rf
    entry["displacement_norms"], entry["energy_norms"] = [], []
    energy0 = None  # |du_0 . R_0|, FEBio's reference of the energy norm
    exact_from = None  # iteration from which the step's linear solves are exact
    nw.exact = False
    from_rest = not np.any(u[nw.free])
    nw.exact_tangent = opt.tensile_pressure_stiffness_below <= 0.0  # for the rest of the step
    for it in range(opt.max_newton + 1):
        if opt.deadline is not None and time.perf_counter() > opt.deadline:
            raise SolverError(f"mechanics: the time budget ran out at load {lam:.4g} "
                              f"(Newton iteration {it} of the step)")
        ref = max(rc, r0, 1e-300)
        rel = rf / ref
        entry["residuals"].append(rel)
        if opt.progress:
            log.info("  load %.4f iteration %d: relative residual %.3e", lam, it, rel)
        if rel <= opt.tol:
            entry["converged_by"] = "residual"
            return True, u, ev, None
        if it == opt.max_newton:
            return _stop_early(opt, entry, u, ev,
                               f"no convergence in {opt.max_newton} iterations")
        if rf > 1e6 * max(r0, 1e-300) and it > 0:
            return False, u, ev, "residual diverged"
        if _stagnating(opt, entry["residuals"], it, rel, exact_from, from_rest):
            reason = f"stagnating (relative residual {rel:.1e} after {it})"
            if exact_from is not None or rel > opt.stagnate_above:
                return _stop_early(opt, entry, u, ev, reason)
            # Close to convergence: first rule out the linear solver (a reused or
            # single-precision factor) as what holds the residual up.
            exact_from = entry["exact_linear_from"] = it
            nw.exact = True
            nw.exact_steps += 1
        # A reused factorisation is kept while Newton halves the residual with it, else the
        # next direction is factorised anew (full-000's supine solve from rest at 1 kPa:
        # stalled near 1 on inexact steps, 50 iterations in 8 steps, 3 cut back; with this
        # rule 9 in 2 steps, the solve 9.9 -> 3.2 s)
        slow = it > 0 and nw.reused and rel > _REUSE_PROGRESS * entry["residuals"][-2]
        du, failure = _direction(nw, A, R, u, rel, entry, first_from_rest=it == 0 and from_rest,
                                 fresh=slow)
        if du is None:
            return False, u, ev, failure
        entry["newton"] += 1
        if energy0 is None:  # the step's first direction and residual
            energy0 = abs(float(du[nw.free] @ R[nw.free]))
        entry.setdefault("linear_residuals", []).append(nw.last_linear_residual)
        modified = nw.no_pressure_stiffness  # how A was made (the next line: the trials')
        nw.no_pressure_stiffness = not (nw.exact_tangent or nw.exact) \
            and rel > opt.tensile_pressure_stiffness_below
        # the trials replace this iterate's evaluation and matrix (a failed step returns
        # none): dropped before they are made (150k tets: about 50 MB of the peak)
        ev = A = None
        accepted, valid_eta = _line_search(nw, u, du, lam, R)
        if accepted is None:
            return False, u, ev, "element inversion (J <= 0) along the Newton direction"
        if modified and _modified_raised(nw, accepted[2], r0, rel, entry, it):
            eta, accepted = accepted[0], None  # its matrix goes before the exact one is made
            accepted = (eta, *nw.evaluate(u + eta * du, lam, tangent=True))
        if it == 0 and from_rest and valid_eta < 1.0 and opt.first_inversion_shrink > 0.0:
            # From rest the first direction is the load times the tangent's response: where
            # it inverts an element unless scaled by eta, the load is too large by about
            # 1 / eta (see SolverOptions.first_inversion_shrink).
            entry["shrink"] = valid_eta * opt.first_inversion_shrink
            return False, u, ev, (f"the first Newton direction inverts an element unless "
                                  f"scaled by {valid_eta:.3g}")
        eta, ev, R, A = accepted
        u = u + eta * du
        _record_norms(nw, entry, eta * du[nw.free], u, u_start, R, energy0)
        rf, rc = nw.norms(R)
        if not np.isfinite(rf):
            return False, u, ev, "residual is not finite"
    return False, u, ev, "no convergence"
