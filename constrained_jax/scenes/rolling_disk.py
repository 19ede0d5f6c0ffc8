"""A vertical disk rolling without slipping on a plane: nonholonomic constraints.

Coordinates `q = (x, y, theta, phi)`: the contact point, the heading and the rolling
angle of a disk of radius `R`, mass `m`, moments of inertia `I_roll` (about its axle)
and `I_turn` (about the vertical). The Lagrangian is kinetic only,

    L = m (xdot^2 + ydot^2)/2 + I_roll phidot^2 / 2 + I_turn thetadot^2 / 2,

and rolling without slipping, `xdot = R cos(theta) phidot`,
`ydot = R sin(theta) phidot`,
is the Pfaffian form with rows `(1, 0, 0, -R cos theta)`, `(0, 1, 0, -R sin theta)`,
which is not integrable (the disk can reach any (x, y, theta, phi) by rolling and
turning). Then `phidot = nu` and `thetadot = omega` are constant and the contact point
moves on a circle of radius `R nu / omega`:

    x(t) = x0 + (R nu / omega)(sin(theta0 + omega t) - sin theta0),
    y(t) = y0 - (R nu / omega)(cos(theta0 + omega t) - cos theta0),

with the multipliers the centripetal force, `lambda = m (xddot, yddot)
= m R nu omega (-sin theta, cos theta)`.
"""

import jax.numpy as jnp

from .._constraints import Pfaffian
from .._system import LagrangianSystem


def lagrangian(q, qd, t, args):
    return (
        0.5 * args["m"] * (qd[0] ** 2 + qd[1] ** 2)
        + 0.5 * args["I_roll"] * qd[3] ** 2
        + 0.5 * args["I_turn"] * qd[2] ** 2
    )


def rolling(q, t, args):
    """The rows `g_{j sigma}` of `dx - R cos(theta) dphi = 0`, `dy - R sin(theta) dphi
    = 0`."""
    theta, big_r = q[2], args["R"]
    zero, one = jnp.zeros_like(theta), jnp.ones_like(theta)
    return jnp.stack(
        [
            jnp.stack([one, zero, zero, -big_r * jnp.cos(theta)]),
            jnp.stack([zero, one, zero, -big_r * jnp.sin(theta)]),
        ]
    )


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=(Pfaffian(rolling),))


def default_args(m=1.0, R=0.5, I_roll=0.125, I_turn=0.0625) -> dict:
    return {
        "m": jnp.asarray(m, float),
        "R": jnp.asarray(R, float),
        "I_roll": jnp.asarray(I_roll, float),
        "I_turn": jnp.asarray(I_turn, float),
    }


def initial_state(theta0, nu, omega, args):
    """At the origin, heading `theta0`, rolling rate `nu`, turning rate `omega`."""
    q0 = jnp.stack([0.0, 0.0, theta0, 0.0])
    big_r = args["R"]
    qd0 = jnp.stack(
        [big_r * jnp.cos(theta0) * nu, big_r * jnp.sin(theta0) * nu, omega, nu]
    )
    return q0, qd0


def closed_form(t, theta0, nu, omega, args):
    """`q(t)` and the multipliers along the circular motion."""
    radius = args["R"] * nu / omega
    theta = theta0 + omega * t
    q = jnp.stack(
        [
            radius * (jnp.sin(theta) - jnp.sin(theta0)),
            -radius * (jnp.cos(theta) - jnp.cos(theta0)),
            theta,
            nu * t,
        ],
        axis=-1,
    )
    force = args["m"] * args["R"] * nu * omega
    multipliers = jnp.stack([-force * jnp.sin(theta), force * jnp.cos(theta)], axis=-1)
    return q, multipliers
