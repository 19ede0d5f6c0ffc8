"""The phases of a run of [`constrained_jax.simulate`][]: one `diffrax.diffeqsolve`
each, in a contact mode.

Every run is a sequence of phases, and its kind is decided once, at trace time, by a
`Plan`. A system without [`constrained_jax.Unilateral`][] constraints runs one phase.
With them each phase is in a contact mode: which groups are attached. A release run
(one group, released once) has two phases whose modes are known at trace time: the
full system, then the system without the group's rows. An event run (`max_events`)
is a loop over phases (`lax.scan`) in which the mode is data, a boolean per group,
not a compiled branch: the system of every mode is the full system with the rows of
the free groups inactive (`LagrangianSystem.with_active`: solved as trivial rows with
zero multipliers), so one phase program serves every mode, whatever the number of
groups.

A phase ends at its first event: a release (the pushing multiplier of an attached
group falls through zero: that group is freed) or a contact (the gap of a free group
falls through zero). With `max_events` a contact is an impact
(`constrained_jax._contact.impact`: the velocities jump, and the group is attached
again when the impact is inelastic or slower than its rest speed); without it (one
group, released once) the run stops at re-contact.
"""

import abc
import functools
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._compat import unvmap_all
from ._constraints import Unilateral
from ._contact import back_to_contact, Events, impact
from ._diffrax_integrate import diffeqsolve
from ._misc import all_finite, float_tolerance
from ._results import RESULTS
from ._stabilization import AbstractStabilization, Unstabilized
from ._system import friction_dynamics, LagrangianSystem, off_constraints, project
from ._variational_integrator import (
    AbstractVariationalIntegrator,
    integrate_variational,
)
from ._vector_field import (
    diverged_condition,
    field_and_multipliers,
    solve_accelerations,
    vector_field,
)
from ._watch import Illinois, WatchedSolver
from ._wrapped_solver import prepare_to_wrap


def _gap_margin(q):
    """How far a free group's gap must fall below where its phase starts (or below
    zero) for a contact: `sqrt(eps) (1 + |q|)`, so that round-off and the integration
    error of a gap that grows from zero right after a release or an impact are not a
    collision. An impact then acts where the gap closes (`back_to_contact`), so the
    margin only bounds the slowest impact resolved."""
    return jnp.sqrt(jnp.finfo(q.dtype).eps) * (1 + jnp.max(jnp.abs(q)))


class Plan(eqx.Module):
    """How `simulate` runs a system (static, decided once at trace time).

    `indices[i]` is the position of the `i`-th `Unilateral` group among the system's
    constraints, `rows[i]` the range of its rows of `A`; `k` is the number of rows in
    all. `max_events` is `None` for a run without impacts: one phase for a system
    without groups, or a release run (one group, released once, stopped at
    re-contact: two phases at most).
    """

    indices: tuple[int, ...] = eqx.field(static=True)
    rows: tuple[tuple[int, int], ...] = eqx.field(static=True)
    k: int = eqx.field(static=True)
    max_events: int | None = eqx.field(static=True)
    # Per group, the row of its `Coulomb` friction's tangent (its last), or -1.
    tangents: tuple[int, ...] = eqx.field(static=True, default=())

    @classmethod
    def make(cls, system: LagrangianSystem, n: int, args, dtype, max_events):
        sizes = [c.num_constraints(n, args, dtype) for c in system.constraints]
        starts = np.cumsum([0] + sizes)
        indices = tuple(i for i, c in enumerate(system.constraints) if c.unilateral)
        rows = tuple((int(starts[i]), int(starts[i + 1])) for i in indices)
        tangents = []
        for i, (_, stop) in zip(indices, rows, strict=True):
            friction = system.constraints[i].friction
            if friction is None:
                tangents.append(-1)
                continue
            if friction.tangent.num_constraints(n, args, dtype) != 1:
                raise ValueError(
                    "The `tangent` of a `cjax.Coulomb` must have one row (the slip "
                    "velocity of a planar contact); got "
                    f"{friction.tangent.num_constraints(n, args, dtype)}."
                )
            tangents.append(stop - 1)
        return cls(indices, rows, int(starts[-1]), max_events, tuple(tangents))

    @property
    def friction(self) -> bool:
        """Whether some group has Coulomb friction (a slip state per group)."""
        return any(t >= 0 for t in self.tangents)

    @property
    def contacts(self) -> bool:
        """Whether the run watches contacts (a loop over phases)."""
        return bool(self.indices)

    @property
    def impacts(self) -> bool:
        """Whether a contact is an impact (else the end of the run)."""
        return self.max_events is not None

    @property
    def num_phases(self) -> int:
        if not self.contacts:
            return 1
        return 2 if self.max_events is None else self.max_events + 1

    @property
    def num_records(self) -> int:
        """The events recorded: `max_events`, or the release and the re-contact."""
        return 2 if self.max_events is None else self.max_events

    def groups(self, system) -> list[Unilateral]:
        return [system.constraints[i] for i in self.indices]

    def membership(self) -> np.ndarray:
        """`(g, k)`: the rows of each group."""
        out = np.zeros((len(self.rows), self.k), bool)
        for i, (start, stop) in enumerate(self.rows):
            out[i, start:stop] = True
        return out

    def row_mask(self, active: Bool[Array, " g"], slip=None) -> Bool[Array, " k"]:
        """The rows that hold when the groups `active` are attached: the bilateral
        rows and the attached groups', less the tangential row of a group that slips
        (`slip`, per group: `0` sticking, `+-1` the slip direction)."""
        member = jnp.asarray(self.membership())
        free_rows = jnp.any(member & jnp.invert(active)[:, None], axis=0)
        if slip is not None and self.friction:
            free_rows = free_rows.at[self._tangent_rows()].set(
                free_rows[self._tangent_rows()] | (slip[self._friction_groups()] != 0)
            )
        return jnp.invert(free_rows)

    def slip_rows(self, slip) -> Float[Array, " k"] | None:
        """Per row of `A`: the slip direction on a slipping tangential row, `0`
        elsewhere (`None` without friction)."""
        if slip is None or not self.friction:
            return None
        out = jnp.zeros((self.k,), slip.dtype)
        return out.at[self._tangent_rows()].set(slip[self._friction_groups()])

    def _friction_groups(self) -> np.ndarray:
        return np.asarray([i for i, t in enumerate(self.tangents) if t >= 0], int)

    def _tangent_rows(self) -> np.ndarray:
        return np.asarray([t for t in self.tangents if t >= 0], int)


