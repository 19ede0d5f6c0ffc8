"""Contacts that come and go: the contact modes of a system with several
[`constrained_jax.Unilateral`][] groups, and the impact law at re-contact.

A mode says which groups are attached (their rows hold, their multipliers push) and
which are free (their rows dropped, their gaps watched). With `G` groups there are
`2^G` modes, numbered by bits: bit `i` set when group `i` (in the order of
`system.constraints`) is attached. Each mode is its own `LagrangianSystem` (the
bilateral constraints and the attached groups), built once at trace time.

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
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._constraints import Unilateral
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
    - `mode`: the contact mode at the end of the run (bit `i` set when group `i` is
        attached).
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


class _Modes(eqx.Module):
    """The contact modes of `system` (see the module docstring), built at trace time.

    `groups[i]` is the `i`-th `Unilateral` of the system, at `indices[i]` among its
    constraints. For mode `m`: `systems[m]` (the system with the free groups
    removed), `keep_rows[m]` (the rows of the full system that it keeps, in order),
    `first_rows[m][i]` (the row, in `systems[m]`, of the first row of attached group
    `i`; `None` when free) and `group_rows[m][i]` (the rows, in `systems[m]`, of
    group `i`; empty when free)."""

    groups: tuple
    indices: tuple
    systems: tuple
    keep_rows: tuple
    first_rows: tuple
    group_rows: tuple

    @property
    def num_groups(self) -> int:
        return len(self.groups)

    @property
    def num_modes(self) -> int:
        return 2 ** len(self.groups)

    def attached(self, mode: int) -> list[int]:
        return [i for i in range(self.num_groups) if mode >> i & 1]

    def free(self, mode: int) -> list[int]:
        return [i for i in range(self.num_groups) if not mode >> i & 1]


def find_unilaterals(system) -> list[tuple[int, Unilateral]]:
    return [
        (i, c) for i, c in enumerate(system.constraints) if isinstance(c, Unilateral)
    ]


def build_modes(system, n: int, args, dtype) -> _Modes:
    """Every contact mode of `system` (static: Python structure only)."""
    found = find_unilaterals(system)
    indices = tuple(i for i, _ in found)
    groups = tuple(c for _, c in found)
    sizes = [c.num_constraints(n, args, dtype) for c in system.constraints]
    starts = [sum(sizes[:j]) for j in range(len(sizes))]
    systems, keep_rows, first_rows, group_rows = [], [], [], []
    for mode in range(2 ** len(groups)):
        dropped = [indices[i] for i in range(len(groups)) if not mode >> i & 1]
        sub = system
        for index in sorted(dropped, reverse=True):
            sub = sub.without(index)
        keep, first, rows = [], [], []
        for j in range(len(sizes)):
            if j not in dropped:
                keep.extend(range(starts[j], starts[j] + sizes[j]))
        for index in indices:
            if index in dropped:
                first.append(None)
                rows.append(())
            else:
                at = keep.index(starts[index])
                first.append(at)
                rows.append(tuple(range(at, at + sizes[index])))
        systems.append(sub)
        keep_rows.append(tuple(keep))
        first_rows.append(tuple(first))
        group_rows.append(tuple(rows))
    return _Modes(
        groups,
        indices,
        tuple(systems),
        tuple(keep_rows),
        tuple(first_rows),
        tuple(group_rows),
    )


def impact(system, rows, e, q, qd, t, args, iterations: int = 3):
    """The state after an impact (see the module docstring): `(q, qd+, Lambda,
    singular)`.

    `system` holds every row that holds through the impact; `rows` are the
    impacting group's rows in it, whose velocity residual is reversed and scaled by
    `e`. The positions are first put back on the holonomic rows (the event is found
    a little past the contact: Gauss-Newton in the metric of `M`, `iterations`
    steps), as `constrained_jax.consistent_initial_state` does: one projection,
    `constrained_jax._system.project`.
    """
    n, dtype = q.shape[0], q.dtype
    k = system.num_constraints(n, args, dtype)
    scale = jnp.ones((k,), dtype).at[jnp.asarray(rows, int)].add(e)
    return project(system, q, qd, t, args, iterations, velocity_scale=scale)
