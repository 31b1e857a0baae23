"""Options and errors of :func:`mechanics.solver.solve`: what a solve may do (tolerances,
load stepping, linear solves, the acceptance by FEBio's norms) and how it says it failed
(a stalled Newton, or a model with no equilibrium)."""

from __future__ import annotations

from dataclasses import dataclass

from mechanics.state import State


@dataclass(frozen=True)
class SolverOptions:
    """Options of :func:`solve`.

    tol : relative residual norm at convergence
    max_newton : Newton iterations per load step before the step is cut back
    initial_steps : the first load increment is 1 / initial_steps; a solve given an initial
        guess (``u0``, a nearby problem's solution at full load) first tries the whole load
        from it in one step, and follows the path of these increments only where that fails
    min_step : smallest load increment before giving up
    max_cutbacks : total cut-backs allowed in one solve
    grow_below : grow the increment (x2) after a step that took at most this many iterations
    predictor : a step's first iterate: "secant" (the default: the last two converged
        states extrapolated; before the first converged step the initial guess scaled to the
        load), "converged" (the last converged state, moved along the initial guess if one
        was given; a step that fails from there is tried once more from the extrapolation
        before it is cut back) or "auto" (of those two, the one whose first iterate leaves
        the smaller residual norm on the free dofs, both norms in the step's log as
        ``predictor_residuals``; a path that ends without equilibrium is solved once more
        from the extrapolation, see ``mechanics.newton.stepping._solve``). Measured with
        two initial steps on the 17k-tet suite mesh (``bench/effects_box.py --points
        best,0 --predictor auto``): the softest corner in prone 62 -> 38 Newton iterations
        (CPU 2.1x the paper's best moduli, against 3.9x), in supine 400 (240 on a path that
        ends at load 0.86, then 160 from the extrapolation) against 160; the box on the five
        suite meshes 135 of 135 either way, 1850 -> 1825 iterations. Not the default: with
        friction the two starts follow different equilibrium branches, and the fits of the
        validation suite have not been rerun with it. Choosing the extrapolation unless its
        residual was over 4x the converged state's lost a slow diagnosis test (the fascia
        candidate's verified tilted error 0.40 mm against the bound 0.31). "converged" alone
        (``bench/step_control.py``) lost a sliding candidate's solve in the slow
        diagnosis tests: it diverged at load 0.75 (13 cut-backs) where the extrapolation
        converges. That contact with friction has more than one equilibrium: from the same
        converged state at load 0.25 the two predictors converge at 0.5 to states up to
        0.52 mm apart (56 nodes over 0.1 mm); the branch the converged state follows ends
        near 0.749 (every step beyond stalls at a relative residual of about 0.05, as at a
        fold), the other reaches full load
    first_inversion_shrink : where > 0, a first step from rest whose first Newton direction
        inverts an element unless scaled by eta (the line search's largest valid length) is
        cut back at once to ``eta * first_inversion_shrink`` of its load instead of being
        left to Newton (from rest that direction is the load times the tangent's response).
        Off by default: measured with 0.5 and "converged" (``bench/step_control.py``,
        ``bench/effects_box.py``), the softest corner on the 17k-tet suite mesh took 39
        Newton iterations against 52, but on the suite's small meshes many box points that
        converge at full load in one step of 10-13 iterations took 22-46 in 3-5 steps
    linear_solver : "auto" (PARDISO if installed, else scipy), "scipy" or "pardiso"
    line_search : Crisfield-type line search on R . du
    reuse_factor : solve with GMRES preconditioned by the last factorisation (that of an
        earlier iteration or load step; an inexact Newton step whose linear tolerance
        follows the nonlinear residual, so convergence stays quadratic), and refactorise
        only if GMRES does not converge; the GMRES iteration budget is what a new
        factorisation would cost in triangular solves, so reuse never costs much more than
        it saves (``bench/vs_febio.py``: at 150k tets one factorisation per solve)
    reuse_below : reuse only once the relative residual is below this; None (default):
        always for a symmetric tangent, below 0.05 for an unsymmetric one (frictional
        sliding, whose tangent changes with the stick/slip state: reused at every residual,
        the 20k-tet phantom's supine solve took 17-27 iterations with 4-7 factorisations,
        once cut back, against 18 iterations and 12 factorisations below 0.05)
    reuse_max_iterations : most GMRES iterations of one reusing solve (each stores a vector
        of the system's size), below the budget above
    tensile_pressure_stiffness_below : while a step's relative residual is above this, the
        Newton matrix leaves out the geometric stiffness p d2v/dx2 of the elements whose
        pressure is tensile (p > 0; the residual keeps it); 0: always the exact tangent.
        In soft, nearly incompressible tissue under gravity the pressure (rho g h, about
        0.5 kPa over 5 cm) is several times the shear modulus (0.07-0.1 kPa) and this term
        makes the tangent indefinite away from equilibrium: the 20k-tet phantom's supine
        solve took 8 Newton iterations whose full steps inverted 800-2150 elements of one
        breast (line-search steps of 1.5-6 %); 18 -> 13 iterations without it (prone 15 ->
        10, tilted 13 -> 12). Leaving out every pressure's term did as well there but
        failed a warm start of the 0.1 kPa hemisphere (11 -> 51-62 iterations, cut back), the
        compressive ones alone did worse (supine 26). The first direction from such a
        matrix that raises the residual ends this for the rest of the step
    stagnate_after, stagnate_above : cut a step back early once it has taken
        ``stagnate_after`` iterations (a step from rest whose relative residual lies between
        ``stagnate_above`` and 0.1: twice as many, see ``mechanics.newton.iteration._NEAR``)
        and the relative residual is still above
        ``stagnate_above`` (or, below it, the best residual has not halved in 5 iterations)
        and fell less than 10x over the last 3 iterations, and shows no other progress
        (see ``_progressing``; measured: friction solves leaving their first iterations'
        stick/slip transients were cut back while falling 50x in 3 iterations);
        ``stagnate_after = 0`` turns the check off and leaves only ``max_newton`` (linearly
        converging solves, e.g. friction)
    singular_shift : what to do when the tangent A is singular (its factorisation fails or
        its solve does not satisfy the system): solve the Newton correction with A + rho S,
        rho = min(1, relative residual), S the regularising stiffness that effects offer
        (``regularization(X, x)``: the sliding effect's stick stiffness at contact points
        without pressure, whose friction gives no tangential stiffness at the first iterate
        of a solve), else (or if that is singular too) with A + singular_shift * rho
        |diag(A)| on the displacement block (Levenberg-Marquardt). Only the Newton matrix
        changes, never the residual, so the converged state is the unregularised
        equilibrium. 0 turns both off (a singular tangent then cuts the step back).
    dtol, etol : FEBio's displacement and energy norms (its defaults): at every iteration
        the step's log records ``||eta du|| / ||u - u_step_start||`` (``displacement_norms``)
        and ``|eta du . R_new| / |du_0 . R_0|`` (``energy_norms``), FEBio's
        ``FESolidSolver2`` measures. The residual test (``tol``) decides convergence; a
        step that stagnates (see ``stagnate_after``) even with exact linear solves, or that
        runs out of iterations, is accepted when both norms are below these and the
        relative residual is below ``accept_residual``: what FEBio would call converged
        (it checks no residual by default), with the residual bounded on top. Each
        accepted step says so in its log (``converged_by``) and the solve's
        ``stats["convergence"]`` states the criteria and the last step's norms.
    accept_residual : the largest relative residual of a step accepted by the norms above
        (0: never accept a step by the norms)
    pattern_drop_below : an effect's tangent entries outside the pattern the solve's Newton
        matrices share are left out of the matrix where their 2-norm is at most this
        fraction of the effect's tangent's (a modified Newton step; else the pattern grows
        and the factorisation's symbolic analysis is redone), never in a step that solves
        exactly; 0: always grow (:mod:`mechanics.pattern`)
    progress : log every Newton iteration at INFO level
    threads : MKL threads of the PARDISO phases; None: the environment variable
        ``BREASTMODEL_THREADS``, else the cores this process may run on (never the load;
        see :func:`mechanics.linear_solvers.resolve_threads`). The Newton loop's own BLAS
        calls (vector operations) run on one thread.
    deadline : a ``time.perf_counter()`` instant after which the solve stops at its next
        Newton iteration with :class:`SolverError` (a caller's time budget: a diagnosis'
        evaluation); None: no limit
    """

    tol: float = 1e-8
    max_newton: int = 20
    initial_steps: int = 1
    min_step: float = 1e-4
    max_cutbacks: int = 20
    grow_below: int = 6
    predictor: str = "secant"
    first_inversion_shrink: float = 0.0
    linear_solver: str = "auto"
    line_search: bool = True
    reuse_factor: bool = True
    reuse_below: float | None = None
    reuse_max_iterations: int = 100
    tensile_pressure_stiffness_below: float = 0.3
    stagnate_after: int = 8
    stagnate_above: float = 1e-3
    singular_shift: float = 1e-2
    dtol: float = 1e-3
    etol: float = 1e-2
    accept_residual: float = 1e-3
    pattern_drop_below: float = 1e-3
    progress: bool = False
    threads: int | None = None
    deadline: float | None = None


class SolverError(RuntimeError):
    """Divergence after the last cut-back, or an unconstrained model.

    ``state`` is the last converged :class:`State` (``converged=False``, its ``load`` < 1).
    ``verdict`` is None for a numerical failure, else a dict that says why the model has no
    equilibrium (see :class:`NoEquilibrium`).
    """

    verdict: dict | None = None

    def __init__(self, message: str, state: State | None = None):
        super().__init__(message)
        self.state = state


class NoEquilibrium(SolverError):
    """A physical verdict, not a stalled Newton: the model as built has no equilibrium (a
    rigid-body mode nothing holds, or a load the supports and structures cannot carry).
    ``verdict``: ``kind`` ("no equilibrium"), ``reason`` and the force budget or the free
    modes behind it."""

    def __init__(self, message: str, state: State | None = None, *, verdict: dict):
        super().__init__(message, state)
        self.verdict = verdict
