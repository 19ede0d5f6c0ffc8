"""The friction scenes' references, checked among themselves without the library's
solvers: each closed form against an independent integration.

The independent integration (`_stick_slip`) takes each scene's own `lagrangian`,
`gap` and `tangent_row` (the functions its `system()` is built from), forms the
equations of motion by automatic differentiation (`M = d^2L/dqdot^2`,
`F = dL/dq - d^2L/dqdot dq qdot`), solves the contact's KKT system in NumPy
(sticking: both rows held; slipping: the normal row held and the friction force
`-s mu_k N` along the tangent row) and switches between them at SciPy events
(`|lambda_t| = mu_s N` while sticking, `v_t = 0` while slipping, `N = 0`). So the
closed forms are checked against the builders' Lagrangians and rows too.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import minimize_scalar

import constrained_jax as cjax
from constrained_jax.scenes import (
    incline_block as incline,
    painleve_rod as rod,
    sliding_disk as disk,
    two_cylinders as cyl,
    two_cylinders_friction as cylf,
)

from .helpers import finite_difference_grad


RTOL = 1e-12


def _parts(mod, args):
    """`(M, F, a_n, b_n, a_t, b_t)` at `(q, qd)` from the scene's functions: the
    acceleration-level rows are `a qddot + b`."""
    lagrangian = lambda q, qd: mod.lagrangian(q, qd, 0.0, args)
    gap = lambda q: mod.gap(q, 0.0, args)
    row = lambda q: mod.tangent_row(q, 0.0, args)[0]

    @jax.jit
    def parts(q, qd):
        mass = jax.hessian(lagrangian, argnums=1)(q, qd)
        mixed = jax.jacfwd(jax.grad(lagrangian, argnums=1), argnums=0)(q, qd)
        force = jax.grad(lagrangian, argnums=0)(q, qd) - mixed @ qd
        a_n = jax.grad(gap)(q)
        b_n = qd @ jax.hessian(gap)(q) @ qd
        a_t, da_t = jax.jvp(row, (q,), (qd,))
        return mass, force, a_n, b_n, a_t, da_t @ qd

    def numpy_parts(q, qd):
        return tuple(np.asarray(p) for p in parts(jnp.asarray(q), jnp.asarray(qd)))

    return numpy_parts


def _stick(parts, q, qd):
    """`(qddot, N, lambda_t)` with both rows held."""
    mass, force, a_n, b_n, a_t, b_t = parts(q, qd)
    n = q.size
    kkt = np.zeros((n + 2, n + 2))
    kkt[:n, :n] = mass
    kkt[:n, n], kkt[:n, n + 1] = -a_n, -a_t
    kkt[n, :n], kkt[n + 1, :n] = a_n, a_t
    sol = np.linalg.solve(kkt, np.concatenate([force, [-b_n, -b_t]]))
    return sol[:n], sol[n], sol[n + 1]


def _slip(parts, q, qd, s, mu_k):
    """`(qddot, N, lambda_t)` with the normal row held and `lambda_t = -s mu_k N`."""
    mass, force, a_n, b_n, a_t, _ = parts(q, qd)
    n = q.size
    kkt = np.zeros((n + 1, n + 1))
    kkt[:n, :n] = mass
    kkt[:n, n] = -(a_n - s * mu_k * a_t)
    kkt[n, :n] = a_n
    sol = np.linalg.solve(kkt, np.concatenate([force, [-b_n]]))
    return sol[:n], sol[n], -s * mu_k * sol[n]


def _stick_slip(mod, args, q0, qd0, t1, max_phases=6):
    """Integrates the contact with Coulomb friction from `(q0, qd0)` (on the contact)
    to `t1` or to a lift-off. Returns `(dense, switches)`: a function of `t` giving
    `(q, qd, N, lambda_t, mode)` and the list of `(t, mode)` at each switch (`mode` 0
    sticking, +-1 slipping, None lifted off)."""
    parts = _parts(mod, args)
    mu_s, mu_k = float(args["mu_s"]), float(args["mu_k"])
    n = np.size(q0)
    y = np.concatenate([np.asarray(q0, float), np.asarray(qd0, float)])

    def slip_velocity(y):
        return float(parts(y[:n], y[n:])[4] @ y[n:])

    def choose(y):
        vt = slip_velocity(y)
        if vt != 0.0 and abs(vt) > 1e-12 * (1 + np.abs(y[n:]).max()):
            return float(np.sign(vt))
        _, nf, lam = _stick(parts, y[:n], y[n:])
        if abs(lam) <= mu_s * nf:
            return 0.0
        return float(-np.sign(lam))

    def accel(mode, y):
        if mode == 0.0:
            return _stick(parts, y[:n], y[n:])
        return _slip(parts, y[:n], y[n:], mode, mu_k)

    t, mode, pieces, switches = 0.0, choose(y), [], []
    switches.append((0.0, mode))
    for _ in range(max_phases):
        m = mode

        def rhs(t, y, m=m):
            return np.concatenate([y[n:], accel(m, y)[0]])

        def normal(t, y, m=m):
            return accel(m, y)[1]

        def switch(t, y, m=m):
            if m == 0.0:
                _, nf, lam = accel(m, y)
                return abs(lam) - mu_s * nf
            return slip_velocity(y)

        normal.terminal, normal.direction = True, -1
        switch.terminal = True
        switch.direction = 1 if m == 0.0 else -m
        sol = solve_ivp(
            rhs,
            (t, t1),
            y,
            method="DOP853",
            rtol=RTOL,
            atol=RTOL,
            events=(normal, switch),
            dense_output=True,
        )
        pieces.append((t, sol.t[-1], sol.sol, m))
        t, y = sol.t[-1], sol.y[:, -1]
        if sol.status == 0:
            break
        if sol.t_events[0].size:
            switches.append((t, None))
            break
        if m == 0.0:
            _, _, lam = _stick(parts, y[:n], y[n:])
            mode = float(-np.sign(lam))
        else:
            y = y.copy()
            mode = choose_at_rest(parts, y, n, mu_s)
        switches.append((t, mode))

    def dense(tq):
        for a, b, fn, m in pieces:
            if a <= tq <= b:
                yq = fn(tq)
                _, nf, lam = accel(m, yq)
                return yq[:n], yq[n:], nf, lam, m
        raise ValueError(f"t = {tq} outside the integrated window")

    return dense, switches


def choose_at_rest(parts, y, n, mu_s):
    """At `v_t = 0` after a slip: stick if the stick multipliers are inside the
    cone, else slip the way the stick force would push."""
    _, nf, lam = _stick(parts, y[:n], y[n:])
    return 0.0 if abs(lam) <= mu_s * nf else float(-np.sign(lam))


# ---------------------------------------------------------------- incline block


@pytest.mark.parametrize(
    "theta, mu_s, mu_k, v0",
    [
        (0.4, 0.5, 0.3, 0.0),  # sticks from rest
        (0.6, 0.5, 0.3, 0.0),  # slides from rest
        (0.2, 0.5, 0.3, 1.0),  # downhill, decelerates, sticks
        (0.4, 0.5, 0.3, 2.0),  # downhill, accelerates for ever
        (0.4, 0.5, 0.3, -2.0),  # uphill, stops, sticks
        (0.6, 0.7, 0.3, -2.0),  # uphill, stops, sticks (tan 0.6 < 0.7)
        (0.6, 0.5, 0.3, -2.0),  # uphill, stops, slides back down
    ],
)
def test_incline_closed_forms(theta, mu_s, mu_k, v0):
    args = incline.default_args(theta=theta, mu_s=mu_s, mu_k=mu_k)
    q0, qd0 = incline.state(0.0, v0)
    t1 = 1.5
    dense, switches = _stick_slip(incline, args, q0, qd0, t1)
    t_stop = float(incline.stop_time(v0, args)) if v0 != 0 else 0.0
    if np.isfinite(t_stop) and t_stop > 0:
        assert switches[1][0] == pytest.approx(t_stop, rel=1e-10)
    for t in (0.1, 0.37, 0.8, 1.4):
        q, qd, nf, lam, mode = dense(t)
        assert q[0] == pytest.approx(
            float(incline.displacement(t, v0, args)), abs=1e-10
        )
        assert qd[0] == pytest.approx(float(incline.velocity(t, v0, args)), abs=1e-10)
        assert q[1] == pytest.approx(0.0, abs=1e-10)
        assert nf == pytest.approx(float(incline.normal_force(args)), rel=1e-10)
        assert lam == pytest.approx(
            float(incline.friction_force(t, v0, args)), rel=1e-10
        )
        assert mode == float(incline.slip_state(t, v0, args))
    # Downhill stops only where tan(theta) < mu_k, and then always stick.
    assert bool(incline.sticks_from_rest(args)) == (np.tan(theta) <= mu_s)


def test_incline_gradients():
    def stop(theta):
        return incline.stop_time(2.0, incline.default_args(theta=theta))

    def x(mu_k):
        return incline.displacement(0.7, -2.0, incline.default_args(mu_k=mu_k))

    for fn, p in ((stop, 0.2), (x, 0.25)):
        grad = float(jax.grad(fn)(jnp.asarray(p)))
        assert grad == pytest.approx(finite_difference_grad(fn, p)[()], rel=1e-7)


# ---------------------------------------------------------------- sliding disk


@pytest.mark.parametrize(
    "k, v0, omega0",
    [(0.5, 2.0, 0.0), (0.4, 2.0, 0.0), (0.5, 2.0, 30.0), (1.0, -1.0, 2.0)],
)
def test_sliding_disk_closed_forms(k, v0, omega0):
    args = disk.default_args(k=k)
    q0, qd0 = disk.state(v0, args, omega0)
    ts = float(disk.slip_time(v0, omega0, args))
    g, mu_k = float(args["g"]), float(args["mu_k"])
    vt0 = v0 + float(args["R"]) * omega0
    assert ts == pytest.approx(abs(vt0) / ((1 + 1 / k) * mu_k * g), rel=1e-14)
    if omega0 == 0.0 and k == 0.5:
        assert ts == pytest.approx(v0 / (3 * mu_k * g), rel=1e-14)
        assert float(disk.rolling_speed(v0, 0.0, args)) == pytest.approx(2 * v0 / 3)
    if omega0 == 0.0 and k == 0.4:
        assert ts == pytest.approx(2 * v0 / (7 * mu_k * g), rel=1e-14)
        assert float(disk.rolling_speed(v0, 0.0, args)) == pytest.approx(5 * v0 / 7)
    t1 = 3 * ts
    dense, switches = _stick_slip(disk, args, np.asarray(q0), np.asarray(qd0), t1)
    assert [m for _, m in switches] == [float(np.sign(vt0)), 0.0]
    assert switches[1][0] == pytest.approx(ts, rel=1e-10)
    for t in (0.3 * ts, 0.9 * ts, 1.2 * ts, 2.9 * ts):
        q, qd, nf, lam, _ = dense(t)
        q_cf, qd_cf = disk.motion(t, v0, omega0, args)
        np.testing.assert_allclose(q, q_cf, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(qd, qd_cf, rtol=1e-10, atol=1e-10)
        assert nf == pytest.approx(float(disk.normal_force(args)), rel=1e-10)
        # While rolling the stick multiplier is 0 (a round-off of the KKT solve).
        assert lam == pytest.approx(
            float(disk.friction_force(t, v0, omega0, args)), abs=1e-12
        )
    # Energy: what friction took.
    m, inertia = float(args["m"]), k * float(args["m"]) * float(args["R"]) ** 2
    v = float(disk.rolling_speed(v0, omega0, args))
    lost = 0.5 * m * v0**2 + 0.5 * inertia * omega0**2
    lost -= 0.5 * (m + inertia / float(args["R"]) ** 2) * v**2
    assert lost == pytest.approx(
        float(disk.dissipated_energy(v0, omega0, args)), rel=1e-12
    )


def test_sliding_disk_frictionless_never_sticks():
    args = disk.default_args(mu_s=0.0, mu_k=0.0)
    q0, qd0 = disk.state(2.0, args)
    dense, switches = _stick_slip(disk, args, np.asarray(q0), np.asarray(qd0), 1.0)
    assert switches == [(0.0, 1.0)]
    q, qd, _, lam, _ = dense(1.0)
    np.testing.assert_allclose(qd, [2.0, 0.0, 0.0], atol=1e-12)
    assert lam == 0.0


def test_sliding_disk_gradients():
    def x(v0):
        return disk.motion(0.5, v0, 0.0, disk.default_args())[0][0]

    def t_star(k):
        return disk.slip_time(2.0, 0.0, disk.default_args(k=k))

    for fn, p in ((x, 2.0), (t_star, 0.4)):
        grad = float(jax.grad(fn)(jnp.asarray(p)))
        assert grad == pytest.approx(finite_difference_grad(fn, p)[()], rel=1e-7)


# ---------------------------------------------------------------- two cylinders


@pytest.mark.parametrize("mu_s", [0.15, 0.3, 1.0, 10.0, 1e4])
def test_two_cylinders_slip_angle(mu_s):
    theta0 = 0.3
    args = cylf.default_args(mu_s=mu_s, mu_k=0.5 * mu_s)
    theta_s = cylf.slip_angle(theta0, args)
    theta_star = cyl.detachment_angle(theta0, args)
    # On the cone's edge, between the release and the frictionless detachment.
    n = cyl.normal_force(theta_s, theta0, args)
    lam = cyl.no_slip_multiplier(theta_s, args)
    # `mu_s N` carries the round-off of `N`'s cancellation, `eps M g (3 + alpha)`.
    round_off = 10 * np.finfo(float).eps * mu_s * float(args["M"] * args["g"]) * 3.5
    assert float(jnp.abs(lam)) == pytest.approx(
        float(mu_s * n), rel=1e-12, abs=round_off
    )
    assert float(theta0) < float(theta_s) < float(theta_star)
    if mu_s == 1e4:
        assert float(theta_s) == pytest.approx(float(theta_star), abs=1e-4)


def test_two_cylinders_slips_at_once():
    # tan(theta0) > mu_s (1 + alpha)/alpha: the cone is left at the release.
    args = cylf.default_args(mu_s=0.05, mu_k=0.05)
    assert float(cylf.slip_function(0.3, 0.3, args)) > 0
    assert float(cylf.slip_angle(0.3, args)) == 0.3
    assert float(cylf.slip_time(0.3, args)) == pytest.approx(0.0, abs=1e-12)


def test_two_cylinders_rolling_to_slip_integrated():
    """The rolling phase integrated (KKT of both rows, hand-written equations) ends
    on the cone's edge at the closed-form angle and time; the autodiff-built
    integration agrees."""
    theta0 = 0.3
    args = cylf.default_args(mu_s=0.3, mu_k=0.2)
    t, y, (nf, lam) = cylf.rolling_reference(theta0, args)
    assert y[1] == pytest.approx(float(cylf.slip_angle(theta0, args)), rel=1e-11)
    assert t == pytest.approx(float(cylf.slip_time(theta0, args)), rel=1e-11)
    assert lam == pytest.approx(-0.3 * nf, rel=1e-10)
    q0, qd0 = cyl.state(jnp.asarray(theta0), jnp.asarray(0.0), args)
    dense, switches = _stick_slip(cylf, args, np.asarray(q0), np.asarray(qd0), 2.0)
    assert [m for _, m in switches] == [0.0, 1.0, None]
    assert switches[1][0] == pytest.approx(t, rel=1e-10)
    # The detachment with friction: the autodiff-built sliding phase against the
    # hand-derived sliding equations.
    ref = cylf.slip_and_detachment(theta0, args)
    assert switches[2][0] == pytest.approx(ref.t_detach, rel=1e-10)
    q, qd, nf, _, _ = dense(switches[2][0])
    np.testing.assert_allclose(q, ref.q_detach, rtol=1e-9)
    np.testing.assert_allclose(qd, ref.qd_detach, rtol=1e-9, atol=1e-9)
    assert abs(nf) < 1e-8


@pytest.mark.parametrize("mu_s, mu_k", [(0.3, 0.2), (0.3, 0.3), (1.0, 0.5)])
def test_two_cylinders_detachment_with_friction(mu_s, mu_k):
    theta0 = 0.3
    args = cylf.default_args(mu_s=mu_s, mu_k=mu_k)
    ref = cylf.slip_and_detachment(theta0, args)
    assert ref.energy_error < 1e-11
    assert ref.friction_work > 0
    assert ref.theta_slip < ref.theta_detach
    assert ref.t_slip < ref.t_detach
    # At detachment N = M (g cos(theta1) - rho theta1dot^2) = 0.
    rho = float(args["R"] + args["a"])
    g = float(args["g"])
    assert g * np.cos(ref.theta_detach) == pytest.approx(rho * ref.qd_detach[1] ** 2)
    # Energy balance from the release at rest.
    m, inertia = float(args["M"]), float(args["I"])
    e0 = m * g * rho * np.cos(theta0)
    e1 = (
        0.5 * m * rho**2 * ref.qd_detach[1] ** 2 + 0.5 * inertia * ref.qd_detach[2] ** 2
    )
    e1 += m * g * rho * np.cos(ref.theta_detach)
    assert e1 + ref.friction_work == pytest.approx(e0, rel=1e-12)


def test_two_cylinders_frictionless_sliding_limit():
    theta0 = 0.3
    exact = cylf.default_args(mu_s=0.3, mu_k=0.0)
    ref = cylf.slip_and_detachment(theta0, exact)
    closed = float(cylf.frictionless_sliding_detachment_angle(theta0, exact))
    assert ref.theta_detach == pytest.approx(closed, rel=1e-11)
    errors = []
    for mu_k in (1e-2, 1e-3):
        args = cylf.default_args(mu_s=0.3, mu_k=mu_k)
        errors.append(abs(cylf.slip_and_detachment(theta0, args).theta_detach - closed))
    # Continuous, first order in mu_k.
    assert errors[1] < errors[0] / 5 and errors[1] < 1e-3


def test_two_cylinders_slip_angle_gradient():
    """`d theta_s / d mu_s` by the implicit function theorem on `f = 0`, and by
    finite differences, against `jax.grad` of the closed form."""
    theta0 = 0.3

    def angle(mu_s):
        return cylf.slip_angle(theta0, cylf.default_args(mu_s=mu_s))

    mu = 0.3
    grad = float(jax.grad(angle)(jnp.asarray(mu)))
    theta_s = angle(mu)
    args = cylf.default_args(mu_s=mu)
    f_theta = jax.grad(cylf.slip_function)(theta_s, theta0, args)
    f_mu = jax.grad(
        lambda m: cylf.slip_function(theta_s, theta0, cylf.default_args(m))
    )(jnp.asarray(mu))
    assert grad == pytest.approx(float(-f_mu / f_theta), rel=1e-12)
    assert grad == pytest.approx(finite_difference_grad(angle, mu)[()], rel=1e-7)
    fd = finite_difference_grad(
        lambda m: cylf.slip_time(theta0, cylf.default_args(m)), mu
    )
    grad_t = jax.grad(lambda m: cylf.slip_time(theta0, cylf.default_args(m)))(
        jnp.asarray(mu)
    )
    assert float(grad_t) == pytest.approx(fd[()], rel=1e-6)


# ---------------------------------------------------------------- Painlevé's rod


def test_painleve_critical_coefficient():
    res = minimize_scalar(
        lambda th: float(rod.critical_mu(th)),
        bounds=(0.1, 1.5),
        method="bounded",
        options={"xatol": 1e-12},
    )
    assert res.fun == pytest.approx(4 / 3, rel=1e-12)
    assert res.x == pytest.approx(np.arctan(2.0), rel=1e-6)
    assert float(rod.critical_mu(np.arctan(2.0))) == pytest.approx(4 / 3, rel=1e-14)
    assert float(jax.grad(rod.critical_mu)(jnp.arctan(2.0))) == pytest.approx(
        0.0, abs=1e-12
    )
    for theta in (0.3, 0.9, 1.3):
        mu_c = rod.critical_mu(theta)
        assert float(rod.consistency(theta, mu_c, 1.0)) == pytest.approx(0.0, abs=1e-14)
        assert float(rod.consistency(theta, mu_c, -1.0)) > 0


def test_painleve_normal_force_against_autodiff_equations():
    """The hand-derived `N` and sliding accelerations against the KKT system built
    by autodiff from the scene's `lagrangian`, `gap` and `tangent_row`."""
    args = rod.default_args(mu_s=0.9, mu_k=0.9)
    parts = _parts(rod, args)
    rng = np.random.default_rng(0)
    for _ in range(5):
        theta, thetadot, v = rng.uniform(0.2, 1.3), rng.normal(), rng.normal()
        q, qd = (np.asarray(a) for a in rod.state(theta, v, args, thetadot=thetadot))
        s = float(np.sign(v))
        qdd, nf, lam = _slip(parts, q, qd, s, 0.9)
        qdd_cf, n_cf, lam_cf = rod.sliding_acceleration(q, qd, args)
        np.testing.assert_allclose(qdd, qdd_cf, rtol=1e-12, atol=1e-12)
        assert nf == pytest.approx(float(n_cf), rel=1e-12)
        assert lam == pytest.approx(float(lam_cf), rel=1e-12)
        y = np.concatenate([q, qd, [0.0]])
        np.testing.assert_allclose(
            rod.sliding_rhs(0.0, y, args, s)[3:6], qdd, rtol=1e-12
        )


