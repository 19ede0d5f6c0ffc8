"""A cylinder rolling without slipping on a fixed cylinder (the lecture's example).

Rolling cylinder: mass `M`, moment of inertia `I`, radius `a`; fixed cylinder: radius
`R`. Coordinates `q = (r, theta1, theta2)`: the distance between the axes, the angle
of the line of centres from the upward vertical, and the rotation angle of the rolling
cylinder. The Lagrangian

    L = M (rdot^2 + r^2 theta1dot^2)/2 + I theta2dot^2/2 - M g r cos(theta1)

with the constraints, in the lecture's Pfaffian form, `g = [[1, 0, 0], [0, R+a, -a]]`,
`h = 0`:

    contact  r = R + a                  (j = 1; lambda_1 = Q_r, the normal force),
    no slip  R theta1 = a (theta2 - theta1)   (j = 2).

Released from rest at `theta1 = theta0`, with `alpha = I / (M a^2)`:

    theta1dot^2 = 2 g (cos theta0 - cos theta1) / ((1 + alpha)(R + a)),
    theta1ddot  = g sin(theta1) / ((1 + alpha)(R + a)),
    Q_r = lambda_1 = M g ((3 + alpha) cos theta1 - 2 cos theta0) / (1 + alpha),
    lambda_2 = -(I / a^2)(R + a) theta1ddot,

and the normal force vanishes at the detachment angle
`theta* = arccos(2 cos theta0 / (3 + alpha))`. (Some sources print the formula for
`theta1dot` without the square and without the factor `1 + alpha`; the above follows
from energy conservation.)

With `alpha = 0` (`I = 0`) the mass matrix is singular, but the KKT matrix is not: the
no-slip constraint fixes `theta2`. Once released (`contact_system`), nothing fixes
`theta2` and nothing acts on it: a free gauge, whose acceleration is set to zero, so
the spin rate at release is held while the centre flies as a projectile.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._constraints import Pfaffian, Unilateral
from .._system import LagrangianSystem


def lagrangian(q, qd, t, args) -> Float[Array, ""]:
    r, theta1 = q[0], q[1]
    rd, theta1d, theta2d = qd[0], qd[1], qd[2]
    m, inertia, g = args["M"], args["I"], args["g"]
    kinetic = 0.5 * m * (rd**2 + r**2 * theta1d**2) + 0.5 * inertia * theta2d**2
    return kinetic - m * g * r * jnp.cos(theta1)


def pfaffian_rows(q, t, args) -> Float[Array, "2 3"]:
    """The lecture's `g_{j sigma}`: contact `(1, 0, 0)`, no slip `(0, R+a, -a)`."""
    big_r, a = args["R"], args["a"]
    zero, one = jnp.zeros_like(a), jnp.ones_like(a)
    return jnp.stack([jnp.stack([one, zero, zero]), jnp.stack([zero, big_r + a, -a])])


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=(Pfaffian(pfaffian_rows),))


def contact_system() -> LagrangianSystem:
    """The same system with the contact unilateral: both rows (contact and no slip)
    hold while the normal force `Q_r = lambda_1 >= 0` and are released together at
    the detachment angle; after that the cylinder flies freely until re-contact,
    `r = R + a` again (the gap `r - (R + a)` falls through zero)."""
    contact = Unilateral(
        Pfaffian(pfaffian_rows),
        sign=1.0,
        gap=lambda q, t, args: q[0] - (args["R"] + args["a"]),
    )
    return LagrangianSystem(lagrangian, constraints=contact)


def default_args(M=1.0, alpha=0.5, a=0.3, R=1.0, g=9.81) -> dict:
    M, a = jnp.asarray(M, float), jnp.asarray(a, float)
    return {
        "M": M,
        "I": jnp.asarray(alpha, float) * M * a**2,
        "a": a,
        "R": jnp.asarray(R, float),
        "g": jnp.asarray(g, float),
    }


def alpha(args):
    return args["I"] / (args["M"] * args["a"] ** 2)


def state(theta1, theta1dot, args):
    """The attached state at `theta1` (with `theta2 = (1 + R/a) theta1`)."""
    big_r, a = args["R"], args["a"]
    ratio = 1 + big_r / a
    q = jnp.stack([big_r + a, theta1, ratio * theta1])
    qd = jnp.stack([jnp.zeros_like(theta1dot), theta1dot, ratio * theta1dot])
    return q, qd