class Options(eqx.Module):
    """`simulate`'s options, as the jitted core receives them (one module)."""

    integrator: "AbstractIntegrator"
    stabilization: AbstractStabilization
    stepsize_controller: diffrax.AbstractStepSizeController
    dt0: Float[Array, ""] | None
    max_steps: int = eqx.field(static=True)
    adjoint: diffrax.AbstractAdjoint
    progress_meter: diffrax.AbstractProgressMeter
    saveat: Any  # a `constrained_jax.SaveAt`
    consistency_tol: Any

    @property
    def adaptive(self) -> bool:
        return isinstance(
            self.stepsize_controller, diffrax.AbstractAdaptiveStepSizeController
        )


class Run(eqx.Module):
    """What the phases give `_simulate`: the states at the save times (`inf` where
    not reached), which groups were attached at each save time (`active`, `None`
    without contacts: every row holds), the last state reached and its groups, the
    result and statistics, and the record of a contact run (`Events` with
    `max_events`, else the release and re-contact of a release run, as
    `(released, at_start, time, q, qd, recontact, recontact_time)`)."""

    q: Float[Array, "T n"]
    qd: Float[Array, "T n"]
    active: Bool[Array, "T g"] | None
    t_end: Float[Array, ""]
    q_end: Float[Array, " n"]
    qd_end: Float[Array, " n"]
    active_end: Bool[Array, " g"] | None
    result: RESULTS
    stats: dict
    events: Events | None = None
    release: tuple | None = None
    slip: Float[Array, "T g"] | None = None
    slip_end: Float[Array, " g"] | None = None


class Phase(eqx.Module):
    """One diffrax solve (`run_phase`): the states at the save times, the last state
    reached, and diffrax's result, statistics and event mask."""

    saved: tuple[Float[Array, "T n"], Float[Array, "T n"]] | None
    t_end: Float[Array, ""]
    q_end: Float[Array, " n"]
    qd_end: Float[Array, " n"]
    result: diffrax.RESULTS
    stats: dict
    event_mask: tuple


def run_phase(
    system, options: Options, solver, t0, t1, y0, ts, event, args, watch=None
):
    """One diffrax solve of `system` from `(t0, y0)` to `t1`, saving at `ts` (or not,
    if `None`), stopped by `event` (a `diffrax.Event`).

    `watch`, if given, is `(watch_fn, pick, start)`: the multiplier the phase samples
    inside each step (`WatchedSolver`), as a function of the state and as a function
    of all the multipliers, and its value at `(t0, y0)`."""
    stabilization = options.stabilization
    solver = stabilization.wrap_solver(
        solver, system, options.stepsize_controller, options.adjoint
    )
    if watch is not None:
        watch_fn, pick, start = watch
        stages = jax.tree_util.Partial(
            _stages, field_and_multipliers(system, stabilization), pick
        )
        solver = prepare_to_wrap(solver, options.stepsize_controller, options.adjoint)
        solver = WatchedSolver(solver, watch_fn, start, options.adaptive, stages)
    subs = [diffrax.SubSaveAt(t1=True)]
    if ts is not None:
        subs.append(diffrax.SubSaveAt(ts=ts))
    sol = diffeqsolve(
        diffrax.ODETerm(vector_field(system, stabilization)),
        solver,
        t0,
        t1,
        options.dt0,
        y0,
        args,
        saveat=diffrax.SaveAt(subs=subs),
        stepsize_controller=options.stepsize_controller,
        max_steps=options.max_steps,
        adjoint=options.adjoint,
        event=event,
        progress_meter=options.progress_meter,
        throw=False,
        # `simulate` made `ts` valid (`_time_grid_ok`, then clipped to each phase's
        # span): no host callbacks, so the program can be cached.
        save_times_checked=True,
    )
    (q_end, qd_end) = sol.ys[0]
    return Phase(
        saved=sol.ys[1] if ts is not None else None,
        t_end=sol.ts[0][0],
        q_end=q_end[0],
        qd_end=qd_end[0],
        result=sol.result,
        stats=sol.stats,
        event_mask=sol.event_mask,
    )


def _stages(field, pick, t, y_and_w, args):
    derivative, lam = field(t, y_and_w[0], args)
    return derivative, pick(lam)


class AbstractIntegrator(eqx.Module):
    """How `simulate` integrates one kind of `solver`: `check` (in `simulate`, at
    trace time) refuses what it cannot do; `run` (in `_simulate`) integrates a run
    without contacts; `solver`, where contacts are watched, is the diffrax solver of
    the phases."""

    @abc.abstractmethod
    def check(self, system, stabilization, dt0, progress_meter) -> None:
        """Raise a `ValueError` for the options this solver cannot honour."""

    @abc.abstractmethod
    def run(self, system, options, t0, t1, q0, qd0, args, ts, ends) -> Run:
        """Integrate from `(q0, qd0)` at `t0` to `t1`, saving at `ts`; `ends` is
        `(save t0, save t1)` when `ts` is only those ends (the states are then
        saved from the start and the last state reached, without a save loop)."""


