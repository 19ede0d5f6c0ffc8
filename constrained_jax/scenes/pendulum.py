"""The simple pendulum in Cartesian coordinates with the constraint `r = l`.

`q = (x, y)` with `y` up, `L = m (xdot^2 + ydot^2)/2 - m g y`, and the holonomic
constraint `G = sqrt(x^2 + y^2) - l = 0`. Since `grad G` is the outward unit vector,
the multiplier is the radial force of constraint: `lambda = -T`, with the tension

    T = m (g cos(theta) + l thetadot^2),   thetadot^2 = 2 g (cos theta - cos theta0)/l

for a release from rest at `theta0` (angle from the downward vertical). The period is
`4 sqrt(l/g) K(sin(theta0/2))`, `K` the complete elliptic integral of the first kind
(parameter convention `K(k)`, modulus `k`).
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._constraints import Holonomic
from .._system import LagrangianSystem


def lagrangian(q, qd, t, args) -> Float[Array, ""]:
    """`L = m |qdot|^2 / 2 - m g y`."""
    return 0.5 * args["m"] * jnp.dot(qd, qd) - args["m"] * args["g"] * q[1]


def rod(q, t, args) -> Float[Array, "1"]:
    """`G = r - l`."""
    return jnp.stack([jnp.sqrt(q[0] ** 2 + q[1] ** 2) - args["l"]])


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=(Holonomic(rod),))


def default_args(m=1.0, g=9.81, l=1.0) -> dict:
    return {
        "m": jnp.asarray(m, float),
        "g": jnp.asarray(g, float),
        "l": jnp.asarray(l, float),
    }


def state(theta, thetadot, args):
    """`(q, qd)` at angle `theta` from the downward vertical, rate `thetadot`."""
    l = args["l"]
    q = jnp.stack([l * jnp.sin(theta), -l * jnp.cos(theta)])
    qd = jnp.stack([l * jnp.cos(theta), l * jnp.sin(theta)]) * thetadot
    return q, qd


def tension(theta, thetadot, args):
    """`T = m (g cos theta + l thetadot^2)`; the multiplier is `-T`."""
    return args["m"] * (args["g"] * jnp.cos(theta) + args["l"] * thetadot**2)


def angular_acceleration(theta, args):
    """`thetaddot = -(g/l) sin theta`."""
    return -args["g"] / args["l"] * jnp.sin(theta)


def period(theta0, args):
    """`4 sqrt(l/g) K(sin(theta0/2))`, by the arithmetic-geometric mean."""
    k = jnp.sin(jnp.asarray(theta0) / 2)
    a, b = jnp.ones_like(k), jnp.sqrt(1 - k**2)
    for _ in range(30):
        a, b = (a + b) / 2, jnp.sqrt(a * b)
    return 4 * jnp.sqrt(args["l"] / args["g"]) * jnp.pi / (2 * a)