def test_painleve_sliding_reference():
    args = rod.default_args()
    q0, qd0 = rod.default_state(args)
    t1 = 0.2
    q, qd, nf, work = rod.sliding_reference(q0, qd0, t1, args)
    # The contact is held: gap and its rate stay zero (the N formula is right).
    assert abs(float(rod.gap(q, t1, args))) < 1e-11
    assert abs(qd[1] - float(args["l"]) * np.cos(q[2]) * qd[2]) < 1e-11
    # Energy balance.
    e0, e1 = rod.energy(q0, qd0, args), rod.energy(q, qd, args)
    assert float(e1) + work == pytest.approx(float(e0), rel=1e-12)
    assert nf == pytest.approx(float(rod.normal_force(q, qd, args)), rel=1e-11)
    assert nf > 0 and float(rod.slip_velocity(q, qd, args)) > 0
    # The autodiff-built integration agrees (no stick, no lift-off in the window).
    dense, switches = _stick_slip(rod, args, np.asarray(q0), np.asarray(qd0), t1)
    assert switches == [(0.0, 1.0)]
    q_ad, qd_ad, n_ad, _, _ = dense(t1)
    np.testing.assert_allclose(q_ad, q, rtol=1e-10, atol=1e-11)
    np.testing.assert_allclose(qd_ad, qd, rtol=1e-10, atol=1e-11)
    assert n_ad == pytest.approx(nf, rel=1e-10)