class DiffraxIntegrator(AbstractIntegrator):
    """A diffrax solver: one phase without contacts, the phases of `run_contacts`
    with them."""

    solver: diffrax.AbstractSolver

    def check(self, system, stabilization, dt0, progress_meter):
        pass  # Every stabilization, contacts and progress meters.

    def run(self, system, options, t0, t1, q0, qd0, args, ts, ends):
        event = diffrax.Event(diverged_condition(system, q0, t0, args))
        if ends is None:
            one = run_phase(
                system, options, self.solver, t0, t1, (q0, qd0), ts, event, args
            )
            q, qd = one.saved
        else:
            # Only the ends are saved: from the last state reached, not by a save
            # loop over `ts` (a smaller program). As diffrax saves `ts`, an end not
            # reached is `inf`: `t1` if the run stopped early, `t0` too if it
            # stopped before its first accepted step.
            one = run_phase(
                system, options, self.solver, t0, t1, (q0, qd0), None, event, args
            )
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
        return Run(
            q, qd, None, one.t_end, one.q_end, one.qd_end, None, result, one.stats
        )


class VariationalIntegrator(AbstractIntegrator):
    """A [`constrained_jax.AbstractVariationalIntegrator`][]: fixed steps that land on
    the save times, its own loop (not diffrax's), the constraints kept at every
    step."""

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
        if any(c.unilateral for c in system.constraints):
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

    def run(self, system, options, t0, t1, q0, qd0, args, ts, ends):
        del ends  # Saved at `ts` by its own loop.
        variational = integrate_variational(
            self.integrator,
            system,
            t0,
            t1,
            options.dt0,
            q0,
            qd0,
            args,
            ts_save=ts,
            max_steps=options.max_steps,
            # `simulate` has tested the start with its own `consistency_tol`: the
            # variational integrator does not test it again.
            consistency_tol=float("inf"),
            throw=False,
        )
        q, qd = variational.q, variational.qd
        return Run(
            q,
            qd,
            None,
            ts[-1],
            q[-1],
            qd[-1],
            None,
            variational.result,
            variational.stats,
        )


@functools.singledispatch
def integrator(solver) -> AbstractIntegrator:
    """The integrator of a `solver`: dispatched on its type (the solver families are
    not ours to give a method), a `ValueError` for anything else."""
    raise ValueError(
        "`solver` must be a diffrax solver (e.g. `diffrax.Tsit5()`) or "
        f"`cjax.VariationalIntegrator()`, got {type(solver).__name__}."
    )


@integrator.register
def _(solver: diffrax.AbstractSolver):
    return DiffraxIntegrator(solver)


@integrator.register
def _(solver: AbstractVariationalIntegrator):
    return VariationalIntegrator(solver)


def initial_contacts(plan: Plan, system, q0, qd0, t0, args, tol):
    """The groups attached at the start, their slip states, and whether the start
    is consistent with them. With impacts (`max_events`): a group is attached when
    its gap and the velocity residual of its normal rows are zero (to `tol`,
    relative to `1 + |q|` and `1 + |qd|`), free otherwise; no gap may be negative
    (penetration) beyond `tol`; an attached group with friction slips where its
    slip velocity is not zero, or where sticking would need a force outside its
    cone (`decide_slip`). A release run starts attached. The rows of the bilateral
    constraints and of the attached groups must hold (positions and velocities, to
    `tol`). The slip states are `None` without friction."""
    groups = plan.groups(system)
    if not plan.impacts:
        active = jnp.ones((len(groups),), bool)
        ok = jnp.invert(off_constraints(system, q0, qd0, t0, args, tol))
        return active, None, ok
    scale_q = tol * (1 + jnp.max(jnp.abs(q0)))
    scale_qd = tol * (1 + jnp.max(jnp.abs(qd0)))
    attached, ok = [], jnp.array(True)
    for group, tangent in zip(groups, plan.tangents, strict=True):
        gap = group.gap(q0, t0, args)
        velocity = group.velocity_residual(q0, qd0, t0, args)
        if tangent >= 0:
            velocity = velocity[:-1]  # (The normal rows: a start may slip.)
        attached.append(
            (jnp.abs(gap) <= scale_q) & jnp.all(jnp.abs(velocity) <= scale_qd)
        )
        ok = ok & (gap >= -scale_q)
    active = jnp.stack(attached)
    slip = None
    if plan.friction:
        slip = jnp.zeros((len(groups),), q0.dtype)
        for which in plan._friction_groups():
            decided = decide_slip(plan, system, active, slip, which, t0, q0, qd0, args)
            slip = jnp.where(active[which], slip.at[which].set(decided), slip)
    held = system.with_active(plan.row_mask(active, slip), plan.slip_rows(slip))
    off = off_constraints(held, q0, qd0, t0, args, tol)
    return active, slip, ok & jnp.invert(off)


def decide_slip(
    plan: Plan, system, active, slip, which, t, q, qd, args, moving=True, leaving=False
):
    """The slip state of the attached group `which` (with friction) at `(t, q, qd)`:
    where `moving`, the sign of its slip velocity `v_t` where it is not zero (beyond
    `sqrt(eps) (1 + |qd|)`); else `0` (stick) where the multipliers of the mode that
    sticks lie in the cone, `|lambda_t| <= mu_s N`, and otherwise the direction
    opposite to `lambda_t` (the force that would be needed to stick). At a
    stick-slip event `moving` is false: `v_t` is zero there to the event's
    tolerance, whatever its size in round-off. `leaving`: the event where a sticking
    contact reached the cone's edge, which it leaves (the located point is on the
    edge to the root find's tolerance, either side): it slips, opposite to
    `lambda_t`."""
    group = plan.groups(system)[which]
    coulomb = group.friction
    first, _ = plan.rows[which]
    tangent = plan.tangents[which]
    v_t = _slip_velocity(group, q, qd, t, args)
    moving = moving & (
        jnp.abs(v_t) > jnp.sqrt(jnp.finfo(q.dtype).eps) * (1 + jnp.max(jnp.abs(qd)))
    )
    stick = slip.at[which].set(0.0)
    held = system.with_active(plan.row_mask(active, stick), plan.slip_rows(stick))
    lam = solve_accelerations(held, q, qd, t, args)[1]
    normal = group.sign * lam[first]
    force = lam[tangent]
    mu_s = jnp.asarray(coulomb.coefficients(args)[0], q.dtype)
    # (`mu_s = inf` never slips, also where `N = 0`.)
    inside = jnp.invert(leaving) & (jnp.isinf(mu_s) | (jnp.abs(force) <= mu_s * normal))
    return jnp.where(
        moving, jnp.sign(v_t), jnp.where(inside, 0.0, -jnp.sign(force))
    ).astype(q.dtype)


