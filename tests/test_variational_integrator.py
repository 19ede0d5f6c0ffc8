"""The constrained variational integrator (RATTLE for a general Lagrangian).

Closed forms (the pendulum's elliptic-function motion, RATTLE written out by hand, the
rolling disk's circle), second-order slopes, the geometric invariants (constraints to
round-off, bounded energy error against a drifting Runge-Kutta, time reversibility),
gradients against finite differences, jit/vmap, and the failure statuses.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.special

import constrained_jax as cjax
from constrained_jax.scenes import (
    pendulum,
    rolling_disk as disk,
    rotating_hoop as hoop,
    two_cylinders as cyl2,
)

from .helpers import finite_difference_grad, tree_allclose


TS = jnp.array([0.25, 0.5])


def _pendulum_runner(integrator, max_steps=1_000):
    """`run(theta0, thetadot0, args, dt0, ts)`: the Cartesian pendulum from angle
    `theta0` at `t0 = 0`, saved at `ts` (`t1 = ts[-1]`)."""
    system = pendulum.system()

    @jax.jit
    def run_jit(theta0, thetadot0, args, dt0, ts):
        q0, qd0 = pendulum.state(theta0, thetadot0, args)
        return cjax.integrate_variational(
            integrator,
            system,
            0.0,
            ts[-1],
            dt0,
            q0,
            qd0,
            args,
            ts_save=ts,
            max_steps=max_steps,
            throw=False,
        )

    def run(theta0, thetadot0, args, dt0, ts):
        # Same dtypes on every call: one compilation per shape of `ts`.
        as_float = lambda x: jnp.asarray(x, float)
        return run_jit(
            as_float(theta0), as_float(thetadot0), args, as_float(dt0), as_float(ts)
        )

    return run


@pytest.fixture(scope="module")
def runners():
    return {
        "trapezoidal": _pendulum_runner(cjax.VariationalIntegrator()),
        "midpoint": _pendulum_runner(
            cjax.VariationalIntegrator(quadrature=cjax.Midpoint())
        ),
    }


def _pendulum_closed_form(t, theta0, args):
    """Released from rest at `theta0`: `sin(theta/2) = k sn(K(k^2) - sqrt(g/l) t)`,
    `k = sin(theta0/2)` (Jacobi elliptic functions, parameter `m = k^2`)."""
    k = np.sin(theta0 / 2)
    m = k**2
    omega0 = np.sqrt(float(args["g"]) / float(args["l"]))
    sn, _, _, _ = scipy.special.ellipj(scipy.special.ellipk(m) - omega0 * t, m)
    theta = 2 * np.arcsin(k * sn)
    length = float(args["l"])
    return np.stack([length * np.sin(theta), -length * np.cos(theta)], axis=-1)


def test_matches_rattle_written_out(runners):
    """For the pendulum (`m = 1`) the trapezoidal discrete Lagrangian is RATTLE:
    `q1 = q0 + h p0 + h^2/2 f + c q0` with `|q1| = l` (a quadratic for `c`), then
    `p1 = (q1 - q0)/h + h/2 f` projected onto `q1 . p1 = 0` (Hairer-Lubich-Wanner
    VII.1.4). Written out by hand here; the integrator must agree to round-off."""
    args = pendulum.default_args(l=0.9)
    h, steps = 0.05, 40
    theta0, thetadot0 = 1.1, 0.7
    sol = runners["trapezoidal"](
        theta0, thetadot0, args, h, jnp.array([steps * h / 2, steps * h])
    )
    assert sol.result == cjax.RESULTS.successful
    assert int(sol.stats["num_steps"]) == steps
    length, f = 0.9, np.array([0.0, -9.81])
    q_ref, p_ref = (np.asarray(x) for x in pendulum.state(theta0, thetadot0, args))
    for _ in range(steps):
        a = q_ref + h * (p_ref + h / 2 * f)
        b = a @ q_ref / length**2
        c = -b + np.sqrt(b**2 - (a @ a - length**2) / length**2)
        q_new = a + c * q_ref
        p_new = (q_new - q_ref) / h + h / 2 * f
        p_ref = p_new - (p_new @ q_new) / length**2 * q_new
        q_ref = q_new
    np.testing.assert_allclose(sol.q[-1], q_ref, rtol=0, atol=1e-13)
    np.testing.assert_allclose(sol.qd[-1], p_ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["trapezoidal", "midpoint"])
def test_second_order_convergence(runners, name):
    """Error at a generic time (0.3 periods) against the closed-form motion: slope 2
    in log error against log h."""
    args = pendulum.default_args()
    theta0 = 0.8
    t1 = 0.3 * float(pendulum.period(jnp.asarray(theta0), args))
    exact = _pendulum_closed_form(t1, theta0, args)
    steps = np.array([20, 40, 80, 160])
    errors = []
    for num in steps:
        sol = runners[name](theta0, 0.0, args, t1 / num, jnp.array([t1 / 2, t1]))
        assert sol.result == cjax.RESULTS.successful
        assert int(sol.stats["num_steps"]) == num
        errors.append(float(np.linalg.norm(sol.q[-1] - exact)))
    slope = np.polyfit(np.log(1.0 / steps), np.log(errors), 1)[0]
    assert 1.9 < slope < 2.1, (errors, slope)


@pytest.mark.parametrize("name", ["trapezoidal", "midpoint"])
def test_time_reversible(runners, name):
    """Forward 400 steps, flip the velocity, 400 more: back at the start with the
    velocity flipped, to round-off (the method is symmetric)."""
    args = pendulum.default_args()
    run = runners[name]
    theta0, thetadot0, h = jnp.asarray(1.3), jnp.asarray(0.4), 0.02
    ts = jnp.array([200 * h, 400 * h])
    sol = run(theta0, thetadot0, args, h, ts)
    assert sol.result == cjax.RESULTS.successful
    q, qd = sol.q, sol.qd
    q0, qd0 = pendulum.state(theta0, thetadot0, args)
    assert float(jnp.linalg.norm(q[-1] - q0)) > 0.1  # it really moved
    # Restart from (q, -qd): the angle and rate of that state.
    theta1 = jnp.arctan2(q[-1, 0], -q[-1, 1])
    thetadot1 = (q[-1, 0] * qd[-1, 1] - q[-1, 1] * qd[-1, 0]) / args["l"] ** 2
    back_q0, back_qd0 = pendulum.state(theta1, -thetadot1, args)
    np.testing.assert_allclose(back_q0, q[-1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(back_qd0, -qd[-1], rtol=0, atol=1e-14)
    back = run(theta1, -thetadot1, args, h, ts)
    assert back.result == cjax.RESULTS.successful
    np.testing.assert_allclose(back.q[-1], q0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.qd[-1], -qd0, rtol=0, atol=1e-11)


def _energy(system, q, qd, args):
    return jax.vmap(lambda a, b: system.energy(a, b, 0.0, args))(q, qd)


# The long run: 10^4 periods at 20 steps per period, saved every 99 steps (not a
# whole number of periods, so every phase of the oscillation is sampled).
LONG_STEPS_PER_PERIOD, LONG_SAVE_EVERY, LONG_SAVES = 20, 99, 2021


@pytest.fixture(scope="module")
def long_run():
    args = pendulum.default_args()
    theta0 = jnp.asarray(1.0)
    h = pendulum.period(theta0, args) / LONG_STEPS_PER_PERIOD
    ts = h * LONG_SAVE_EVERY * jnp.arange(float(LONG_SAVES))  # 9,999 periods
    run = _pendulum_runner(cjax.VariationalIntegrator(), max_steps=210_000)
    sol = run(theta0, 0.0, args, h, ts)
    return dict(
        args=args,
        theta0=theta0,
        h=h,
        ts=ts,
        q=sol.q,
        qd=sol.qd,
        result=sol.result,
        stats=sol.stats,
    )


def _max_error_first_and_last_tenth(energy):
    error = np.abs(np.asarray(energy - energy[0]))
    tenth = len(error) // 10
    return error[:tenth].max(), error[-tenth:].max()


@pytest.mark.slow
def test_long_horizon_constraints_and_bounded_energy(long_run):
    """2 x 10^5 steps (10^4 periods): the constraint holds to round-off at every save,
    and the energy error does not grow: its largest value in the last tenth of the
    run is no larger than in the first tenth (up to 20%)."""
    args, q, qd = long_run["args"], long_run["q"], long_run["qd"]
    assert long_run["result"] == cjax.RESULTS.successful
    assert int(long_run["stats"]["num_steps"]) == (LONG_SAVES - 1) * LONG_SAVE_EVERY
    radius = jnp.linalg.norm(q, axis=1)
    assert float(jnp.max(jnp.abs(radius - args["l"]))) <= 1e-12 * float(args["l"])
    speed_scale = float(jnp.max(jnp.linalg.norm(qd, axis=1)))
    assert float(jnp.max(jnp.abs(jnp.sum(q * qd, axis=1)))) <= 1e-12 * speed_scale
    first, last = _max_error_first_and_last_tenth(
        _energy(pendulum.system(), q, qd, args)
    )
    assert last <= 1.2 * first, (first, last)
    # The bound itself is the O(h^2) oscillation, not a drift: a few per cent of
    # the energy scale m g l at 20 steps per period.
    assert first < 0.05 * float(args["m"] * args["g"] * args["l"])


@pytest.mark.slow
def test_runge_kutta_with_projection_drifts(long_run):
    """The comparison at the same step and save times: Tsit5 (order 5, six
    evaluations per step) with projection onto the constraint manifold after every
    step keeps the constraint, but its energy error grows linearly over the 10^4
    periods (its last tenth is several times its first), while the variational
    integrator's does not. (Tsit5's error is the smaller one for a long while: a
    fifth-order method at 20 steps per period; the point is the growth.)"""
    system = pendulum.system()
    args, ts, h = long_run["args"], long_run["ts"], long_run["h"]
    q0, qd0 = pendulum.state(long_run["theta0"], jnp.asarray(0.0), args)
    traj = cjax.simulate(
        system,
        (0.0, ts[-1]),
        q0,
        qd0,
        args,
        solver=diffrax.Tsit5(),
        stabilization=cjax.Projection(),
        stepsize_controller=diffrax.ConstantStepSize(),
        dt0=h,
        max_steps=210_000,
        saveat=cjax.SaveAt(ts=ts, multipliers=False),
    )
    assert traj.result == cjax.RESULTS.successful
    assert float(jnp.max(jnp.abs(traj.violation["position"]))) <= 1e-12
    rk_first, rk_last = _max_error_first_and_last_tenth(traj.energy)
    assert rk_last > 5 * rk_first, (rk_first, rk_last)
    # Linear growth: the error at the end is about ten times that at a tenth.
    rk_error = np.abs(np.asarray(traj.energy - traj.energy[0]))
    slope = np.polyfit(np.log(ts[10:]), np.log(rk_error[10:] + 1e-300), 1)[0]
    assert 0.8 < slope < 1.2, slope
    vi_first, vi_last = _max_error_first_and_last_tenth(
        _energy(system, long_run["q"], long_run["qd"], args)
    )
    assert vi_last <= 1.2 * vi_first


def test_rheonomic_constraint_hoop():
    """Bead on a spinning hoop, `G(q, t) = 0` with `t` explicit: the constraints hold at
    every step to round-off (enforced at `t_{k+1}`), and the angle converges at order
    2 to a tight solve of the reduced equation `thetaddot = sin(theta)(omega^2
    cos(theta) - g/rho)`."""
    args = hoop.default_args()
    theta0, thetadot0, t1 = 0.3, 0.0, 1.0
    omega2, g_rho = float(args["omega"]) ** 2, float(args["g"] / args["rho"])
    reduced = scipy.integrate.solve_ivp(
        lambda t, y: [y[1], np.sin(y[0]) * (omega2 * np.cos(y[0]) - g_rho)],
        (0.0, t1),
        [theta0, thetadot0],
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    theta_exact = reduced.y[0, -1]
    system = hoop.system()
    integrator = cjax.VariationalIntegrator()

    @jax.jit
    def run(dt0):
        q0, qd0 = hoop.state(jnp.asarray(theta0), jnp.asarray(thetadot0), 0.0, args)
        ts = jnp.linspace(0.0, t1, 11)
        sol = cjax.integrate_variational(
            integrator,
            system,
            0.0,
            t1,
            dt0,
            q0,
            qd0,
            args,
            ts_save=ts,
            max_steps=1000,
            throw=False,
        )
        q, qd = sol.q, sol.qd
        position = jax.vmap(lambda a, t: system.holonomic_residual(a, t, args))(q, ts)
        velocity = jax.vmap(lambda a, b, t: system.velocity_residual(a, b, t, args))(
            q, qd, ts
        )
        return hoop.angle(q[-1], ts[-1], args), position, velocity, sol.result

    steps = np.array([50, 100, 200, 400])
    errors = []
    for num in steps:
        theta, position, velocity, result = run(t1 / num)
        assert result == cjax.RESULTS.successful
        assert float(jnp.max(jnp.abs(position))) <= 1e-14
        assert float(jnp.max(jnp.abs(velocity))) <= 1e-13
        errors.append(abs(float(theta) - theta_exact))
    slope = np.polyfit(np.log(1.0 / steps), np.log(errors), 1)[0]
    assert 1.9 < slope < 2.1, (errors, slope)


def test_nonholonomic_rolling_disk():
    """Pfaffian, non-integrable rolling constraints (discrete Lagrange-d'Alembert,
    imposed at the midpoint): the contact point converges at order 2 to the
    closed-form circle, the velocity constraint holds to round-off at the saved
    states, and the energy (kinetic; the constraints do no work) is conserved to
    the integration error."""
    args = disk.default_args()
    theta0, nu, omega, t1 = 0.3, 2.0, 1.5, 2.0
    system = disk.system()
    integrator = cjax.VariationalIntegrator()

    @jax.jit
    def run(dt0):
        q0, qd0 = disk.initial_state(jnp.asarray(theta0), nu, omega, args)
        ts = jnp.linspace(0.0, t1, 5)
        sol = cjax.integrate_variational(
            integrator, system, 0.0, t1, dt0, q0, qd0, args, ts_save=ts, throw=False
        )
        q, qd = sol.q, sol.qd
        velocity = jax.vmap(lambda a, b: system.velocity_residual(a, b, 0.0, args))(
            q, qd
        )
        return q, _energy(system, q, qd, args), velocity, sol.result

    exact, _ = disk.closed_form(jnp.asarray(t1), theta0, nu, omega, args)
    steps = np.array([50, 100, 200, 400])
    errors = []
    for num in steps:
        q, energy, velocity, result = run(t1 / num)
        assert result == cjax.RESULTS.successful
        assert float(jnp.max(jnp.abs(velocity))) <= 1e-13
        np.testing.assert_allclose(energy, energy[0], rtol=1e-3)
        errors.append(float(jnp.linalg.norm(q[-1] - exact)))
    slope = np.polyfit(np.log(1.0 / steps), np.log(errors), 1)[0]
    assert 1.9 < slope < 2.1, (errors, slope)


def test_pfaffian_rows_and_singular_mass_two_cylinders():
    """The lecture's two cylinders, constraints given as Pfaffian rows, with
    `alpha = 0` (singular mass matrix, regular KKT matrix): contact and no slip hold
    to round-off, and `theta1dot^2` along the motion converges at order 2 to the
    closed form from energy conservation."""
    args = cyl2.default_args(alpha=0.0)
    theta0 = jnp.asarray(0.3)
    q0, qd0 = cyl2.state(theta0, jnp.asarray(0.0), args)
    ts = jnp.linspace(0.0, 0.8, 9)

    @jax.jit
    def run(dt0):
        return cjax.integrate_variational(
            cjax.VariationalIntegrator(),
            cyl2.system(),
            0.0,
            0.8,
            dt0,
            q0,
            qd0,
            args,
            ts_save=ts,
            throw=False,
        )

    errors = []
    for dt0 in [0.004, 0.002]:
        sol = run(dt0)
        assert sol.result == cjax.RESULTS.successful
        q, qd = sol.q, sol.qd
        assert float(q[-1, 1]) > float(theta0) + 0.3  # it really rolled
        np.testing.assert_allclose(q[:, 0], args["R"] + args["a"], rtol=1e-14)
        ratio = 1 + args["R"] / args["a"]
        np.testing.assert_allclose(q[:, 2], ratio * q[:, 1], rtol=1e-13)
        exact = cyl2.angular_velocity_squared(q[:, 1], theta0, args)
        errors.append(float(jnp.max(jnp.abs(qd[:, 1] ** 2 - exact))))
    assert 3.6 < errors[0] / errors[1] < 4.4, errors


def test_forces_damped_pendulum():
    """A linear drag `Q = -c qdot` by the discrete Lagrange-d'Alembert principle:
    order 2 against a tight solve of the reduced equation
    `thetaddot = -(g/l) sin(theta) - (c/m) thetadot`."""
    args = dict(pendulum.default_args(), c=jnp.asarray(0.7))
    system = cjax.LagrangianSystem(
        pendulum.lagrangian,
        constraints=cjax.Holonomic(pendulum.rod),
        forces=lambda q, qd, t, a: -a["c"] * qd,
    )
    q0, qd0 = pendulum.state(jnp.asarray(1.0), jnp.asarray(0.5), args)
    t1 = 1.3
    g_l, c_m = float(args["g"] / args["l"]), float(args["c"] / args["m"])
    reduced = scipy.integrate.solve_ivp(
        lambda t, y: [y[1], -g_l * np.sin(y[0]) - c_m * y[1]],
        (0.0, t1),
        [1.0, 0.5],
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    reference, _ = pendulum.state(reduced.y[0, -1], 0.0, args)

    @jax.jit
    def run(dt0):
        return cjax.integrate_variational(
            cjax.VariationalIntegrator(),
            system,
            0.0,
            t1,
            dt0,
            q0,
            qd0,
            args,
            ts_save=jnp.array([t1]),
            throw=False,
        )

    steps = np.array([25, 50, 100, 200])
    errors = []
    for num in steps:
        sol = run(t1 / num)
        assert sol.result == cjax.RESULTS.successful
        errors.append(float(jnp.linalg.norm(sol.q[-1] - reference)))
    slope = np.polyfit(np.log(1.0 / steps), np.log(errors), 1)[0]
    assert 1.9 < slope < 2.1, (errors, slope)


def test_save_times_hit_exactly(runners):
    """Save times at `t0`, repeated, and not multiples of `dt0`: each interval gets the
    fewest equal steps `<= dt0`; `t0` returns the initial state, a repeated time the
    same state, and the state at an intermediate time equals a run that ends there."""
    args = pendulum.default_args()
    run = runners["trapezoidal"]
    theta0, thetadot0 = 0.9, 0.0
    q0, qd0 = pendulum.state(jnp.asarray(theta0), jnp.asarray(thetadot0), args)
    sol = run(theta0, thetadot0, args, 0.1, jnp.array([0.0, 0.33]))
    assert sol.result == cjax.RESULTS.successful
    assert int(sol.stats["num_steps"]) == 4  # ceil(0.33 / 0.1)
    np.testing.assert_array_equal(sol.q[0], q0)
    np.testing.assert_array_equal(sol.qd[0], qd0)
    sol2 = run(theta0, thetadot0, args, 0.1, jnp.array([0.33, 0.33]))
    assert sol2.result == cjax.RESULTS.successful
    assert int(sol2.stats["num_steps"]) == 4
    np.testing.assert_array_equal(sol2.q[0], sol2.q[1])
    np.testing.assert_array_equal(sol2.qd[0], sol2.qd[1])
    np.testing.assert_allclose(sol2.q[1], sol.q[1], rtol=0, atol=1e-15)
    # 0.33 then 0.5: 4 steps of 0.0825, then ceil(0.17 / 0.1) = 2 of 0.085.
    sol3 = run(theta0, thetadot0, args, 0.1, jnp.array([0.33, 0.5]))
    assert int(sol3.stats["num_steps"]) == 6
    np.testing.assert_allclose(sol3.q[0], sol.q[1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(sol3.qd[0], sol.qd[1], rtol=0, atol=1e-14)
    sol4 = run(theta0, thetadot0, args, 0.5 / 6, jnp.array([0.25, 0.5]))
    assert int(sol4.stats["num_steps"]) == 6
    # Same number of steps, slightly different sizes: close, not equal.
    assert 0 < float(jnp.linalg.norm(sol4.q[1] - sol3.q[1])) < 1e-3


def test_jit_vmap_matches_loop(runners):
    """`jax.vmap` over the release angle and the length equals a Python loop."""
    run = runners["trapezoidal"]
    thetas = jnp.array([0.2, 0.9, 1.6])
    lengths = jnp.array([0.5, 1.0, 2.0])
    ts = jnp.array([0.4, 1.0])

    def one(theta0, length):
        return run(theta0, jnp.asarray(0.0), pendulum.default_args(l=length), 0.01, ts)

    batched = jax.vmap(one)(thetas, lengths)
    for i in range(3):
        single = one(thetas[i], lengths[i])
        row = jax.tree.map(lambda x, i=i: x[i], (batched.q, batched.qd))
        assert tree_allclose(row, (single.q, single.qd), rtol=1e-13, atol=1e-14)
    assert bool(jnp.all(batched.result == cjax.RESULTS.successful))


def test_gradients_match_finite_differences(runners):
    """`jax.grad` through the whole run (the Newton solves differentiated implicitly)
    with respect to the parameters `(l, g)` and the initial angle and rate."""
    run = runners["trapezoidal"]
    ts = jnp.array([0.7, 1.5])

    def objective(p):
        args = pendulum.default_args(l=p[0], g=p[1])
        sol = run(p[2], p[3], args, 0.02, ts)
        return sol.q[-1, 0] + 0.3 * sol.qd[-1, 1] + sol.q[0, 1]

    p = jnp.array([0.8, 9.81, 0.7, 0.3])
    grad = jax.jit(jax.grad(objective))(p)
    fd = finite_difference_grad(objective, p, rel_step=1e-6)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)


def test_failures_are_reported(runners):
    args = pendulum.default_args()
    run = runners["trapezoidal"]
    theta0 = jnp.asarray(0.5)
    zero = jnp.asarray(0.0)
    # Step budget: 1,000 steps of 0.001 reach t = 1 but not 2.
    sol = run(theta0, zero, args, 0.001, jnp.array([1.0, 2.0]))
    assert sol.result == cjax.RESULTS.max_steps_reached
    assert int(sol.stats["num_steps"]) == 1000
    assert bool(jnp.all(jnp.isfinite(sol.q[0]))) and bool(jnp.all(jnp.isinf(sol.q[1])))
    # Bad grid.
    sol = run(theta0, zero, args, -0.1, jnp.array([1.0]))
    assert sol.result == cjax.RESULTS.invalid_time_grid
    sol = run(theta0, zero, args, 0.1, jnp.array([0.5, 0.2]))
    assert sol.result == cjax.RESULTS.invalid_time_grid
    sol = run(theta0, zero, dict(args, g=jnp.asarray(jnp.nan)), 0.1, TS)
    assert sol.result == cjax.RESULTS.invalid_input
    # One Newton iteration cannot reach the tolerance on the nonlinear constraint.
    one_iteration = _pendulum_runner(cjax.VariationalIntegrator(newton_steps=1))
    sol = one_iteration(theta0, jnp.asarray(1.0), args, 0.1, TS)
    assert sol.result == cjax.RESULTS.variational_step_failed
    # With `throw=True` (the default) a failure raises, naming its cause.
    q0, qd0 = pendulum.state(theta0, zero, args)
    with pytest.raises(eqx.EquinoxRuntimeError, match="newton_steps"):
        cjax.integrate_variational(
            cjax.VariationalIntegrator(newton_steps=1),
            pendulum.system(),
            0.0,
            1.0,
            0.1,
            q0,
            qd0,
            args,
            ts_save=TS,
        )


def test_bad_structure_raises():
    system = pendulum.system()
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)
    vi = cjax.VariationalIntegrator()
    with pytest.raises(ValueError, match="dt0=0.01"):
        cjax.integrate_variational(
            vi, system, 0.0, 1.0, None, q0, qd0, args, ts_save=TS
        )
    with pytest.raises(ValueError, match="AbstractVariationalIntegrator"):
        cjax.integrate_variational(
            diffrax.Tsit5(), system, 0.0, 1.0, 0.1, q0, qd0, args, ts_save=TS
        )
    with pytest.raises(ValueError, match="1-dimensional"):
        cjax.integrate_variational(
            vi, system, 0.0, 1.0, 0.1, q0, qd0, args, ts_save=jnp.zeros((2, 2))
        )
    with pytest.raises(ValueError, match="newton_steps"):
        cjax.VariationalIntegrator(newton_steps=0)
    with pytest.raises(ValueError, match="quadrature"):
        cjax.VariationalIntegrator(quadrature="midpoint")


def test_selectable_in_simulate():
    """`simulate(..., solver=cjax.VariationalIntegrator(), dt0=h)`: the constraint
    holds to round-off at every save, the energy error is O(h^2) small, and the
    multipliers are the tension of the closed-form pendulum at the saves."""
    args = pendulum.default_args()
    theta0 = jnp.asarray(0.7)
    q0, qd0 = pendulum.state(theta0, jnp.asarray(0.0), args)
    period = pendulum.period(theta0, args)
    ts = jnp.linspace(0.0, 1.0, 9) * period
    traj = cjax.simulate(
        pendulum.system(),
        (0.0, period),
        q0,
        qd0,
        args,
        solver=cjax.VariationalIntegrator(),
        dt0=float(period) / 400,
        saveat=cjax.SaveAt(ts=ts),
    )
    assert traj.result == cjax.RESULTS.successful
    assert np.max(np.abs(traj.violation["position"])) < 1e-12
    energy0 = pendulum.system().energy(q0, qd0, 0.0, args)
    assert np.max(np.abs(traj.energy - energy0)) < 1e-3 * abs(energy0)
    np.testing.assert_allclose(traj.q[-1], q0, atol=1e-3)
    with pytest.raises(ValueError, match="dt0"):
        cjax.simulate(
            pendulum.system(),
            (0.0, 1.0),
            q0,
            qd0,
            args,
            solver=cjax.VariationalIntegrator(),
        )
    with pytest.raises(ValueError, match="Unstabilized"):
        cjax.simulate(
            pendulum.system(),
            (0.0, 1.0),
            q0,
            qd0,
            args,
            solver=cjax.VariationalIntegrator(),
            dt0=0.01,
            stabilization=cjax.Projection(),
        )


def test_failed_run_has_nan_gradient(runners):
    """A run cut short by `max_steps` (5,000 steps needed, 1,000 allowed) has no
    derivative: `jax.grad` of a saved coordinate is NaN, not the zero that flows
    back through the unreached (`inf`) save. The same program with a step that
    needs 50 steps has a finite gradient (the step size is traced: one program)."""
    run = runners["trapezoidal"]
    args = pendulum.default_args()
    assert run(0.5, 0.0, args, 1e-4, TS).result == cjax.RESULTS.max_steps_reached
    grad = jax.jit(jax.grad(lambda th, dt: run(th, 0.0, args, dt, TS).q[-1, 0]))
    assert np.isnan(grad(0.5, 1e-4))
    assert np.isfinite(grad(0.5, 0.01))


def test_start_off_the_constraints_is_refused():
    """The first step puts the state on the constraints: a start off them (the rod
    10 % too long, a radial velocity) used to be integrated from the wrong state,
    with `successful`. It is refused now, as `simulate` refuses it, and takes no
    step."""
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)

    @jax.jit
    def run(q0_, qd0_):
        return cjax.integrate_variational(
            cjax.VariationalIntegrator(),
            pendulum.system(),
            0.0,
            0.5,
            0.05,
            q0_,
            qd0_,
            args,
            ts_save=TS,
            throw=False,
        )

    assert run(q0, qd0).result == cjax.RESULTS.successful
    for start in [(1.1 * q0, qd0), (q0, qd0 + 0.5 * q0)]:
        sol = run(*start)
        assert sol.result == cjax.RESULTS.inconsistent_initial_state
        assert int(sol.stats["num_steps"]) == 0
