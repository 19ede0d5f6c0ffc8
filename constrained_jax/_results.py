"""Status codes of every solve in the library.

`RESULTS` extends `diffrax.RESULTS` (which extends `optimistix.RESULTS`, which extends
`lineax.RESULTS`), so that a status coming from any of those libraries can be
promoted into ours with `RESULTS.promote(...)` and reported with the same machinery.
Each member's value is the message the user reads when `throw=True` raises.
"""

import diffrax


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    successful = ""
    invalid_input = (
        "The initial guess or the parameters `args` contain NaN or inf. Check the "
        "inputs: every leaf of `x0`, `multipliers0` and `args` must be finite."
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
        "The linear solve for the Newton step failed (the Krylov method did not "
        "converge within its `max_steps`, or produced non-finite values). Increase "
        "the linear solver's `max_steps`, loosen its tolerance, or use `DenseLU()` "
        "when the problem is small enough to form the KKT matrix."
    )
    inconsistent_initial_state = (
        "The initial state (q0, qd0) violates the constraints (G(q0, t0) != 0 or "
        "A qd0 + a != 0 beyond `consistency_tol`). Project it onto the constraint "
        "manifold first with `cjax.consistent_initial_state(system, q0, qd0, t0, "
        "args)`, or fix the initial condition."
    )
    singular_dynamics = (
        "The KKT matrix [[M, -A^T], [A, 0]] of the equations of motion became "
        "singular during the simulation: the Lagrangian is not regular in a velocity "
        "direction the constraints leave free, or the constraints became dependent."
    )
    variational_step_failed = (
        "A step of the variational integrator failed: its Newton iteration did not "
        "converge within `newton_steps` iterations, or its Jacobian was singular. "
        "Reduce the step `dt0`, increase `newton_steps` (or loosen `rtol`/`atol` in "
        "float32), or check that the constraints are independent and the Lagrangian "
        "is regular on them."
    )
    invalid_time_grid = (
        "The time grid of a fixed-step integration is invalid: `dt0` must be "
        "positive, `t0 <= t1`, and the save times nondecreasing within [t0, t1]."
    )
    inconsistent_boundary = (
        "The boundary values of the `Functional` violate its holonomic constraint: "
        "G(y(xL), xL, args) or G(y(xR), xR, args) is not zero (beyond a few rounding "
        "errors of the values). No curve from y(xL) to y(xR) can satisfy G = 0 on the "
        "whole interval. Put the end points on the constraint surface, or fix G."
    )
    infeasible_constraints = (
        "No function satisfying the integral constraints was found: the default "
        "start (the straight line, corrected in smooth modes) could not satisfy "
        "int N_j dx = C_j, and Newton's method did not converge. The values C_j may "
        "be unattainable (a length shorter than the distance between the end "
        "points, for instance). Check them, or pass a starting guess `y0` that "
        "satisfies the constraints."
    )
    functional_singular_kkt = (
        "The KKT matrix of the discretized functional is singular at the start or at "
        "an iterate: F + lambda.N is flat along a direction the constraints leave "
        "free, or an integral constraint's gradient vanishes (a length at a straight "
        "line, G = g**2), or the stationary point is degenerate. Pass a different "
        "starting guess `y0` to `solve_functional`, or check that the problem has an "
        "isolated extremal."
    )
    functional_line_search_failed = (
        "The line search on the KKT residual of the discretized functional could not "
        "make progress: the iterate is far from any extremal, or the residual has a "
        "local minimum that is not a solution. Pass a starting guess `y0` to "
        "`solve_functional` nearer to the extremal you want (a coarser solve, or a "
        "curve that satisfies the integral constraints)."
    )
