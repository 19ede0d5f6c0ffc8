"""Painlevé's rod: a rod sliding on a rough floor, and the paradox of Coulomb friction.

A uniform rod of length `2 l`, mass `m`, moment of inertia `m l^2 / 3` about its
centre, rests with its lower end on the floor. Coordinates `q = (x, y, theta)`: the
centre and the angle between the rod and the floor (`0 < theta < pi/2`), the rod
leaning so that the lower end is ahead in `+x`:

    lower end  (x + l cos(theta), y - l sin(theta)),
    upper end  (x - l cos(theta), y + l sin(theta)),

    L = m (xdot^2 + ydot^2)/2 + m l^2 thetadot^2 / 6 - m g y.

Rows of the contact group (`Q^c = A^T lambda`):

    normal   G = y - l sin(theta) = 0   A_n = (0, 1, -l cos(theta)) (Holonomic),
                                        gap G, sign +1, lambda_n = N >= 0;
    tangent  v_t = xdot - l sin(theta) thetadot   A_t = (1, 0, -l sin(theta))
                                        (Pfaffian), the lower end's horizontal
                                        velocity; lambda_t the friction force on it
                                        along `+x`.

Equations of motion:

    m xddot = lambda_t,
    m yddot = -m g + N,
    m l^2 thetaddot / 3 = -l cos(theta) N - l sin(theta) lambda_t.

Sliding with `s = sign(v_t)` (`s = +1`: the lower end leading) and the contact held
(`Gddot = yddot - l cos(theta) thetaddot + l sin(theta) thetadot^2 = 0`), with
`lambda_t = -s mu N`: `thetaddot = -3 N (cos(theta) - s mu sin(theta)) / (m l)` and

    N = m (g - l sin(theta) thetadot^2) / D,
    D = 1 + 3 cos^2(theta) - 3 mu s sin(theta) cos(theta).

For `s = -1`, `D > 0` always. For `s = +1`, `D > 0` (the contact problem has exactly
one solution, whatever the sign of the numerator: `N >= 0` held, or lift-off) iff
`mu < mu_c(theta)`,

    mu_c(theta) = (1 + 3 cos^2(theta)) / (3 sin(theta) cos(theta))
                = (tan^2(theta) + 4) / (3 tan(theta)),

whose minimum over `theta` is `4/3`, at `tan(theta) = 2`. Past it (`D < 0`): with
`g > l sin(theta) thetadot^2` (the free motion's `Gddot = -g + l sin(theta)
thetadot^2 < 0` would go through the floor) held contact needs `N < 0`: no solution
(Painlevé's inconsistency); with `g < l sin(theta) thetadot^2` both lift-off and a
held contact with `N > 0` solve it (indeterminacy). `cjax.simulate` answers both with
`RESULTS.painleve_paradox`. For `mu < 4/3` neither can happen.

The sliding equations (`N` eliminated) are a first-order system in
`(q, qdot)`; the energy `m |(xdot, ydot)|^2/2 + m l^2 thetadot^2/6 + m g y` falls
by the friction work, `dE/dt = lambda_t v_t = -mu N |v_t|`. `sliding_reference`
integrates them independently of the library (SciPy's DOP853, `rtol = atol = 1e-13`,
float64), with events where `v_t` or `N` reaches zero, a reference for
`cjax.simulate`.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._constraints import Unilateral
from .._system import LagrangianSystem
from ._rough import rough_contact


def lagrangian(q, qd, t, args) -> Float[Array, ""]:
    """`L = m (xdot^2 + ydot^2)/2 + m l^2 thetadot^2 / 6 - m g y`."""
    m, length = args["m"], args["l"]
    kinetic = 0.5 * m * (qd[0] ** 2 + qd[1] ** 2) + m * length**2 * qd[2] ** 2 / 6
    return kinetic - m * args["g"] * q[1]


def gap(q, t, args) -> Float[Array, ""]:
    """`G = y - l sin(theta)`: the lower end's height, the normal row and the gap."""
    return q[1] - args["l"] * jnp.sin(q[2])


def tangent_row(q, t, args) -> Float[Array, "1 3"]:
    """`A_t = (1, 0, -l sin(theta))`: the lower end's horizontal velocity."""
    s = args["l"] * jnp.sin(q[2])
    return jnp.stack([jnp.stack([jnp.ones_like(s), jnp.zeros_like(s), -s])])


