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
