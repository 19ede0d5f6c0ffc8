"""A disk (or ball) launched sliding on a rough floor: slip, then rolling.

A disk of radius `R`, mass `m`, moment of inertia `I = k m R^2` about its centre
(`k = 1/2` a disk, `2/5` a solid sphere, `1` a ring) moves in the vertical plane on
the floor `y = R`. Coordinates `q = (x, y, phi)`: the centre, and the rotation angle
`phi` counterclockwise (`x` to the right, `y` up), so that the contact point's
velocity is

    v_t = xdot + R phidot

(rolling without slipping to the right is `xdot = -R phidot`, `phidot < 0`).

    L = m (xdot^2 + ydot^2)/2 + I phidot^2 / 2 - m g y.

Rows of the contact group (`Q^c = A^T lambda`):

    normal   G = y - R = 0         A_n = (0, 1, 0), gap y - R, sign +1, lambda_n = N;
    tangent  v_t = xdot + R phidot A_t = (1, 0, R) (Pfaffian); lambda_t the friction
                                   force on the contact point along +x.

Equations: `m xddot = lambda_t`, `I phiddot = R lambda_t`, `m yddot = -m g + N`, so
`N = m g` throughout.

Slipping with `s = sign(v_t)`: `lambda_t = -s mu_k m g`, `xddot = -s mu_k g`,
`phiddot = -s mu_k g / (k R)`, and `v_t` falls at the rate `(1 + 1/k) mu_k g`:

    v_t(t) = v_t0 - s (1 + 1/k) mu_k g t,
    t* = |v_t0| / ((1 + 1/k) mu_k g)     (v0/(3 mu_k g) disk, 2 v0/(7 mu_k g) sphere,
                                          for a launch at v0 without spin).

Sticking (rolling): `xddot + R phiddot = 0` with `xddot = lambda_t / m`,
`phiddot = R lambda_t / I` gives `lambda_t (1/m + R^2/I) = 0`: `lambda_t = 0`, inside
the cone for every `mu_s >= 0`, so at `t*` the disk re-sticks and rolls for ever at

    v = (v0 - k R omega0) / (1 + k)      (v0/(1+k): 2 v0/3 disk, 5 v0/7 sphere),

launched at `xdot = v0`, `phidot = omega0`. Piecewise, for `t <= t*`:
`x = x0 + v0 t - s mu_k g t^2/2`, `phidot = omega0 - s mu_k g t / (k R)`,
`phi = omega0 t - s mu_k g t^2 / (2 k R)`; after `t*`: `xdot = v`, `phidot = -v / R`.

Frictionless, `mu_s = mu_k = 0`: nothing acts along the floor; `v_t` keeps its launch
value and the disk never sticks unless `v_t = 0` exactly (then the stick multiplier
`0` is on the cone's edge `|0| <= 0 * N`, and sticking and slipping are the same
motion). The energy lost to friction, `m v0^2/2 + I omega0^2/2 - (m + I/R^2) v^2/2`,
equals `mu_k N |v_t0| t* / 2` (the work `int mu_k N |v_t| dt` at linearly falling
`|v_t|`).
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._constraints import Unilateral
from .._system import LagrangianSystem
from ._rough import rough_contact


def lagrangian(q, qd, t, args) -> Float[Array, ""]:
    """`L = m (xdot^2 + ydot^2)/2 + I phidot^2/2 - m g y`, `I = k m R^2`."""
    m = args["m"]
    inertia = args["k"] * m * args["R"] ** 2
    kinetic = 0.5 * m * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * inertia * qd[2] ** 2
    return kinetic - m * args["g"] * q[1]


def gap(q, t, args) -> Float[Array, ""]:
    """`G = y - R`: the normal row and the gap."""
    return q[1] - args["R"]


def tangent_row(q, t, args) -> Float[Array, "1 3"]:
    """`A_t = (1, 0, R)`: the contact point's velocity `v_t = xdot + R phidot`."""
    big_r = args["R"]
    return jnp.stack([jnp.stack([jnp.ones_like(big_r), jnp.zeros_like(big_r), big_r])])


