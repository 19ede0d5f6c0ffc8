"""The indirect method: shooting on the Euler-Lagrange equations.

With integral constraints only, the extremal solves the Euler-Lagrange equations of
`L* = L + sum_j lambda_j N_j`,

    d2L*/dy'2 y'' = dL*/dy - d2L*/dy'dy y' - d2L*/dy'dx,

a second-order ODE once the constants `lambda_j` are known. Shooting treats the
initial slope `y'(xL)` and the multipliers as unknowns, integrates from `xL` with
diffrax (carrying `I_j(x) = int_{xL}^x N_j dx` along), and finds the root of

    (y(xR) - yR,  I_j(xR) - C_j)

by Newton's method (optimistix). An alternative to the direct method
([`constrained_jax.solve_functional`][]) with which to compare it; it needs a good
starting slope and multipliers and an ODE that stays regular (`d2L*/dy'2`
invertible) along the way.
"""

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import ArrayLike

from ._custom_types import Args
from ._diffrax_integrate import diffeqsolve, step_floor
from ._discretization import Chebyshev
from ._functional import (
    Functional,
    FunctionalMultipliers,
    FunctionalSolution,
)
from ._implicit import nan_derivatives_if_failed
from ._misc import all_finite, as_traced_args, check_max_steps, full_precision
from ._results import raise_if_failed, RESULTS


def _second_derivative(lagrangian_star: Callable, y, yp, x, args):
    """`y''` from the Euler-Lagrange equations of `L*` (all shapes `(n,)`)."""
    dl_dyp = lambda y_, yp_, x_: jax.grad(lagrangian_star, argnums=1)(y_, yp_, x_, args)
    hess = jax.jacfwd(dl_dyp, argnums=1)(y, yp, x)
    _, mixed = jax.jvp(
        lambda y_, x_: dl_dyp(y_, yp, x_), (y, x), (yp, jnp.ones_like(x))
    )
    dl_dy = jax.grad(lagrangian_star, argnums=0)(y, yp, x, args)
    return jnp.linalg.solve(hess, dl_dy - mixed)


@full_precision
def solve_shooting(
    functional: Functional,
    args: Args = None,
    *,
    slope0: ArrayLike,
    multipliers0: ArrayLike | None = None,
    num_nodes: int = 32,
    ode_solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    rtol: float = 1e-11,
    atol: float = 1e-11,
    root_tol: float = 1e-10,
    max_steps: int = 64,
    ode_max_steps: int = 100_000,
    throw: bool = True,
) -> FunctionalSolution:
    """Solve the Euler-Lagrange equations of a functional by shooting.

    **Arguments:**

    - `functional`: a [`constrained_jax.Functional`][] with integral constraints
        only (holonomic constraints make the Euler-Lagrange equations a DAE: use
        [`constrained_jax.solve_functional`][]).
    - `args`: parameters passed last to `L`, `N_j` and callable `C_j`.
    - `slope0`: the starting guess for `y'(xL)` (shaped like the boundary values).
    - `multipliers0`: the starting guess for the integral multipliers, shape `(k,)`.
    - `num_nodes`: the solution is saved at this many Chebyshev-Gauss-Lobatto points
        and interpolated spectrally between them.
    - `ode_solver`, `rtol`, `atol`: the diffrax solver and its step-size tolerances.
    - `root_tol`: tolerance of the Newton iteration (optimistix) on the shooting
        unknowns.
    - `max_steps`: the most Newton steps.
    - `ode_max_steps`: the most steps of each trial's integration from `xL` to `xR`
        (accepted and rejected). A trial that needs more is refused like one that
        blows up (below). Lower it to bound the cost of a far start: each Newton
        step integrates once, and a steep but finite trial may take many steps.
    - `throw`: raise on failure if `True`; otherwise report it in `result`.

    **Returns:**

    A [`constrained_jax.FunctionalSolution`][] (its `discretization` is the
    `Chebyshev(num_nodes)` interpolant of the saved values; `stats` holds the Newton
    steps of the root find).

    !!! note

        Derivatives: forward mode only (the ODE solves use `diffrax.ForwardMode`,
        which the Newton iteration needs for its Jacobian).

    !!! note "A start far from the solution"

        Each trial integrates from `xL` to `xR` (at most `ode_max_steps` steps,
        100,000 by default, with a floor on the step at `16 eps max(|xL|, |xR|)`).
        A trial that does not reach `xR` (its solution blows up, or needs more
        steps) gives a NaN residual, and the solve is refused (`RESULTS.nonfinite`),
        as is one that reaches a NaN iterate; such trials cost no integration after
        that (a `jax.vmap` batch does not wait on them). Newton is undamped: start
        near the solution (e.g. from a coarse [`constrained_jax.solve_functional`][]).
    """
    args = as_traced_args(args)
    sol = _solve_shooting(
        functional,
        args,
        jnp.asarray(slope0),
        multipliers0,
        num_nodes,
        ode_solver,
        rtol,
        atol,
        root_tol,
        max_steps,
        ode_max_steps,
    )
    return raise_if_failed(sol, throw)


