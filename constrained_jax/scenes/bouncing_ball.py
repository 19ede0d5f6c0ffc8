"""A ball bouncing on a floor: contacts that come and go, with Newton's restitution.

`q = (x, y)`, `y` the height of the ball's centre above the floor (radius absorbed),
`L = m (xdot^2 + ydot^2)/2 - m g y`. The floor is a `Unilateral` holonomic constraint
`G = y = 0` (multiplier `lambda = m g` at rest, pushing up) with gap `y` and
restitution `e`: at each impact `ydot+ = -e ydot-`, `xdot` unchanged (the impulse is
normal to the floor).

Dropped from rest at height `h` (any horizontal speed `u`), the first impact is at
`t_1 = sqrt(2 h / g)` with speed `v_1 = sqrt(2 g h)`; the `k`-th impact has speed
`v_k = e^(k-1) v_1`, each flight in between lasts `2 v / g`, so the impact times
form a geometric series

    t_k = t_1 + (2 v_1 / g) (e + e^2 + ... + e^(k-1)),

that converges for `e < 1` to `t_inf = t_1 + 2 e v_1 / (g (1 - e))`: infinitely
many bounces in finite time (Zeno). The apex after the `k`-th impact is
`h_k = e^(2k) h`, and the energy `m g y + m ydot^2 / 2` is multiplied by `e^2` at each
impact. With `rest_speed = v_r`, the first impact slower than `v_r`, number
`k_r = 1 + ceil(log(v_r / v_1) / log(e))` (the first `k` with `e^(k-1) v_1 < v_r`), is
taken as inelastic: the ball rests on the floor from `t_(k_r)` on.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._constraints import Holonomic, Unilateral
from .._system import LagrangianSystem


def lagrangian(q, qd, t, args) -> Float[Array, ""]:
    """`L = m |qdot|^2 / 2 - m g y`."""
    return 0.5 * args["m"] * jnp.dot(qd, qd) - args["m"] * args["g"] * q[1]


def height(q, t, args) -> Float[Array, ""]:
    """`G = y`: the floor's constraint, and its gap."""
    return q[1]


def floor() -> Unilateral:
    """The floor: holds `y = 0` while it pushes, restitution `args["e"]`, resting
    contact below the impact speed `args["rest_speed"]`."""
    return Unilateral(
        Holonomic(height),
        sign=1.0,
        gap=height,
        restitution=lambda args: args["e"],
        rest_speed=lambda args: args["rest_speed"],
    )


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=floor())


def default_args(e=0.8, m=1.0, g=9.81, rest_speed=0.0) -> dict:
    return {
        "e": jnp.asarray(e, float),
        "m": jnp.asarray(m, float),
        "g": jnp.asarray(g, float),
        "rest_speed": jnp.asarray(rest_speed, float),
    }


def state(h, u=0.0):
    """`(q, qd)`: at rest vertically at height `h`, moving sideways at `u`."""
    q = jnp.stack([jnp.zeros_like(jnp.asarray(h, float)), jnp.asarray(h, float)])
    qd = jnp.stack([jnp.asarray(u, float), jnp.zeros_like(jnp.asarray(h, float))])
    return q, qd


def first_impact(h, args):
    """`(t_1, v_1) = (sqrt(2 h / g), sqrt(2 g h))`."""
    return jnp.sqrt(2 * h / args["g"]), jnp.sqrt(2 * args["g"] * h)


def impact_time(k: int, h, args):
    """`t_k = t_1 + (2 v_1 / g) sum_{j=1}^{k-1} e^j` (`k >= 1`, static)."""
    t1, v1 = first_impact(h, args)
    e = args["e"]
    series = sum((e**j for j in range(1, k)), jnp.zeros_like(e))
    return t1 + 2 * v1 / args["g"] * series


def impact_speed(k: int, h, args):
    """`v_k = e^(k-1) v_1`."""
    return args["e"] ** (k - 1) * first_impact(h, args)[1]


def apex_height(k: int, h, args):
    """The apex after the `k`-th impact, `e^(2k) h`."""
    return args["e"] ** (2 * k) * h


def zeno_time(h, args):
    """`t_inf = t_1 + 2 e v_1 / (g (1 - e))` (`e < 1`)."""
    t1, v1 = first_impact(h, args)
    e = args["e"]
    return t1 + 2 * e * v1 / (args["g"] * (1 - e))


def rest_impact(h, e, g, rest_speed) -> int:
    """`k_r`: the first impact slower than `rest_speed` (NumPy, concrete values)."""
    v1 = np.sqrt(2 * g * h)
    k = 1
    while e ** (k - 1) * v1 >= rest_speed:
        k += 1
    return k