def contact() -> Unilateral:
    """The floor: normal row `y - R`, sign `+1`, gap `y - R`, Coulomb friction on
    the tangent row `xdot + R phidot` with `args["mu_s"]`, `args["mu_k"]`."""
    return rough_contact(gap, tangent_row)


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=contact())


def default_args(k=0.5, mu_s=0.4, mu_k=0.3, R=0.2, m=1.5, g=9.81) -> dict:
    return {
        "k": jnp.asarray(k, float),
        "mu_s": jnp.asarray(mu_s, float),
        "mu_k": jnp.asarray(mu_k, float),
        "R": jnp.asarray(R, float),
        "m": jnp.asarray(m, float),
        "g": jnp.asarray(g, float),
    }


def state(v0, args, omega0=0.0, x0=0.0):
    """`(q, qd)`: on the floor (`y = R`) at `x0`, `phi = 0`, moving at `xdot = v0`
    and spinning at `phidot = omega0`."""
    v0, omega0 = jnp.asarray(v0, float), jnp.asarray(omega0, float)
    big_r = args["R"]
    zero = jnp.zeros_like(v0)
    q = jnp.stack([jnp.asarray(x0, float) + zero, big_r + zero, zero])
    qd = jnp.stack([v0, zero, omega0])
    return q, qd


def normal_force(args):
    """`N = lambda_n = m g`."""
    return args["m"] * args["g"]


def slip_velocity(v0, omega0, args):
    """`v_t0 = v0 + R omega0`."""
    return v0 + args["R"] * omega0


def slip_time(v0, omega0, args):
    """`t* = |v_t0| / ((1 + 1/k) mu_k g)`: when `v_t` reaches 0 and the disk sticks."""
    vt0 = slip_velocity(v0, omega0, args)
    return jnp.abs(vt0) / ((1 + 1 / args["k"]) * args["mu_k"] * args["g"])


def rolling_speed(v0, omega0, args):
    """`v = (v0 - k R omega0) / (1 + k)`: `xdot` while rolling after `t*`."""
    k = args["k"]
    return (v0 - k * args["R"] * omega0) / (1 + k)


def motion(t, v0, omega0, args, x0=0.0):
    """`(q(t), qd(t))` in closed form: slipping until `t*`, rolling after."""
    k, big_r, g, mu = args["k"], args["R"], args["g"], args["mu_k"]
    s = jnp.sign(slip_velocity(v0, omega0, args))
    ts = slip_time(v0, omega0, args)
    v = rolling_speed(v0, omega0, args)
    tau = jnp.minimum(t, ts)
    after = jnp.maximum(t - ts, 0.0)
    x = x0 + v0 * tau - 0.5 * s * mu * g * tau**2 + v * after
    phi = omega0 * tau - 0.5 * s * mu * g * tau**2 / (k * big_r) - v / big_r * after
    xd = jnp.where(t < ts, v0 - s * mu * g * t, v)
    phid = jnp.where(t < ts, omega0 - s * mu * g * t / (k * big_r), -v / big_r)
    zero = jnp.zeros_like(x)
    return jnp.stack([x, big_r + zero, phi]), jnp.stack([xd, zero, phid])


def friction_force(t, v0, omega0, args):
    """`lambda_t(t)`: `-s mu_k m g` while slipping, `0` while rolling."""
    s = jnp.sign(slip_velocity(v0, omega0, args))
    kinetic = -s * args["mu_k"] * normal_force(args)
    return jnp.where(t < slip_time(v0, omega0, args), kinetic, jnp.zeros_like(kinetic))


def dissipated_energy(v0, omega0, args):
    """`mu_k N |v_t0| t* / 2`: the kinetic energy friction takes."""
    vt0 = slip_velocity(v0, omega0, args)
    return (
        0.5
        * args["mu_k"]
        * normal_force(args)
        * jnp.abs(vt0)
        * slip_time(v0, omega0, args)
    )
