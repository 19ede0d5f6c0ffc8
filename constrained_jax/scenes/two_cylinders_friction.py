"""The lecture's two cylinders with a finite friction coefficient: rolling, slipping,
detaching.

The scene of `two_cylinders` (same `q = (r, theta1, theta2)`, `L`, `alpha = I/(M a^2)`)
with the no-slip row replaced by Coulomb friction. Rows of the contact group
(`Q^c = A^T lambda`):

    normal   G = r - (R + a) = 0   A_n = (1, 0, 0) (Holonomic), gap r - (R + a),
                                   sign +1, lambda_n = N = Q_r >= 0;
    tangent  v_t = (R + a) theta1dot - a theta2dot   A_t = (0, R + a, -a) (Pfaffian),

`v_t` the slip velocity of the rolling cylinder's contact point along the direction
of increasing `theta1`, and `lambda_t` the friction force on it along that direction
(its generalised force is `A_t^T lambda_t`; its power `lambda_t v_t`).

The equations of motion with the contact held (`r = R + a`, `rho = R + a`):

    r:       -M rho theta1dot^2 + M g cos(theta1) = N,
    theta1:  M rho^2 theta1ddot - M g rho sin(theta1) = rho lambda_t,
    theta2:  I theta2ddot = -a lambda_t.

Rolling (sticking, `v_t = 0`), from rest at `theta0 > 0`: `two_cylinders`' closed
forms, `N = two_cylinders.normal_force`, `lambda_t = two_cylinders.no_slip_multiplier
= -alpha M g sin(theta1) / (1 + alpha)` (negative: friction holds the contact point
back), time `two_cylinders.time_to_angle`. It stays inside the cone
`|lambda_t| <= mu_s N` until the slip angle `theta_s`, the root of

    f(theta) = alpha sin(theta) - mu_s ((3 + alpha) cos(theta) - 2 cos(theta0)) = 0.

Writing `f = rho_f sin(theta - delta) + 2 mu_s cos(theta0)` with
`rho_f = hypot(alpha, mu_s (3 + alpha))`, `delta = atan2(mu_s (3 + alpha), alpha)`,

    theta_s = delta + arcsin(-2 mu_s cos(theta0) / rho_f)

(closed form, differentiable); `f` increases on `[theta0, theta*]`
(`theta* = arccos(2 cos(theta0) / (3 + alpha))` the frictionless detachment angle, where
`f = alpha sin(theta*) > 0`), so `theta_s < theta*` for every finite `mu_s`
(`alpha > 0`) and `theta_s -> theta*` as `mu_s -> inf`. Where `f(theta0) > 0`
(`tan(theta0) > mu_s (1 + alpha)/alpha`) it slips at once: `theta_s = theta0`.

Sliding (`theta_s` on): `lambda_t = -mu_k N` (`v_t > 0`: without friction the centre
would run ahead of the spin), `N` from the radial equation; the first-order system in
`(theta1, theta1dot, theta2, theta2dot)`:

    N           = M (g cos(theta1) - rho theta1dot^2),
    theta1ddot  = (g sin(theta1) - mu_k N / M) / rho,
    theta2ddot  = a mu_k N / I,
    d v_t / dt  = g sin(theta1) - mu_k (1 + 1/alpha) N / M,

started from the rolling state at `theta_s` (`theta1dot^2 =
two_cylinders.angular_velocity_squared`, `theta2dot = (1 + R/a) theta1dot`, `v_t = 0`)
and run until `N = 0`: detachment with friction. (`d v_t/dt >= 0` at `theta_s` when
`mu_k <= mu_s`, and grows as `N` falls: no re-stick before detachment.) The energy
`E = M rho^2 theta1dot^2/2 + I theta2dot^2/2 + M g rho cos(theta1)` falls by the
friction work, `dE/dt = lambda_t v_t = -mu_k N v_t`. With `mu_k = 0` after the slip
the centre slides as a particle on the circle of radius `rho` (the spin frozen):
energy `rho theta1dot^2 = rho omega_s^2 + 2 g (cos(theta_s) - cos(theta1))` and `N = 0`
at

    cos(theta_d) = (2 cos(theta_s) + rho omega_s^2 / g) / 3
                 = (2 cos(theta_s) + 2 (cos(theta0) - cos(theta_s)) / (1 + alpha)) / 3.

`slip_and_detachment` integrates the sliding system independently of the library
(SciPy's DOP853, `rtol = atol = 1e-13`, float64), a reference for `cjax.simulate`.
"""

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._constraints import Unilateral
from .._system import LagrangianSystem
from . import two_cylinders
from ._rough import rough_contact