def contact() -> Unilateral:
    """The floor: normal row `y - l sin(theta)`, sign `+1`, the same gap, Coulomb
    friction on the lower end's horizontal velocity with `args["mu_s"]`,
    `args["mu_k"]`."""
    return rough_contact(gap, tangent_row)


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=contact())


def default_args(mu_s=0.5, mu_k=0.5, l=0.5, m=1.0, g=9.81) -> dict:  # noqa: E741
    return {
        "mu_s": jnp.asarray(mu_s, float),
        "mu_k": jnp.asarray(mu_k, float),
        "l": jnp.asarray(l, float),
        "m": jnp.asarray(m, float),
        "g": jnp.asarray(g, float),
    }


def state(theta, v, args, thetadot=0.0, x=0.0):
    """`(q, qd)` with the lower end on the floor (`y = l sin(theta)`,
    `ydot = l cos(theta) thetadot`), the lower end sliding at `v_t = v`."""
    theta, v = jnp.asarray(theta, float), jnp.asarray(v, float)
    thetadot = jnp.asarray(thetadot, float)
    length = args["l"]
    q = jnp.stack([jnp.asarray(x, float), length * jnp.sin(theta), theta])
    qd = jnp.stack(
        [
            v + length * jnp.sin(theta) * thetadot,
            length * jnp.cos(theta) * thetadot,
            thetadot,
        ]
    )
    return q, qd


def default_state(args):
    """The reference case: `theta = 0.6`, `thetadot = 0`, the lower end sliding
    forwards at `v_t = 3`. With `default_args` (`mu = 0.5`, below `4/3`: no paradox
    at any angle) the rod falls while sliding; up to `t = 0.2` it keeps `N > 0`,
    `v_t > 2.9`, `theta > 0.33` (it lies flat, `theta = 0`, near `t = 0.29`)."""
    return state(0.6, 3.0, args)