def angular_velocity_squared(theta1, theta0, args):
    """`theta1dot^2 = 2 g (cos theta0 - cos theta1) / ((1 + alpha)(R + a))`."""
    return (
        2
        * args["g"]
        * (jnp.cos(theta0) - jnp.cos(theta1))
        / ((1 + alpha(args)) * (args["R"] + args["a"]))
    )


def angular_acceleration(theta1, args):
    """`theta1ddot = g sin theta1 / ((1 + alpha)(R + a))`."""
    return args["g"] * jnp.sin(theta1) / ((1 + alpha(args)) * (args["R"] + args["a"]))


def normal_force(theta1, theta0, args):
    """`Q_r = M g ((3 + alpha) cos theta1 - 2 cos theta0) / (1 + alpha)`."""
    al = alpha(args)
    return (
        args["M"]
        * args["g"]
        * ((3 + al) * jnp.cos(theta1) - 2 * jnp.cos(theta0))
        / (1 + al)
    )


def no_slip_multiplier(theta1, args):
    """`lambda_2 = -(I / a^2)(R + a) theta1ddot`."""
    return (
        -args["I"]
        / args["a"] ** 2
        * (args["R"] + args["a"])
        * angular_acceleration(theta1, args)
    )


def detachment_angle(theta0, args):
    """`theta* = arccos(2 cos theta0 / (3 + alpha))` for a start at rest above the
    equator (`cos theta0 >= 0`); below it the normal force at rest, `M g cos theta0`,
    is already negative and the cylinder leaves at once: `theta* = theta0` (the two
    agree at the equator). (The formula alone gave an angle the cylinder never
    reaches, `theta* < theta0`.)"""
    cos0 = jnp.cos(theta0)
    above = cos0 >= 0
    formula = jnp.arccos(2 * jnp.where(above, cos0, 0.0) / (3 + alpha(args)))
    return jnp.where(above, formula, theta0)


def _carlson_rf(x, y, z, iterations: int = 40):
    """Carlson's symmetric elliptic integral `R_F(x, y, z)` by duplication."""

    def body(_, xyz):
        x, y, z = xyz
        sx, sy, sz = jnp.sqrt(x), jnp.sqrt(y), jnp.sqrt(z)
        lam = sx * sy + sy * sz + sz * sx
        return (x + lam) / 4, (y + lam) / 4, (z + lam) / 4

    x, y, z = jax.lax.fori_loop(0, iterations, body, (x, y, z))
    return 1 / jnp.sqrt((x + y + z) / 3)


def time_to_angle(theta1, theta0, args):
    """The time to roll from rest at `theta0` to `theta1` (attached, `theta1 >=
    theta0 > 0`): the quadrature `t = int dtheta / theta1dot` in closed form.

    The attached motion is an inverted pendulum, `theta1ddot = k sin theta1`,
    `k = g/((1 + alpha)(R + a))`; with `m = cos^2(theta0/2)` and
    `sin u = cos(theta1/2) / cos(theta0/2)`,

        t = (K(m) - F(u | m)) / sqrt(k),

    with `K` and `F` the complete and incomplete elliptic integrals of the first kind
    (Carlson's `R_F`, written with the complementary parameter `sin^2(theta0/2)` so
    that small `theta0`, where `m -> 1`, keeps its accuracy). Infinite for
    `theta0 = 0` (balanced on top).
    """
    k = angular_acceleration(jnp.pi / 2, args)
    kc2 = jnp.sin(theta0 / 2) ** 2  # 1 - m
    sin_u = jnp.cos(theta1 / 2) / jnp.cos(theta0 / 2)
    cos2_u = (1 - sin_u) * (1 + sin_u)
    one, zero = jnp.ones_like(kc2), jnp.zeros_like(kc2)
    big_k = _carlson_rf(zero, kc2, one)
    f = sin_u * _carlson_rf(cos2_u, cos2_u + kc2 * sin_u**2, one)
    return (big_k - f) / jnp.sqrt(k)


def detachment_time(theta0, args):
    """The time from rest at `theta0` to detachment, `time_to_angle(theta*, theta0)`
    (0 below the equator, where it leaves at once)."""
    return time_to_angle(detachment_angle(theta0, args), theta0, args)
