"""A block on a rough incline: Coulomb friction, sticking and slipping.

A point mass `m` on a plane inclined at `theta` (`0 <= theta < pi/2`) to the
horizontal. Coordinates in the incline's frame, `q = (x, y)`: `x` along the slope,
positive downhill; `y` along the outward normal (away from the plane), `y = 0` on it.
The height above a fixed level is `-x sin(theta) + y cos(theta)`, so

    L = m (xdot^2 + ydot^2)/2 - m g (-x sin(theta) + y cos(theta)).

Rows of the contact group (`Q^c = A^T lambda`):

    normal   G = y = 0             A_n = (0, 1) (Holonomic), gap y, sign +1:
                                   lambda_n = N >= 0 pushes the block off the plane;
    tangent  v_t = xdot            A_t = (1, 0) (Pfaffian), lambda_t the friction
                                   force along +x (downhill).

Equations of motion while in contact: `m xddot = m g sin(theta) + lambda_t`,
`0 = m yddot = -m g cos(theta) + N`, so

    N = m g cos(theta)                                  (in every phase).

Sticking (`xdot = 0` held): `lambda_t = -m g sin(theta)` (negative: friction points
uphill), inside the cone `|lambda_t| <= mu_s N` iff `tan(theta) <= mu_s`. So from rest
the block sticks iff `tan(theta) <= mu_s`.

Slipping with direction `s = sign(xdot)` (`+1` downhill): `lambda_t = -s mu_k N`
(negative downhill, positive uphill) and

    xddot = a_s = g (sin(theta) - s mu_k cos(theta)).

From rest with `tan(theta) > mu_s`: `x(t) = x0 + a_+ t^2 / 2` downhill for ever.
Launched at `v0 != 0` (`s = sign(v0)`): `xdot = v0 + a_s t`. Downhill (`v0 > 0`) with
`tan(theta) < mu_k`, `a_+ < 0` and the block stops at

    t_stop = v0 / (g (mu_k cos(theta) - sin(theta)));

downhill with `tan(theta) >= mu_k` it never stops. Uphill (`v0 < 0`) it always stops,
at `t_stop = -v0 / (g (sin(theta) + mu_k cos(theta)))`. At the stop it sticks if
`tan(theta) <= mu_s` (`lambda_t = -m g sin(theta)` from then on; slip state `0`),
else it slides back down from rest at `a_+` (slip state `+1`). Downhill stops need
`tan(theta) < mu_k <= mu_s`, so they always stick.

Friction's work: the energy `m |qdot|^2 / 2 - m g x sin(theta)` (on the plane) falls
by `mu_k N |dx|` along each slipping stretch.
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._constraints import Unilateral
from .._system import LagrangianSystem
from ._rough import rough_contact


def lagrangian(q, qd, t, args) -> Float[Array, ""]:
    """`L = m |qdot|^2 / 2 - m g (-x sin(theta) + y cos(theta))`."""
    th = args["theta"]
    height = -q[0] * jnp.sin(th) + q[1] * jnp.cos(th)
    return 0.5 * args["m"] * jnp.dot(qd, qd) - args["m"] * args["g"] * height


def gap(q, t, args) -> Float[Array, ""]:
    """`G = y`: the normal row (held while `N = lambda_n >= 0`) and the gap."""
    return q[1]


def tangent_row(q, t, args) -> Float[Array, "1 2"]:
    """`A_t = (1, 0)`: the slip velocity `v_t = xdot` (downhill positive)."""
    one = jnp.ones_like(q[0])
    return jnp.stack([jnp.stack([one, jnp.zeros_like(one)])])


def contact() -> Unilateral:
    """The contact: normal row `y`, sign `+1`, gap `y`, Coulomb friction on the
    tangent row `xdot` with `args["mu_s"]`, `args["mu_k"]`."""
    return rough_contact(gap, tangent_row)


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=contact())


def default_args(theta=0.4, mu_s=0.5, mu_k=0.3, m=2.0, g=9.81) -> dict:
    return {
        "theta": jnp.asarray(theta, float),
        "mu_s": jnp.asarray(mu_s, float),
        "mu_k": jnp.asarray(mu_k, float),
        "m": jnp.asarray(m, float),
        "g": jnp.asarray(g, float),
    }


def state(x0=0.0, v0=0.0):
    """`(q, qd)`: on the plane at `x0`, moving along it at `v0` (downhill positive)."""
    x0, v0 = jnp.asarray(x0, float), jnp.asarray(v0, float)
    zero = jnp.zeros_like(x0)
    return jnp.stack([x0, zero]), jnp.stack([v0, jnp.zeros_like(v0)])


def normal_force(args):
    """`N = lambda_n = m g cos(theta)`."""
    return args["m"] * args["g"] * jnp.cos(args["theta"])


def sticks_from_rest(args):
    """`tan(theta) <= mu_s`."""
    return jnp.tan(args["theta"]) <= args["mu_s"]


def stick_friction(args):
    """`lambda_t = -m g sin(theta)` while sticking (uphill)."""
    return -args["m"] * args["g"] * jnp.sin(args["theta"])


def sliding_acceleration(direction, args):
    """`a_s = g (sin(theta) - s mu_k cos(theta))`, `s = direction = sign(xdot)`."""
    th = args["theta"]
    return args["g"] * (jnp.sin(th) - direction * args["mu_k"] * jnp.cos(th))


def kinetic_friction(direction, args):
    """`lambda_t = -s mu_k N` while slipping in direction `s`."""
    return -direction * args["mu_k"] * normal_force(args)


def stop_time(v0, args):
    """The time at which a block launched at `v0 != 0` first comes to rest:
    `-v0 / a_s` (`s = sign(v0)`) where that is positive, `inf` where it never stops
    (downhill with `tan(theta) >= mu_k`)."""
    s = jnp.sign(v0)
    a = sliding_acceleration(s, args)
    stops = s * a < 0
    return jnp.where(stops, -v0 / jnp.where(stops, a, -s), jnp.inf)


def _phases(t, v0, args):
    """`(t1, a1, a2, s2)`: the first phase lasts `t1` at acceleration `a1`; after it,
    acceleration `a2` with slip state `s2` (0: sticking)."""
    s = jnp.sign(v0)
    a1 = sliding_acceleration(s, args)
    t1 = jnp.where(v0 == 0, 0.0, stop_time(v0, args))
    sticks = sticks_from_rest(args)
    a2 = jnp.where(sticks, 0.0, sliding_acceleration(1.0, args))
    s2 = jnp.where(sticks, 0.0, 1.0)
    return t1, a1, a2, s2


def velocity(t, v0, args):
    """`xdot(t)`, piecewise: slip at `a_s` until the stop, then stick or slide down."""
    t1, a1, a2, _ = _phases(t, v0, args)
    first = t <= t1
    t1f = jnp.where(jnp.isfinite(t1), t1, 0.0)
    return jnp.where(first, v0 + a1 * t, a2 * (t - t1f))


def displacement(t, v0, args):
    """`x(t) - x0`, piecewise (see `velocity`)."""
    t1, a1, a2, _ = _phases(t, v0, args)
    first = t <= t1
    t1f = jnp.where(jnp.isfinite(t1), t1, 0.0)
    x1 = v0 * t1f + 0.5 * a1 * t1f**2
    return jnp.where(first, v0 * t + 0.5 * a1 * t**2, x1 + 0.5 * a2 * (t - t1f) ** 2)


def slip_state(t, v0, args):
    """The slip state at `t` (as `Events.slip`): `sign(xdot)` while slipping, `0`
    while sticking."""
    t1, _, _, s2 = _phases(t, v0, args)
    return jnp.where((t < t1) & (v0 != 0), jnp.sign(v0), s2)


def friction_force(t, v0, args):
    """`lambda_t(t)`: `-s mu_k N` while slipping in direction `s`, `-m g sin(theta)`
    while sticking."""
    s = slip_state(t, v0, args)
    return jnp.where(s == 0, stick_friction(args), kinetic_friction(s, args))