class _Contacts(eqx.Module):
    """The contact data of a run with groups (static): what the events, the watch
    and the impacts read. `solve`: how a phase's multipliers are found, `None` for a
    mode known at run time only (solved where some group is attached), `True` for a
    phase known at trace time to have every group attached, `False` for one known to
    have none (no solve)."""

    groups: tuple = eqx.field(static=True)
    firsts: tuple[int, ...] = eqx.field(static=True)
    signs: tuple[float, ...] = eqx.field(static=True)
    k: int = eqx.field(static=True)
    solve: bool | None = eqx.field(static=True, default=None)

    def pushing(self, lam, active):
        """`sign * lambda` of each group's first row, `+inf` for a free group."""
        values = jnp.asarray(self.signs, lam.dtype) * lam[np.asarray(self.firsts)]
        return jnp.where(active, values, jnp.inf)

    def gaps(self, q, t, args):
        """Each group's gap (`+inf` for a group without one: never re-contacts)."""
        inf = jnp.asarray(jnp.inf, q.dtype)
        return jnp.stack(
            [
                inf
                if g.gap is None
                else jnp.reshape(g.gap(q, t, args), ()).astype(q.dtype)
                for g in self.groups
            ]
        )

    def multipliers(self, system, t, y, args):
        """The multipliers of `system` at `(t, y)`, in the rows of the full system
        (zeros when no group is attached: no solve is needed then)."""
        q, qd = y
        zeros = jnp.zeros((self.k,), q.dtype)
        if self.solve is False:
            return zeros

        def solve():
            return solve_accelerations(system, q, qd, t, args)[1]

        if self.solve:
            return solve()
        return jax.lax.cond(jnp.any(system.active), solve, lambda: zeros)


def _watched(contacts, active, lam):
    """The smallest pushing multiplier of the attached groups (`1` when none is
    attached: nothing to watch, and the watch then sees a constant)."""
    return jnp.where(jnp.any(active), jnp.min(contacts.pushing(lam, active)), 1.0)


def _watch_fn(contacts, active, system, t, y, args, **kwargs):
    del kwargs
    return _watched(contacts, active, contacts.multipliers(system, t, y, args))


def _event_values(contacts, active, system, offsets, friction, t, y, args):
    """Per group: the pushing multiplier of an attached one, the gap (less its
    offset) of a free one; with `friction` (a `_Friction`), then per group the
    stick-slip value (less its offset) and the Painleve consistency of a slipping
    one: all start `>= 0`, and the first to fall through zero is the next event."""
    if friction is None:
        lam = contacts.multipliers(system, t, y, args)
    else:
        lam, consistency = _coupled(system, t, y, args)
    primary = jnp.where(
        active, contacts.pushing(lam, active), contacts.gaps(y[0], t, args) - offsets
    )
    if friction is None:
        return primary
    stick_slip = friction.values(contacts, active, t, y, args, lam) - friction.offsets
    paradox = friction.consistency(active, consistency)
    return jnp.concatenate([primary, stick_slip, paradox])


def _next_event(contacts, active, system, offsets, friction, t, y, args, **kwargs):
    # One condition, the smallest value: diffrax keeps only the first condition (in
    # order) of those that change sign in a step, which need not be the first in
    # time.
    del kwargs
    return jnp.min(
        _event_values(contacts, active, system, offsets, friction, t, y, args)
    )


def _slip_velocity(group, q, qd, t, args):
    """`v_t = A_t qdot + a_t` of a group's friction."""
    return jnp.reshape(group.friction.tangent.velocity_residual(q, qd, t, args), ())


def _coupled(system, t, y, args):
    """`(lambda, consistency)` of a mode with friction (`friction_dynamics`)."""
    q, qd = y
    _, lam, _, consistency = friction_dynamics(
        system, q, qd, jnp.asarray(t, q.dtype), args, fill=jnp.nan
    )
    return lam, consistency


class _Friction(eqx.Module):
    """The friction data of a phase: per group the tangential row (`-1`: none), the
    static coefficient, the slip state (`0` stick, `+-1` the slip direction) and the
    offsets of the stick-slip event values."""

    tangents: tuple[int, ...] = eqx.field(static=True)
    mu_s: Float[Array, " g"]
    slip: Float[Array, " g"] | None = None
    offsets: Float[Array, " g"] | None = None

    def consistency(self, active, consistency):
        """Per group: the coefficient of its normal multiplier in the coupled
        system (`friction_dynamics`'s `consistency`, per contact with friction)
        where it slips, `inf` for the others."""
        per_group = jnp.ones((len(self.tangents),), consistency.dtype)
        groups = np.asarray([i for i, r in enumerate(self.tangents) if r >= 0])
        per_group = per_group.at[groups].set(consistency)
        return jnp.where(active & (self.slip != 0), per_group, jnp.inf)

    def values(self, contacts, active, t, y, args, lam):
        """Per group with friction, attached: `mu_s N - |lambda_t|` while it sticks
        (the distance to the cone's edge), `s v_t` while it slips (the slip speed);
        `inf` for the others."""
        q, qd = y
        firsts = np.asarray(contacts.firsts)
        rows = np.maximum(np.asarray(self.tangents), 0)
        normal = jnp.asarray(contacts.signs, lam.dtype) * lam[firsts]
        force = jnp.abs(lam[rows])
        zero = jnp.zeros((), q.dtype)
        v_t = jnp.stack(
            [
                zero if g.friction is None else _slip_velocity(g, q, qd, t, args)
                for g in contacts.groups
            ]
        )
        stick = jnp.where(jnp.isinf(self.mu_s), jnp.inf, self.mu_s * normal - force)
        value = jnp.where(self.slip == 0, stick, self.slip * v_t)
        has = jnp.asarray(np.asarray(self.tangents) >= 0)
        return jnp.where(active & has, value, jnp.inf)


