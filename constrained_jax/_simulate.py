"""Simulate a constrained Lagrangian system with diffrax: the entry point, its checks,
and the trajectory it returns.

The state is `(q, qdot)`; the vector field is `(qdot, qddot)` with `qddot` from the KKT
solve of [`constrained_jax.LagrangianSystem`][] (`_vector_field.py`). A run is a
sequence of phases (`_phases.py`: one without contacts; with `Unilateral` groups, one
per contact mode). Multipliers, constraint forces, energy and constraint violation are
computed afterwards, only at the saved times and only if asked for (`SaveAt`), each
with the rows that held there.
"""

import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._adjoint import default_adjoint
from ._contact import Events
from ._diffrax_integrate import step_floor
from ._implicit import nan_derivatives_if_failed
from ._misc import (
    all_finite,
    as_traced_args,
    check_consistency_tol,
    check_max_steps,
    CONSISTENCY_TOLERANCE,
    float_tolerance,
    full_precision,
    inexact_asarray,
    SIMULATE_TOLERANCE,
    warn_near_mapping_limit,
)
from ._phases import (
    initial_contacts,
    integrator,
    Options,
    Plan,
    Run,
    run_contacts,
    signs_agree,
)
from ._results import error_if, raise_if_failed, RESULTS
from ._stabilization import AbstractStabilization, project_state, Unstabilized
from ._system import LagrangianSystem, off_constraints
from ._vector_field import solve_accelerations
from ._watch import each


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
        evaluations), summed over the phases.
    - `release`: for a system with a [`constrained_jax.Unilateral`][] constraint, a
        [`constrained_jax.Release`][] (when and where it let go, and re-contact);
        `None` otherwise. In the free phase the released rows of `multipliers` are
        `0`, and `violation` reports the released constraints' residuals as they are
        (a gap, not an error).
    - `events`: for a run with `max_events` (contacts that come and go), the
        [`constrained_jax.Events`][]: every release and impact in order; `None`
        otherwise (then `release` is `None`). The rows of `multipliers` of a group
        that is free at a saved time are `0`.
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
    release: "Release | None" = None
    events: Events | None = None


@full_precision
def consistent_initial_state(
    system: LagrangianSystem,
    q0,
    qd0,
    t0=0.0,
    args=None,
    *,
    iterations: int = 8,
    consistency_tol: float | None = None,
):
    """Project `(q0, qd0)` onto the constraint manifold, in the kinetic-energy metric.

    Positions by Gauss-Newton on the holonomic constraints (the smallest correction in
    the metric of `M`), velocities onto `A qdot + a = 0`. Returns `(q0, qd0)`.

    Raises (at run time, also under `jit`) if the projected state still violates the
    constraints beyond `consistency_tol` (the test of
    [`constrained_jax.simulate`][], with its default), or is not finite: the
    constraint Jacobian is singular at or near `q0` (the pendulum's rod `r = l` at
    the origin), `q0` is too far for
    `iterations` Gauss-Newton steps, or the constraints have no solution near `q0`.
    """
    q0 = inexact_asarray(q0)
    qd0 = jnp.asarray(qd0, q0.dtype)
    system.check(q0, qd0, t0, args)
    if consistency_tol is None:
        consistency_tol = float_tolerance(*CONSISTENCY_TOLERANCE, q0.dtype)
    else:
        consistency_tol = check_consistency_tol(consistency_tol)
    t0 = jnp.asarray(t0, q0.dtype)
    q, qd = project_state(system, q0, qd0, t0, args, iterations)
    bad = jnp.invert(all_finite((q, qd))) | off_constraints(
        system, q, qd, t0, args, consistency_tol
    )
    return error_if(
        (q, qd),
        bad,
        "`consistent_initial_state`: the projected state still violates the "
        "constraints (beyond `consistency_tol`) or is not finite. The constraint "
        "Jacobian may be singular at or near `q0` (e.g. the pendulum's rod at the "
        "origin), `q0` too far from the constraint surface for `iterations` "
        "Gauss-Newton steps (raise it), or the constraints without a solution near "
        "`q0`. Start nearer to the constraint surface.",
    )


