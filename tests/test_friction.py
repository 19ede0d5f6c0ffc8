"""Coulomb friction on a contact (`cjax.Coulomb`): stick, slip, the transitions
between them and their gradients, against the closed forms and the independent
(hand-derived, SciPy-integrated) references of the friction scenes."""

import json

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import (
    incline_block as incline,
    painleve_rod as rod,
    sliding_disk as disk,
    two_cylinders_friction as cylinders,
)

from .helpers import run_python


TOL = 1e-12  # the integration tolerance (rtol = atol)
MAX_EVENTS = 6


def _run(scene, q0, qd0, args, t1, ts, throw=False, **kwargs):
    """One program per scene (and dtype): three save times, multipliers, six
    events; everything else traced (`throw` acts after the program)."""
    kwargs.setdefault("stepsize_controller", diffrax.PIDController(rtol=TOL, atol=TOL))
    return cjax.simulate(
        scene.system(),
        (0.0, t1),
        q0,
        qd0,
        args,
        saveat=cjax.SaveAt(ts=jnp.asarray(ts), multipliers=True),
        max_events=MAX_EVENTS,
        throw=throw,
        **kwargs,
    )


def _incline(theta, mu_s, mu_k, v0=0.0, t1=1.0):
    args = incline.default_args(theta=theta, mu_s=mu_s, mu_k=mu_k)
    q0, qd0 = incline.state(0.0, v0)
    ts = np.array([0.25, 0.5, 1.0]) * t1
    return _run(incline, q0, qd0, args, t1, ts), args, ts


# --- a block on an incline ----------------------------------------------------


def test_incline_sticks_from_rest_below_the_cone():
    """`tan(theta) < mu_s`: it sticks, `N = m g cos`, `lambda_t = -m g sin`."""
    traj, args, _ = _incline(0.4, 0.5, 0.3)
    assert traj.result == cjax.RESULTS.successful
    assert int(traj.events.count) == 0
    np.testing.assert_allclose(traj.q, 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.multipliers[:, 0], incline.normal_force(args))
    np.testing.assert_allclose(traj.multipliers[:, 1], incline.stick_friction(args))


def test_incline_slides_from_rest_above_the_cone():
    """`tan(theta) > mu_s`: it slides from the start with `g (sin - mu_k cos)`,
    the friction force `-mu_k N`."""
    traj, args, ts = _incline(0.6, 0.5, 0.3)
    assert traj.result == cjax.RESULTS.successful
    x = incline.displacement(jnp.asarray(ts), 0.0, args)
    np.testing.assert_allclose(traj.q[:, 0], x, rtol=1e-10)
    np.testing.assert_allclose(
        traj.multipliers[:, 1], incline.kinetic_friction(1.0, args), rtol=1e-10
    )