def critical_mu(theta):
    """`mu_c(theta) = (1 + 3 cos^2(theta)) / (3 sin(theta) cos(theta))`; minimum
    `4/3` at `tan(theta) = 2`."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return (1 + 3 * c**2) / (3 * s * c)


def consistency(theta, mu, s):
    """`D = 1 + 3 cos^2(theta) - 3 mu s sin(theta) cos(theta)` (`s = sign(v_t)`):
    positive where the sliding contact problem has one solution."""
    c = jnp.cos(theta)
    return 1 + 3 * c**2 - 3 * s * mu * jnp.sin(theta) * c


def slip_velocity(q, qd, args):
    """`v_t = xdot - l sin(theta) thetadot`."""
    return qd[0] - args["l"] * jnp.sin(q[2]) * qd[2]


def normal_force(q, qd, args, s=None):
    """`N = m (g - l sin(theta) thetadot^2) / D` while sliding in direction `s`
    (default `sign(v_t)`) with the contact held, `mu = mu_k`."""
    s = jnp.sign(slip_velocity(q, qd, args)) if s is None else s
    theta, thetadot = q[2], qd[2]
    num = args["m"] * (args["g"] - args["l"] * jnp.sin(theta) * thetadot**2)
    return num / consistency(theta, args["mu_k"], s)


def sliding_acceleration(q, qd, args, s=None):
    """`(qddot, N, lambda_t)` while sliding (contact held, `lambda_t = -s mu_k N`)."""
    s = jnp.sign(slip_velocity(q, qd, args)) if s is None else s
    m, length, theta = args["m"], args["l"], q[2]
    n = normal_force(q, qd, args, s)
    lam = -s * args["mu_k"] * n
    qdd = jnp.stack(
        [
            lam / m,
            -args["g"] + n / m,
            -3
            * n
            * (jnp.cos(theta) - s * args["mu_k"] * jnp.sin(theta))
            / (m * length),
        ]
    )
    return qdd, n, lam


def contact_case(q, qd, args, s=None):
    """What the sliding contact problem admits, `s = sign(v_t)` by default: `1.0`
    one solution with the contact held (`D > 0`, `N >= 0`), `0.0` one solution,
    lift-off (`D > 0`, `N < 0`), `-1.0` no solution (`D < 0`, free motion would
    penetrate), `2.0` two (`D < 0`, lift-off and held contact both)."""
    s = jnp.sign(slip_velocity(q, qd, args)) if s is None else s
    d = consistency(q[2], args["mu_k"], s)
    num = args["g"] - args["l"] * jnp.sin(q[2]) * qd[2] ** 2
    return jnp.where(
        d > 0, jnp.where(num >= 0, 1.0, 0.0), jnp.where(num > 0, -1.0, 2.0)
    )


def energy(q, qd, args):
    """`m (xdot^2 + ydot^2)/2 + m l^2 thetadot^2/6 + m g y`."""
    m = args["m"]
    kinetic = 0.5 * m * (qd[0] ** 2 + qd[1] ** 2) + m * args["l"] ** 2 * qd[2] ** 2 / 6
    return kinetic + m * args["g"] * q[1]


def sliding_rhs(t, y, args, s):
    """The sliding equations in NumPy, hand-written:
    `y = (x, y, theta, xdot, ydot, thetadot, W)`, `W = int mu_k N |v_t| dt`."""
    m, length, g, mu = (float(args[k]) for k in ("m", "l", "g", "mu_k"))
    theta, xd, thd = y[2], y[3], y[5]
    c, sn = np.cos(theta), np.sin(theta)
    n = m * (g - length * sn * thd**2) / (1 + 3 * c**2 - 3 * s * mu * sn * c)
    lam = -s * mu * n
    vt = xd - length * sn * thd
    return np.array(
        [
            y[3],
            y[4],
            y[5],
            lam / m,
            -g + n / m,
            -3 * n * (c - s * mu * sn) / (m * length),
            -lam * vt,
        ]
    )


def sliding_reference(q0, qd0, t1, args, rtol=1e-13, atol=1e-13):
    """`(q, qd, N, W)` at `t1`: the sliding equations integrated from `(q0, qd0)`
    (contact held, slip direction `sign(v_t(0))`), `W` the friction work so far.
    Raises where `v_t` or `N` reaches zero, or `D` its sign change, before `t1`
    (a stop or a lift-off: not this reference's case)."""
    from scipy.integrate import solve_ivp

    q0, qd0 = np.asarray(q0, float), np.asarray(qd0, float)
    length, mu = float(args["l"]), float(args["mu_k"])
    s = float(np.sign(qd0[0] - length * np.sin(q0[2]) * qd0[2]))
    if s == 0:
        raise ValueError("the lower end is not sliding")

    def slip(t, y):
        return y[3] - length * np.sin(y[2]) * y[5]

    def normal(t, y):
        return float(args["g"]) - length * np.sin(y[2]) * y[5] ** 2

    def denominator(t, y):
        c = np.cos(y[2])
        return 1 + 3 * c**2 - 3 * s * mu * np.sin(y[2]) * c

    for event in (slip, normal, denominator):
        event.terminal = True
    y0 = np.concatenate([q0, qd0, [0.0]])
    sol = solve_ivp(
        lambda t, y: sliding_rhs(t, y, args, s),
        (0.0, t1),
        y0,
        method="DOP853",
        rtol=rtol,
        atol=atol,
        events=(slip, normal, denominator),
    )
    if sol.status != 0:
        raise ValueError(f"the sliding phase ends before t1 ({sol.message})")
    y = sol.y[:, -1]
    q, qd = y[:3], y[3:6]
    n = float(normal(t1, y)) * float(args["m"]) / float(denominator(t1, y))
    return q, qd, n, float(y[6])


def pivot_multipliers(y, args):
    """`(thetaddot, N, lambda_t)` while sticking (the lower end a fixed pivot),
    hand-derived, NumPy: about the pivot, `(4/3) m l^2 thetaddot = -m g l cos(theta)`;
    the centre, `(x_p - l cos(theta), l sin(theta))`, accelerates at
    `xddot = l (sin(theta) thetaddot + cos(theta) thetadot^2)`,
    `yddot = l (cos(theta) thetaddot - sin(theta) thetadot^2)`, so
    `lambda_t = m xddot`, `N = m (g + yddot)`."""
    m, length, g = (float(args[k]) for k in ("m", "l", "g"))
    theta, thd = y[2], y[5]
    c, sn = np.cos(theta), np.sin(theta)
    thdd = -3 * g * c / (4 * length)
    xdd = length * (sn * thdd + c * thd**2)
    ydd = length * (c * thdd - sn * thd**2)
    return thdd, m * (g + ydd), m * xdd


def _pivot_rhs(t, y, args):
    thdd, n, lam = pivot_multipliers(y, args)
    m = float(args["m"])
    return np.array([y[3], y[4], y[5], lam / m, n / m - float(args["g"]), thdd, 0.0])


def stick_slip_reference(q0, qd0, t1, args, max_switches=6, rtol=1e-13, atol=1e-13):
    """The rod with Coulomb friction from `(q0, qd0)` (lower end on the floor) to
    `t1`, hand-derived equations only (`sliding_rhs` while slipping,
    `pivot_multipliers` while sticking), SciPy's DOP853 between switches found by
    events: slip -> `v_t = 0`, then stick where `|lambda_t| <= mu_s N` for the pivot's
    multipliers, else slip the other way; stick -> `|lambda_t| = mu_s N`, then slip
    with `s = -sign(lambda_t)`. Returns `(switches, q, qd)`: `switches` the list of
    `(t, slip state after it)` (`0.0` sticking, `+-1.0` slipping), starting with
    `(0.0, initial state)`, and the state at `t1`. Raises at a lift-off (`N = 0`),
    a paradox (`D = 0`) or more than `max_switches` switches."""
    from scipy.integrate import solve_ivp

    mu_s, mu_k = float(args["mu_s"]), float(args["mu_k"])
    length = float(args["l"])

    def vt(y):
        return y[3] - length * np.sin(y[2]) * y[5]

    def at_rest(y):
        _, n, lam = pivot_multipliers(y, args)
        return 0.0 if abs(lam) <= mu_s * n else float(-np.sign(lam))

    y = np.concatenate([np.asarray(q0, float), np.asarray(qd0, float), [0.0]])
    v = vt(y)
    mode = at_rest(y) if v == 0 else float(np.sign(v))
    t, switches = 0.0, [(0.0, mode)]
    for _ in range(max_switches + 1):
        s = mode
        if s == 0.0:

            def rhs(t, y):
                return _pivot_rhs(t, y, args)

            def normal(t, y):
                return pivot_multipliers(y, args)[1]

            def switch(t, y):
                _, n, lam = pivot_multipliers(y, args)
                return abs(lam) - mu_s * n

            switch.direction = 1
            events = (normal, switch)
        else:

            def rhs(t, y, s=s):
                return sliding_rhs(t, y, args, s)

            def normal(t, y):
                return float(args["g"]) - length * np.sin(y[2]) * y[5] ** 2

            def switch(t, y):
                return vt(y)

            def paradox(t, y, s=s):
                c = np.cos(y[2])
                return 1 + 3 * c**2 - 3 * s * mu_k * np.sin(y[2]) * c

            switch.direction = -s
            paradox.terminal = True
            events = (normal, switch, paradox)
        normal.terminal, switch.terminal, normal.direction = True, True, -1
        sol = solve_ivp(
            rhs, (t, t1), y, method="DOP853", rtol=rtol, atol=atol, events=events
        )
        t, y = float(sol.t[-1]), sol.y[:, -1]
        if sol.status == 0:
            return switches, y[:3], y[3:6]
        if sol.t_events[0].size:
            raise ValueError(f"lift-off at t = {t}")
        if len(events) == 3 and sol.t_events[2].size:
            raise ValueError(f"Painlevé paradox at t = {t}")
        mode = (
            float(-np.sign(pivot_multipliers(y, args)[2])) if s == 0.0 else at_rest(y)
        )
        switches.append((t, mode))
    raise ValueError("more switches than max_switches")


def stick_slip_state(args):
    """A case with a stop and a reversal: `theta = 0.9`, `thetadot = 0`, the lower
    end sliding forwards at `v_t = 0.3`. With `default_args(mu_s=0.7, mu_k=0.6)` it
    slides forwards, sticks (`t ~ 0.254`), slips backwards (`t ~ 0.322`), and keeps
    `N > 0`, `theta > 0.25` up to `t = 0.38`."""
    return state(0.9, 0.3, args)
