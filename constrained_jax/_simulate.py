"""Simulate a constrained Lagrangian system with diffrax.

The state is `(q, qdot)`; the vector field is `(qdot, qddot)` with `qddot` from the KKT
solve of [`constrained_jax.LagrangianSystem`][]. Multipliers, constraint forces,
energy and constraint violation are computed afterwards, only at the saved times and
only if asked for (`SaveAt`).
"""

import abc
import functools
import warnings
from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ._adjoint import default_adjoint
from ._contact import build_modes, Events, find_unilaterals, impact
from ._diffrax_integrate import diffeqsolve, step_floor
from ._implicit import nan_derivatives_if_failed
from ._misc import (
    all_finite,
    as_traced_args,
    check_max_steps,
    CONSISTENCY_TOLERANCE,
    float_tolerance,
    full_precision,
    inexact_asarray,
    SIMULATE_TOLERANCE,
)
from ._results import raise_if_failed, RESULTS
from ._stabilization import AbstractStabilization, project_state, Unstabilized
from ._system import LagrangianSystem, off_constraints, solve_dynamics
from ._variational_integrator import (
    AbstractVariationalIntegrator,
    integrate_variational,
)
from ._wrapped_solver import AbstractForwardingSolver, prepare_to_wrap


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
    the origin, where it used to return the origin unchanged), `q0` is too far for
    `iterations` Gauss-Newton steps, or the constraints have no solution near `q0`.
    """
    q0 = inexact_asarray(q0)
    qd0 = jnp.asarray(qd0, q0.dtype)
    system.check(q0, qd0, t0, args)
    if consistency_tol is None:
        consistency_tol = float_tolerance(*CONSISTENCY_TOLERANCE, q0.dtype)
    t0 = jnp.asarray(t0, q0.dtype)
    q, qd = project_state(system, q0, qd0, t0, args, iterations)
    bad = jnp.invert(all_finite((q, qd))) | off_constraints(
        system, q, qd, t0, args, consistency_tol
    )
    return eqx.error_if(
        (q, qd),
        bad,
        "`consistent_initial_state`: the projected state still violates the "
        "constraints (beyond `consistency_tol`) or is not finite. The constraint "
        "Jacobian may be singular at or near `q0` (e.g. the pendulum's rod at the "
        "origin), `q0` too far from the constraint surface for `iterations` "
        "Gauss-Newton steps (raise it), or the constraints without a solution near "
        "`q0`. Start nearer to the constraint surface.",
    )


def _solve_accelerations(system, q, qd, t, args, bias_correction=None):
    """`system.solve_accelerations`, traced once per system and shapes.

    Each trace of the equations of motion adds a copy of the derivatives of the
    Lagrangian to the traced program; one run calls them at many places (the vector
    field in diffrax's initial step and in the stages, the release event, the watched
    multiplier, the saved multipliers, the singular check), some of which diffrax
    traces more than once. Under `jit` the later calls reuse the first trace (and XLA
    inlines the calls, so the compiled program is the same). `t` is cast to the dtype
    of `q` (not weakly typed) so that every call site has the same signature.
    `qddot` is NaN where `singular` (see `_field`)."""
    t = jnp.asarray(t, q.dtype)
    return _jit_solve_accelerations(system, q, qd, t, args, bias_correction)


@eqx.filter_jit
def _jit_solve_accelerations(system, q, qd, t, args, bias_correction):
    return solve_dynamics(system, q, qd, t, args, bias_correction, fill=jnp.nan)


def _field_and_multipliers(system, stabilization):
    """`(t, (q, qdot), args) -> ((qdot, qddot), lambda)`: one KKT solve.

    (A `jax.tree_util.Partial`, not a closure: the arrays of `system`, a Lagrangian
    module's parameters say, are leaves of the vector field, so the solve's adjoint
    sees no closed-over array and traces the solve once, see `_adjoint.py`.)"""
    return jax.tree_util.Partial(_field, system, stabilization)


def _field(system, stabilization, t, y, args):
    q, qd = y
    correction = stabilization.bias_correction(system, q, qd, t, args)
    # A singular KKT matrix makes the step fail: `qdd` is then NaN, which the
    # controller rejects (set inside the solve's branches, where XLA fuses it: a
    # `where` here cost a two-cylinder trajectory 3.9 against 3.4 us per step); the
    # status is recovered afterwards at the saved states.
    qdd, lam, _ = _solve_accelerations(system, q, qd, t, args, correction)
    return (qd, qdd), lam


def _vector_field(system, stabilization):
    return jax.tree_util.Partial(_derivative, system, stabilization)


def _derivative(system, stabilization, t, y, args):
    return _field(system, stabilization, t, y, args)[0]


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
        alone may exceed it).
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
        `max_steps` is static (it sizes the buffers).
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
        one `Unilateral`, released once, the run stopping at re-contact. An integer
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
    driver = _driver(solver)
    driver.check(system, stabilization, dt0, progress_meter)
    check_max_steps(max_steps)
    _check_max_events(system, max_events)
    args = as_traced_args(args)
    t0, t1 = t_span
    _check_time_grid(t0, t1, saveat.ts, dt0, bool(find_unilaterals(system)))
    # Floating inputs keep their precision (float32 runs in float32); others become
    # the default float.
    q0 = inexact_asarray(q0)
    dtype = q0.dtype
    qd0 = jnp.asarray(qd0, dtype)
    stepsize_controller, consistency_tol = _dtype_defaults(
        stepsize_controller, consistency_tol, dtype
    )
    adjoint = default_adjoint(adjoint)
    # A traced step: another `dt0` (a fixed-step convergence study, a sweep) reuses
    # the compiled program.
    dt0 = None if dt0 is None else jnp.asarray(dt0, dtype)
    traj = _simulate(
        system,
        jnp.asarray(t0, dtype),
        jnp.asarray(t1, dtype),
        q0,
        qd0,
        args,
        driver,
        stabilization,
        stepsize_controller,
        saveat,
        dt0,
        max_steps,
        adjoint,
        consistency_tol,
        progress_meter,
        max_events,
    )
    return raise_if_failed(traj, throw)


def _check_max_events(system, max_events):
    """Refuse, at trace time, a `max_events` that does not fit the system."""
    groups = [c for _, c in find_unilaterals(system)]
    if max_events is None:
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
    elif isinstance(consistency_tol, (int, float)) and consistency_tol < 10 * eps:
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


def _find_unilateral(system):
    groups = find_unilaterals(system)
    if len(groups) > 1:
        raise ValueError(
            "Without `max_events`, `simulate` handles one `cjax.Unilateral` "
            "constraint per system. Group the constraints that release together into "
            "one `Unilateral`, or give each group a `restitution` and pass "
            "`simulate(..., max_events=N)` for contacts released and re-made "
            "independently."
        )
    return groups[0] if groups else None


# A state is taken as diverged when a constraint residual, as a distance (the residual
# over the row norm of the constraint Jacobian at the start of the phase), exceeds
# this fraction of the size of the state: not drift but a trajectory that has left
# the manifold (or is about to overflow).
_DIVERGED = 0.25
# Where the watched multiplier of a `Unilateral` is sampled inside each step of the
# attached phase (fractions of the step), besides its end, when the solver's stages
# cannot be read (see `_WatchedSolver`).
_WATCH_SAMPLES = (1 / 3, 2 / 3)
# A step of the attached phase is refined while the multiplier at the samples departs
# from the chord between its end values by more than this fraction of the larger end
# value (it is then not resolved well enough to trust its sign between samples).
_WATCH_ROUGHNESS = 0.25
# The widest gap, as a fraction of the step, between the points at which the watched
# multiplier is known inside a step of a Runge-Kutta solver (its stage times and the
# extra samples on the dense output).
_WATCH_GAP = 0.3


class _IllinoisState(eqx.Module):
    lower: Float[Array, ""]
    upper: Float[Array, ""]
    f_lower: Float[Array, ""]
    f_upper: Float[Array, ""]
    side: Int[Array, ""]
    t: Float[Array, ""]
    f: Float[Array, ""]
    diff: Float[Array, ""]
    stage: Int[Array, ""]  # 0: evaluate `lower`, 1: `upper`, 2: secant steps


class _Illinois(optx.AbstractRootFinder):
    """The release (and re-contact) time: a bracketed secant (Illinois) root find
    along the dense output of the step where the event changed sign.

    Derivative-free (Newton would differentiate the KKT solve along the
    interpolation: a copy of its derivative in the program for nothing), and never
    leaves the bracket `[lower, upper]` that diffrax passes in `options`. The event
    function is evaluated once per step, at one point (the bracket's ends at the first
    two steps, the new iterate after), so that it is traced once and not batched (a
    `jax.vmap` over two points would turn the `lax.cond`s of the KKT solve inside it
    into selects that run, and compile, both branches). It stops as `optx.Newton`
    does, when the last step is below `atol + rtol |t|` and the value below `atol`, or
    when the bracket has shrunk to round-off; convergence is superlinear (order about
    1.44), so the root is at round-off when it stops. diffrax zeroes all event values
    but the triggered one's: their sum is the function whose root is found.
    """

    rtol: float
    atol: float
    norm: Callable = jnp.abs

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del y, fn, args, f_struct, aux_struct, tags
        dtype = jnp.result_type(options["lower"])
        lower = jnp.asarray(options["lower"], dtype)
        upper = jnp.asarray(options["upper"], dtype)
        inf = jnp.asarray(jnp.inf, dtype)
        return _IllinoisState(
            lower, upper, inf, inf, jnp.array(0), upper, inf, inf, jnp.array(0)
        )

    @staticmethod
    def _secant(a, b, fa, fb):
        denominator = jnp.where(fb == fa, 1, fb - fa)
        # (A sign change, or a root at an end, is given; the clip guards round-off.)
        secant = jnp.clip(
            (a * fb - b * fa) / denominator, jnp.minimum(a, b), jnp.maximum(a, b)
        )
        return jnp.where(fb == 0, b, jnp.where(fa == 0, a, secant))

    def step(self, fn, y, args, options, state, tags):
        del y, options, tags
        a, b, fa, fb = state.lower, state.upper, state.f_lower, state.f_upper
        stage = state.stage
        t = jnp.where(
            stage == 0, a, jnp.where(stage == 1, b, self._secant(a, b, fa, fb))
        )
        values, aux = fn(t, args)
        f = sum(jnp.asarray(v, t.dtype) for v in jax.tree.leaves(values))
        # `t` replaces the end whose value has the same sign; an end kept twice in a
        # row has its value halved (Illinois), so that both ends converge.
        replace_upper = jnp.sign(f) == jnp.sign(fb)
        side = jnp.where(replace_upper, -1, 1)
        halve = jnp.where(side == state.side, 0.5, 1.0)
        update = _IllinoisState(
            lower=jnp.where(replace_upper, a, t),
            upper=jnp.where(replace_upper, t, b),
            f_lower=jnp.where(replace_upper, halve * fa, f),
            f_upper=jnp.where(replace_upper, f, halve * fb),
            side=side,
            t=t,
            f=f,
            diff=t - state.t,
            stage=jnp.array(2),
        )
        # The first two steps only record `f(lower)`, then `f(upper)`; a root found
        # at `lower` ends the search there (`f == 0`, `terminate`).
        at_lower = _IllinoisState(
            a, b, f, fb, jnp.array(0), a, f, jnp.inf, jnp.array(1)
        )
        at_upper = _IllinoisState(
            a, b, fa, f, jnp.array(0), b, f, jnp.inf, jnp.array(2)
        )
        new = jax.tree.map(
            lambda x, y_, z: jnp.where(stage == 0, x, jnp.where(stage == 1, y_, z)),
            at_lower,
            at_upper,
            update,
        )
        return t, new, aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, args, options, tags
        small_step = jnp.abs(state.diff) < self.atol + self.rtol * jnp.abs(y)
        eps = jnp.finfo(jnp.result_type(y)).eps
        collapsed = jnp.abs(state.upper - state.lower) <= 4 * eps * jnp.maximum(
            jnp.abs(state.upper), jnp.abs(state.lower)
        )
        done = (small_step & (jnp.abs(state.f) < self.atol)) | collapsed
        # (Before both ends are evaluated only an exact root stops it.)
        started = state.stage == 2
        return (started & done) | (state.f == 0), optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


def _diverged_condition(system, q_ref, t_ref, args):
    """A boolean event: non-finite state, or constraint residuals beyond `_DIVERGED`.

    Checked by diffrax at every accepted step (fixed steps included, where diffrax
    checks nothing). The residuals are scaled by the row norms of `A` at `q_ref`, so
    that the bound reads as a distance and does not depend on how `G` is written.

    (A `jax.tree_util.Partial`, not a closure: the row norms are a leaf of the event,
    so the solve's adjoint sees no closed-over array, see `_adjoint.py`.)
    """
    jac = system.constraint_jacobian(q_ref, t_ref, args)
    row_norms = None
    if jac.shape[0]:
        tiny = jnp.finfo(q_ref.dtype).tiny
        row_norms = jnp.maximum(jnp.linalg.norm(jac, axis=1), tiny)
    return jax.tree_util.Partial(_diverged, system, row_norms)


def _diverged(system, row_norms, t, y, args, **kwargs):
    del kwargs
    q, qd = y
    bad = jnp.invert(all_finite((q, qd)))
    if row_norms is not None:
        position = system.position_residual(q, t, args) / row_norms
        velocity = system.velocity_residual(q, qd, t, args) / row_norms
        bad = (
            bad
            | jnp.any(jnp.abs(position) > _DIVERGED * (1 + jnp.max(jnp.abs(q))))
            | jnp.any(jnp.abs(velocity) > _DIVERGED * (1 + jnp.max(jnp.abs(qd))))
        )
    return bad


def _gap_below(group, delta, t, y, args, **kwargs):
    """Re-contact condition: the group's gap plus `delta` (falls through zero)."""
    del kwargs
    return group.gap(y[0], t, args) + delta


class _WatchedSolver(AbstractForwardingSolver):
    """The attached phase's solver: samples the watched multiplier inside each step.

    diffrax evaluates an event condition only at the ends of the steps, and the state
    of an attached motion can be so smooth (even exactly linear: a body resting on a
    floor) that the controller takes steps far longer than the time the multiplier
    stays of one sign. So each step also looks at the multiplier inside the step, and

    - a step whose ends keep the sign but a sample does not is rejected (adaptive
        controllers then shrink it until an end lies past the sign change, where the
        release event brackets it and root-finds); under a fixed-step controller, which
        cannot reject, it fails with `RESULTS.release_missed` (signalled as diffrax's
        `dt_min_reached`, which a fixed-step controller never reports);
    - a step along which the samples depart from the chord of the end values by more
        than `_WATCH_ROUGHNESS` of the larger end value is rejected (adaptive only), so
        that the steps resolve the multiplier where it comes near zero.

    The samples. A Runge-Kutta solver (not wrapped by `Projection`) integrates the
    state together with a dummy component whose derivative is the watched multiplier
    (`stages`: the vector field and the multipliers from one KKT solve), so its
    stages hand over the multiplier at every stage time for free, and at the end of
    the step too for a first-same-as-last tableau. Where the stage times leave a gap
    wider than `_WATCH_GAP` of the step (Tsit5: between 0.327 and 0.9), the
    multiplier is also evaluated on the dense output there (`_gap_samples`). Other
    solvers sample the dense output at `_WATCH_SAMPLES`. The dummy component takes no
    part in the error estimate, so the steps, and the state, are the same as without
    it.

    The multiplier at the start of the step is carried in the solver state; at the
    start of the phase it is `start` (computed once, by `_release_run`).
    """

    solver: diffrax.AbstractSolver
    watch: Callable
    start: Float[Array, ""]
    adaptive: bool = eqx.field(static=True)
    stages: Callable | None = None

    def _tableau(self):
        """The Butcher tableau whose stages carry the multiplier, or `None`."""
        if self.stages is None or not isinstance(
            self.solver, diffrax.AbstractRungeKutta
        ):
            return None
        tableau = getattr(self.solver, "tableau", None)
        return tableau if isinstance(tableau, diffrax.ButcherTableau) else None

    def init(self, terms, t0, t1, y0, args):
        w0 = self.start
        if self._tableau() is None:
            return self.solver.init(terms, t0, t1, y0, args), w0
        stages = diffrax.ODETerm(self.stages)
        return self.solver.init(stages, t0, t1, (y0, w0), args), w0

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner_state, w0 = solver_state
        tableau = self._tableau()
        dtype = jnp.result_type(t0)
        if tableau is None:
            y1, y_error, dense_info, inner_state, result = self.solver.step(
                terms, t0, t1, y0, args, inner_state, made_jump
            )
            theta = np.asarray(_WATCH_SAMPLES)
            w1 = self.watch(t1, y1, args)
            ws = jnp.zeros((0,), dtype)
            theta_stages = np.zeros((0,))
        else:
            (y1, _), y_error, dense, inner_state, result = self.solver.step(
                diffrax.ODETerm(self.stages),
                t0,
                t1,
                (y0, w0),
                args,
                inner_state,
                made_jump,
            )
            # The dummy component is dropped: from the error (so that it does not
            # steer the step size) and from the dense output.
            y_error = None if y_error is None else y_error[0]
            dense_info = {key: value[0] for key, value in dense.items()}
            # The multiplier at the stages (diffrax keeps the stage increments,
            # derivative times step).
            ws = dense["k"][1] / (t1 - t0)
            theta_stages = np.concatenate([[0.0], np.asarray(tableau.c)])
            w1 = ws[-1] if tableau.fsal else self.watch(t1, y1, args)
            theta = _gap_samples(theta_stages)
        if theta.size:
            interpolation = self.solver.interpolation_cls(t0=t0, t1=t1, **dense_info)
            ts = t0 + jnp.asarray(theta, dtype) * (t1 - t0)
            sample = lambda t: self.watch(t, interpolation.evaluate(t), args)
            # Unbatched (`_each`): the solve traced already for the stages, not a
            # batched copy of it; Tsit5 has one sample.
            ws = jnp.concatenate([ws, _each(sample, ts)])
        theta = jnp.asarray(np.concatenate([theta_stages, theta]), dtype)
        dipped = (w0 >= 0) & (w1 >= 0) & jnp.any(ws < 0)
        if self.adaptive:
            chord = w0 + theta * (w1 - w0)
            rough = (w0 > 0) & (
                jnp.max(jnp.abs(ws - chord))
                > _WATCH_ROUGHNESS * jnp.maximum(jnp.abs(w0), jnp.abs(w1))
            )
            reject = dipped | rough
            if y_error is not None:
                y_error = jax.tree.map(lambda e: jnp.where(reject, jnp.inf, e), y_error)
        else:
            # (A fixed-step controller never reports `dt_min_reached`: `_simulate`
            # reads it back as `RESULTS.release_missed`.)
            result = diffrax.RESULTS.where(
                dipped, diffrax.RESULTS.dt_min_reached, result
            )
        return y1, y_error, dense_info, (inner_state, w1), result


def _each(fn, *points, loop: bool = True):
    """`fn` at each of `points` (arrays with a leading axis: the saved states, the
    samples of `_WatchedSolver`): a plain call for one point; else with `loop` a loop
    around the unbatched function (`lax.map`), without it `jax.vmap`.

    The loop for the KKT solve: a batched KKT solve is a program of its own, with
    the batch's `lax.cond` and both branches, to trace and compile, while the steps
    have traced the unbatched one already (the tour's two cylinders, 121 saves in
    two phases: the first call 4.5 -> 3.7 s; the run 2 % slower, and at 1,000 saves
    0.9 -> 1.5 ms with XLA's defaults, 0.30 -> 0.32 ms with `use_loop_kernels()`,
    `benchmarks/README.md`). `jax.vmap` for `A`, the energy and the residuals, which
    compile batched about as fast (a loop for `A` made no difference either way).
    One point, a plain call: the first `jit(simulate)` of the two cylinders
    (`SaveAt(t1=True)`) 4 % faster than with a `jax.vmap` over one, and the tour's
    release program (one sample per step) about 10 % faster."""
    if jax.tree.leaves(points)[0].shape[0] == 1:
        out = fn(*jax.tree.map(lambda x: x[0], points))
        return jax.tree.map(lambda x: x[None], out)
    if loop:
        return jax.lax.map(lambda point: fn(*point), points)
    return jax.vmap(fn)(*points)


class _Phase(eqx.Module):
    """One diffrax solve (`_run_phase`): the states at the save times, the last state
    reached, and diffrax's result, statistics and event mask."""

    saved: tuple[Float[Array, "T n"], Float[Array, "T n"]] | None
    t_end: Float[Array, ""]
    q_end: Float[Array, " n"]
    qd_end: Float[Array, " n"]
    result: diffrax.RESULTS
    stats: dict
    event_mask: Any


def _gap_samples(theta_stages: np.ndarray) -> np.ndarray:
    """Fractions of the step at which to sample the dense output, so that with the
    stage times no gap is wider than `_WATCH_GAP`: the midpoint of the widest gap,
    again and again (static, numpy)."""
    points = sorted({float(t) for t in theta_stages if 0.0 <= t <= 1.0} | {0.0, 1.0})
    extra = []
    while True:
        gaps = np.diff(points)
        i = int(np.argmax(gaps))
        if gaps[i] <= _WATCH_GAP:
            return np.asarray(extra, dtype=float)
        mid = 0.5 * (points[i] + points[i + 1])
        extra.append(mid)
        points = sorted(points + [mid])


def _run_phase(
    system,
    t0,
    t1,
    y0,
    ts,
    event,
    watch=None,
    *,
    args,
    solver,
    stabilization,
    stepsize_controller,
    dt0,
    max_steps,
    adjoint,
    progress_meter,
    adaptive=True,
) -> _Phase:
    """One diffrax solve of `system` from `(t0, y0)` to `t1`, saving at `ts` (or not,
    if `None`).

    `event` is a tuple of condition functions (the phase's own, if any, then the
    divergence check); `watch`, if given, is `(watch_fn, pick)`: the multiplier the
    attached phase samples inside each step, as a function of the state and as a
    function of all the multipliers (`_WatchedSolver`), and its value at `(t0, y0)`,
    under an `adaptive` controller or not."""
    solver = stabilization.wrap_solver(solver, system, stepsize_controller, adjoint)
    if watch is not None:
        watch_fn, pick, start = watch
        field = _field_and_multipliers(system, stabilization)

        def stages(t, y_and_w, args):
            derivative, lam = field(t, y_and_w[0], args)
            return derivative, pick(lam)

        solver = prepare_to_wrap(solver, stepsize_controller, adjoint)
        solver = _WatchedSolver(solver, watch_fn, start, adaptive, stages)
    terms = diffrax.ODETerm(_vector_field(system, stabilization))
    subs = [diffrax.SubSaveAt(t1=True)]
    if ts is not None:
        subs.append(diffrax.SubSaveAt(ts=ts))
    sol = diffeqsolve(
        terms,
        solver,
        t0,
        t1,
        dt0,
        y0,
        args,
        saveat=diffrax.SaveAt(subs=subs),
        stepsize_controller=stepsize_controller,
        max_steps=max_steps,
        adjoint=adjoint,
        event=event,
        progress_meter=progress_meter,
        throw=False,
        # `simulate` made `ts` valid (`_time_grid_ok`, then clipped to each phase's
        # span): no host callbacks, so the program can be cached.
        save_times_checked=True,
    )
    (q_end, qd_end) = sol.ys[0]
    return _Phase(
        saved=sol.ys[1] if ts is not None else None,
        t_end=sol.ts[0][0],
        q_end=q_end[0],
        qd_end=qd_end[0],
        result=sol.result,
        stats=sol.stats,
        event_mask=sol.event_mask,
    )


class _ReleasePhases(eqx.Module):
    """Where the save times of a release run fall: in the `attached` phase (the full
    system), after re-contact (`beyond`: not computed, `inf`), or else in the free
    phase (the system `free`, without the `Unilateral`, whose multipliers fill the
    rows `keep_rows` of the full system's)."""

    attached: Bool[Array, " T"]
    beyond: Bool[Array, " T"]
    free: LagrangianSystem
    keep_rows: Int[Array, " k_free"]

    def combine(self, attached: Float[Array, "T n"], free: Float[Array, "T n"]):
        """The attached phase's rows where attached, `inf` beyond re-contact, and
        the free phase's rows elsewhere."""
        return jnp.where(
            self.attached[:, None],
            attached,
            jnp.where(self.beyond[:, None], jnp.inf, free),
        )


class _Run(eqx.Module):
    """What a driver's integration gives `_simulate`: the states at the save times,
    the last state reached, the result and statistics, and for a release run the
    [`constrained_jax.Release`][] and its `_ReleasePhases` (`None` otherwise)."""

    q: Float[Array, "T n"]
    qd: Float[Array, "T n"]
    t_end: Float[Array, ""]
    q_end: Float[Array, " n"]
    qd_end: Float[Array, " n"]
    result: RESULTS
    stats: dict
    release: Release | None = None
    phases: "_ReleasePhases | _ModePhases | None" = None
    events: Events | None = None


class _ModePhases(eqx.Module):
    """Where the save times of a run with `max_events` fall: `mode[i]` is the contact
    mode at save time `i` (`-1` past the end of the run: `inf`), `systems[m]` the
    system of mode `m` and `keep_rows[m]` the rows of the full system it keeps."""

    mode: Int[Array, " T"]
    end_mode: Int[Array, ""]
    systems: tuple
    keep_rows: tuple

    def select(self, per_mode, mode=None):
        """`per_mode[m]` where the mode is `m` (stacked along the first axis)."""
        mode = self.mode if mode is None else mode
        out = per_mode[0]
        for m in range(1, len(per_mode)):
            shape = mode.shape + (1,) * (per_mode[m].ndim - mode.ndim)
            out = jnp.where((mode == m).reshape(shape), per_mode[m], out)
        return out


class _AbstractDriver(eqx.Module):
    """How `simulate` runs one kind of `solver`: `check` (in `simulate`, at trace
    time) refuses what it cannot do, `run` (in `_simulate`) integrates."""

    @abc.abstractmethod
    def check(self, system, stabilization, dt0, progress_meter) -> None:
        """Raise a `ValueError` for the options this solver cannot honour."""

    @abc.abstractmethod
    def run(self, system, t0, t1, q0, qd0, args, ts, **options) -> _Run:
        """Integrate from `(q0, qd0)` at `t0` to `t1`, saving at `ts`; `options` are
        `simulate`'s `stabilization`, `stepsize_controller`, `dt0`, `max_steps`,
        `adjoint` and `progress_meter`, and `ends`: `(save t0, save t1)` when `ts`
        is only those ends (a driver may then save them more cheaply), else
        `None`."""


class _DiffraxDriver(_AbstractDriver):
    """A diffrax solver: one phase, or for a `Unilateral` an attached and a free one."""

    solver: diffrax.AbstractSolver

    def check(self, system, stabilization, dt0, progress_meter):
        pass  # Every stabilization, release events and progress meters.

    def run(
        self,
        system,
        t0,
        t1,
        q0,
        qd0,
        args,
        ts,
        *,
        ends=None,
        max_events=None,
        modes=None,
        mode0=None,
        **options,
    ):
        phase = functools.partial(_run_phase, args=args, solver=self.solver, **options)
        adaptive = isinstance(
            options["stepsize_controller"], diffrax.AbstractAdaptiveStepSizeController
        )
        if max_events is not None:
            return _event_run(
                phase, modes, mode0, max_events, t0, t1, q0, qd0, args, ts, adaptive
            )
        found = _find_unilateral(system)
        if found is not None:
            return _release_run(
                phase, system, found, t0, t1, q0, qd0, args, ts, adaptive
            )
        diverged_event = diffrax.Event(_diverged_condition(system, q0, t0, args))
        if ends is None:
            one = phase(system, t0, t1, (q0, qd0), ts, diverged_event)
            q, qd = one.saved
        else:
            # Only the ends are saved: from the last state reached, not by a save
            # loop over `ts` (a smaller program). As diffrax saves `ts`, an end not
            # reached is `inf`: `t1` if the run stopped early, `t0` too if it
            # stopped before its first accepted step.
            one = phase(system, t0, t1, (q0, qd0), None, diverged_event)
            reached = one.t_end == t1
            started = reached | (one.stats["num_accepted_steps"] > 0)

            def mask(saved, ok):
                return jax.tree.map(lambda x: jnp.where(ok, x, jnp.inf), saved)

            saved = [mask((q0, qd0), started)] if ends[0] else []
            if ends[1]:
                saved.append(mask((one.q_end, one.qd_end), reached))
            q, qd = (jnp.stack(xs) for xs in zip(*saved, strict=True))
        result = RESULTS.where(
            one.result == diffrax.RESULTS.event_occurred,
            RESULTS.diverged,
            RESULTS.promote(one.result),
        )
        return _Run(q, qd, one.t_end, one.q_end, one.qd_end, result, one.stats)


class _VariationalDriver(_AbstractDriver):
    """A [`constrained_jax.AbstractVariationalIntegrator`][]: fixed steps that land on
    the save times, its own loop (not diffrax's), the constraints kept at every step."""

    integrator: AbstractVariationalIntegrator

    def check(self, system, stabilization, dt0, progress_meter):
        if dt0 is None:
            raise ValueError(
                "A variational integrator takes fixed steps: pass the step size, e.g. "
                "`simulate(..., solver=cjax.VariationalIntegrator(), dt0=0.01)`."
            )
        if not isinstance(stabilization, Unstabilized):
            raise ValueError(
                "A variational integrator enforces the constraints itself at every "
                "step: use `stabilization=cjax.Unstabilized()` (the default)."
            )
        if find_unilaterals(system):
            raise ValueError(
                "Release events (`cjax.Unilateral`) are not implemented for the "
                "variational integrator; use a diffrax solver."
            )
        if not isinstance(progress_meter, diffrax.NoProgressMeter):
            raise ValueError(
                "`progress_meter` is not supported by the variational integrator (it "
                "runs its own loop, not diffrax's): leave it to its default "
                "`diffrax.NoProgressMeter()`, use a diffrax solver for a progress bar "
                "of one run, or `cjax.sweep` for a bar over many runs."
            )

    def run(self, system, t0, t1, q0, qd0, args, ts, *, dt0, max_steps, **options):
        del options  # Checked in `check` (or `ends`, not needed): nothing to honour.
        variational = integrate_variational(
            self.integrator,
            system,
            t0,
            t1,
            dt0,
            q0,
            qd0,
            args,
            ts_save=ts,
            max_steps=max_steps,
            # `simulate` has tested the start with its own `consistency_tol`: the
            # variational integrator does not test it again.
            consistency_tol=float("inf"),
            throw=False,
        )
        q, qd = variational.q, variational.qd
        return _Run(q, qd, ts[-1], q[-1], qd[-1], variational.result, variational.stats)


@functools.singledispatch
def _driver(solver) -> _AbstractDriver:
    """The driver of a `solver`: dispatched on its type (the solver families are not
    ours to give a method), a `ValueError` for anything else."""
    raise ValueError(
        "`solver` must be a diffrax solver (e.g. `diffrax.Tsit5()`) or "
        f"`cjax.VariationalIntegrator()`, got {type(solver).__name__}."
    )


@_driver.register
def _(solver: diffrax.AbstractSolver):
    return _DiffraxDriver(solver)


@_driver.register
def _(solver: AbstractVariationalIntegrator):
    return _VariationalDriver(solver)


def _release_run(phase, system, found, t0, t1, q0, qd0, args, ts, adaptive) -> _Run:
    """Phase 1, attached, until the `Unilateral`'s multiplier falls through zero;
    phase 2, free, from there to `t1` or to re-contact."""
    index, group = found
    free = system.without(index)
    row = sum(
        c.num_constraints(q0.shape[0], args, q0.dtype)
        for c in system.constraints[:index]
    )

    def watched(lam):
        return group.sign * lam[row]

    def contact_force(t, y, args, **kwargs):
        del kwargs
        _, lam, _ = _solve_accelerations(system, y[0], y[1], t, args)
        return watched(lam)

    force_at_start = contact_force(t0, (q0, qd0), args)
    at_start = force_at_start < 0
    # Root-finding tolerance: 1e-12, raised to 100 eps in float32 (unreachable).
    root_tol = float_tolerance(1e-12, 100.0, q0.dtype)
    release_event = diffrax.Event(
        (contact_force, _diverged_condition(system, q0, t0, args)),
        root_finder=_Illinois(rtol=root_tol, atol=root_tol),
    )
    # Phase 1, attached: from t0 until the multiplier falls through zero (an empty
    # phase if it already has the wrong sign).
    # (diffrax needs t0 < t1: the empty phase is a tiny one, discarded.)
    tiny = 64 * jnp.finfo(q0.dtype).eps * (1 + jnp.abs(t0))
    t_attach_end = jnp.where(at_start, t0 + tiny, t1)
    attached_phase = phase(
        system,
        t0,
        t_attach_end,
        (q0, qd0),
        jnp.clip(ts, t0, t_attach_end),
        release_event,
        (contact_force, watched, force_at_start),
        adaptive=adaptive,
    )
    result1 = attached_phase.result
    stopped = result1 == diffrax.RESULTS.event_occurred
    by_release = attached_phase.event_mask[0]
    released_by_event = stopped & by_release
    # (A fixed-step controller never reports `dt_min_reached`: it is `_WatchedSolver`
    # signalling a missed release.)
    missed = False if adaptive else result1 == diffrax.RESULTS.dt_min_reached
    result1 = RESULTS.where(
        stopped,
        RESULTS.where(by_release, RESULTS.successful, RESULTS.diverged),
        RESULTS.where(missed, RESULTS.release_missed, RESULTS.promote(result1)),
    )
    released = at_start | released_by_event
    t_rel = jnp.where(at_start, t0, jnp.where(released, attached_phase.t_end, t1))
    q_rel = jnp.where(at_start, q0, attached_phase.q_end)
    qd_rel = jnp.where(at_start, qd0, attached_phase.qd_end)
    result1 = RESULTS.where(at_start, RESULTS.successful, result1)
    # Phase 2, free: from the release to t1 (empty if never released), ending at
    # re-contact if a gap is given.
    diverged_free = _diverged_condition(free, q_rel, t_rel, args)
    recontact_event = diffrax.Event((diverged_free,))
    if group.gap is not None:
        # The gap is zero at release: re-contact is when it falls below
        # -delta, delta = sqrt(eps) (1 + |q_release|), so that round-off right
        # after release is not taken for a collision.
        delta = jnp.sqrt(jnp.finfo(q0.dtype).eps) * (1 + jnp.max(jnp.abs(q_rel)))
        recontact_event = diffrax.Event(
            (
                diverged_free,
                jax.tree_util.Partial(_gap_below, group, delta),
            ),
            root_finder=_Illinois(rtol=root_tol, atol=root_tol),
        )
    free_phase = phase(
        free, t_rel, t1, (q_rel, qd_rel), jnp.clip(ts, t_rel, t1), recontact_event
    )
    stopped2 = free_phase.result == diffrax.RESULTS.event_occurred
    by_divergence = free_phase.event_mask[0]
    recontact = stopped2 & jnp.invert(by_divergence)
    result2 = RESULTS.where(
        stopped2,
        RESULTS.where(by_divergence, RESULTS.diverged, RESULTS.successful),
        RESULTS.promote(free_phase.result),
    )
    n = q0.shape[0]
    k_all = sum(c.num_constraints(n, args, q0.dtype) for c in system.constraints)
    k_group = group.num_constraints(n, args, q0.dtype)
    phases = _ReleasePhases(
        attached=(ts <= t_rel) & jnp.invert(at_start),
        # After re-contact nothing is computed: those save times are inf.
        beyond=recontact & (ts > free_phase.t_end),
        free=free,
        keep_rows=jnp.asarray(
            [j for j in range(k_all) if not row <= j < row + k_group], int
        ),
    )
    stats1, stats2 = attached_phase.stats, free_phase.stats
    return _Run(
        q=phases.combine(attached_phase.saved[0], free_phase.saved[0]),
        qd=phases.combine(attached_phase.saved[1], free_phase.saved[1]),
        t_end=free_phase.t_end,
        q_end=free_phase.q_end,
        qd_end=free_phase.qd_end,
        result=RESULTS.where(result1 == RESULTS.successful, result2, result1),
        stats={
            k: stats1[k] + stats2[k] for k in stats1 if k in stats2 and k != "max_steps"
        },
        release=Release(
            released=released,
            at_start=at_start,
            time=t_rel,
            q=q_rel,
            qd=qd_rel,
            recontact=recontact,
            recontact_time=jnp.where(recontact, free_phase.t_end, t1),
        ),
        phases=phases,
    )


# How far below its starting value (or zero) a free group's gap must fall, in units
# of `eps (1 + |q|)`, for re-contact (see `_event_run`).
_GAP_MARGIN = 1000.0


def _initial_mode(modes, q0, qd0, t0, args, tol):
    """The contact mode at the start, and whether the start is consistent with it:
    a group is attached when its gap and the velocity residual of its rows are zero
    (to `tol`), free otherwise; no gap may be negative (penetration) beyond `tol`,
    and the rows of the bilateral constraints and of the attached groups must hold
    (positions and velocities, to `tol`)."""
    scale_q = tol * (1 + jnp.max(jnp.abs(q0)))
    scale_qd = tol * (1 + jnp.max(jnp.abs(qd0)))
    mode = jnp.array(0)
    ok = jnp.array(True)
    for i, group in enumerate(modes.groups):
        gap = group.gap(q0, t0, args)
        velocity = group.velocity_residual(q0, qd0, t0, args)
        attached = (jnp.abs(gap) <= scale_q) & jnp.all(jnp.abs(velocity) <= scale_qd)
        mode = mode + jnp.where(attached, 2**i, 0)
        ok = ok & (gap >= -scale_q)

    def residuals(m):
        sys_m = modes.systems[m]
        position = sys_m.holonomic_residual(q0, t0, args)
        velocity = sys_m.velocity_residual(q0, qd0, t0, args)
        return jnp.all(jnp.abs(position) <= scale_q) & jnp.all(
            jnp.abs(velocity) <= scale_qd
        )

    consistent = jax.lax.switch(
        mode, [functools.partial(residuals, m) for m in range(modes.num_modes)]
    )
    return mode, ok & consistent


def _event_run(phase, modes, mode0, max_events, t0, t1, q0, qd0, args, ts, adaptive):
    """Contacts that come and go: a sequence of phases, each one diffrax solve in a
    contact mode (`constrained_jax._contact`), ended by an event: a release (the
    smallest pushing multiplier of the attached groups falls through zero; that
    group is dropped) or an impact (a free group's gap falls through zero: the
    velocities jump, see `constrained_jax._contact.impact`, and with `e = 0` the
    group is attached again).

    `lax.scan` over `max_events + 1` phases (reverse-mode autodiff goes through it,
    unlike a `while_loop`); each step is a `lax.switch` on the mode, with one more
    branch, once the run is over, that passes the state through. Under `jax.jit`
    alone only the taken branch runs; under `jax.vmap` every branch does."""
    dtype = q0.dtype
    n = q0.shape[0]
    num_modes = modes.num_modes
    eps = jnp.finfo(dtype).eps
    tiny = 64 * eps * (1 + jnp.abs(t1))
    root_tol = float_tolerance(1e-12, 100.0, dtype)
    root_finder = _Illinois(rtol=root_tol, atol=root_tol)
    restitution, rest_speed = [], []
    for group in modes.groups:
        e = jnp.asarray(group.restitution_value(args), dtype)
        v = jnp.asarray(group.rest_speed_value(args), dtype)
        restitution.append(e)
        rest_speed.append(v)
    valid = jnp.all(
        jnp.stack(
            [
                (e >= 0) & (e <= 1) & (v >= 0)
                for e, v in zip(restitution, rest_speed, strict=True)
            ]
        )
    )
    # Invalid values run as inelastic impacts (the status says why).
    restitution = [jnp.where(valid, e, 0.0) for e in restitution]
    rest_speed = [jnp.where(valid, v, 0.0) for v in rest_speed]
    num_ts = ts.shape[0]
    inf = jnp.asarray(jnp.inf, dtype)
    zero_stats = {
        k: jnp.array(0)
        for k in ("num_steps", "num_accepted_steps", "num_rejected_steps")
    }
    carry = {
        "t": t0,
        "q": q0,
        "qd": qd0,
        "mode": jnp.asarray(mode0, int),
        "count": jnp.array(0),
        # A start with NaN or inf (refused by `_simulate` as `invalid_input`) runs
        # no phase: its steps would be rejected until `max_steps` (under `jax.vmap`
        # the whole batch waiting for it).
        "done": jnp.invert(all_finite((q0, qd0, args))),
        "result": RESULTS.successful,
        "q_saved": jnp.full((num_ts, n), inf),
        "qd_saved": jnp.full((num_ts, n), inf),
        "mode_saved": jnp.full((num_ts,), -1),
        "stats": zero_stats,
        "time": jnp.full((max_events,), inf),
        "group": jnp.full((max_events,), -1),
        "impact": jnp.zeros((max_events,), bool),
        "attached": jnp.zeros((max_events,), bool),
        "speed": jnp.zeros((max_events,), dtype),
        "impulse": jnp.zeros((max_events,), dtype),
        "q_event": jnp.full((max_events, n), inf),
        "qd_event": jnp.full((max_events, n), inf),
    }

    def mode_step(m, c):
        sys_m = modes.systems[m]
        attached, free = modes.attached(m), modes.free(m)
        t_start = jnp.minimum(c["t"], t1 - tiny)
        q, qd = c["q"], c["qd"]
        watch = None
        if attached:
            firsts = [modes.first_rows[m][i] for i in attached]
            signs = [modes.groups[i].sign for i in attached]

            def pushing(lam):
                # `sign * lambda` of each attached group's first row.
                return jnp.stack(
                    [s * lam[r] for s, r in zip(signs, firsts, strict=True)]
                )

            def pick(lam):
                return jnp.min(pushing(lam))

            def contact_force(t, y, args, **kwargs):
                del kwargs
                _, lam, _ = _solve_accelerations(sys_m, y[0], y[1], t, args)
                return pick(lam)

            _, lam_start, _ = _solve_accelerations(sys_m, q, qd, t_start, args)
            start = pick(lam_start)
            watch = (contact_force, pick, start)
        # A gap is zero (to the root find) where a phase starts at an event: it
        # closes when it falls `delta = 1000 eps (1 + |q|)` below where it starts
        # (or below zero), so that round-off right after a release or an impact is
        # not taken for a collision. (Smaller than the `sqrt(eps)` of `_release_run`:
        # each impact is found `delta / speed` late, a delay that adds up over a
        # series of bounces.)
        delta = _GAP_MARGIN * eps * (1 + jnp.max(jnp.abs(q)))
        offsets = [
            jnp.minimum(modes.groups[i].gap(q, t_start, args), 0) - delta for i in free
        ]

        def event_values(t, y, args, offsets):
            """The pushing multipliers of the attached groups, then the gaps (less
            their offsets) of the free ones: all start >= 0, and the first to fall
            through zero is the next event."""
            parts = []
            if attached:
                _, lam, _ = _solve_accelerations(sys_m, y[0], y[1], t, args)
                parts.append(pushing(lam))
            for i, offset in zip(free, offsets, strict=True):
                gap = modes.groups[i].gap(y[0], t, args)
                parts.append(jnp.reshape(gap - offset, (1,)))
            return jnp.concatenate(parts)

        def next_event(offsets, t, y, args, **kwargs):
            # One condition, the smallest value: diffrax keeps only the first
            # condition (in order) of those that change sign in a step, which need
            # not be the first in time.
            del kwargs
            return jnp.min(event_values(t, y, args, offsets))

        # (The offsets are a leaf of the event, not closed over: see `_adjoint.py`.)
        event = diffrax.Event(
            (
                jax.tree_util.Partial(next_event, offsets),
                _diverged_condition(sys_m, q, t_start, args),
            ),
            root_finder=root_finder,
        )

        def integrate(_):
            one = phase(
                sys_m,
                t_start,
                t1,
                (q, qd),
                jnp.clip(ts, t_start, t1),
                event,
                watch,
                adaptive=adaptive,
            )
            stopped = one.result == diffrax.RESULTS.event_occurred
            diverged = stopped & one.event_mask[1]
            missed = (
                jnp.array(False)
                if adaptive or not attached
                else one.result == diffrax.RESULTS.dt_min_reached
            )
            result = RESULTS.where(
                stopped,
                RESULTS.where(diverged, RESULTS.diverged, RESULTS.successful),
                RESULTS.where(
                    missed, RESULTS.release_missed, RESULTS.promote(one.result)
                ),
            )
            # Which event: 0 none, else 1 + the index of the smallest value (a
            # release of attached[j], or an impact of free[j - len(attached)]).
            which = jnp.argmin(
                event_values(one.t_end, (one.q_end, one.qd_end), args, offsets)
            )
            kind = jnp.where(stopped & jnp.invert(diverged), 1 + which, 0)
            in_phase = (ts >= c["t"]) & (ts <= one.t_end)
            saved = (
                jnp.where(in_phase[:, None], one.saved[0], c["q_saved"]),
                jnp.where(in_phase[:, None], one.saved[1], c["qd_saved"]),
                jnp.where(in_phase, m, c["mode_saved"]),
            )
            stats = {
                k: v + jnp.asarray(one.stats[k], v.dtype) for k, v in c["stats"].items()
            }
            return one.t_end, one.q_end, one.qd_end, kind, result, saved, stats

        def released_at_start(_):
            # A multiplier already pulls: release it at once, no integration.
            saved = (c["q_saved"], c["qd_saved"], c["mode_saved"])
            kind = 1 + jnp.argmin(pushing(lam_start))
            return t_start, q, qd, kind, RESULTS.successful, saved, c["stats"]

        if attached:
            outcome = jax.lax.cond(start < 0, released_at_start, integrate, None)
        else:
            outcome = integrate(None)
        t_end, q_end, qd_end, kind, result, saved, stats = outcome

        def no_event():
            return q_end, qd_end, jnp.asarray(m), jnp.array(-1), False, False, 0.0, 0.0

        def release(i):
            return (
                q_end,
                qd_end,
                jnp.asarray(m - 2**i),
                jnp.asarray(i),
                False,
                False,
                0.0,
                0.0,
            )

        def hit(i):
            group = modes.groups[i]
            m2 = m + 2**i
            gap_rate = jax.jvp(
                lambda q_, t_: group.gap(q_, t_, args),
                (q_end, t_end),
                (qd_end, jnp.ones_like(t_end)),
            )[1]
            speed = -gap_rate
            e = jnp.where(speed < rest_speed[i], 0.0, restitution[i])
            q2, qd2, lam, singular = impact(
                modes.systems[m2],
                modes.group_rows[m2][i],
                e,
                q_end,
                qd_end,
                t_end,
                args,
            )
            attach = e == 0
            impulse = lam[modes.first_rows[m2][i]]
            q2 = jnp.where(singular, jnp.nan, q2)
            return (
                q2,
                qd2,
                jnp.where(attach, m2, m),
                jnp.asarray(i),
                True,
                attach,
                speed,
                impulse,
            )

        branches = [no_event]
        branches += [functools.partial(release, i) for i in attached]
        branches += [functools.partial(hit, i) for i in free]

        def as_arrays(out):
            q2, qd2, mode, group, is_impact, attach, speed, impulse = out
            return (
                q2,
                qd2,
                jnp.asarray(mode, int),
                jnp.asarray(group, int),
                jnp.asarray(is_impact),
                jnp.asarray(attach),
                jnp.asarray(speed, dtype),
                jnp.asarray(impulse, dtype),
            )

        q2, qd2, mode2, group, is_impact, attach, speed, impulse = jax.lax.switch(
            kind, [lambda f=f: as_arrays(f()) for f in branches]
        )
        happened = kind > 0
        over_budget = happened & (c["count"] >= max_events)
        record = happened & jnp.invert(over_budget)
        singular = jnp.invert(all_finite((q2, qd2)))
        result = RESULTS.where(
            over_budget,
            RESULTS.max_events_reached,
            RESULTS.where(record & singular, RESULTS.singular_dynamics, result),
        )
        at = jnp.minimum(c["count"], max_events - 1)

        def put(array, value):
            return jnp.where(record, array.at[at].set(value), array)

        new = dict(c)
        new.update(
            t=t_end,
            q=jnp.where(record, q2, q_end),
            qd=jnp.where(record, qd2, qd_end),
            mode=jnp.where(record, mode2, m),
            count=c["count"] + record.astype(c["count"].dtype),
            done=jnp.invert(record) | (result != RESULTS.successful),
            result=result,
            q_saved=saved[0],
            qd_saved=saved[1],
            mode_saved=saved[2],
            stats=stats,
            time=put(c["time"], t_end),
            group=put(c["group"], group),
            impact=put(c["impact"], is_impact),
            attached=put(c["attached"], attach),
            speed=put(c["speed"], speed),
            impulse=put(c["impulse"], impulse),
            q_event=put(c["q_event"], q2),
            qd_event=put(c["qd_event"], qd2),
        )
        return new

    branches = [functools.partial(mode_step, m) for m in range(num_modes)]
    branches.append(lambda c: c)

    def body(c, _):
        index = jnp.where(c["done"], num_modes, c["mode"])
        return jax.lax.switch(index, branches, c), None

    c, _ = jax.lax.scan(body, carry, None, length=max_events + 1)
    result = RESULTS.where(valid, c["result"], RESULTS.invalid_restitution)
    # (`done` is false only if every iteration recorded an event: the budget is
    # spent and the run has not reached `t1`.)
    result = RESULTS.where(
        c["done"] | (result != RESULTS.successful), result, RESULTS.max_events_reached
    )
    events = Events(
        count=c["count"],
        time=c["time"],
        group=c["group"],
        impact=c["impact"],
        attached=c["attached"],
        speed=c["speed"],
        impulse=c["impulse"],
        q=c["q_event"],
        qd=c["qd_event"],
        mode=c["mode"],
    )
    return _Run(
        q=c["q_saved"],
        qd=c["qd_saved"],
        t_end=c["t"],
        q_end=c["q"],
        qd_end=c["qd"],
        result=result,
        stats=c["stats"],
        phases=_ModePhases(
            mode=c["mode_saved"],
            end_mode=c["mode"],
            systems=modes.systems,
            keep_rows=tuple(jnp.asarray(k, int) for k in modes.keep_rows),
        ),
        events=events,
    )


@eqx.filter_jit
def _simulate(
    system,
    t0,
    t1,
    q0,
    qd0,
    args,
    driver,
    stabilization,
    stepsize_controller,
    saveat,
    dt0,
    max_steps,
    adjoint,
    consistency_tol,
    progress_meter,
    max_events,
):
    system.check(q0, qd0, t0, args)
    start_ok = all_finite((q0, qd0, args, t0, t1, dt0))
    modes = mode0 = None
    if max_events is None:
        consistent = jnp.invert(
            off_constraints(system, q0, qd0, t0, args, consistency_tol)
        )
    else:
        modes = build_modes(system, q0.shape[0], args, q0.dtype)
        mode0, consistent = _initial_mode(modes, q0, qd0, t0, args, consistency_tol)

    # The user's save times, as one array (diffrax's own t0/t1 flags are folded in).
    parts = []
    if saveat.t0:
        parts.append(t0[None])
    if saveat.ts is not None:
        parts.append(jnp.asarray(saveat.ts, q0.dtype))
    if saveat.t1:
        parts.append(t1[None])
    ts = jnp.concatenate(parts)
    grid_ok = _time_grid_ok(t0, t1, ts, bool(find_unilaterals(system)))
    # (diffrax raises on such save times whatever `throw` says: run on a valid grid,
    # and report `invalid_time_grid`.)
    ts = jnp.where(grid_ok, ts, t0)
    # A start with NaN or inf (in `q0`, `qd0`, `args`, the span or `dt0`) is refused
    # (`invalid_input`) and runs the empty span at a finite `t0`: integrated, its
    # steps would all be rejected until `max_steps`, and under `jax.vmap` (a sweep)
    # every other lane of the batch would wait for it (160x the time of a batch of
    # four pendulums).
    t_start = jnp.where(jnp.isfinite(t0), t0, jnp.zeros_like(t0))
    t0_run = jnp.where(start_ok, t0, t_start)
    t1_run = jnp.where(start_ok, t1, t_start)
    ts = jnp.where(start_ok, ts, t_start)
    stepsize_controller, floored = step_floor(stepsize_controller, t0_run, t1_run)

    run = driver.run(
        system,
        t0_run,
        t1_run,
        q0,
        qd0,
        args,
        ts,
        stabilization=stabilization,
        stepsize_controller=stepsize_controller,
        dt0=dt0,
        max_steps=max_steps,
        adjoint=adjoint,
        progress_meter=progress_meter,
        ends=(saveat.t0, saveat.t1) if saveat.ts is None else None,
        **(
            {}
            if max_events is None
            else dict(max_events=max_events, modes=modes, mode0=mode0)
        ),
    )
    phases = run.phases
    by_mode = isinstance(phases, _ModePhases)
    # Saved states between steps are interpolated: the stabilization may correct them
    # too (each phase with its own system; states after re-contact stay inf).
    if phases is None:
        q, qd = stabilization.project_saved(system, run.q, run.qd, ts, args)
    elif by_mode:
        projected = [
            stabilization.project_saved(sys_m, run.q, run.qd, ts, args)
            for sys_m in phases.systems
        ]
        q = phases.select(jnp.stack([p[0] for p in projected]))
        qd = phases.select(jnp.stack([p[1] for p in projected]))
    else:
        qa, qda = stabilization.project_saved(system, run.q, run.qd, ts, args)
        qf, qdf = stabilization.project_saved(phases.free, run.q, run.qd, ts, args)
        q, qd = phases.combine(qa, qf), phases.combine(qda, qdf)

    def solved(sys_, keep_rows, end: bool):
        """The multipliers (in the rows of `system`) and the singular flags of
        `sys_`'s KKT solve at the saved states, and with `end` also the flag at the
        last state reached (one traced solve for all of them)."""

        def one(q_, qd_, t_):
            _, lam, singular = _solve_accelerations(sys_, q_, qd_, t_, args)
            if keep_rows is not None:
                lam = jnp.zeros((system_k,), q_.dtype).at[keep_rows].set(lam)
            return lam, singular

        if not end:
            return _each(one, q, qd, ts), None
        if only_t1 and phases is None:
            # The one saved state is the last state reached, if the run got to `t1`
            # (else it is inf): one solve serves both (`SaveAt(t1=True)`, the
            # default). Against the batched solve over the two points it replaced:
            # the first `jit(simulate)` of the two cylinders 1.64 -> 1.35 s in a
            # fresh process; against `_each` over them, 2-3 % (`benchmarks/README.md`).
            got_there = jnp.all(jnp.isfinite(q[0]))
            point = jax.tree.map(
                lambda a, b: jnp.where(got_there, a, b),
                (q[0], qd[0], ts[0]),
                (run.q_end, run.qd_end, run.t_end),
            )
            lam, singular = one(*point)
            # Not reached: as a solve at the inf state reports it (singular, zeros).
            lam_saved = jnp.where(got_there, lam, jnp.zeros_like(lam))
            saved = (lam_saved[None], (singular | jnp.invert(got_there))[None])
            return saved, singular
        points = jax.tree.map(
            lambda a, b: jnp.concatenate([a, b[None]]),
            (q, qd, ts),
            (run.q_end, run.qd_end, run.t_end),
        )
        lam, singular = _each(one, *points)
        return (lam[:-1], singular[:-1]), singular[-1]

    # One saved time, `t1` (`SaveAt(t1=True)`, the default).
    only_t1 = saveat.t1 and not saveat.t0 and saveat.ts is None
    n = q0.shape[0]
    system_k = sum(c.num_constraints(n, args, q0.dtype) for c in system.constraints)
    extra = {}
    # A run that failed where the KKT matrix is singular failed because of it: the
    # vector field returns NaN there, so the steps were rejected until the budget ran
    # out. Checked at the last state reached (and at the saved states if available).
    end_system = system if phases is None or by_mode else phases.free
    if saveat.multipliers:
        if by_mode:
            per_mode = [
                solved(sys_m, keep, True)
                for sys_m, keep in zip(phases.systems, phases.keep_rows, strict=True)
            ]
            lam = phases.select(jnp.stack([p[0][0] for p in per_mode]))
            singular_saved = phases.select(jnp.stack([p[0][1] for p in per_mode]))
            singular_end = phases.select(
                jnp.stack([p[1] for p in per_mode]), phases.end_mode
            )
        else:
            (lam, singular_saved), singular_end = solved(system, None, phases is None)
        if phases is not None and not by_mode:
            (lam_f, singular_f), singular_end = solved(
                phases.free, phases.keep_rows, True
            )
            lam = jnp.where(phases.attached[:, None], lam, lam_f)
            singular_saved = jnp.where(phases.attached, singular_saved, singular_f)

        # (The released rows of the free phase's multipliers are zero: one product
        # with the full system's `A` serves both phases.)
        def constraint_force(q_, t_, lam_):
            return system.constraint_jacobian(q_, t_, args).T @ lam_

        extra["multipliers"] = lam
        extra["constraint_forces"] = _each(constraint_force, q, ts, lam, loop=False)
        extra["singular"] = singular_saved
    if saveat.energy:
        extra["energy"] = _each(
            lambda q_, qd_, t_: system.energy(q_, qd_, t_, args), q, qd, ts, loop=False
        )
    if saveat.violation:
        extra["position"] = _each(
            lambda q_, t_: system.holonomic_residual(q_, t_, args), q, ts, loop=False
        )
        extra["velocity"] = _each(
            lambda q_, qd_, t_: system.velocity_residual(q_, qd_, t_, args),
            q,
            qd,
            ts,
            loop=False,
        )

    result = run.result
    # Only a finite state can tell that its KKT matrix is singular: at a state that
    # overflowed (a fixed step that blew up) the solve is non-finite whatever the
    # matrix, and the run has `diverged`.
    end_finite = all_finite((run.q_end, run.qd_end))
    if saveat.multipliers:
        reached = jnp.all(jnp.isfinite(q), axis=1)
        singular = (singular_end & end_finite) | jnp.any(extra["singular"] & reached)
    elif by_mode:
        flags = [
            _solve_accelerations(sys_m, run.q_end, run.qd_end, run.t_end, args)[2]
            for sys_m in phases.systems
        ]
        singular = phases.select(jnp.stack(flags), phases.end_mode) & end_finite
    else:
        _, _, singular = _solve_accelerations(
            end_system, run.q_end, run.qd_end, run.t_end, args
        )
        singular = singular & end_finite
    # A run stopped by the divergence check (the state left the manifold: a step too
    # large) keeps `diverged`, even where the runaway state's KKT matrix is singular.
    result = RESULTS.where(
        singular & (result != RESULTS.successful) & (result != RESULTS.diverged),
        RESULTS.singular_dynamics,
        result,
    )
    # Fixed steps are not checked by diffrax: a blow-up to inf/NaN must not pass as
    # success.
    result = RESULTS.where(
        (result == RESULTS.successful) & jnp.invert(end_finite),
        RESULTS.nonfinite,
        result,
    )
    if floored:
        result = RESULTS.where(
            result == RESULTS.dt_min_reached, RESULTS.step_size_underflow, result
        )
    result = RESULTS.where(grid_ok, result, RESULTS.invalid_time_grid)
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
        stats=run.stats,
        release=run.release,
        events=run.events,
    )
    # The derivatives of a failed run are NaN (forward and reverse): `throw=True`
    # raises only where the trajectory itself is used (see `raise_if_failed`).
    return nan_derivatives_if_failed(
        traj, (system, q0, qd0, args, t0, t1), result != RESULTS.successful
    )
