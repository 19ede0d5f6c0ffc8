"""Status codes of every solve in the library.

`RESULTS` extends `diffrax.RESULTS` (which extends `optimistix.RESULTS`, which extends
`lineax.RESULTS`), so that a status coming from any of those libraries can be
promoted into ours with `RESULTS.promote(...)` and reported with the same machinery.
Each member's value is the message the user reads when `throw=True` raises
(`RESULTS[item]`); an item prints as its name (`RESULTS.successful`).
"""

import diffrax
import equinox as eqx
import jax
import numpy as np

from ._compat import NamedEnumerationMeta


class RESULTS(diffrax.RESULTS, metaclass=NamedEnumerationMeta):  # pyright: ignore[reportGeneralTypeIssues]
    successful = ""
    invalid_input = (
        "The initial guess or the parameters `args` contain NaN or inf. Check the "
        "inputs: every leaf of the start (`x0` and `multipliers0` of `extremize`, "
        "`y0` and the boundary values of `solve_functional`, `q0`, `qd0`, `t_span` "
        "and a traced `dt0` of `simulate`, `params0` of `fit`) and of `args` must be "
        "finite."
    )
    singular_kkt = (
        "The KKT matrix [[H, J^T], [J, 0]] is singular (H is the Hessian of "
        "F* = F + lambda.G, J the constraint Jacobian). The stationary point is "
        "degenerate, or F is flat along the constraint surface near the iterate. Try a "
        "different starting point `x0`, or check that the problem has an isolated "
        "stationary point."
    )
    redundant_constraints = (
        "The constraint Jacobian dG/dx is rank-deficient: some constraints are "
        "redundant (linearly dependent on the others) or their gradients vanish at "
        "the solution (e.g. G = g(x)**2). The multipliers are then not unique. Remove "
        "the dependent constraints, or write each constraint so that its gradient is "
        "nonzero where it holds."
    )
    line_search_failed = (
        "The line search on the KKT residual could not make progress: the iterate is "
        "far from any stationary point of F + lambda.G, or has reached a point where "
        "the residual has a local minimum that is not a solution. Try a different "
        "starting point `x0` (and `multipliers0`)."
    )
    linear_solve_failed = (
        "The iterative (Krylov) linear solver for the Newton step, e.g. `MINRES`, did "
        "not converge within its `max_steps`. Increase the linear solver's "
        "`max_steps`, loosen its tolerance, or use `DenseLU()` when the problem is "
        "small enough to form the KKT matrix."
    )
    inconsistent_initial_state = (
        "The initial state (q0, qd0) violates the constraints (G(q0, t0) != 0 or "
        "A qd0 + a != 0 beyond `consistency_tol`). Project it onto the constraint "
        "manifold first with `cjax.consistent_initial_state(system, q0, qd0, t0, "
        "args)`, or fix the initial condition."
    )
    singular_dynamics = (
        "The KKT matrix [[M, -A^T], [A, 0]] of the equations of motion became "
        "singular during the simulation, with no solution: a force acts along a "
        "velocity direction that has no inertia and that the constraints leave free "
        "(a direction with no inertia and no force is a free gauge and gets zero "
        "acceleration), or the constraints became dependent."
    )
    variational_step_failed = (
        "A step of the variational integrator failed: its Newton iteration did not "
        "converge within `newton_steps` iterations, or its Jacobian was singular. "
        "Reduce the step `dt0`, increase `newton_steps` (or loosen `rtol`/`atol` in "
        "float32), or check that the constraints are independent and the Lagrangian "
        "is regular on them."
    )
    invalid_time_grid = (
        "The time grid is invalid: the save times must lie within `t_span` and be "
        "sorted in the direction of integration, and `dt0` must point from `t0` to "
        "`t1` (a fixed-step variational integration, and release events of a "
        "`cjax.Unilateral`, need `t0 <= t1`)."
    )
    diverged = (
        "The simulation diverged: at an accepted step the state became non-finite, or "
        "left the constraint manifold (a constraint residual, as a distance, exceeded "
        "a quarter of the size of the state). The step is too large for the solver: "
        "reduce `dt0`, use an adaptive step-size controller (e.g. "
        "`diffrax.PIDController`), or `cjax.Projection()`; with `cjax.Baumgarte`, "
        "smaller gains."
    )
    step_size_underflow = (
        "The adaptive step size fell below round-off (16 eps of |t|), where no step "
        "can pass the error test: the vector field is not finite just ahead of the "
        "state (NaN from the Lagrangian, the forces or a constraint, e.g. an "
        "`integrate_pfaffian` constraint where its quadrature is refused; or a "
        "solution that blows up), or the equations are too stiff for the solver (try "
        "an implicit one, e.g. `diffrax.Kvaerno5()`). The run stopped there instead "
        "of spending `max_steps` on rejected steps."
    )
    release_missed = (
        "The watched multiplier of a `cjax.Unilateral` constraint changed sign inside "
        "a fixed step (both ends of the step kept its sign), so the release cannot be "
        "located. Reduce `dt0`, or use an adaptive step-size controller (e.g. "
        "`diffrax.PIDController`), which refines such steps."
    )
    max_events_reached = (
        "The run used its whole budget of contact events (`simulate(..., "
        "max_events=N)`: releases and impacts of `cjax.Unilateral` constraints) "
        "before `t1`, and stopped there; later save times are inf. Increase "
        "`max_events`. If the events accumulate in finite time (Zeno: a ball with "
        "restitution e < 1 bounces infinitely often before it comes to rest), give "
        "the `Unilateral` a `rest_speed`: impacts slower than it are taken as "
        "inelastic and the contact is re-made (resting contact)."
    )
    impact_not_approaching = (
        "A `cjax.Unilateral`'s gap fell through zero where it was not closing (its "
        "approach speed -d gap/dt was not positive): no impact law applies there. "
        "The gap must be a continuous, differentiable function of (q, t) that is "
        "positive while separated and falls through zero at contact (not a step, "
        "e.g. from `jnp.where`)."
    )
    contact_sign_mismatch = (
        "A `cjax.Unilateral`'s `sign` disagrees with its `gap` at the start: the "
        "force of its first row while it pushes (`sign * lambda > 0`) would close the "
        "gap instead of opening it, so the contact would let go where it should hold "
        "and the bodies pass through each other. `sign` is the sign of the first "
        "row's multiplier while the constraint pushes; `gap` is positive while "
        "separated. Flip one of them. The run was not integrated."
    )
    recontact = (
        "A released `cjax.Unilateral` made contact again (its `gap` fell through "
        "zero) before `t1`. A release run (`max_events=None`) models one release and "
        "stops there: `traj.release.recontact_time` says when, and later save times "
        "are inf. To run on through the impact, give the `Unilateral` a "
        "`restitution` and pass `simulate(..., max_events=N)`."
    )
    painleve_paradox = (
        "A slipping `cjax.Unilateral` with `cjax.Coulomb` friction has no consistent "
        "motion (the Painleve paradox): with the kinetic friction force coupled to "
        "the normal force, the coefficient of the normal multiplier in the contact's "
        "equation is not positive, so the equations have no solution or several "
        "(a slender rod sliding on a floor rougher than its critical coefficient). "
        "The run stops where it arises (at the start of a slip, or where the "
        "coefficient falls through zero during one), recorded as the last event of "
        "`traj.events`: its time and contact (`group`), still attached, slipping. "
        "Lower `mu_k`, or model the contact as compliant."
    )
    invalid_friction = (
        "A `cjax.Coulomb` coefficient from `args` is out of range: the kinetic "
        "coefficient must satisfy 0 <= mu_k <= mu_s (NaN fails). The run did not "
        "start."
    )
    invalid_restitution = (
        "A `cjax.Unilateral`'s `restitution(args)` is not in [0, 1] (or is NaN), or "
        "its `rest_speed(args)` is negative or NaN. Newton's coefficient of "
        "restitution e must satisfy 0 <= e <= 1 (e > 1 would create energy)."
    )
    fit_diverged = (
        "The fit ended with a higher loss than it started from: the optimizer "
        "diverged (its steps are too large for the curvature of the loss; plain "
        "gradient descent grows the loss once the learning rate exceeds 2 / the "
        "largest curvature). Lower the learning rate, use a schedule, or an optimizer "
        "with a line search (`optax.lbfgs()`). The fit returns `params0`."
    )
    discretization_error = (
        "The discretization does not resolve the solution to the requested "
        "tolerance: its a-posteriori error estimate (`sol.stats['error_estimate']`) "
        "exceeds `atol + rtol * max|y|` (`sol.stats['error_tolerance']`). Use more "
        "nodes; if the solution or the integrand is singular at an end (a vertical "
        "tangent, `1/sqrt(y)` where `y = 0`), grade the grid there with "
        "`cjax.Graded(discretization, left=p)` (p = 3 for a cycloid's cusp, 2 for "
        "`sqrt(x - xL)`); for a boundary layer use `cjax.PiecewiseLinear` with more "
        "nodes or a `Graded` grid at that end; or pass a looser `rtol`/`atol`. (An "
        "estimate at the round-off level of the discretization, "
        "`discretization.roundoff_rtol(dtype) * max|y|`, grows with the nodes: ask "
        "for no less than that.)"
    )
    infeasible_constraints = (
        "The constraints could not be satisfied. `extremize`: the iterates approach "
        "a point where G != 0 but the constraint Jacobian J = dG/dx has lost rank, a "
        "stationary point of |G|^2 (J^T G = 0) that is not a solution; the "
        "constraints may be inconsistent (e.g. x.x + 1 = 0), or x0 lies in the basin "
        "of a local minimum of |G|: check that G = 0 has a solution, and start "
        "nearer to it. `solve_functional`: the start (the straight line, or the "
        "curve `y0`, corrected in smooth modes) could not satisfy int N_j dx = C_j "
        "and Newton's method did not converge; the values C_j may be unattainable (a "
        "length "
        "shorter than the distance between the end points, for instance): check "
        "them, or pass a starting guess `y0` that satisfies the constraints."
    )
    nonfinite_objective = (
        "F, G or their derivatives (gradient, constraint Jacobian, Hessian) are NaN "
        "or inf at the starting point x0 (or at the point the solver stopped), "
        "although x0, multipliers0 and args are finite: the point lies outside the "
        "domain of F or G (e.g. the log or sqrt of a negative number) or on a "
        "singularity. Start inside the domain, or write F and G so that they are "
        "finite wherever the solver may step."
    )
    inconsistent_boundary = (
        "The boundary values of the `Functional` violate its holonomic constraint: "
        "G(y(xL), xL, args) or G(y(xR), xR, args) is not zero (beyond a few rounding "
        "errors of the values). No curve from y(xL) to y(xR) can satisfy G = 0 on the "
        "whole interval. Put the end points on the constraint surface, or fix G."
    )
    functional_singular_start = (
        "The KKT matrix of the discretized functional is singular at the start, "
        "before any step: the start is the cause, not the problem. For instance the "
        "straight line where an integral constraint is a length (its gradient "
        "vanishes there), or a curve that creeps along an end value where the "
        "integrand is singular (the brachistochrone's 1/sqrt(-y) near y = 0), so "
        "stiff there that the matrix is numerically singular. Pass a starting guess "
        "`y0` to `solve_functional` that leaves such an end steeply; with no `y0`, "
        "grade the grid at that end (`cjax.Graded(discretization, left=p)`), whose "
        "default start does."
    )
    functional_singular_kkt = (
        "The KKT matrix of the discretized functional is singular at the start or at "
        "an iterate: F + lambda.N is flat along a direction the constraints leave "
        "free, or an integral constraint's gradient vanishes (a length at a straight "
        "line, G = g**2), or the stationary point is degenerate. Pass a different "
        "starting guess `y0` to `solve_functional`, or check that the problem has an "
        "isolated extremal."
    )
    functional_redundant_constraints = (
        "The integral constraints of the functional have no multipliers: two of "
        "them are the same constraint (or one is a combination of the others), or "
        "a constraint holds only where its gradient vanishes, such as a length "
        "equal to the distance between the end points, which only the straight "
        "line has (the tension would be infinite). Give each integral constraint "
        "once, and make a length longer than the chord."
    )
    functional_line_search_failed = (
        "The line search on the KKT residual of the discretized functional could not "
        "make progress: the iterate is far from any extremal, or the residual has a "
        "local minimum that is not a solution. Pass a starting guess `y0` to "
        "`solve_functional` nearer to the extremal you want (a coarser solve, or a "
        "curve that satisfies the integral constraints)."
    )
    infeasible_inequalities = (
        "`extremize` with inequalities: the solve stopped at a point where some "
        "H_i(x) > 0 (or a bound is violated) and could not reduce the violation: the "
        "inequalities (with the equality constraints) may have no common solution, "
        "e.g. `x <= -1` and `x >= 1`, or `lower > upper`. Check that the feasible set "
        "is not empty; if it is not, start nearer to it."
    )
    kkt_conditions_violated = (
        "`extremize` with inequalities: the iteration stopped, but at that point the "
        "KKT conditions (stationarity, feasibility, the sign of the multipliers mu, "
        "complementarity mu_i H_i = 0) do not hold to the tolerance checked "
        "(`sol.stats['kkt_tolerance']`, relative). The problem may be badly scaled or "
        "degenerate: rescale x or H, or start elsewhere."
    )
    unbounded_objective = (
        "`extremize` with inequalities: the objective has no optimum in the direction "
        "of the iterates: they ran off (more than 1000 times the size of `x0` from "
        "it) while F kept improving in the direction of `sense`, as when maximizing a "
        "convex function. Check `sense`, and bound the unknowns (`lower`, `upper`) or "
        "add the constraints that make the feasible set bounded."
    )
    not_an_optimum = (
        "`extremize` with `sense`: the point found satisfies the first-order (KKT) "
        "conditions, but its second-order test (`sol.kind`, the Hessian of "
        "F + lambda.G + mu.H on the tangent space of the equality constraints and the "
        "strictly active inequalities) contradicts `sense`: a maximum or a saddle "
        "when minimizing, a minimum or a saddle when maximizing; or, with "
        "inequalities, the Hessian has curvature of the wrong sign for `sense` on "
        "the subspace that keeps every active constraint at zero (no local optimum "
        "there, even where `kind` is inconclusive). Start from another `x0`."
    )