def test_painleve_contact_cases():
    args = rod.default_args(mu_s=1.5, mu_k=1.5)
    theta = np.arctan(2.0)
    q, qd = rod.state(theta, 1.0, args)
    assert float(rod.contact_case(q, qd, args)) == -1.0  # no solution
    q, qd = rod.state(theta, 1.0, args, thetadot=10.0)
    assert float(rod.contact_case(q, qd, args)) == 2.0  # two solutions
    q, qd = rod.state(theta, -1.0, args)
    assert float(rod.contact_case(q, qd, args)) == 1.0  # trailing end: fine
    below = rod.default_args(mu_s=1.3, mu_k=1.3)
    q, qd = rod.state(theta, 1.0, below)
    assert float(rod.contact_case(q, qd, below)) == 1.0


def test_painleve_gradients():
    args = rod.default_args()
    q, qd = rod.state(0.6, 1.0, args, thetadot=-1.0)

    def n_of_theta(theta):
        return rod.normal_force(q.at[2].set(theta), qd, args)

    grad = float(jax.grad(n_of_theta)(jnp.asarray(0.6)))
    assert grad == pytest.approx(finite_difference_grad(n_of_theta, 0.6)[()], rel=1e-7)


@pytest.mark.parametrize(
    "mu_s, mu_k, theta0, v, t1, modes",
    [
        (0.7, 0.6, 0.9, 0.3, 0.38, [1.0, 0.0, -1.0]),  # `stick_slip_state`
        (0.7, 0.5, 1.0, 0.5, 0.42, [1.0, -1.0]),  # reversal without a stick
    ],
)
def test_painleve_stick_slip_reference(mu_s, mu_k, theta0, v, t1, modes):
    """The hand-derived stick-slip reference (pivot equations while sticking)
    against the autodiff-built one: the same switches at the same times, the same
    state at the end."""
    args = rod.default_args(mu_s=mu_s, mu_k=mu_k)
    q0, qd0 = rod.state(theta0, v, args)
    if theta0 == 0.9:
        np.testing.assert_array_equal(q0, rod.stick_slip_state(args)[0])
    switches, q, qd = rod.stick_slip_reference(q0, qd0, t1, args)
    dense, switches_ad = _stick_slip(rod, args, np.asarray(q0), np.asarray(qd0), t1)
    assert [m for _, m in switches] == modes
    assert [m for _, m in switches_ad] == modes
    np.testing.assert_allclose(
        [t for t, _ in switches], [t for t, _ in switches_ad], rtol=1e-10
    )
    q_ad, qd_ad, n_ad, _, _ = dense(t1)
    np.testing.assert_allclose(q, q_ad, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(qd, qd_ad, rtol=1e-9, atol=1e-10)
    assert n_ad > 0 and q[2] > 0.2
    # The contact is held throughout (pivot and sliding equations alike).
    assert abs(float(rod.gap(q, t1, args))) < 1e-11


@pytest.mark.parametrize(
    "mod, args, q, a_n, a_t",
    [
        (incline, incline.default_args(), [0.3, 0.0], [0, 1], [1, 0]),
        (disk, disk.default_args(R=0.2), [0.3, 0.2, 1.0], [0, 1, 0], [1, 0, 0.2]),
        (
            cylf,
            cylf.default_args(a=0.3, R=1.0),
            [1.3, 0.4, 1.7],
            [1, 0, 0],
            [0, 1.3, -0.3],
        ),
        (
            rod,
            rod.default_args(l=0.5),
            [0.0, 0.5 * np.sin(0.7), 0.7],
            [0, 1, -0.5 * np.cos(0.7)],
            [1, 0, -0.5 * np.sin(0.7)],
        ),
    ],
)
def test_rows(mod, args, q, a_n, a_t):
    """The builders' rows, through the library's constraint classes (the group
    without its friction), are the ones the closed forms are derived for."""
    q = jnp.asarray(q, float)
    t = jnp.asarray(0.0)
    normal = cjax.Holonomic(mod.gap)
    tangent = cjax.Pfaffian(mod.tangent_row)
    assert normal.num_constraints(q.size, args) == 1
    assert tangent.num_constraints(q.size, args) == 1
    np.testing.assert_allclose(normal.velocity_form(q, t, args)[0], [a_n], atol=1e-15)
    np.testing.assert_allclose(tangent.velocity_form(q, t, args)[0], [a_t], atol=1e-15)
    assert float(mod.gap(q, t, args)) == pytest.approx(0.0, abs=1e-15)