@full_precision
def simulate(
    system: LagrangianSystem,
    t_span: tuple[float, float],
    q0,
    qd0,
    args=None,
    *,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stabilization: AbstractStabilization = Unstabilized(),
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    saveat: SaveAt = SaveAt(t1=True),
    dt0: float | None = None,
    max_steps: int = 16384,
    adjoint: diffrax.AbstractAdjoint | None = None,
    consistency_tol: float | None = None,
    progress_meter: diffrax.AbstractProgressMeter = diffrax.NoProgressMeter(),
    max_events: int | None = None,
    throw: bool = True,
) -> Trajectory:
    """Integrate the constrained equations of motion from `(q0, qd0)` at `t_span[0]`.

    **Arguments:**

    - `system`: a [`constrained_jax.LagrangianSystem`][].
    - `t_span`: `(t0, t1)`.
    - `q0`, `qd0`: the initial state, shape `(n,)`; it must satisfy the constraints
        to within `consistency_tol` (relative to `1 + |q0|`, `1 + |qd0|`); see
        [`constrained_jax.consistent_initial_state`][]. `consistency_tol=None`
        (default) follows the dtype of `q0`: `1e-8` in float64, `1000 eps = 1.2e-4`
        in float32. An explicit value below `10 eps` is warned about (round-off
        alone may exceed it); a negative or NaN one is refused (`ValueError`).
        Lists (`[1.0, 0.0]`) are the arrays they spell.
    - `args`: parameters, passed last to every user function (traced).
    - `solver`: any diffrax ODE solver, or a
        [`constrained_jax.VariationalIntegrator`][] (symplectic, fixed step `dt0`,
        constraints kept at every step; `stepsize_controller` is then ignored, the
        steps are chosen to land on the save times, and the run ends at the last
        save time).
    - `stabilization`: `Unstabilized()`, `Baumgarte(alpha, beta)` or `Projection()`.
    - `stepsize_controller`, `dt0`, `max_steps`: as in
        `diffrax.diffeqsolve`. `dt0=None` lets an adaptive controller choose.
        `dt0` is traced (another step size reuses the compiled program);
        `max_steps` is static (it sizes the buffers): a Python or NumPy integer.
        `stepsize_controller=None` (default) is
        `diffrax.PIDController(rtol=tol, atol=tol)` with `tol` following the dtype
        of `q0`: `1e-8` in float64, `100 eps = 1.2e-5` in float32 (where `1e-8`
        cannot be met). An explicit `PIDController` whose `rtol` and `atol` are
        both below `4 eps` of the dtype is warned about (the run would stop at
        `max_steps`), not changed.
    - `saveat`: a [`constrained_jax.SaveAt`][].
    - `adjoint`: how reverse-mode autodiff goes through the solve, a diffrax adjoint;
        `None` (default) is chosen per case: `jax.grad` runs in forward mode when few
        input scalars are differentiated (up to 16 for a small state) and by
        `diffrax.RecursiveCheckpointAdjoint()` otherwise (see
        `constrained_jax._adjoint` for the measurements). `jax.jvp` / `jax.jacfwd`
        need `diffrax.ForwardMode()`.
    - `progress_meter`: diffrax's progress meter for a long single run, e.g.
        `diffrax.TqdmProgressMeter()` (a bar per phase when a `Unilateral`
        constraint releases; refused by the variational integrator, which is not a
        diffrax loop). For many runs use [`constrained_jax.sweep`][], which has its
        own bar over chunks.
    - `max_events`: contacts that come and go (see
        [`constrained_jax.Unilateral`][]'s `restitution`). `None` (default): at most
        one `Unilateral`, released once, the run stopping at re-contact (with
        `RESULTS.recontact`: later save times are inf). An integer
        `N >= 1`: any number of `Unilateral` groups, each with a `gap` and a
        `restitution`, each released (its multiplier lets go) and re-made (its gap
        closes: an impact) independently, up to `N` events in all, in one compiled
        call; the run is a sequence of phases, one `diffrax.diffeqsolve` each, in a
        contact mode (which groups are attached). A group starts attached when its
        gap and the velocity residual of its rows are zero (to `consistency_tol`),
        else free; only the bilateral constraints and the attached groups must hold
        at the start. The events are in `traj.events`
        ([`constrained_jax.Events`][]). A run that needs more events stops with
        `RESULTS.max_events_reached` (later save times `inf`). Each phase has its
        own `max_steps`.
    - `throw`: raise on failure if `True`; otherwise report it in `result`.

    **Returns:** a [`constrained_jax.Trajectory`][].

    !!! note "Checked at every accepted step"

        - Divergence: a non-finite state, or a constraint residual that, as a distance
            (the residual over the row norm of the constraint Jacobian at the start),
            exceeds a quarter of the size of the state, stops the run with
            `RESULTS.diverged` (fixed steps included, which diffrax does not check).
            Smaller drift is not an error: it is reported in `violation`.
        - Step floor: an adaptive `diffrax.PIDController` without its own `dtmin`
            gets `dtmin = 16 eps max(|t0|, |t1|)` (not forced), and a step below it
            stops the run with `RESULTS.step_size_underflow` (or
            `RESULTS.singular_dynamics` where the KKT matrix is singular there). A
            vector field that is NaN just ahead of the state has every step rejected;
            without the floor the run went on to `max_steps`.
        - Release: the watched multiplier of a `Unilateral` is also sampled inside each
            step of the attached phase; an adaptive controller refines the steps where
            it changes sign between the ends or is not resolved, so a release inside a
            long step is found; a fixed step over such a sign change gives
            `RESULTS.release_missed`. A sign change in a window shorter than the
            sample spacing of the steps the state allows can still be missed: bound
            the step (`diffrax.PIDController(..., dtmax=...)`) when the forces have
            such short features.

    Time: `t1 < t0` integrates backwards (`dt0`, if given, negative), except with a
    `Unilateral` (refused: release is defined forwards in time). Save times outside
    `t_span` or not sorted in the direction of integration are refused (`ValueError`
    when concrete, `RESULTS.invalid_time_grid` when traced).

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
    if not isinstance(progress_meter, diffrax.AbstractProgressMeter):
        raise ValueError(
            "`progress_meter` must be a diffrax progress meter, e.g. "
            "`diffrax.TqdmProgressMeter()`."
        )
    integrate = integrator(solver)
    integrate.check(system, stabilization, dt0, progress_meter)
    max_steps = check_max_steps(max_steps)
    _check_max_events(system, max_events)
    unilateral = any(c.unilateral for c in system.constraints)
    args = as_traced_args(args)
    t0, t1 = t_span
    _check_time_grid(t0, t1, saveat.ts, dt0, unilateral)
    # Floating inputs keep their precision (float32 runs in float32); others become
    # the default float.
    q0 = inexact_asarray(q0)
    dtype = q0.dtype
    qd0 = jnp.asarray(qd0, dtype)
    system.check(q0, qd0, t0, args)
    stepsize_controller, consistency_tol = _dtype_defaults(
        stepsize_controller, consistency_tol, dtype
    )
    plan = Plan.make(system, q0.shape[0], args, dtype, max_events)
    options = Options(
        integrator=integrate,
        stabilization=stabilization,
        stepsize_controller=stepsize_controller,
        # A traced step: another `dt0` (a fixed-step convergence study, a sweep)
        # reuses the compiled program.
        dt0=None if dt0 is None else jnp.asarray(dt0, dtype),
        max_steps=max_steps,
        adjoint=default_adjoint(adjoint),
        progress_meter=progress_meter,
        saveat=saveat,
        consistency_tol=consistency_tol,
    )
    traj = _simulate(
        system,
        plan,
        options,
        jnp.asarray(t0, dtype),
        jnp.asarray(t1, dtype),
        q0,
        qd0,
        args,
    )
    return raise_if_failed(traj, throw)


def _check_max_events(system, max_events):
    """Refuse, at trace time, a `max_events` that does not fit the system."""
    groups = [c for c in system.constraints if c.unilateral]
    if max_events is None:
        if any(c.friction is not None for c in groups):
            raise ValueError(
                "A `cjax.Unilateral` with `cjax.Coulomb` friction sticks and slips: "
                "each transition is an event. Give it a `gap` and a `restitution` "
                "(`0.0`: contacts that close stay closed) and pass the budget of "
                "events, e.g. `simulate(..., max_events=16)`."
            )
        if len(groups) > 1:
            raise ValueError(
                "Without `max_events`, `simulate` handles one `cjax.Unilateral` "
                "constraint per system. Group the constraints that release together "
                "into one `Unilateral`, or give each group a `restitution` and pass "
                "`simulate(..., max_events=N)` for contacts released and re-made "
                "independently."
            )
        if any(c.restitution is not None for c in groups):
            raise ValueError(
                "A `cjax.Unilateral` with a `restitution` makes contacts that come "
                "and go: pass the budget of events, e.g. "
                "`simulate(..., max_events=32)`."
            )
        return
    if isinstance(max_events, bool) or not isinstance(max_events, (int, np.integer)):
        raise ValueError(
            f"`max_events` must be a positive integer or None; got {max_events!r}."
        )
    if max_events < 1:
        raise ValueError(f"`max_events` must be at least 1; got {max_events}.")
    if not groups:
        raise ValueError(
            "`max_events` counts the events of `cjax.Unilateral` constraints, and the "
            "system has none: leave it to `None`."
        )
    if any(c.restitution is None for c in groups):
        raise ValueError(
            "With `max_events`, every `cjax.Unilateral` needs a `gap` and a "
            "`restitution` (the impact law at re-contact; `restitution=0.0` re-makes "
            "the contact)."
        )


def _concrete(x):
    """`x` as a NumPy array, or `None` when it is traced."""
    try:
        return np.asarray(x)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError):
        return None


def _check_time_grid(t0, t1, ts, dt0, unilateral):
    """Refuse, at trace time, a time grid whose concrete values are invalid (traced
    values are checked in `_simulate`, which returns `RESULTS.invalid_time_grid`)."""
    t0, t1, ts, dt0 = (None if x is None else _concrete(x) for x in (t0, t1, ts, dt0))
    if t0 is None or t1 is None:
        return
    if unilateral and t1 < t0:
        raise ValueError(
            f"`t_span = ({t0}, {t1})` runs backwards: release events of a "
            "`cjax.Unilateral` constraint are defined forwards in time only (a contact "
            "force that may only push, watched as time increases). Pass `t0 <= t1`."
        )
    if dt0 is not None and not (np.isfinite(dt0) and dt0 != 0):
        raise ValueError(
            f"`dt0 = {dt0}`: the first step must be finite and nonzero (or `None`, "
            "for an adaptive controller to choose it)."
        )
    if dt0 is not None and t1 != t0 and np.sign(dt0) != np.sign(t1 - t0):
        raise ValueError(
            f"`dt0 = {dt0}` points away from `t1`: it must have the sign of "
            f"`t1 - t0 = {t1 - t0}`."
        )
    if ts is not None:
        lo, hi = min(t0, t1), max(t0, t1)
        if ts.size and (np.min(ts) < lo or np.max(ts) > hi):
            raise ValueError(
                f"`SaveAt(ts=...)` has times outside `t_span = ({t0}, {t1})` (from "
                f"{np.min(ts)} to {np.max(ts)}): every save time must lie in the span."
            )
        steps = np.diff(ts) if t1 >= t0 else -np.diff(ts)
        if np.any(steps < 0):
            raise ValueError(
                "`SaveAt(ts=...)` is not sorted in the direction of integration "
                "(increasing for `t0 <= t1`, decreasing for `t1 < t0`): sort it."
            )


def _time_grid_ok(t0, t1, ts, unilateral):
    """The checks of `_check_time_grid`, on traced values."""
    lo, hi = jnp.minimum(t0, t1), jnp.maximum(t0, t1)
    steps = jnp.where(t1 >= t0, jnp.diff(ts), -jnp.diff(ts))
    ok = jnp.all((ts >= lo) & (ts <= hi)) & jnp.all(steps >= 0)
    if unilateral:
        ok = ok & (t1 >= t0)
    return ok


def _dtype_defaults(stepsize_controller, consistency_tol, dtype):
    """The defaults that follow the dtype, and a warning for explicit tolerances
    that the dtype cannot reach."""
    eps = float(jnp.finfo(dtype).eps)
    if stepsize_controller is None:
        tol = float_tolerance(*SIMULATE_TOLERANCE, dtype)
        stepsize_controller = diffrax.PIDController(rtol=tol, atol=tol)
    elif isinstance(stepsize_controller, diffrax.PIDController):
        try:
            rtol = float(stepsize_controller.rtol)
            atol = float(stepsize_controller.atol)
        except (TypeError, jax.errors.ConcretizationTypeError):
            rtol = atol = None  # traced tolerances: not checked
        if rtol is not None and max(rtol, atol) < 4 * eps:
            warnings.warn(
                f"`stepsize_controller` has rtol={rtol:g}, atol={atol:g}, below what "
                f"{dtype} can reach (4 eps = {4 * eps:.1e}): the error estimate is "
                "round-off, and the run will likely stop at `max_steps`. Loosen the "
                "tolerances, leave `stepsize_controller` to its default (it follows "
                "the dtype), or enable float64 with "
                "`jax.config.update('jax_enable_x64', True)`.",
                UserWarning,
                stacklevel=3,
            )
    if consistency_tol is None:
        consistency_tol = float_tolerance(*CONSISTENCY_TOLERANCE, dtype)
    else:
        consistency_tol = check_consistency_tol(consistency_tol)
    if isinstance(consistency_tol, float) and consistency_tol < 10 * eps:
        warnings.warn(
            f"`consistency_tol={consistency_tol:g}` is below what {dtype} can check "
            f"(10 eps = {10 * eps:.1e}): a consistent initial state may be rejected. "
            "Leave it to its default (`None`, it follows the dtype).",
            UserWarning,
            stacklevel=3,
        )
    return stepsize_controller, consistency_tol


class Release(eqx.Module):
    """What happened to the [`constrained_jax.Unilateral`][] constraint of a run.

    **Attributes:**

    - `released`: whether the constraint let go (its multiplier's sign flipped, or it
        was already on the wrong side at the start).
    - `at_start`: released at `t0` because the initial state is already past release
        (the multiplier had the wrong sign): the whole run is free.
    - `time`: the release time (`t1` if never released), found by a root find of the
        multiplier along the attached motion.
    - `q`, `qd`: the state at release (the final attached state if never released).
    - `recontact`: whether the free phase ended at re-contact (`gap` fell through
        zero); the run stops there, and later save times are `inf`.
    - `recontact_time`: its time (`t1` if none).
    """

    released: Bool[Array, ""]
    at_start: Bool[Array, ""]
    time: Float[Array, ""]
    q: Float[Array, " n"]
    qd: Float[Array, " n"]
    recontact: Bool[Array, ""]
    recontact_time: Float[Array, ""]


@eqx.filter_jit
def _simulate(system, plan, options, t0, t1, q0, qd0, args):
    """The jitted core: the start checked, the phases run, the derived quantities
    computed at the save times, the status decided."""
    warn_near_mapping_limit()  # (at trace time: before a compilation)
    saveat, consistency_tol = options.saveat, options.consistency_tol
    start_ok = all_finite((q0, qd0, args, t0, t1, options.dt0))
    if plan.contacts:
        active0, slip0, consistent = initial_contacts(
            plan, system, q0, qd0, t0, args, consistency_tol
        )
        signs_ok = signs_agree(plan, system, q0, qd0, t0, args)
    else:
        active0, slip0, signs_ok = None, None, jnp.array(True)
        consistent = jnp.invert(
            off_constraints(system, q0, qd0, t0, args, consistency_tol)
        )
    # The user's save times, as one array (diffrax's own t0/t1 flags are folded in).
    parts = []
    if saveat.t0:
        parts.append(t0[None])
    if saveat.ts is not None:
        parts.append(jnp.asarray(saveat.ts, q0.dtype))
    if saveat.t1:
        parts.append(t1[None])
    ts = jnp.concatenate(parts)
    grid_ok = _time_grid_ok(t0, t1, ts, plan.contacts)
    # (diffrax raises on such save times whatever `throw` says: run on a valid grid,
    # and report `invalid_time_grid`.)
    ts = jnp.where(grid_ok, ts, t0)
    # A start with NaN or inf (in `q0`, `qd0`, `args`, the span or `dt0`) is refused
    # (`invalid_input`) and runs the empty span at a finite `t0`: integrated, its
    # steps would all be rejected until `max_steps`, and under `jax.vmap` (a sweep)
    # every other lane of the batch would wait for it.
    # A contact whose `sign` disagrees with its gap is refused the same way.
    runs = start_ok & signs_ok
    t_start = jnp.where(jnp.isfinite(t0), t0, jnp.zeros_like(t0))
    t0_run = jnp.where(runs, t0, t_start)
    t1_run = jnp.where(runs, t1, t_start)
    ts = jnp.where(runs, ts, t_start)
    controller, floored = step_floor(options.stepsize_controller, t0_run, t1_run)
    options = eqx.tree_at(lambda o: o.stepsize_controller, options, controller)
    if plan.contacts:
        run = run_contacts(
            plan,
            options,
            options.integrator.solver,
            system,
            t0_run,
            t1_run,
            q0,
            qd0,
            args,
            ts,
            active0,
            slip0,
        )
    else:
        ends = (saveat.t0, saveat.t1) if saveat.ts is None else None
        run = options.integrator.run(
            system, options, t0_run, t1_run, q0, qd0, args, ts, ends
        )
    derived = _derived(system, plan, options.stabilization, saveat, run, ts, args)
    result = _status(run, derived, saveat, floored)
    result = RESULTS.where(grid_ok, result, RESULTS.invalid_time_grid)
    result = RESULTS.where(signs_ok, result, RESULTS.contact_sign_mismatch)
    result = RESULTS.where(consistent, result, RESULTS.inconsistent_initial_state)
    result = RESULTS.where(start_ok, result, RESULTS.invalid_input)
    release = None if run.release is None else Release(*run.release)
    traj = Trajectory(
        ts=ts,
        q=derived["q"],
        qd=derived["qd"],
        multipliers=derived.get("multipliers"),
        constraint_forces=derived.get("constraint_forces"),
        energy=derived.get("energy"),
        violation=derived.get("violation"),
        result=result,
        stats=run.stats,
        release=release,
        events=run.events,
    )
    # The derivatives of a failed run are NaN (forward and reverse): `throw=True`
    # raises only where the trajectory itself is used (see `raise_if_failed`). A
    # release run stopped at re-contact keeps them: what it reached (the release,
    # the landing, the saves before it) is right.
    failed = (result != RESULTS.successful) & (result != RESULTS.recontact)
    return nan_derivatives_if_failed(traj, (system, q0, qd0, args, t0, t1), failed)


def _derived(system, plan, stabilization, saveat, run: Run, ts, args) -> dict:
    """The saved states (corrected by the stabilization), and what `saveat` asks for
    at them: each with the rows that held at its save time (`run.active`: the one
    form every kind of run gives), and the singular flag of the KKT solve at the last
    state reached."""
    masks = None
    if run.active is not None:
        masks = jax.vmap(plan.row_mask)(run.active, run.slip)
        if run.slip is not None:
            masks = (masks, jax.vmap(plan.slip_rows)(run.slip))
    end_mask = None
    if run.active_end is not None:
        end_mask = plan.row_mask(run.active_end, run.slip_end)
        if run.slip_end is not None:
            end_mask = (end_mask, plan.slip_rows(run.slip_end))

    def held(mask):
        # (A mode: the rows that hold, with friction also the slip per row.)
        if mask is None:
            return system
        return (
            system.with_active(*mask)
            if isinstance(mask, tuple)
            else (system.with_active(mask))
        )

    # Saved states between steps are interpolated: the stabilization may correct them
    # too (with the rows that held there; states never reached stay inf).
    row_masks = masks[0] if isinstance(masks, tuple) else masks
    q, qd = stabilization.project_saved(system, run.q, run.qd, ts, args, row_masks)
    out = {"q": q, "qd": qd}
    end = (run.q_end, run.qd_end, run.t_end)
    if saveat.multipliers:

        def one(q_, qd_, t_, mask=None):
            _, lam, singular = solve_accelerations(held(mask), q_, qd_, t_, args)
            return lam, singular

        only_t1 = saveat.t1 and not saveat.t0 and saveat.ts is None
        if only_t1 and masks is None:
            # The one saved state is the last state reached, if the run got to `t1`
            # (else it is inf): one solve serves both (`SaveAt(t1=True)`, the
            # default).
            got_there = jnp.all(jnp.isfinite(q[0]))
            point = jax.tree.map(
                lambda a, b: jnp.where(got_there, a, b), (q[0], qd[0], ts[0]), end
            )
            lam, singular_end = one(*point)
            # Not reached: as a solve at the inf state reports it (singular, zeros).
            lam_saved = jnp.where(got_there, lam, jnp.zeros_like(lam))[None]
            singular_saved = (singular_end | jnp.invert(got_there))[None]
        else:
            # One traced solve for the saves and the last state.
            points = jax.tree.map(
                lambda a, b: jnp.concatenate([a, b[None]]), (q, qd, ts), end
            )
            if masks is not None:
                both = jax.tree.map(
                    lambda a, b: jnp.concatenate([a, b[None]]), masks, end_mask
                )
                points = (*points, both)
            lam, singular = each(one, *points)
            lam_saved, singular_saved = lam[:-1], singular[:-1]
            singular_end = singular[-1]

        def constraint_force(q_, t_, lam_):
            return system.constraint_jacobian(q_, t_, args).T @ lam_

        out["multipliers"] = lam_saved
        # (The rows that do not hold have zero multipliers: the full `A` serves.)
        out["constraint_forces"] = each(constraint_force, q, ts, lam_saved, loop=False)
        out["singular_saved"] = singular_saved
    else:
        singular_end = solve_accelerations(held(end_mask), *end[:2], end[2], args)[2]
    out["singular_end"] = singular_end
    if saveat.energy:
        out["energy"] = each(
            lambda q_, qd_, t_: system.energy(q_, qd_, t_, args), q, qd, ts, loop=False
        )
    if saveat.violation:
        out["violation"] = {
            "position": each(
                lambda q_, t_: system.holonomic_residual(q_, t_, args),
                q,
                ts,
                loop=False,
            ),
            "velocity": each(
                lambda q_, qd_, t_: system.velocity_residual(q_, qd_, t_, args),
                q,
                qd,
                ts,
                loop=False,
            ),
        }
    return out


def _status(run: Run, derived: dict, saveat, floored: bool) -> RESULTS:
    """The run's result, with the causes only the saved states and the last state
    reached can tell."""
    result = run.result
    # A run that failed where the KKT matrix is singular failed because of it: the
    # vector field returns NaN there, so the steps were rejected until the budget ran
    # out. Only a finite state can tell that its KKT matrix is singular: at a state
    # that overflowed (a fixed step that blew up) the solve is non-finite whatever
    # the matrix, and the run has `diverged`.
    end_finite = all_finite((run.q_end, run.qd_end))
    singular = derived["singular_end"] & end_finite
    if saveat.multipliers:
        reached = jnp.all(jnp.isfinite(derived["q"]), axis=1)
        singular = singular | jnp.any(derived["singular_saved"] & reached)
    # A run stopped by the divergence check (the state left the manifold: a step too
    # large) keeps `diverged`, even where the runaway state's KKT matrix is singular.
    # (Nor does a Painleve paradox: its coupled system is singular by definition.)
    keep = (result == RESULTS.diverged) | (result == RESULTS.painleve_paradox)
    result = RESULTS.where(
        singular & (result != RESULTS.successful) & jnp.invert(keep),
        RESULTS.singular_dynamics,
        result,
    )
    # Fixed steps are not checked by diffrax: a blow-up to inf/NaN must not pass as
    # success, nor, whatever the cause, a saved state that is not finite.
    saved_finite = all_finite((run.q, run.qd))
    result = RESULTS.where(
        (result == RESULTS.successful) & jnp.invert(end_finite & saved_finite),
        RESULTS.nonfinite,
        result,
    )
    if floored:
        result = RESULTS.where(
            result == RESULTS.dt_min_reached, RESULTS.step_size_underflow, result
        )
    return result