# Re-exported: the rolling phase's closed forms are `two_cylinders`'.
from .two_cylinders import (
    alpha as alpha,
    angular_velocity_squared as angular_velocity_squared,
    detachment_angle as detachment_angle,
    detachment_time as detachment_time,
    lagrangian as lagrangian,
    no_slip_multiplier as no_slip_multiplier,
    normal_force as normal_force,
    state as state,
    time_to_angle as time_to_angle,
)


def gap(q, t, args) -> Float[Array, ""]:
    """`G = r - (R + a)`: the normal row `(1, 0, 0)` and the gap."""
    return q[0] - (args["R"] + args["a"])


def tangent_row(q, t, args) -> Float[Array, "1 3"]:
    """`A_t = (0, R + a, -a)`: the lecture's no-slip row, the slip velocity `v_t`."""
    return two_cylinders.pfaffian_rows(q, t, args)[1:]


def contact() -> Unilateral:
    """The contact with Coulomb friction: normal row `r - (R + a)`, sign `+1`, the
    same gap, friction on `(0, R + a, -a)` with `args["mu_s"]`, `args["mu_k"]`."""
    return rough_contact(gap, tangent_row)


def system() -> LagrangianSystem:
    return LagrangianSystem(lagrangian, constraints=contact())


def default_args(mu_s=0.3, mu_k=0.2, M=1.0, alpha=0.5, a=0.3, R=1.0, g=9.81) -> dict:
    args = two_cylinders.default_args(M=M, alpha=alpha, a=a, R=R, g=g)
    args["mu_s"] = jnp.asarray(mu_s, float)
    args["mu_k"] = jnp.asarray(mu_k, float)
    return args


def slip_function(theta1, theta0, args):
    """`f = alpha sin(theta1) - mu_s ((3 + alpha) cos(theta1) - 2 cos(theta0))`:
    `(|lambda_t| - mu_s N) (1 + alpha) / (M g)` while rolling from rest at `theta0`."""
    al = alpha(args)
    return al * jnp.sin(theta1) - args["mu_s"] * (
        (3 + al) * jnp.cos(theta1) - 2 * jnp.cos(theta0)
    )


def slip_angle(theta0, args):
    """`theta_s = max(theta0, delta + arcsin(-2 mu_s cos(theta0) / rho_f))`: where
    rolling from rest at `theta0` (`0 < theta0 < pi/2`) reaches the friction cone's
    edge (`theta0` itself where it slips at once)."""
    al = alpha(args)
    b = args["mu_s"] * (3 + al)
    rho_f = jnp.hypot(al, b)
    root = jnp.arctan2(b, al) + jnp.arcsin(-2 * args["mu_s"] * jnp.cos(theta0) / rho_f)
    return jnp.maximum(theta0, root)


def slip_time(theta0, args):
    """The time from rest at `theta0` to the slip angle (`time_to_angle`)."""
    return time_to_angle(slip_angle(theta0, args), theta0, args)


def slip_onset_state(theta0, args):
    """`(q, qd)` at the slip angle: the rolling state, `theta1dot^2` in closed form."""
    theta_s = slip_angle(theta0, args)
    w2 = angular_velocity_squared(theta_s, theta0, args)
    return state(theta_s, jnp.sqrt(jnp.maximum(w2, 0.0)), args)


def frictionless_sliding_detachment_angle(theta0, args):
    """`theta_d` with `mu_k = 0` after the slip:
    `arccos((2 cos(theta_s) + 2 (cos(theta0) - cos(theta_s)) / (1 + alpha)) / 3)`."""
    cs = jnp.cos(slip_angle(theta0, args))
    c = (2 * cs + 2 * (jnp.cos(theta0) - cs) / (1 + alpha(args))) / 3
    return jnp.arccos(c)


def sliding_rhs(t, y, args, mu_k=None):
    """The sliding equations, NumPy: `y = (theta1, theta1dot, theta2, theta2dot, W)`,
    `W` the friction work `int mu_k N |v_t| dt`."""
    m, inertia, a, g = (float(args[k]) for k in ("M", "I", "a", "g"))
    rho = float(args["R"]) + a
    mu = float(args["mu_k"]) if mu_k is None else mu_k
    th1, w1, _, w2, _ = y
    n = m * (g * np.cos(th1) - rho * w1**2)
    vt = rho * w1 - a * w2
    s = np.sign(vt) if vt != 0 else 1.0
    lam = -s * mu * n
    return np.array(
        [w1, (g * np.sin(th1) + lam / m) / rho, w2, -a * lam / inertia, -lam * vt]
    )


class SlipDetachment(NamedTuple):
    t_slip: float
    theta_slip: float
    t_detach: float
    theta_detach: float
    q_detach: np.ndarray
    qd_detach: np.ndarray
    friction_work: float
    energy_error: float