def _scalar_gap(gap, q, t, args):
    return jnp.reshape(gap(q, t, args), ())


def signs_agree(plan: Plan, system, q0, qd0, t0, args):
    """Whether each group's `sign` agrees with its `gap` at the start: the force of
    the group's first row while it pushes (`sign * lambda > 0`) must open the gap,
    `sign * grad(gap) . M^-1 a_1 >= 0`. A group without a gap, or where the product
    is zero to round-off (the row cannot move the gap), is not judged. A start that
    is not finite is judged elsewhere (`invalid_input`)."""
    groups = plan.groups(system)
    if not any(g.gap is not None for g in groups):
        return jnp.array(True)
    mass = system.mass_matrix(q0, qd0, t0, args)
    rows = system.constraint_jacobian(q0, t0, args)
    eps = jnp.finfo(q0.dtype).eps
    agree = jnp.array(True)
    for group, (first, _) in zip(groups, plan.rows, strict=True):
        if group.gap is None:
            continue
        grad = jax.grad(_scalar_gap, argnums=1)(group.gap, q0, t0, args)
        moved = jnp.linalg.solve(mass, rows[first])
        opens = group.sign * jnp.dot(grad, moved)
        scale = jnp.linalg.norm(grad) * jnp.linalg.norm(moved)
        agree = agree & jnp.invert(opens < -jnp.sqrt(eps) * scale)
    return agree


def run_contacts(
    plan, options, solver, system, t0, t1, q0, qd0, args, ts, active0, slip0=None
):
    """The phases of a run with `Unilateral` groups (see the module docstring):
    `lax.scan` over `plan.num_phases` phases (reverse-mode autodiff goes through it,
    unlike a `while_loop`), each skipped once the run is over."""
    run = _ContactRun(plan, options, solver, system, args, ts, t1)
    carry = run.initial(t0, q0, qd0, active0, slip0)
    if not plan.impacts:
        # A release run: its modes are known at trace time, attached then free, so
        # each phase runs its own system (the free one without the group's rows).
        attached = functools.partial(run.phase, static=True)
        free = functools.partial(run.phase, static=False)
        c = attached(carry)
        # (The free phase always runs, over an empty span at `t1` where the run is
        # over: cheaper than a `lax.cond` around a solve.)
        after = free(dict(c, t=jnp.where(c["done"], t1, c["t"])))
        c = jax.tree.map(lambda x, y: jnp.where(c["done"], x, y), c, after)
        return run.finish(c, t0)

    def body(c, _):
        # Skipped once every lane of a `jax.vmap` batch is over (`unvmap_all`: the
        # predicate is never batched, so this stays a `lax.cond`); the lanes over
        # before the others run the phase over an empty span (`phase`), discarded
        # by `jnp.where`. A batched predicate would make the `lax.cond` a select,
        # and reverse mode inside `jax.vmap` (`vmap(grad)`) would then run the
        # phase's backward pass on the lanes that skipped it with the residuals of
        # the skipping branch, zeros: NaN in the implicit linear solves (Lineax's
        # non-finite input error), and a checkpointed loop whose step count differs
        # across the batch (`equinox.internal`'s "Nonconstant batch").
        def step(c_):
            new = run.phase(c_)
            return jax.tree.map(lambda x, y: jnp.where(c_["done"], x, y), c_, new)

        return jax.lax.cond(unvmap_all(c["done"]), lambda c_: c_, step, c), None

    c, _ = jax.lax.scan(body, carry, None, length=plan.num_phases)
    return run.finish(c, t0)


