"""Contacts that come and go (`simulate(..., max_events=N)`): a ball bouncing on a
floor against the geometric series of its impact times, resting contact ending the
Zeno series, an exhausted event budget, two independent contacts, a release and an
inelastic landing, gradients through the impacts, careless inputs."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import constrained_jax as cjax
from constrained_jax.scenes import bouncing_ball as ball, two_cylinders as cyl


TIGHT = diffrax.PIDController(rtol=1e-10, atol=1e-10)
H, U, T1, MAX_EVENTS = 1.0, 0.5, 2.4, 12
TS = jnp.linspace(0.0, T1, 25)
# (e, rest_speed): three series that do not reach t_inf before T1; the Zeno series
# e = 0.5 (t_inf = 1.355) ended by resting contact at the fifth impact (speeds
# 4.43 * 0.5^(k-1): 0.277 < 0.3 first at k = 5); e = 0 (rests at the first impact);
# e = 0.5 without rest speed (its twelve events are spent before t_inf); e = 1.5 (not
# a restitution).
CASES = [(0.7, 0.0), (0.8, 0.0), (0.9, 0.0), (0.5, 0.3), (0.0, 0.0), (0.5, 0.0)]
INVALID = [(1.5, 0.0), (float("nan"), 0.0)]
# (e, rest_speed, h): starting at rest on the floor (attached from the start), and
# below it (inconsistent).
STARTS = [(0.5, 0.0, 0.0), (0.5, 0.0, -0.01)]


def _drop(e, rest_speed, h=H):
    args = ball.default_args(e=e, rest_speed=rest_speed)
    q0, qd0 = ball.state(h, U)
    return cjax.simulate(
        ball.system(),
        (0.0, T1),
        q0,
        qd0,
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(ts=TS),
        max_events=MAX_EVENTS,
        throw=False,
    )


_drops = jax.jit(jax.vmap(_drop))


@pytest.fixture(scope="module")
def drops():
    cases = [(e, r, H) for e, r in CASES + INVALID] + STARTS
    e, rest, h = (jnp.asarray(x) for x in zip(*cases, strict=True))
    return e, rest, _drops(e, rest, h)


def _closed_form(e, rest_speed, g=9.81):
    """The impacts before T1 (at most MAX_EVENTS), and whether the ball rests."""
    args = ball.default_args(e=e)
    k_rest = ball.rest_impact(H, e, g, rest_speed) if rest_speed > 0 else None
    times = []
    for k in range(1, MAX_EVENTS + 1):
        t_k = float(ball.impact_time(k, H, args))
        if t_k > T1:
            break
        times.append(t_k)
        if e == 0 or k == k_rest:
            return np.asarray(times), True
    return np.asarray(times), False


def _height(t, times, e, g=9.81):
    """The closed-form height at `t`: free fall, then after the k-th impact a flight
    launched at e v_k (0 once resting)."""
    v1 = np.sqrt(2 * g * H)
    before = times[times <= t]
    if before.size == 0:
        return H - g * t**2 / 2
    k = before.size
    s = t - before[-1]
    return e**k * v1 * s - g * s**2 / 2


def test_impact_times_form_a_geometric_series(drops):
    e_all, rest_all, traj = drops
    for i, (e, rest) in enumerate(CASES):
        times, rests = _closed_form(e, rest)
        ev = traj.events
        count = int(ev.count[i])
        zeno = e == 0.5 and rest == 0.0
        assert count == (MAX_EVENTS if zeno else times.size)
        np.testing.assert_allclose(ev.time[i, :count], times, rtol=1e-8)
        assert np.all(np.isinf(ev.time[i, count:]))
        assert np.all(ev.impact[i, :count]) and np.all(ev.group[i, :count] == 0)
        # Impact speeds v_k = e^(k-1) v_1; the impulse m (1 + e) v_k (e = 0 for the
        # resting impact); after the impact ydot = e v_k, xdot unchanged.
        k = np.arange(1, count + 1)
        args = ball.default_args(e=e)
        speeds = np.asarray([ball.impact_speed(j, H, args) for j in k])
        # (An impact is located where the gap is delta = 1000 eps (1 + |q|), about
        # 4e-13, below zero: the speed there exceeds the contact speed v by
        # g delta / v, 2e-9 for the slowest impact here, v = 2e-3.)
        np.testing.assert_allclose(ev.speed[i, :count], speeds, rtol=1e-8, atol=1e-8)
        e_applied = np.where(ev.attached[i, :count], 0.0, e)
        np.testing.assert_allclose(
            ev.impulse[i, :count], (1 + e_applied) * speeds, rtol=1e-8, atol=1e-8
        )
        np.testing.assert_allclose(
            ev.qd[i, :count, 1], e_applied * speeds, rtol=1e-8, atol=1e-8
        )
        np.testing.assert_allclose(ev.qd[i, :count, 0], U, rtol=1e-12)
        # On the floor at each impact (the position put back from the event's
        # delta = sqrt(eps) below it).
        np.testing.assert_allclose(ev.q[i, :count, 1], 0.0, atol=1e-14)
        assert list(ev.attached[i, :count]) == [rests and j == count for j in k]
        assert int(ev.mode[i]) == (1 if rests else 0)


def test_trajectory_between_impacts(drops):
    """Heights against the closed-form flights (apex e^(2k) h after the k-th
    impact), x = u t throughout, the energy m g y + m |qdot|^2 / 2 constant between
    impacts and multiplied by e^2 at each, the floor's multiplier m g once resting
    and 0 in flight."""
    _, _, traj = drops
    g, m = 9.81, 1.0
    for i, (e, rest) in enumerate(CASES[:5]):
        times, rests = _closed_form(e, rest)
        np.testing.assert_array_equal(traj.result._value[i], 0)
        y = np.asarray([_height(float(t), times, e) for t in TS])
        if rests:
            y = np.where(np.asarray(TS) >= times[-1], 0.0, y)
        np.testing.assert_allclose(traj.q[i, :, 1], y, rtol=0, atol=1e-8)
        np.testing.assert_allclose(traj.q[i, :, 0], U * TS, rtol=1e-10)
        k = np.searchsorted(times, np.asarray(TS), side="right")
        energy = m * g * H * e ** (2.0 * k) + m * U**2 / 2
        if rests:
            energy = np.where(k == times.size, m * U**2 / 2, energy)
        np.testing.assert_allclose(traj.energy[i], energy, rtol=1e-8)
        on_floor = (np.asarray(TS) >= times[-1]) if rests else np.zeros(TS.shape, bool)
        np.testing.assert_allclose(
            traj.multipliers[i, :, 0], np.where(on_floor, m * g, 0.0), atol=1e-8
        )
        # The apex of each full flight, from the launch speed: e^(2k) h.
        launch = np.asarray(traj.events.qd[i, : times.size, 1])
        apex = launch**2 / (2 * g)
        expected = [
            ball.apex_height(j, H, ball.default_args(e=e))
            for j in range(1, times.size + 1)
        ]
        if rests:
            expected[-1] = 0.0
        np.testing.assert_allclose(apex, expected, rtol=1e-8, atol=1e-20)


def test_zeno_is_resolved_or_reported(drops):
    """e = 0.5: with a rest speed the ball rests on the floor from the fifth impact,
    before t_inf, in five events (not max_events, not max_steps); without, the run
    spends its twelve events before t_inf and says so, never `successful`, and
    nothing is reported past the last event."""
    _, _, traj = drops
    args = ball.default_args(e=0.5)
    t_inf = float(ball.zeno_time(H, args))
    i_rest, i_zeno = CASES.index((0.5, 0.3)), CASES.index((0.5, 0.0))
    assert traj.result._value[i_rest] == cjax.RESULTS.successful._value
    assert int(traj.events.count[i_rest]) == 5
    assert traj.events.time[i_rest, 4] < t_inf
    assert traj.stats["num_steps"][i_rest] < 2000
    assert traj.result._value[i_zeno] == cjax.RESULTS.max_events_reached._value
    t_last = float(ball.impact_time(MAX_EVENTS, H, args))
    np.testing.assert_allclose(traj.events.time[i_zeno, -1], t_last, rtol=1e-8)
    after = np.asarray(TS) > t_last
    assert after.any() and np.all(np.isinf(traj.q[i_zeno, after]))
    assert np.all(np.isfinite(traj.q[i_zeno, ~after]))


def test_restitution_outside_the_unit_interval_is_reported(drops):
    """A traced e = 1.5 is refused at run time; a NaN e is invalid input (`args`
    must be finite): never `successful`."""
    _, _, traj = drops
    i = len(CASES)
    assert traj.result._value[i] == cjax.RESULTS.invalid_restitution._value
    assert traj.result._value[i + 1] == cjax.RESULTS.invalid_input._value
    # The NaN lane runs no phase (it used to reject steps until `max_steps`, with
    # the whole batch waiting for it).
    assert int(traj.stats["num_steps"][i + 1]) == 0


def test_initial_contact_mode(drops):
    """At rest on the floor the ball starts attached and stays (no event, y = 0,
    the floor pushing with m g); below the floor the start is inconsistent."""
    _, _, traj = drops
    i = len(CASES) + len(INVALID)
    assert traj.result._value[i] == cjax.RESULTS.successful._value
    assert int(traj.events.count[i]) == 0 and int(traj.events.mode[i]) == 1
    np.testing.assert_allclose(traj.q[i, :, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.q[i, :, 0], U * TS, rtol=1e-10)
    np.testing.assert_allclose(traj.multipliers[i, :, 0], 9.81, rtol=1e-12)
    assert traj.result._value[i + 1] == cjax.RESULTS.inconsistent_initial_state._value


def _third_impact(e):
    args = ball.default_args(e=e)
    q0, qd0 = ball.state(H, U)
    traj = cjax.simulate(
        ball.system(),
        (0.0, 1.8),  # (e = 0.75: t_3 = 1.64, t_4 = 2.02; e = 0.8: 1.75, 2.21)
        q0,
        qd0,
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False),
        max_events=3,
    )
    return traj.events.time[2]


@pytest.mark.slow  # (long to compile, most of it the reverse pass)
def test_gradient_of_an_impact_time():
    """`jax.grad` of t_3 through two impacts, under `jax.vmap` over e, against the
    closed form d t_3 / d e = (2 v_1 / g)(1 + 2 e), and the value
    t_1 + (2 v_1 / g)(e + e^2)."""
    e = jnp.asarray([0.75, 0.8])
    value, grad = jax.jit(jax.vmap(jax.value_and_grad(_third_impact)))(e)
    t1, v1 = (float(x) for x in ball.first_impact(H, ball.default_args()))
    e = np.asarray(e)
    np.testing.assert_allclose(value, t1 + 2 * v1 / 9.81 * (e + e**2), rtol=1e-8)
    np.testing.assert_allclose(grad, 2 * v1 / 9.81 * (1 + 2 * e), rtol=1e-6)


def _two_balls():
    """Two balls on their own floors (two `Unilateral` groups): independent
    events, the second one resting after its fifth impact."""

    def lagrangian(q, qd, t, args):
        return 0.5 * jnp.dot(qd, qd) - 9.81 * jnp.sum(q)

    floors = [
        cjax.Unilateral(
            cjax.Holonomic(lambda q, t, a, i=i: q[i]),
            gap=lambda q, t, a, i=i: q[i],
            restitution=lambda a, i=i: a["e"][i],
            rest_speed=lambda a, i=i: a["rest"][i],
        )
        for i in range(2)
    ]
    return cjax.LagrangianSystem(lagrangian, floors)


def test_two_independent_contacts():
    heights, e, rest = (1.0, 0.5), (0.8, 0.6), (0.0, 0.5)
    args = {"e": jnp.asarray(e), "rest": jnp.asarray(rest)}
    traj = cjax.simulate(
        _two_balls(),
        (0.0, 2.0),
        jnp.asarray(heights),
        jnp.zeros(2),
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(ts=jnp.array([1.0, 2.0])),
        max_events=MAX_EVENTS,
    )
    ev = traj.events
    count = int(ev.count)
    for i in range(2):
        a = ball.default_args(e=e[i])
        k_rest = ball.rest_impact(heights[i], e[i], 9.81, rest[i]) if rest[i] else 99
        expected = [
            float(ball.impact_time(k, heights[i], a)) for k in range(1, k_rest + 1)
        ]
        expected = [t for t in expected if t <= 2.0]
        mine = np.asarray(ev.time[:count])[np.asarray(ev.group[:count]) == i]
        np.testing.assert_allclose(mine, expected, rtol=1e-8)
    assert k_rest == 5  # the second ball rests at its fifth impact
    assert np.all(np.diff(ev.time[:count]) > 0)
    # At the end: the first ball flies, the second rests (mode bit 1), pushed by its
    # floor with m g; the first floor's multiplier is 0.
    assert int(ev.mode) == 2
    np.testing.assert_allclose(traj.q[-1, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.multipliers[-1], [0.0, 9.81], rtol=1e-9, atol=1e-9)


def test_release_and_inelastic_landing():
    """A particle on the floor lifted by a force pulse (as in `test_release.py`):
    released where the pulse exceeds m g, it lands (e = 0) at the closed-form time
    and is attached again, its multiplier the normal force m g - F afterwards."""

    def lagrangian(q, qd, t, args):
        return 0.5 * args["m"] * jnp.dot(qd, qd) - args["m"] * 9.81 * q[1]

    def forces(q, qd, t, args):
        u = t / args["tau"]
        lift = args["A"] * args["m"] * 9.81 * u * jnp.exp(1 - u)
        return jnp.stack([jnp.zeros_like(lift), lift])

    floor = cjax.Unilateral(
        cjax.Holonomic(lambda q, t, a: q[1]),
        gap=lambda q, t, a: q[1],
        restitution=0.0,
    )
    system = cjax.LagrangianSystem(lagrangian, floor, forces)
    a, tau, m = 3.0, 0.5, 2.0
    args = {"m": jnp.asarray(m), "A": jnp.asarray(a), "tau": jnp.asarray(tau)}
    traj = cjax.simulate(
        system,
        (0.0, 20.0),
        jnp.array([0.0, 0.0]),
        jnp.array([1.0, 0.0]),
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(ts=jnp.array([0.05, 19.0])),
        max_events=4,
    )
    u_r = scipy.optimize.brentq(
        lambda u: a * u * np.exp(1 - u) - 1, 0.0, 1.0, xtol=1e-16
    )
    t_r = tau * u_r

    def p(t):
        return a * 9.81 * tau**2 * (t / tau + 2) * np.exp(1 - t / tau)

    def dp(t):
        return -a * 9.81 * tau * (t / tau + 1) * np.exp(1 - t / tau)

    def height(t):
        return p(t) - p(t_r) - dp(t_r) * (t - t_r) - 9.81 * (t - t_r) ** 2 / 2

    t_land = scipy.optimize.brentq(height, t_r + 1e-3, t_r + 100.0, xtol=1e-15)
    ev = traj.events
    assert int(ev.count) == 2
    np.testing.assert_allclose(ev.time[:2], [t_r, t_land], rtol=1e-7)
    assert list(ev.impact[:2]) == [False, True]
    assert list(ev.attached[:2]) == [False, True]
    np.testing.assert_array_equal(ev.qd[1, 1], 0.0)
    u = 19.0 / tau
    np.testing.assert_allclose(
        traj.multipliers[1, 0], m * 9.81 * (1 - a * u * np.exp(1 - u)), rtol=1e-9
    )
    np.testing.assert_allclose(traj.q[1], [19.0, 0.0], atol=1e-9)


def test_careless_inputs():
    gap = lambda q, t, a: q[1]
    rows = cjax.Holonomic(gap)
    for bad in (-0.1, 1.5, float("nan"), "e"):
        with pytest.raises(ValueError, match="restitution"):
            cjax.Unilateral(rows, gap=gap, restitution=bad)
    with pytest.raises(ValueError, match="rest_speed"):
        cjax.Unilateral(rows, gap=gap, restitution=0.5, rest_speed=-1.0)
    with pytest.raises(ValueError, match="gap"):
        cjax.Unilateral(rows, restitution=0.5)
    args = ball.default_args()
    q0, qd0 = ball.state(H)
    with pytest.raises(ValueError, match="max_events"):
        cjax.simulate(ball.system(), (0.0, 1.0), q0, qd0, args)
    for bad in (0, -1, 2.0, True):
        with pytest.raises(ValueError, match="max_events"):
            cjax.simulate(ball.system(), (0.0, 1.0), q0, qd0, args, max_events=bad)
    plain = cjax.LagrangianSystem(ball.lagrangian, cjax.Unilateral(rows, gap=gap))
    with pytest.raises(ValueError, match="restitution"):
        cjax.simulate(plain, (0.0, 1.0), q0, qd0, args, max_events=4)
    with pytest.raises(ValueError, match="none"):
        cjax.simulate(
            cjax.LagrangianSystem(ball.lagrangian),
            (0.0, 1.0),
            q0,
            qd0,
            args,
            max_events=4,
        )


@pytest.mark.slow  # (four contact modes to compile)
def test_two_cylinders_detach_and_bounce_on_a_floor():
    """The lecture's two cylinders, with the contact group (contact and no slip, two
    Pfaffian rows) re-made inelastically and a floor at y = y_f below: released at
    the closed-form detachment time, the rolling cylinder flies as a projectile and
    hits the floor where y* + vy* s - g s^2 / 2 = y_f; the impulse, in the polar
    coordinates (r, theta1), is vertical: vx and the spin are unchanged, vy is
    reversed and scaled by e."""
    y_floor, e = -1.0, 0.6

    def floor_height(q, t, args):
        return q[0] * jnp.cos(q[1]) - y_floor

    contact = cjax.Unilateral(
        cjax.Pfaffian(cyl.pfaffian_rows),
        gap=lambda q, t, args: q[0] - (args["R"] + args["a"]),
        restitution=0.0,
    )
    floor = cjax.Unilateral(
        cjax.Holonomic(floor_height), gap=floor_height, restitution=e
    )
    system = cjax.LagrangianSystem(cyl.lagrangian, (contact, floor))
    args = cyl.default_args()
    theta0 = jnp.asarray(0.3)
    q0, qd0 = cyl.state(theta0, jnp.zeros_like(theta0), args)
    traj = cjax.simulate(
        system,
        (0.0, 2.0),
        q0,
        qd0,
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(t1=True),
        max_events=2,
        throw=False,
    )
    ev = traj.events
    assert list(ev.group) == [0, 1] and list(ev.impact) == [False, True]
    np.testing.assert_allclose(ev.time[0], cyl.detachment_time(theta0, args), rtol=1e-8)
    np.testing.assert_allclose(
        ev.q[0, 1], cyl.detachment_angle(theta0, args), rtol=1e-9
    )

    def cartesian(q, qd):
        r, th, rd, thd = q[0], q[1], qd[0], qd[1]
        return (
            r * np.sin(th),
            r * np.cos(th),
            rd * np.sin(th) + r * thd * np.cos(th),
            rd * np.cos(th) - r * thd * np.sin(th),
        )

    x_r, y_r, vx_r, vy_r = cartesian(np.asarray(ev.q[0]), np.asarray(ev.qd[0]))
    g = 9.81
    s = (vy_r + np.sqrt(vy_r**2 + 2 * g * (y_r - y_floor))) / g
    np.testing.assert_allclose(ev.time[1] - ev.time[0], s, rtol=1e-8)
    x, y, vx, vy = cartesian(np.asarray(ev.q[1]), np.asarray(ev.qd[1]))
    np.testing.assert_allclose([x, y], [x_r + vx_r * s, y_floor], rtol=1e-8)
    np.testing.assert_allclose(vx, vx_r, rtol=1e-8)
    np.testing.assert_allclose(vy, -e * (vy_r - g * s), rtol=1e-8)
    np.testing.assert_allclose(ev.qd[1, 2], ev.qd[0, 2], rtol=1e-10)
    # The next floor impact, 2 vy / g later, would be a third event: the run is
    # successful only if that falls after t1.
    beyond = float(ev.time[1]) + 2 * vy / g > 2.0
    expected = cjax.RESULTS.successful if beyond else cjax.RESULTS.max_events_reached
    assert traj.result == expected
