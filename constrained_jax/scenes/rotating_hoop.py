"""A bead on a hoop spinning about its vertical diameter: a rheonomic constraint.

Cartesian coordinates `q = (x, y, z)` of a bead of mass `m` on a hoop of radius `rho`
that turns at the prescribed rate `omega` about the vertical axis. Two holonomic,
time-dependent constraints:

    |q|^2 - rho^2 = 0,     n(t) . q = 0,   n(t) = (-sin(omega t), cos(omega t), 0),

with `L = m |qdot|^2 / 2 - m g z`. With `theta` the angle from the bottom of the hoop,
the reduced equation is

    thetaddot = sin(theta) (omega^2 cos(theta) - g / rho),

and the Jacobi integral of the reduced system,
`h = m rho^2 (thetadot^2 - omega^2 sin^2 theta) / 2 - m g rho cos(theta)`,
is conserved although the energy in the inertial frame is not (the hoop's drive does
work). For `omega^2 > g / rho` the bottom is unstable and the bead settles around
`cos(theta*) = g / (rho omega^2)`.
"""

import jax
import jax.numpy as jnp

from .._constraints import Holonomic
from .._system import LagrangianSystem


def lagrangian(q, qd, t, args):
    return 0.5 * args["m"] * jnp.dot(qd, qd) - args["m"] * args["g"] * q[2]


def hoop(q, t, args):
    omega = args["omega"]
    normal = jnp.stack([-jnp.sin(omega * t), jnp.cos(omega * t), jnp.zeros_like(t)])
    return jnp.stack([jnp.dot(q, q) - args["rho"] ** 2, jnp.dot(normal, q)])


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=(Holonomic(hoop),))


def default_args(m=1.0, rho=0.5, omega=6.0, g=9.81) -> dict:
    return {
        "m": jnp.asarray(m, float),
        "rho": jnp.asarray(rho, float),
        "omega": jnp.asarray(omega, float),
        "g": jnp.asarray(g, float),
    }


def position(theta, t, args):
    """The bead at angle `theta` from the bottom, at time `t`."""
    omega = args["omega"]
    horizontal = jnp.stack([jnp.cos(omega * t), jnp.sin(omega * t), jnp.zeros_like(t)])
    vertical = jnp.array([0.0, 0.0, 1.0])
    return args["rho"] * (jnp.sin(theta) * horizontal - jnp.cos(theta) * vertical)


def state(theta, thetadot, t, args):
    """`(q, qdot)` for angle `theta` and rate `thetadot` at time `t`."""
    fn = lambda th, tt: position(th, tt, args)
    t = jnp.asarray(t, float)
    return jax.jvp(
        fn,
        (jnp.asarray(theta, float), t),
        (jnp.asarray(thetadot, float), jnp.ones_like(t)),
    )


def angle(q, t, args):
    """`theta` from `q` at time `t`: `atan2(q . e_h(t), -z)`, `e_h` the hoop's
    horizontal direction."""
    omega = args["omega"]
    horizontal = jnp.stack([jnp.cos(omega * t), jnp.sin(omega * t), jnp.zeros_like(t)])
    return jnp.arctan2(jnp.dot(q, horizontal), -q[2])


def angular_acceleration(theta, args):
    """`thetaddot = sin(theta) (omega^2 cos(theta) - g/rho)`."""
    return jnp.sin(theta) * (
        args["omega"] ** 2 * jnp.cos(theta) - args["g"] / args["rho"]
    )


def jacobi_integral(theta, thetadot, args):
    """`h = m rho^2 (thetadot^2 - omega^2 sin^2 theta)/2 - m g rho cos theta`."""
    m, rho, omega, g = args["m"], args["rho"], args["omega"], args["g"]
    return 0.5 * m * rho**2 * (thetadot**2 - omega**2 * jnp.sin(theta) ** 2) - (
        m * g * rho * jnp.cos(theta)
    )