def slip_and_detachment(theta0, args, rtol=1e-13, atol=1e-13) -> SlipDetachment:
    """From rest at `theta0`: the slip onset (closed form) and the detachment with
    kinetic friction `args["mu_k"]` (the sliding equations integrated by SciPy's
    DOP853 until `N = 0`). Returns times from the release, angles, the state at
    detachment (`r = R + a`, `rdot = 0`), the friction work and the largest
    violation of the energy balance `E + W = const` at the saved steps. Raises where
    the slip velocity falls back to zero before detachment (a re-stick: not this
    reference's case)."""
    from scipy.integrate import solve_ivp

    theta_s = float(slip_angle(theta0, args))
    t_s = float(slip_time(theta0, args))
    q_s, qd_s = (np.asarray(v) for v in slip_onset_state(theta0, args))
    m, inertia, a, g = (float(args[k]) for k in ("M", "I", "a", "g"))
    rho = float(args["R"]) + a

    def normal(t, y):
        return m * (g * np.cos(y[0]) - rho * y[1] ** 2)

    def slip(t, y):
        return rho * y[1] - a * y[3]

    normal.terminal, normal.direction = True, -1
    slip.terminal, slip.direction = True, -1

    def energy(y):
        return (
            0.5 * m * rho**2 * y[1] ** 2
            + 0.5 * inertia * y[3] ** 2
            + m * g * rho * np.cos(y[0])
        )

    y0 = np.array([q_s[1], qd_s[1], q_s[2], qd_s[2], 0.0])
    sol = solve_ivp(
        lambda t, y: sliding_rhs(t, y, args),
        (0.0, 100.0),
        y0,
        method="DOP853",
        rtol=rtol,
        atol=atol,
        events=(normal, slip),
    )
    if sol.t_events[1].size:
        raise ValueError("the slip velocity returned to zero before detachment")
    if not sol.t_events[0].size:
        raise ValueError("no detachment within the integration window")
    y_d = sol.y_events[0][0]
    balance = np.array([energy(y) + y[4] for y in sol.y.T])
    r = rho
    q_d = np.array([r, y_d[0], y_d[2]])
    qd_d = np.array([0.0, y_d[1], y_d[3]])
    return SlipDetachment(
        t_slip=t_s,
        theta_slip=theta_s,
        t_detach=t_s + float(sol.t_events[0][0]),
        theta_detach=float(y_d[0]),
        q_detach=q_d,
        qd_detach=qd_d,
        friction_work=float(y_d[4]),
        energy_error=float(np.max(np.abs(balance - balance[0]))),
    )


def rolling_reference(theta0, args, t1=None, rtol=1e-13, atol=1e-13):
    """The rolling phase from rest at `theta0`, integrated without the closed forms:
    the full equations in `(r, theta1, theta2)` with both rows held (the 5x5 KKT
    system solved at each step, NumPy) until `|lambda_t| = mu_s N` (or `t1`).
    Returns `(t, y, multipliers)` at the end: `y = (q, qd)` stacked, multipliers
    `(N, lambda_t)`."""
    from scipy.integrate import solve_ivp

    m, inertia, a, g = (float(args[k]) for k in ("M", "I", "a", "g"))
    big_r, mu_s = float(args["R"]), float(args["mu_s"])
    jac = np.array([[1.0, 0.0, 0.0], [0.0, big_r + a, -a]])

    def solve(y):
        r, th1 = y[0], y[1]
        rd, w1 = y[3], y[4]
        mass = np.diag([m, m * r**2, inertia])
        force = np.array(
            [
                m * r * w1**2 - m * g * np.cos(th1),
                -2 * m * r * rd * w1 + m * g * r * np.sin(th1),
                0.0,
            ]
        )
        kkt = np.block([[mass, -jac.T], [jac, np.zeros((2, 2))]])
        sol = np.linalg.solve(kkt, np.concatenate([force, np.zeros(2)]))
        return sol[:3], sol[3:]

    def rhs(t, y):
        return np.concatenate([y[3:], solve(y)[0]])

    def cone(t, y):
        lam = solve(y)[1]
        return abs(lam[1]) - mu_s * lam[0]

    cone.terminal, cone.direction = True, 1
    q0, qd0 = (np.asarray(v) for v in state(jnp.asarray(theta0, float), 0.0, args))
    y0 = np.concatenate([q0, qd0])
    sol = solve_ivp(
        rhs,
        (0.0, 100.0 if t1 is None else t1),
        y0,
        method="DOP853",
        rtol=rtol,
        atol=atol,
        events=cone if t1 is None else None,
    )
    if t1 is None:
        t_end, y_end = float(sol.t_events[0][0]), sol.y_events[0][0]
    else:
        t_end, y_end = float(sol.t[-1]), sol.y[:, -1]
    return t_end, y_end, solve(y_end)[1]
