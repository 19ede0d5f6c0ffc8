"""Simulate a constrained Lagrangian system with diffrax.

The state is `(q, qdot)`; the vector field is `(qdot, qddot)` with `qddot` from the KKT
solve of [`constrained_jax.LagrangianSystem`][]. Multipliers, constraint forces,
energy and constraint violation are computed afterwards, only at the saved times and
only if asked for (`SaveAt`).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._misc import all_finite, as_traced_args, check_max_steps, inexact_asarray
from ._results import RESULTS
from ._stabilization import (
    AbstractStabilization,
    Baumgarte,
    project_state,
    ProjectedSolver,
    Projection,
    resolve_implicit_tolerances,
    Unstabilized,
)
from ._system import LagrangianSystem


class SaveAt(eqx.Module):
    """Which times to save, and which derived quantities to compute there.

    **Arguments:**

    - `t0`, `t1`: save the initial / final time.
    - `ts`: an array of times to save at (inside `[t0, t1]`).
    - `multipliers`: compute the multipliers `lambda` and the constraint forces
        `Q^c = A^T lambda` at the saved times.
    - `energy`: compute the energy function `qdot . dL/dqdot - L`.
    - `violation`: compute the position (`G`) and velocity (`A qdot + a`) residuals.
    """

    t0: bool = False
    t1: bool = False
    ts: Float[Array, " times"] | None = None
    multipliers: bool = True
    energy: bool = True
    violation: bool = True

    def __check_init__(self):
        if not (self.t0 or self.t1 or self.ts is not None):
            raise ValueError("`SaveAt` saves nothing: set `t0`, `t1` or `ts`.")


class Trajectory(eqx.Module):
    """The result of [`constrained_jax.simulate`][].

    **Attributes:**

    - `ts`: the saved times, shape `(T,)`.
    - `q`, `qd`: coordinates and velocities, shape `(T, n)`.
    - `multipliers`: `lambda`, shape `(T, k)`, or `None` if not asked for.
    - `constraint_forces`: `A^T lambda`, shape `(T, n)`, or `None`.
    - `energy`: shape `(T,)`, or `None`.
    - `violation`: `{"position": (T, k_holonomic), "velocity": (T, k)}`, or `None`.
    - `result`: a [`constrained_jax.RESULTS`][] member.
    - `stats`: diffrax's statistics (steps, accepted and rejected steps, function
        evaluations).
    """

    ts: Float[Array, " T"]
    q: Float[Array, "T n"]
    qd: Float[Array, "T n"]
    multipliers: Float[Array, "T k"] | None
    constraint_forces: Float[Array, "T n"] | None
    energy: Float[Array, " T"] | None
    violation: dict | None
    result: RESULTS
    stats: dict


def consistent_initial_state(
    system: LagrangianSystem, q0, qd0, t0=0.0, args=None, *, iterations: int = 8
):
    """Project `(q0, qd0)` onto the constraint manifold, in the kinetic-energy metric.

    Positions by Gauss-Newton on the holonomic constraints (the smallest correction in
    the metric of `M`), velocities onto `A qdot + a = 0`. Returns `(q0, qd0)`.
    """
    q0 = inexact_asarray(q0)
    qd0 = jnp.asarray(qd0, q0.dtype)
    system.check(q0, qd0, t0, args)
    return project_state(system, q0, qd0, jnp.asarray(t0, q0.dtype), args, iterations)


def _vector_field(system, stabilization):
    def field(t, y, args):
        q, qd = y
        correction = None
        if isinstance(stabilization, Baumgarte):
            correction = stabilization.bias_correction(system, q, qd, t, args)
        qdd, _, singular = system.solve_accelerations(q, qd, t, args, correction)
        # A singular KKT matrix makes the step fail (NaN rejected by the controller);
        # the status is recovered afterwards at the saved states.
        qdd = jnp.where(singular, jnp.nan, qdd)
        return qd, qdd

    return field


def simulate(
    system: LagrangianSystem,
    t_span: tuple[float, float],
    q0,
    qd0,
    args=None,
    *,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stabilization: AbstractStabilization = Unstabilized(),
    stepsize_controller: diffrax.AbstractStepSizeController = diffrax.PIDController(
        rtol=1e-8, atol=1e-8
    ),
    saveat: SaveAt = SaveAt(t1=True),
    dt0: float | None = None,
    max_steps: int = 16384,
    adjoint: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint(),
    consistency_tol: float = 1e-8,
    throw: bool = True,
) -> Trajectory:
    """Integrate the constrained equations of motion from `(q0, qd0)` at `t_span[0]`.

    **Arguments:**

    - `system`: a [`constrained_jax.LagrangianSystem`][].
    - `t_span`: `(t0, t1)`.
    - `q0`, `qd0`: the initial state, shape `(n,)`; it must satisfy the constraints
        to within `consistency_tol` (relative to `1 + |q0|`, `1 + |qd0|`); see
        [`constrained_jax.consistent_initial_state`][].
    - `args`: parameters, passed last to every user function (traced).
    - `solver`: any diffrax ODE solver.
    - `stabilization`: `Unstabilized()`, `Baumgarte(alpha, beta)` or `Projection()`.
    - `stepsize_controller`, `dt0`, `max_steps`, `adjoint`: as in
        `diffrax.diffeqsolve`. `dt0=None` lets an adaptive controller choose.
    - `saveat`: a [`constrained_jax.SaveAt`][].
    - `throw`: raise on failure if `True`; otherwise report it in `result`.

    **Returns:** a [`constrained_jax.Trajectory`][].

    Differentiable with respect to `args`, `q0` and `qd0` (diffrax's adjoints), and
    composes with `jax.jit` and `jax.vmap`.
    """
    if not isinstance(system, LagrangianSystem):
        raise ValueError("`system` must be a `cjax.LagrangianSystem`.")
    if not isinstance(stabilization, AbstractStabilization):
        raise ValueError(
            "`stabilization` must be `cjax.Unstabilized()`, `cjax.Baumgarte(...)` or "
            f"`cjax.Projection()`, got {type(stabilization).__name__}."
        )
    if not isinstance(saveat, SaveAt):
        raise ValueError("`saveat` must be a `cjax.SaveAt(...)`.")
    check_max_steps(max_steps)
    args = as_traced_args(args)
    t0, t1 = t_span
    # Floating inputs keep their precision (float32 runs in float32); others become
    # the default float.
    q0 = inexact_asarray(q0)
    dtype = q0.dtype
    qd0 = jnp.asarray(qd0, dtype)
    return _simulate(
        system,
        jnp.asarray(t0, dtype),
        jnp.asarray(t1, dtype),
        q0,
        qd0,
        args,
        solver,
        stabilization,
        stepsize_controller,
        saveat,
        dt0,
        max_steps,
        adjoint,
        consistency_tol,
        throw,
    )


@eqx.filter_jit
def _simulate(
    system,
    t0,
    t1,
    q0,
    qd0,
    args,
    solver,
    stabilization,
    stepsize_controller,
    saveat,
    dt0,
    max_steps,
    adjoint,
    consistency_tol,
    throw,
):
    system.check(q0, qd0, t0, args)
    start_ok = all_finite((q0, qd0, args, t0, t1))
    position = system.position_violation(q0, t0, args)
    velocity = system.velocity_violation(q0, qd0, t0, args)
    consistent = jnp.all(
        jnp.abs(position) <= consistency_tol * (1 + jnp.max(jnp.abs(q0)))
    ) & jnp.all(jnp.abs(velocity) <= consistency_tol * (1 + jnp.max(jnp.abs(qd0))))

    if isinstance(stabilization, Projection):
        solver = resolve_implicit_tolerances(solver, stepsize_controller)
        solver = ProjectedSolver(solver, system, stabilization.iterations)
    terms = diffrax.ODETerm(_vector_field(system, stabilization))
    # The user's times, and the last state reached (where a failed run stopped).
    diffrax_saveat = diffrax.SaveAt(
        subs=[
            diffrax.SubSaveAt(t0=saveat.t0, t1=saveat.t1, ts=saveat.ts),
            diffrax.SubSaveAt(t1=True),
        ]
    )
    sol = diffrax.diffeqsolve(
        terms,
        solver,
        t0,
        t1,
        dt0,
        (q0, qd0),
        args,
        saveat=diffrax_saveat,
        stepsize_controller=stepsize_controller,
        max_steps=max_steps,
        adjoint=adjoint,
        throw=False,
    )
    ts, ts_end = sol.ts
    (q, qd), (q_end, qd_end) = sol.ys
    if isinstance(stabilization, Projection):
        # Saved states between steps are interpolated: project them as well.
        q, qd = jax.vmap(
            lambda q_, qd_, t_: project_state(
                system, q_, qd_, t_, args, stabilization.iterations
            )
        )(q, qd, ts)

    def derived(q_, qd_, t_):
        out = {}
        if saveat.multipliers:
            _, lam, singular = system.solve_accelerations(q_, qd_, t_, args)
            out["multipliers"] = lam
            out["constraint_forces"] = system.constraint_jacobian(q_, t_, args).T @ lam
            out["singular"] = singular
        if saveat.energy:
            out["energy"] = system.energy(q_, qd_, t_, args)
        if saveat.violation:
            out["position"] = system.position_violation(q_, t_, args)
            out["velocity"] = system.velocity_violation(q_, qd_, t_, args)
        return out

    extra = jax.vmap(derived)(q, qd, ts)

    result = RESULTS.promote(sol.result)
    # A run that failed where the KKT matrix is singular failed because of it: the
    # vector field returns NaN there, so the steps were rejected until the budget ran
    # out. Checked at the last state reached (and at the saved states if available).
    _, _, singular = system.solve_accelerations(q_end[0], qd_end[0], ts_end[0], args)
    if saveat.multipliers:
        singular = singular | jnp.any(extra["singular"])
    result = RESULTS.where(
        singular & (result != RESULTS.successful), RESULTS.singular_dynamics, result
    )
    result = RESULTS.where(consistent, result, RESULTS.inconsistent_initial_state)
    result = RESULTS.where(start_ok, result, RESULTS.invalid_input)
    violation = None
    if saveat.violation:
        violation = {"position": extra["position"], "velocity": extra["velocity"]}
    traj = Trajectory(
        ts=ts,
        q=q,
        qd=qd,
        multipliers=extra.get("multipliers"),
        constraint_forces=extra.get("constraint_forces"),
        energy=extra.get("energy"),
        violation=violation,
        result=result,
        stats=sol.stats,
    )
    if throw:
        traj = result.error_if(traj, result != RESULTS.successful)
    return traj