def raise_if_failed(sol, throw: bool):
    """`sol` (any solution with a `result` field), raising where `sol.result` is not
    successful if `throw`.

    Applied by each public solve *after* its compiled core (which never sees
    `throw`): so `throw=True` and `throw=False` share one compiled program, and
    switching between them compiles only this small check. A concrete result (the
    solve called outside `jax.jit` and `jax.vmap`) is tested here, on the host, and
    the error is raised in this call: its traceback leads to the caller's line, not to
    the call that compiled the program. A traced one is checked by `eqx.error_if`
    where the program runs (the check rides on the returned solution: a program that
    keeps only a derivative drops it, and the NaN derivative of a failed solve is
    then its refusal).
    """
    if not throw:
        return sol
    result = sol.result
    if not result.is_traced():
        failed = np.asarray(result != RESULTS.successful)
        if failed.ndim == 0:
            if failed:
                raise eqx.EquinoxRuntimeError(RESULTS[result])
            return sol
    return result.error_if(sol, result != RESULTS.successful)


def error_if(x, pred, msg: str):
    """`eqx.error_if(x, pred, msg)`, except that a concrete `pred` (outside `jax.jit`
    and `jax.vmap`) is tested here and raised in this call, so that the traceback
    leads to the current caller. (`eqx.error_if` called eagerly runs a small compiled
    program that keeps the Python stack of its first trace, and its message shows
    that stack, the caller that compiled it, on every later failure.)"""
    if isinstance(pred, jax.core.Tracer):
        return eqx.error_if(x, pred, msg)
    if np.any(np.asarray(pred)):
        raise eqx.EquinoxRuntimeError(msg)
    return x
