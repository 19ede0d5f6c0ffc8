"""Contacts that come and go: the record of their events, and the impact law at
re-contact.

A contact mode says which [`constrained_jax.Unilateral`][] groups are attached (their
rows hold, their multipliers push) and which are free (their rows inactive, their
gaps watched); `constrained_jax._phases` runs the phases of a run, one mode each.

**Impact.** When the gap of a free group falls through zero at `t` with velocities
`qd-`, the velocities jump by an impulse, in the convention of the equations of
motion (`Q^c = A^T lambda`):

    M (qd+ - qd-) = A^T Lambda,    A qd+ + a = -E (A qd- + a),

with `A`, `a` the rows of the constraints that hold through the impact (the mode's
and the impacting group's), `E = e` on the impacting group's rows and `0` on the
others (they keep holding). It is the KKT matrix of the equations of motion,
`[[M, -A^T], [A, 0]] [qd+ - qd-; Lambda] = [0; -(1 + E)(A qd- + a)]`, solved by
the system's saddle-point solver (Newton's law of restitution; Pfeiffer and
Glocker, *Multibody Dynamics with Unilateral Contacts*, Wiley 1996, ch. 5). With
`e = 0` the rows hold after the impact and the group is attached again.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._system import project


class Events(eqx.Module):
    """The contact events of a run of [`constrained_jax.simulate`][] with
    `max_events`: releases (a multiplier let go) and impacts (a gap closed), in
    order. Arrays have one entry per possible event (`max_events`); entries past
    `count` are padding (`time = inf`, `group = -1`).

    **Attributes:**

    - `count`: how many events happened.
    - `time`: their times.
    - `group`: which `Unilateral` (its position among the system's `Unilateral`
        constraints, in order).
    - `impact`: `True` for an impact (re-contact), `False` for a release.
    - `attached`: whether the group is attached after the event (a release: no; an
        impact: yes if inelastic, `e = 0` or slower than `rest_speed`).
    - `speed`: for an impact, the approach speed `-d gap/dt` just before it (`0` for
        a release).
    - `impulse`: for an impact, the impulse `Lambda` of the group's first row (`0`
        for a release).
    - `q`, `qd`: the state just after the event.
    - `mode`: the contact mode at the end of the run (bit `i` set when group `i`, in
        the order of the system's `Unilateral` groups, is attached).
    - `slip`: with [`constrained_jax.Coulomb`][] friction on some group, the event's
        group's slip state after it: `0` sticking (or free), `+1` / `-1` slipping
        with its slip velocity `v_t` positive / negative (`None` without friction).
        A stick-slip transition is an event with `impact = False`, `attached =
        True` (a release has `attached = False`).
    """

    count: Int[Array, ""]
    time: Float[Array, " E"]
    group: Int[Array, " E"]
    impact: Bool[Array, " E"]
    attached: Bool[Array, " E"]
    speed: Float[Array, " E"]
    impulse: Float[Array, " E"]
    q: Float[Array, "E n"]
    qd: Float[Array, "E n"]
    mode: Int[Array, ""]
    slip: Float[Array, " E"] | None = None


def back_to_contact(gap, q, qd, qdd, t, t_min, args, iterations: int = 6):
    """The state where the gap closes, `(q, qd, t, speed)`, from the state `(q, qd)`
    at `t` where the re-contact event was located, and the approach speed
    `-d gap/dt` there (positive for an impact).

    The event is the gap falling through `-delta` (see `constrained_jax._phases`), a
    little past the contact. Acting there, the impact would keep the speed gained over
    `delta` (the positions are put back on the contact, the velocities are not): an
    energy `|g| delta` per impact, `g` the acceleration towards the contact, a relative
    speed error `|g| delta / v^2` that adds up over a series of bounces, and each impact
    `delta / v` late.

    So the contact is found back along the motion: Newton's method in `s` on
    `gap(q(t - s), t - s) = 0` with the Taylor model `q(t - s) = q - s qd + s^2 qdd
    / 2`, `qd(t - s) = qd - s qdd` (exact for constant accelerations; `qdd` the
    mode's accelerations at the event), `s` kept in `[0, t - t_min]`. From `s = 0`
    the iterates increase to the root (the gap is concave in `s` when the
    acceleration is towards the contact): quadratically while the contact speed is
    not far below `sqrt(2 |g| delta)`, halving the error at each step below it, so
    speeds down to about `sqrt(2 |g| delta) / 2^iterations` are resolved.
    """
    dtype = q.dtype
    t = jnp.asarray(t, dtype)

    def state(s):
        return q - s * qd + 0.5 * s**2 * qdd, qd - s * qdd, t - s

    def gap_and_rate(s):
        q_, qd_, t_ = state(s)
        return jax.jvp(lambda a, b: gap(a, b, args), (q_, t_), (qd_, jnp.ones_like(t_)))

    s = jnp.zeros((), dtype)
    for _ in range(iterations):
        value, rate = gap_and_rate(s)
        # d gap(t - s) / ds = -rate.
        step = jnp.where(rate == 0, 0.0, value / jnp.where(rate == 0, 1.0, rate))
        s = jnp.clip(s + step, 0.0, jnp.maximum(t - t_min, 0.0))
    q_c, qd_c, t_c = state(s)
    return q_c, qd_c, t_c, -gap_and_rate(s)[1]


def impact(system, scale, q, qd, t, args, iterations: int = 3):
    """The state after an impact (see the module docstring): `(q, qd+, Lambda,
    singular)`.

    `system` holds every row that holds through the impact (the impacting group's
    and those of the contact mode); `scale` is `1 + E` per row (`E = e` on the
    impacting group's rows, 0 on the others), by which the velocity residual is
    reversed. The positions are first put back on the holonomic rows (the event is
    found a little past the contact: Gauss-Newton in the metric of `M`,
    `iterations` steps), as `constrained_jax.consistent_initial_state` does: one
    projection, `constrained_jax._system.project`.
    """
    return project(system, q, qd, t, args, iterations, velocity_scale=scale)