@eqx.filter_jit
def _solve_shooting(
    functional,
    args,
    slope0,
    multipliers0,
    num_nodes,
    ode_solver,
    rtol,
    atol,
    root_tol,
    max_steps,
    ode_max_steps,
):
    if not isinstance(functional, Functional):
        raise ValueError("`functional` must be a `cjax.Functional`.")
    if functional.holonomic is not None:
        raise ValueError(
            "Shooting handles integral constraints only: with holonomic constraints "
            "the Euler-Lagrange equations are differential-algebraic. Use "
            "`cjax.solve_functional` (the direct method)."
        )
    max_steps = check_max_steps(max_steps)
    ode_max_steps = check_max_steps(ode_max_steps, "ode_max_steps")
    discretization = Chebyshev(num_nodes)
    dtype = functional.boundary[0].dtype
    shape = functional.boundary[0].shape
    n = functional.num_components
    k = len(functional.integral_constraints)
    if slope0.shape != shape:
        raise ValueError(
            f"`slope0` must be shaped like the boundary values, {shape}; got "
            f"{slope0.shape}."
        )
    if multipliers0 is None:
        multipliers0 = jnp.zeros((k,), dtype)
    multipliers0 = jnp.asarray(multipliers0, dtype)
    if multipliers0.shape != (k,):
        raise ValueError(
            f"`multipliers0` must have shape (k,) = ({k},), one per integral "
            f"constraint; got {multipliers0.shape}."
        )
    xl, xr = functional.interval
    yl, yr = functional.boundary
    nodes = discretization.nodes(functional.interval)

    def flat(fn):
        return lambda y, yp, x, a: fn(y.reshape(shape), yp.reshape(shape), x, a)

    def vector_field(x, state, params):
        y, yp, _, _ = state
        lam, a = params
        lstar = flat(functional.extended_lagrangian(lam))
        ypp = _second_derivative(lstar, y, yp, x, a)
        integrals = (
            jnp.stack(
                [
                    flat(c.integrand)(y, yp, x, a)
                    for c in functional.integral_constraints
                ]
            )
            if k
            else jnp.zeros((0,), dtype)
        )
        value = flat(functional.lagrangian)(y, yp, x, a)
        return yp, ypp, integrals, value

    term = diffrax.ODETerm(vector_field)
    # A floor on the step: a trial slope whose solution blows up (or turns NaN)
    # before `xR` stops after about 20 rejected steps instead of running each Newton
    # step's integration to its `ode_max_steps`.
    x_left, x_right = jnp.asarray(xl, dtype), jnp.asarray(xr, dtype)
    controller, _ = step_floor(
        diffrax.PIDController(rtol=rtol, atol=atol), x_left, x_right
    )

    def integrate(unknowns, a, ts=None):
        """The states at `xR` (`ts=None`) or at `ts`, and diffrax's result. A trial
        with NaN or inf (a Newton iterate after a blow-up, a lane of a batch that has
        stopped) integrates the empty span and returns NaN: its steps would all be
        rejected up to `max_steps`, and under `jax.vmap` the other lanes wait. A
        solve that fails returns NaN too."""
        slope, lam = unknowns
        ok = all_finite((unknowns, a))
        state0 = (
            yl.reshape(n),
            slope.reshape(n),
            jnp.zeros((k,), dtype),
            jnp.zeros((), dtype),
        )
        if ts is None:
            saveat = diffrax.SaveAt(t1=True)
        else:
            saveat = diffrax.SaveAt(ts=jnp.where(ok, ts, x_left))
        sol = diffeqsolve(
            term,
            ode_solver,
            x_left,
            jnp.where(ok, x_right, x_left),
            None,
            state0,
            (lam, a),
            saveat=saveat,
            stepsize_controller=controller,
            adjoint=diffrax.ForwardMode(),
            max_steps=ode_max_steps,
            throw=False,
            # `Chebyshev.nodes` are sorted and inside `[xL, xR]`: no host callbacks
            # (diffrax's checks), so the program can be cached.
            save_times_checked=True,
        )
        # A solve that stopped short of `xR` (`max_steps`, the step floor) returns
        # the state where it stopped: as a residual at `xR` that would be wrong.
        reached = ok & (sol.result == diffrax.RESULTS.successful)
        ys = jax.tree.map(lambda v: jnp.where(reached, v, jnp.nan), sol.ys)
        return ys, sol.result

    def residual(unknowns, a):
        ys, _ = integrate(unknowns, a)
        y, _, integrals, _ = jax.tree.map(lambda v: v[-1], ys)
        targets = (
            jnp.stack([c.target(a, dtype) for c in functional.integral_constraints])
            if k
            else jnp.zeros((0,), dtype)
        )
        return y - yr.reshape(n), integrals - targets

    root = optx.root_find(
        residual,
        optx.Newton(rtol=root_tol, atol=root_tol),
        (slope0.reshape(n).astype(dtype), multipliers0),
        args,
        max_steps=max_steps,
        throw=False,
    )
    ys, final_result = integrate(root.value, args, nodes)
    y, _, _, running = ys
    result = RESULTS.promote(root.result)
    result = RESULTS.where(
        result == RESULTS.successful, RESULTS.promote(final_result), result
    )
    result = RESULTS.where(jnp.all(jnp.isfinite(y)), result, RESULTS.nonfinite)
    sol = FunctionalSolution(
        x=nodes,
        y=y.reshape((num_nodes,) + shape),
        multipliers=FunctionalMultipliers(integral=root.value[1], holonomic=None),
        value=running[-1],
        result=result,
        stats={"num_steps": root.stats["num_steps"], "max_steps": max_steps},
        interval=functional.interval,
        discretization=discretization,
    )
    # NaN derivatives for a failed solve (see `nan_derivatives_if_failed`).
    sol = nan_derivatives_if_failed(
        sol, (functional, args, slope0, multipliers0), result != RESULTS.successful
    )
    return sol