class _ContactRun:
    """The pieces of `run_contacts` (trace-time Python, not a pytree): the phase
    body, and the record of the events."""

    def __init__(self, plan, options, solver, system, args, ts, t1):
        self.plan, self.options, self.solver = plan, options, solver
        self.system, self.args, self.ts, self.t1 = system, args, ts, t1
        groups = plan.groups(system)
        self.num_groups = len(groups)
        self.firsts = np.asarray([start for start, _ in plan.rows], int)
        self.contacts = _Contacts(
            tuple(groups),
            tuple(int(r) for r in self.firsts),
            tuple(g.sign for g in groups),
            plan.k,
        )
        dtype = t1.dtype
        self.dtype = dtype
        self.eps = jnp.finfo(dtype).eps
        self.tiny = 64 * self.eps * (1 + jnp.abs(t1))
        # Root-finding tolerance: 1e-12, raised to 100 eps in float32 (unreachable).
        root_tol = float_tolerance(1e-12, 100.0, dtype)
        self.root_finder = Illinois(rtol=root_tol, atol=root_tol)
        self.membership = jnp.asarray(plan.membership(), dtype)
        if plan.impacts:
            e = jnp.stack(
                [jnp.asarray(g.restitution_value(args), dtype) for g in groups]
            )
            v = jnp.stack(
                [jnp.asarray(g.rest_speed_value(args), dtype) for g in groups]
            )
            self.valid = jnp.all((e >= 0) & (e <= 1) & (v >= 0))
            # Invalid values run as inelastic impacts (the status says why).
            self.restitution = jnp.where(self.valid, e, 0.0)
            self.rest_speed = jnp.where(self.valid, v, 0.0)
        self.friction = None
        self.friction_valid = jnp.array(True)
        if plan.friction:
            pairs = [
                (jnp.asarray(0.0), jnp.asarray(0.0))
                if g.friction is None
                else g.friction.coefficients(args)
                for g in groups
            ]
            mu_s = jnp.stack([jnp.asarray(p[0], dtype) for p in pairs])
            mu_k = jnp.stack([jnp.asarray(p[1], dtype) for p in pairs])
            # (NaN fails each test.)
            self.friction_valid = jnp.all((mu_k >= 0) & (mu_k <= mu_s))
            self.friction = _Friction(
                plan.tangents, jnp.where(self.friction_valid, mu_s, 0.0)
            )

    def held(self, active, slip=None):
        """The system of the contact mode `active` (and `slip`, with friction)."""
        plan = self.plan
        return self.system.with_active(
            plan.row_mask(active, slip), plan.slip_rows(slip)
        )

    def mode(self, c, static):
        """`(active, held, contacts)` of a phase: for a mode known at run time only
        (`static=None`), the system with the free groups' rows inactive; for a mode
        known at trace time (`True`: every group attached, `False`: none), the full
        system, or the system without the groups' rows (nothing to solve for them)."""
        if static is None:
            return c["active"], self.held(c["active"], c.get("slip")), self.contacts
        active = jnp.full((self.num_groups,), static)
        held = self.system
        if not static:
            for index in sorted(self.plan.indices, reverse=True):
                held = held.without(index)
        contacts = self.contacts
        contacts = _Contacts(
            contacts.groups, contacts.firsts, contacts.signs, contacts.k, static
        )
        return active, held, contacts

    def initial(self, t0, q0, qd0, active0, slip0=None) -> dict:
        n, size, num_ts = q0.shape[0], self.plan.num_records, self.ts.shape[0]
        inf = jnp.asarray(jnp.inf, self.dtype)
        stats = ("num_steps", "num_accepted_steps", "num_rejected_steps")
        return {
            "t": t0,
            "q": q0,
            "qd": qd0,
            "active": active0,
            "count": jnp.array(0),
            # A start with NaN or inf (refused by `_simulate` as `invalid_input`)
            # runs no phase: its steps would be rejected until `max_steps` (under
            # `jax.vmap` the whole batch waiting for it).
            "done": jnp.invert(all_finite((q0, qd0, self.args)))
            | jnp.invert(self.friction_valid),
            "result": RESULTS.successful,
            "at_start": jnp.array(False),
            "q_saved": jnp.full((num_ts, n), inf),
            "qd_saved": jnp.full((num_ts, n), inf),
            "active_saved": jnp.zeros((num_ts, self.num_groups), bool),
            "stats": {k: jnp.array(0) for k in stats},
            "time": jnp.full((size,), inf),
            "group": jnp.full((size,), -1),
            "impact": jnp.zeros((size,), bool),
            "attached": jnp.zeros((size,), bool),
            "speed": jnp.zeros((size,), self.dtype),
            "impulse": jnp.zeros((size,), self.dtype),
            "q_event": jnp.full((size, n), inf),
            "qd_event": jnp.full((size, n), inf),
        } | (
            {}
            if slip0 is None
            else {
                "slip": slip0,
                "slip_saved": jnp.zeros((num_ts, self.num_groups), self.dtype),
                "slip_event": jnp.zeros((size,), self.dtype),
            }
        )

    def phase(self, c, static=None) -> dict:
        """One phase, in the mode `c["active"]` (or the mode `static` known at trace
        time, see `mode`), and its event."""
        active, held, contacts = self.mode(c, static)
        c = dict(c, active=active)
        t_start = jnp.minimum(c["t"], self.t1 - self.tiny)
        y_start = (c["q"], c["qd"])
        paradox = jnp.array(False)
        if self.friction is None:
            lam_start = contacts.multipliers(held, t_start, y_start, self.args)
        else:
            lam_start, consistency = _coupled(held, t_start, y_start, self.args)
            # A slipping contact whose coupled system has no solution (or several):
            # the Painleve paradox, refused without integrating, recorded as an
            # event of that contact (kind 2, as inside a phase).
            friction = _Friction(self.friction.tangents, self.friction.mu_s, c["slip"])
            per_group = friction.consistency(active, consistency)
            paradox = jnp.any(per_group <= 0)
            paradox_event = 2 * self.num_groups + jnp.argmin(per_group)
        start = _watched(contacts, active, lam_start)
        # A multiplier that already pulls is released at once, without integrating.
        pulls = (jnp.any(active) & (start < 0)) | paradox

        def released_at_start(_):
            saved = self._saved(c)
            pushing = contacts.pushing(lam_start, active)
            which = jnp.asarray(jnp.argmin(pushing), int)
            if self.friction is not None:
                which = jnp.where(paradox, paradox_event, which)
            end = (t_start, c["q"], c["qd"], jnp.array(True), which)
            return end, RESULTS.successful, saved, c["stats"]

        integrate = functools.partial(
            self.integrate, c, held, contacts, t_start, start, lam_start
        )
        if static is False:
            # (Nothing attached: nothing to release.)
            end, result, saved, stats = integrate(None)
        else:
            # Where it pulls, the solve runs over an empty span and is discarded:
            # cheaper than a `lax.cond` around a solve. So does a run that is over
            # (a lane of a `jax.vmap` batch waiting for the others: `run_contacts`).
            empty = pulls | c["done"]
            run = integrate(None, jnp.where(empty, t_start + self.tiny, self.t1))
            released = released_at_start(None)
            result = RESULTS.where(pulls, released[1], run[1])
            end, saved, stats = jax.tree.map(
                lambda a, b: jnp.where(pulls, a, b),
                (released[0], released[2], released[3]),
                (run[0], run[2], run[3]),
            )
        new = self.record(c, end, result, pulls & jnp.invert(paradox))
        new.update(saved, stats=stats)
        return new

    def _saved(self, c) -> dict:
        keys = ("q_saved", "qd_saved", "active_saved")
        if self.friction is not None:
            keys = keys + ("slip_saved",)
        return {k: c[k] for k in keys}

    def integrate(self, c, held, contacts, t_start, start, lam_start, _, stop=None):
        """One diffrax solve from the phase's start to its event (or `stop`, by
        default `t1`)."""
        active, args, ts = c["active"], self.args, self.ts
        stop = self.t1 if stop is None else stop
        q, qd = c["q"], c["qd"]
        watch = None
        if contacts.solve is not False:
            # (A phase known to have nothing attached watches no multiplier.)
            watch = (
                jax.tree_util.Partial(_watch_fn, contacts, active, held),
                jax.tree_util.Partial(_watched, contacts, active),
                start,
            )
        delta = _gap_margin(q)
        offsets = jnp.where(
            active, 0.0, jnp.minimum(contacts.gaps(q, t_start, args), 0) - delta
        )
        friction = self.friction
        if friction is not None:
            # A stick-slip value starts `>= 0` (the mode was decided so); the event
            # is where it falls `margin` below its start (or below zero).
            slip = c["slip"]
            friction = _Friction(friction.tangents, friction.mu_s, slip)
            values = friction.values(
                contacts, active, t_start, (q, qd), args, lam_start
            )
            scale = jnp.where(
                slip == 0,
                jnp.max(jnp.abs(lam_start)),
                1 + jnp.max(jnp.abs(qd)),
            )
            margin = 64 * self.eps * (1 + scale)
            finite = jnp.isfinite(values)
            offsets_f = jnp.where(finite, jnp.minimum(values, 0), 0.0) - margin
            friction = _Friction(friction.tangents, friction.mu_s, slip, offsets_f)
        # (The offsets and the mode are leaves of the event, not closed over: see
        # `_adjoint.py`.)
        event = diffrax.Event(
            (
                jax.tree_util.Partial(
                    _next_event, contacts, active, held, offsets, friction
                ),
                diverged_condition(held, q, t_start, args),
            ),
            root_finder=self.root_finder,
        )
        clipped = jnp.clip(ts, t_start, stop)
        one = run_phase(
            held, self.options, self.solver, t_start, stop, (q, qd), clipped,
            event, args, watch,
        )  # fmt: skip
        stopped = one.result == diffrax.RESULTS.event_occurred
        diverged = stopped & one.event_mask[1]
        # (A fixed-step controller never reports `dt_min_reached`: it is
        # `WatchedSolver` signalling a sign change it could not locate.)
        missed = (
            jnp.array(False)
            if self.options.adaptive
            else jnp.any(active) & (one.result == diffrax.RESULTS.dt_min_reached)
        )
        result = RESULTS.where(
            stopped,
            RESULTS.where(diverged, RESULTS.diverged, RESULTS.successful),
            RESULTS.where(missed, RESULTS.release_missed, RESULTS.promote(one.result)),
        )
        y_end = (one.q_end, one.qd_end)
        values = _event_values(
            contacts, active, held, offsets, friction, one.t_end, y_end, args
        )
        which = jnp.asarray(jnp.argmin(values), int)
        happened = stopped & jnp.invert(diverged)
        in_phase = (ts >= c["t"]) & (ts <= one.t_end)
        saved = dict(
            q_saved=jnp.where(in_phase[:, None], one.saved[0], c["q_saved"]),
            qd_saved=jnp.where(in_phase[:, None], one.saved[1], c["qd_saved"]),
            active_saved=jnp.where(in_phase[:, None], active, c["active_saved"]),
        )
        if friction is not None:
            saved["slip_saved"] = jnp.where(
                in_phase[:, None], c["slip"], c["slip_saved"]
            )
        stats = {
            k: v + jnp.asarray(one.stats[k], v.dtype) for k, v in c["stats"].items()
        }
        return (one.t_end, *y_end, happened, which), result, saved, stats

    def impact(self, active, slip, which, t_start, t, q, qd, is_contact):
        """`(t_c, q+, qd+, attached, speed, impulse)` after a contact of group
        `which`, located at `t`: back to where its gap closes (`t_c`,
        `back_to_contact`), an impact there with the group's restitution (inelastic
        below its rest speed, decided by the approach speed there)."""
        args, dtype = self.args, self.dtype
        group_gap = jax.tree_util.Partial(_group_gap, self.contacts, which)

        def hit(_):
            qdd, _, _ = solve_accelerations(self.held(active, slip), q, qd, t, args)
            q_c, qd_c, t_c, speed = back_to_contact(
                group_gap, q, qd, qdd, t, t_start, args
            )
            e = jnp.where(speed < self.rest_speed[which], 0.0, self.restitution[which])
            # (The impulse is frictionless: the impacting group's tangential row,
            # marked slipping, does not hold through the impact.)
            during = None if slip is None else slip.at[which].set(1.0)
            held = self.held(active.at[which].set(True), during)
            scale = 1 + e * self.membership[which]
            q2, qd2, lam, singular = impact(held, scale, q_c, qd_c, t_c, args)
            q2 = jnp.where(singular, jnp.nan, q2)
            return t_c, q2, qd2, e == 0, speed, lam[self.firsts][which]

        def no_hit(_):
            zero = jnp.zeros((), dtype)
            return t, q, qd, jnp.array(False), zero, zero

        return jax.lax.cond(is_contact, hit, no_hit, None)

    def record(self, c, end, result, pulls) -> dict:
        """The state after the phase's event, and the event in the record."""
        t_end, q_end, qd_end, happened, flat = end
        # (An event value per group and kind: the release or contact, then with
        # friction the stick-slip transition and the Painleve consistency.)
        which, kind = flat % self.num_groups, flat // self.num_groups
        active, slip = c["active"], c.get("slip")
        is_release = happened & (kind == 0) & active[which]
        is_contact = happened & (kind == 0) & jnp.invert(active[which])
        active2 = jnp.where(is_release, active.at[which].set(False), active)
        t2, q2, qd2 = t_end, q_end, qd_end
        attach = not_approaching = jnp.array(False)
        speed = impulse = jnp.zeros((), self.dtype)
        if self.plan.impacts:
            t_start = jnp.minimum(c["t"], self.t1 - self.tiny)
            t2, q2, qd2, attach, speed, impulse = self.impact(
                active, slip, which, t_start, t_end, q_end, qd_end, is_contact
            )
            attach = is_contact & attach
            active2 = jnp.where(attach, active.at[which].set(True), active2)
            # An impact has a positive approach speed: a gap that falls through
            # zero without closing (a step in the gap, or an event located where
            # the gap does not cross) is refused, never taken as an impact (nor as
            # a rest).
            not_approaching = is_contact & jnp.invert(speed > 0)
        slip2 = slip
        if self.friction is not None:
            is_transition = happened & (kind == 1)
            slip2, qd2 = self.slip_after(
                active2, slip, which, t2, q2, qd2, is_release | is_contact,
                is_transition, attach,
            )  # fmt: skip
            # (A paradox leaves the group attached, in its slip.)
            attach = attach | is_transition | (happened & (kind == 2))
            result = RESULTS.where(
                happened & (kind == 2), RESULTS.painleve_paradox, result
            )
        size = self.plan.num_records
        over_budget = happened & (c["count"] >= size)
        record = happened & jnp.invert(over_budget)
        singular = jnp.invert(all_finite((q2, qd2)))
        result = RESULTS.where(
            record & not_approaching, RESULTS.impact_not_approaching, result
        )
        result = RESULTS.where(record & singular, RESULTS.singular_dynamics, result)
        result = RESULTS.where(over_budget, RESULTS.max_events_reached, result)
        at = jnp.minimum(c["count"], size - 1)

        def put(array, value):
            return jnp.where(record, array.at[at].set(value), array)

        stop = jnp.invert(record) | (result != RESULTS.successful)
        if not self.plan.impacts:
            # Without impacts, a contact ends the run (a release run's re-contact),
            # before `t1`: not `successful` (the later saves are inf).
            stop = stop | is_contact
            result = RESULTS.where(
                record & is_contact & (result == RESULTS.successful),
                RESULTS.recontact,
                result,
            )
        extra = {}
        if self.friction is not None:
            extra = dict(
                slip=jnp.where(record, slip2, slip),
                slip_event=put(c["slip_event"], slip2[which]),
            )
        return dict(
            c,
            **extra,
            t=jnp.where(record, t2, t_end),
            q=jnp.where(record, q2, q_end),
            qd=jnp.where(record, qd2, qd_end),
            active=jnp.where(record, active2, active),
            count=c["count"] + record.astype(c["count"].dtype),
            done=stop,
            result=result,
            at_start=c["at_start"] | (pulls & (c["count"] == 0)),
            time=put(c["time"], t2),
            group=put(c["group"], which),
            impact=put(c["impact"], is_contact),
            attached=put(c["attached"], attach),
            speed=put(c["speed"], speed),
            impulse=put(c["impulse"], impulse),
            q_event=put(c["q_event"], q2),
            qd_event=put(c["qd_event"], qd2),
        )

    def slip_after(self, active, slip, which, t, q, qd, freed, transition, landed):
        """`(slip, qd)` after an event of group `which`: a released or impacting
        group does not slip (`freed`); after a stick-slip `transition` or an impact
        that attaches it (`landed`), the group's new state by `decide_slip`, its
        velocities put onto the rows that hold where it sticks again (`v_t = 0`
        exactly)."""
        plan, system, args = self.plan, self.system, self.args
        leaving = transition & (slip[which] == 0)
        slip = jnp.where(freed, slip.at[which].set(0.0), slip)
        new = slip
        decide = transition | landed
        for i in plan._friction_groups():
            i = int(i)
            decided = decide_slip(
                plan, system, active, slip, i, t, q, qd, args, landed, leaving
            )
            new = jnp.where(decide & (which == i), new.at[i].set(decided), new)
        has = jnp.asarray(plan.tangents)[which] >= 0
        sticks = decide & (new[which] == 0) & has
        _, qd_held, _, _ = project(self.held(active, new), q, qd, t, args, 0)
        return new, jnp.where(sticks, qd_held, qd)

    def finish(self, c, t0) -> Run:
        result = c["result"]
        events = release = None
        if self.plan.impacts:
            result = RESULTS.where(self.valid, result, RESULTS.invalid_restitution)
            # (`done` is false only if every phase recorded an event: the budget is
            # spent and the run has not reached `t1`.)
            result = RESULTS.where(
                c["done"] | (result != RESULTS.successful),
                result,
                RESULTS.max_events_reached,
            )
            bits = 2 ** jnp.arange(self.num_groups)
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
                mode=jnp.sum(jnp.where(c["active"], bits, 0)),
                slip=c.get("slip_event"),
            )
            result = RESULTS.where(
                self.friction_valid, result, RESULTS.invalid_friction
            )
        else:
            release = _release_record(c, self.t1)
        return Run(
            q=c["q_saved"],
            qd=c["qd_saved"],
            active=c["active_saved"],
            t_end=c["t"],
            q_end=c["q"],
            qd_end=c["qd"],
            active_end=c["active"],
            result=result,
            stats=c["stats"],
            events=events,
            release=release,
            slip=c.get("slip_saved"),
            slip_end=c.get("slip"),
        )


def _group_gap(contacts, which, q, t, args):
    return contacts.gaps(q, t, args)[which]


def _release_record(c, t1):
    """The release run's record: `(released, at_start, time, q, qd, recontact,
    recontact_time)`, from its first event (the release, if any) and its second (the
    re-contact, if any)."""
    released = (c["count"] >= 1) & jnp.invert(c["impact"][0])
    at_start = released & c["at_start"]
    time = jnp.where(released, c["time"][0], t1)
    q = jnp.where(released, c["q_event"][0], c["q"])
    qd = jnp.where(released, c["qd_event"][0], c["qd"])
    recontact = released & (c["count"] >= 2)
    recontact_time = jnp.where(recontact, c["time"][1], t1)
    return (released, at_start, time, q, qd, recontact, recontact_time)