@pytest.mark.parametrize("v0", [2.0, -2.0])
def test_incline_stops_and_sticks(v0):
    """Launched downhill (`tan < mu_k`: it decelerates) or uphill: it stops at the
    closed-form time (1e-9) and sticks; after it, `lambda_t = -m g sin`."""
    traj, args, ts = _incline(0.25, 0.5, 0.4, v0=v0, t1=3.0)
    assert traj.result == cjax.RESULTS.successful
    events = traj.events
    assert int(events.count) == 1
    assert not bool(events.impact[0]) and bool(events.attached[0])
    assert float(events.slip[0]) == 0.0
    t_stop = incline.stop_time(v0, args)
    assert abs(float(events.time[0]) - float(t_stop)) < 1e-9
    x = incline.displacement(jnp.asarray(ts), v0, args)
    np.testing.assert_allclose(traj.q[:, 0], x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(traj.qd[-1], 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.multipliers[-1, 1], incline.stick_friction(args))


def test_incline_uphill_stops_and_slides_back():
    """`tan > mu_s`: launched uphill, it stops, and slips the other way."""
    traj, args, ts = _incline(0.6, 0.5, 0.3, v0=-2.0, t1=1.0)
    assert traj.result == cjax.RESULTS.successful
    events = traj.events
    assert int(events.count) == 1 and float(events.slip[0]) == 1.0
    assert abs(float(events.time[0]) - float(incline.stop_time(-2.0, args))) < 1e-9
    x = incline.displacement(jnp.asarray(ts), -2.0, args)
    np.testing.assert_allclose(traj.q[:, 0], x, rtol=1e-9, atol=1e-12)


def test_incline_batch_sticks_and_slips():
    """One `vmap` batch in which some lanes stick and some slip (`mu_s` varies)."""
    theta, mu_k = 0.5, 0.2  # tan(0.5) = 0.546

    def final_x(mu_s):
        traj, _, _ = _incline(theta, mu_s, mu_k)
        return traj.q[-1, 0]

    mu_s = jnp.array([0.3, 0.5, 0.6, 2.0])
    x = jax.jit(jax.vmap(final_x))(mu_s)
    args = incline.default_args(theta=theta, mu_s=0.3, mu_k=mu_k)
    sliding = incline.displacement(1.0, 0.0, args)
    np.testing.assert_allclose(x, [sliding, sliding, 0.0, 0.0], rtol=1e-10, atol=1e-12)


def test_incline_gradients_through_a_transition():
    """Launched uphill on a slope it cannot stay on: the stop time and the position
    after it (sliding back), differentiated with respect to `mu_k`, the slope (a
    parameter of the Lagrangian) and the launch speed (the initial state), in
    forward mode (`adjoint=diffrax.ForwardMode()`, as `cjax.fit(jac="fwd")` uses),
    against the closed forms. (Reverse mode: the cylinders' slip angle below.)"""

    def computed(p):
        mu_k, theta, v0 = p
        args = incline.default_args(theta=theta, mu_s=0.5, mu_k=mu_k)
        q0, qd0 = incline.state(0.0, v0)
        traj = _run(
            incline, q0, qd0, args, 1.0, [0.25, 0.5, 1.0],
            adjoint=diffrax.ForwardMode(),
        )  # fmt: skip
        return jnp.stack([traj.events.time[0], traj.q[-1, 0]])

    def closed(p):
        mu_k, theta, v0 = p
        args = incline.default_args(theta=theta, mu_s=0.5, mu_k=mu_k)
        return jnp.stack(
            [incline.stop_time(v0, args), incline.displacement(1.0, v0, args)]
        )

    p = jnp.array([0.3, 0.6, -2.0])
    # (The values and the Jacobian from one program.)
    jac, value = jax.jacfwd(lambda p_: (computed(p_), computed(p_)), has_aux=True)(p)
    np.testing.assert_allclose(value, closed(p), rtol=1e-9)
    np.testing.assert_allclose(jac, jax.jacfwd(closed)(p), rtol=1e-6, atol=1e-9)


def test_incline_edges():
    """Careless coefficients: frictionless (`mu = 0`: slides with `g sin`), huge
    (`1e6`: never slips, even launched), the cone's edge (`tan theta = mu_s = mu_k`:
    it stays), and a `mu_k > mu_s` from `args` (`invalid_friction`)."""
    theta = 0.5
    traj, args, ts = _incline(theta, 0.0, 0.0)
    assert traj.result == cjax.RESULTS.successful
    np.testing.assert_allclose(
        traj.q[:, 0], 0.5 * 9.81 * np.sin(theta) * np.asarray(ts) ** 2, rtol=1e-10
    )
    traj, _, _ = _incline(1.2, 1e6, 1e6, v0=0.0)
    assert traj.result == cjax.RESULTS.successful
    np.testing.assert_allclose(traj.q, 0.0, atol=1e-12)
    mu = float(np.tan(theta))
    traj, _, _ = _incline(theta, mu, mu)
    assert traj.result == cjax.RESULTS.successful
    np.testing.assert_allclose(traj.q, 0.0, atol=1e-9)
    traj, _, _ = _incline(theta, 0.3, 0.4)
    assert traj.result == cjax.RESULTS.invalid_friction
    with pytest.raises(Exception, match="mu_k"):
        args = incline.default_args(theta=theta, mu_s=0.3, mu_k=0.4)
        q0, qd0 = incline.state()
        _run(incline, q0, qd0, args, 1.0, [0.25, 0.5, 1.0], throw=True)


_FLOAT32 = """
import json, warnings
warnings.simplefilter("ignore")
import jax, jax.numpy as jnp
import constrained_jax as cjax
from constrained_jax.scenes import incline_block as incline
args = incline.default_args(0.25, 0.5, 0.4)
args = {k: v.astype(jnp.float32) for k, v in args.items()}
q0, qd0 = (v.astype(jnp.float32) for v in incline.state(0.0, 2.0))
traj = cjax.simulate(incline.system(), (0.0, 3.0), q0, qd0, args, max_events=2,
                     throw=False)
print("RESULT" + json.dumps({"x64": bool(jax.config.jax_enable_x64),
    "dtype": str(traj.q.dtype), "result": str(traj.result),
    "time": float(traj.events.time[0]), "slip": float(traj.events.slip[0]),
    "qd": traj.qd[-1].tolist()}))
"""


def test_incline_float32():
    """float32 (a process with `jax_enable_x64` off, as a float32 user runs): the
    stop time to float32's event tolerance, at rest after it."""
    proc = run_python(_FLOAT32, timeout=600, JAX_ENABLE_X64="0")
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")]
    assert proc.returncode == 0 and lines, proc.stderr[-3000:]
    out = json.loads(lines[-1][len("RESULT") :])
    assert not out["x64"] and out["dtype"] == "float32"
    assert out["result"] == "successful" and out["slip"] == 0.0
    t_stop = float(incline.stop_time(2.0, incline.default_args(0.25, 0.5, 0.4)))
    assert abs(out["time"] - t_stop) < 1e-4 * t_stop
    np.testing.assert_allclose(out["qd"], 0.0, atol=1e-5)


# --- a disk launched sliding on a rough floor ---------------------------------


@pytest.mark.parametrize("k", [0.5, 0.4])
def test_sliding_disk_starts_rolling(k):
    """A disk (`k = 1/2`: `t* = v0 / (3 mu_k g)`, `v = 2 v0 / 3`) or a sphere
    (`k = 2/5`: `2 v0 / (7 mu_k g)`, `5 v0 / 7`) launched sliding without spin."""
    args = disk.default_args(k=k)
    v0 = 3.0
    t_star = float(disk.slip_time(v0, 0.0, args))
    ts = np.array([0.5 * t_star, 1.5 * t_star, 2.0 * t_star])
    q0, qd0 = disk.state(v0, args)
    traj = _run(disk, q0, qd0, args, ts[-1], ts)
    assert traj.result == cjax.RESULTS.successful
    assert int(traj.events.count) == 1 and float(traj.events.slip[0]) == 0.0
    assert abs(float(traj.events.time[0]) - t_star) < 1e-9
    q, qd = jax.vmap(lambda t: disk.motion(t, v0, 0.0, args))(jnp.asarray(ts))
    np.testing.assert_allclose(traj.q, q, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(traj.qd, qd, rtol=1e-9, atol=1e-11)
    assert abs(float(traj.qd[-1, 0]) - v0 / (1 + k)) < 1e-10
    forces = jax.vmap(lambda t: disk.friction_force(t, v0, 0.0, args))(jnp.asarray(ts))
    np.testing.assert_allclose(traj.multipliers[:, 1], forces, atol=1e-9)


def test_sliding_disk_dropped_lands_slides_and_rolls():
    """Impacts with friction on: dropped from `h` with a horizontal speed and no
    spin, it lands at `sqrt(2 h / g)` (a frictionless, inelastic impulse: `xdot`
    kept), slips, and rolls from `t_land + t*` at `v0 / (1 + k)`."""
    args = disk.default_args()
    v0, h = 3.0, 0.2
    q0, qd0 = disk.state(v0, args)
    q0 = q0.at[1].add(h)
    t_land = float(np.sqrt(2 * h / float(args["g"])))
    t_roll = t_land + float(disk.slip_time(v0, 0.0, args))
    traj = _run(disk, q0, qd0, args, t_roll + 0.5, [t_land / 2, t_roll, t_roll + 0.5])
    assert traj.result == cjax.RESULTS.successful
    events = traj.events
    assert int(events.count) == 2
    assert bool(events.impact[0]) and bool(events.attached[0])
    assert float(events.slip[0]) == 1.0 and float(events.slip[1]) == 0.0
    assert abs(float(events.time[0]) - t_land) < 1e-9
    assert abs(float(events.time[1]) - t_roll) < 1e-9
    assert abs(float(traj.qd[-1, 0]) - v0 / (1 + float(args["k"]))) < 1e-9


# --- the lecture's two cylinders with a finite coefficient --------------------


def _cylinders(mu_s, mu_k, theta0=0.3, t1=1.2):
    args = cylinders.default_args(mu_s=mu_s, mu_k=mu_k)
    q0, qd0 = cylinders.state(jnp.asarray(theta0), jnp.asarray(0.0), args)
    return _run(cylinders, q0, qd0, args, t1, [0.3, 0.6, t1]), args


@pytest.fixture(scope="module", params=[0.2, 0.3])
def slipping_cylinders(request):
    """`mu_s = 0.3`; `mu_k = 0.2`, and `mu_k = mu_s` (no jump in the friction
    force at the slip: the slip velocity grows from zero quadratically)."""
    return _cylinders(0.3, request.param)


def test_cylinders_slip_before_they_detach(slipping_cylinders):
    """Rolling from rest at `theta0`, the contact slips where `alpha sin(theta) =
    mu_s ((3 + alpha) cos(theta) - 2 cos(theta0))` (1e-9), before the frictionless
    detachment angle; it then slides with kinetic friction until the normal force
    vanishes, where the independent integration of the sliding equations says
    (time and state, 1e-8)."""
    traj, args = slipping_cylinders
    theta0 = 0.3
    assert traj.result == cjax.RESULTS.successful
    events = traj.events
    assert int(events.count) == 2
    assert float(events.slip[0]) == 1.0 and bool(events.attached[0])
    assert not bool(events.attached[1]) and not bool(events.impact[1])
    reference = cylinders.slip_and_detachment(theta0, args)
    assert abs(float(events.q[0, 1]) - reference.theta_slip) < 1e-9
    assert abs(float(events.time[0]) - reference.t_slip) < 1e-9
    assert reference.theta_slip < float(cylinders.detachment_angle(theta0, args))
    assert abs(float(events.time[1]) - reference.t_detach) < 1e-8
    np.testing.assert_allclose(events.q[1], reference.q_detach, rtol=1e-8)
    np.testing.assert_allclose(events.qd[1], reference.qd_detach, rtol=1e-7, atol=1e-8)


def test_cylinders_slip_angle_over_coefficients():
    """From a contact that slips soon (`mu_s = 0.15`) to one that rolls nearly to
    detachment (`mu_s = 50`), against the closed form (one program: the batch over
    coefficients is the incline's). A contact that slips from the start (`mu_s =
    0.05`: the cone is left at `theta0`) records no slip event: its first is the
    release."""
    for mu_s in (0.15, 0.3, 1.0, 50.0):
        traj, args = _cylinders(mu_s, 0.5 * mu_s)
        assert traj.result == cjax.RESULTS.successful
        assert bool(traj.events.attached[0]) and float(traj.events.slip[0]) == 1.0
        theta_s = cylinders.slip_angle(0.3, args)
        assert abs(float(traj.events.q[0, 1]) - float(theta_s)) < 1e-9, mu_s
    args = cylinders.default_args(mu_s=0.05, mu_k=0.025)
    assert abs(float(cylinders.slip_angle(0.3, args)) - 0.3) < 1e-15
    traj, _ = _cylinders(0.05, 0.025)
    assert traj.result == cjax.RESULTS.successful
    assert not bool(traj.events.attached[0])


def test_cylinders_gradient_through_slip_and_release():
    """Reverse mode through two transitions: the release time's derivatives with
    respect to `mu_s` (which moves the slip) and `mu_k` (which acts after it)
    against central differences of the independent integration."""

    def release_time(mu):
        traj, _ = _cylinders(mu[0], mu[1])
        return traj.events.time[1]

    grad = jax.grad(release_time)(jnp.array([0.3, 0.2]))

    def reference(m_s, m_k):
        args = cylinders.default_args(mu_s=m_s, mu_k=m_k)
        return cylinders.slip_and_detachment(0.3, args).t_detach

    h = 1e-5
    fd = [
        (reference(0.3 + h, 0.2) - reference(0.3 - h, 0.2)) / (2 * h),
        (reference(0.3, 0.2 + h) - reference(0.3, 0.2 - h)) / (2 * h),
    ]
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


# --- the Painleve rod -----------------------------------------------------------


def _rod(q0, qd0, args, t1):
    return _run(rod, q0, qd0, args, t1, [t1 / 4, t1 / 2, t1])


def test_painleve_rod_refused_above_the_critical_coefficient():
    """At `tan(theta) = 2` (critical coefficient `4/3`), sliding with its lower end
    leading: `mu = 1.5` has no consistent motion (`painleve_paradox`, never
    `successful`); the other slip direction, and `mu = 1.2`, run."""
    theta = float(np.arctan(2.0))
    assert abs(float(rod.critical_mu(theta)) - 4 / 3) < 1e-12
    args = rod.default_args(mu_s=1.5, mu_k=1.5)
    q0, qd0 = rod.state(theta, 1.0, args)
    traj = _rod(q0, qd0, args, 0.05)
    assert traj.result == cjax.RESULTS.painleve_paradox
    # Recorded: the contact (group 0) at t = 0, attached, slipping forwards.
    events = traj.events
    assert int(events.count) == 1 and int(events.group[0]) == 0
    assert float(events.time[0]) == 0.0 and float(events.slip[0]) == 1.0
    assert bool(events.attached[0]) and not bool(events.impact[0])
    assert not bool(jnp.any(jnp.isfinite(traj.q[1:])))
    with pytest.raises(Exception, match="Painleve"):
        _run(rod, q0, qd0, args, 0.05, [0.0125, 0.025, 0.05], throw=True)
    q0, qd0 = rod.state(theta, -1.0, args)
    assert _rod(q0, qd0, args, 0.05).result == cjax.RESULTS.successful


def test_painleve_rod_slides_below_it():
    """Below the critical coefficient: the state, the normal force and the
    friction work at `t = 0.2` of the independent integration."""
    args = rod.default_args()
    q0, qd0 = rod.default_state(args)
    traj = _rod(q0, qd0, args, 0.2)
    assert traj.result == cjax.RESULTS.successful
    assert int(traj.events.count) == 0
    q, qd, normal, _ = rod.sliding_reference(q0, qd0, 0.2, args)
    np.testing.assert_allclose(traj.q[-1], q, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(traj.qd[-1], qd, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(traj.multipliers[-1, 0], normal, rtol=1e-9)


def test_painleve_rod_sticks_and_slips_back():
    """Slides forwards, sticks, slips backwards: the switch times (1e-9) and the
    state at the end against the independent stick-slip integration."""
    args = rod.default_args(mu_s=0.7, mu_k=0.6)
    q0, qd0 = rod.stick_slip_state(args)
    traj = _rod(q0, qd0, args, 0.38)
    assert traj.result == cjax.RESULTS.successful
    switches, q, qd = rod.stick_slip_reference(q0, qd0, 0.38, args)
    events = traj.events
    count = int(events.count)
    assert count == len(switches) - 1
    for i, (t, mode) in enumerate(switches[1:]):
        assert abs(float(events.time[i]) - t) < 1e-9
        assert float(events.slip[i]) == mode
    np.testing.assert_allclose(traj.q[-1], q, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(traj.qd[-1], qd, rtol=1e-8, atol=1e-9)


# --- refusals -----------------------------------------------------------------


def test_coefficients_refused_where_given():
    tangent = cjax.Pfaffian(lambda q, t, args: jnp.array([[1.0, 0.0]]))
    with pytest.raises(ValueError, match="must not exceed"):
        cjax.Coulomb(tangent, mu_s=0.3, mu_k=0.5)
    for bad in (-0.1, float("nan"), "rough"):
        with pytest.raises(ValueError, match="mu_s"):
            cjax.Coulomb(tangent, mu_s=bad)
    with pytest.raises(ValueError, match="mu_k"):
        cjax.Coulomb(tangent, mu_s=float("inf"), mu_k=float("inf"))
    with pytest.raises(ValueError, match="tangential row"):
        cjax.Coulomb(lambda q, t, args: q, mu_s=0.3)
    with pytest.raises(ValueError, match="Coulomb"):
        cjax.Unilateral(cjax.Holonomic(lambda q, t, args: q[1]), friction=0.3)


def test_friction_needs_events_and_one_tangential_row():
    args = incline.default_args()
    q0, qd0 = incline.state()
    with pytest.raises(ValueError, match="max_events"):
        cjax.simulate(incline.system(), (0.0, 1.0), q0, qd0, args)
    two_rows = cjax.Unilateral(
        cjax.Holonomic(rod.gap),
        gap=rod.gap,
        restitution=0.0,
        friction=cjax.Coulomb(cjax.Pfaffian(lambda q, t, a: jnp.eye(3)[:2]), mu_s=0.5),
    )
    system = cjax.LagrangianSystem(rod.lagrangian, two_rows)
    args = rod.default_args()
    q0, qd0 = rod.default_state(args)
    with pytest.raises(ValueError, match="one row"):
        cjax.simulate(system, (0.0, 1.0), q0, qd0, args, max_events=2)


def test_two_contacts_each_with_its_own_friction():
    """Two blocks on one incline, each with its own contact and coefficients (two
    groups with friction: the rows, the events and the modes kept apart): the one
    launched uphill on a steep slope stops and slides back, the one launched
    downhill on a rough patch stops and sticks."""

    def lagrangian(q, qd, t, args):
        first = incline.lagrangian(q[:2], qd[:2], t, args)
        return first + incline.lagrangian(q[2:], qd[2:], t, args)

    def contact(offset, mu_s, mu_k):
        gap = lambda q, t, a: q[offset + 1]
        row = lambda q, t, a: jnp.eye(4)[offset][None]
        return cjax.Unilateral(
            cjax.Holonomic(gap),
            gap=gap,
            restitution=0.0,
            friction=cjax.Coulomb(
                cjax.Pfaffian(row), mu_s=lambda a: a[mu_s], mu_k=lambda a: a[mu_k]
            ),
        )

    system = cjax.LagrangianSystem(
        lagrangian, [contact(0, "mu_s", "mu_k"), contact(2, "mu_s2", "mu_k2")]
    )
    theta = 0.5  # tan = 0.546
    args = incline.default_args(theta=theta, mu_s=0.5, mu_k=0.3)
    args |= {"mu_s2": jnp.asarray(0.9), "mu_k2": jnp.asarray(0.8)}
    q0 = jnp.zeros(4)
    qd0 = jnp.array([-2.0, 0.0, 1.0, 0.0])
    traj = cjax.simulate(
        system, (0.0, 1.0), q0, qd0, args, max_events=4, throw=False,
        stepsize_controller=diffrax.PIDController(rtol=TOL, atol=TOL),
    )  # fmt: skip
    assert traj.result == cjax.RESULTS.successful
    second = dict(args, mu_s=args["mu_s2"], mu_k=args["mu_k2"])
    events = traj.events
    assert int(events.count) == 2
    group, time, slip = (
        np.asarray(v[:2]) for v in (events.group, events.time, events.slip)
    )
    times = {int(g): float(t) for g, t in zip(group, time, strict=True)}
    slips = {int(g): float(s) for g, s in zip(group, slip, strict=True)}
    assert abs(times[0] - float(incline.stop_time(-2.0, args))) < 1e-9
    assert abs(times[1] - float(incline.stop_time(1.0, second))) < 1e-9
    assert slips == {0: 1.0, 1: 0.0}
    x1 = incline.displacement(1.0, -2.0, args)
    x2 = incline.displacement(1.0, 1.0, second)
    np.testing.assert_allclose(traj.q[0, [0, 2]], [x1, x2], rtol=1e-9)
