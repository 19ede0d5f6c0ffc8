"""Unilateral constraints that let go: the two cylinders' detachment, a lifted
particle's release and re-contact, gradients through the events."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize

import constrained_jax as cjax
from constrained_jax.scenes import two_cylinders as cyl

from .helpers import finite_difference_grad


TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
ALPHAS = [0.0, 0.5, 1.0]
THETA0S = [1e-3, 0.3, 1.0]


@jax.jit
def _contact_run(args, q0, qd0, t1, ts):
    """The two cylinders in contact from `(q0, qd0)` to `t1`, saved at the 4 times
    `ts`: one compiled program for every test of the attached-then-free run."""
    return cjax.simulate(
        cyl.contact_system(),
        (0.0, t1),
        q0,
        qd0,
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(ts=ts),
        throw=False,
    )


def _roll_off(alpha, theta0):
    args = cyl.default_args(alpha=alpha)
    q0, qd0 = cyl.state(theta0, jnp.zeros_like(theta0), args)
    t_star = cyl.detachment_time(theta0, args)
    ts = jnp.array([0.25, 0.5, 0.9, 1.2]) * t_star
    return _contact_run(args, q0, qd0, jnp.asarray(5.0), ts)


@pytest.fixture(scope="module")
def roll_offs():
    alpha, theta0 = np.meshgrid(ALPHAS, THETA0S, indexing="ij")
    alpha, theta0 = jnp.asarray(alpha.ravel()), jnp.asarray(theta0.ravel())
    return alpha, theta0, jax.jit(jax.vmap(_roll_off))(alpha, theta0)


def test_detachment_angle_and_time(roll_offs):
    """For alpha in [0, 1] and theta0 from 1e-3 to 1: the release is where the
    lecture's normal force vanishes, theta* = arccos(2 cos theta0 / (3 + alpha)), at
    the quadrature time to get there; before it the multiplier is the normal force.

    alpha = 0 (I = 0) included: after release the spin of a cylinder without inertia
    is a free gauge (no inertia, no force), held at its release rate."""
    alpha, theta0, traj = roll_offs
    np.testing.assert_array_equal(traj.result._value, cjax.RESULTS.successful._value)
    rel = traj.release
    assert np.all(rel.released) and not np.any(rel.at_start)
    assert not np.any(rel.recontact)
    for i in range(alpha.shape[0]):
        args = cyl.default_args(alpha=alpha[i])
        np.testing.assert_allclose(
            rel.q[i, 1], cyl.detachment_angle(theta0[i], args), rtol=1e-9
        )
        np.testing.assert_allclose(
            rel.time[i], cyl.detachment_time(theta0[i], args), rtol=1e-8
        )
        # Before release (the first three saves): the closed-form normal force.
        theta1 = traj.q[i, :3, 1]
        np.testing.assert_allclose(
            traj.multipliers[i, :3, 0],
            cyl.normal_force(theta1, theta0[i], args),
            rtol=1e-8,
            atol=1e-9,
        )
        # After release (the last save): free, the cylinder has left the surface and
        # the released multipliers are zero.
        assert traj.q[i, 3, 0] > args["R"] + args["a"]
        np.testing.assert_array_equal(traj.multipliers[i, 3], 0.0)


def test_start_below_the_equator_leaves_at_once():
    """Below the equator the normal force at rest, M g cos theta0, is negative: the
    cylinder leaves at t = 0, where it stands. The closed forms say so (the lecture's
    formula alone gave theta* = 1.81 < theta0 = 2, an angle never reached)."""
    theta0 = jnp.asarray(2.0)
    args = cyl.default_args(alpha=0.5)
    assert cyl.normal_force(theta0, theta0, args) < 0
    assert cyl.detachment_angle(theta0, args) == theta0
    np.testing.assert_allclose(cyl.detachment_time(theta0, args), 0.0, atol=1e-12)
    # Continuous at the equator, where the formula gives theta0 too.
    at = jnp.asarray(np.pi / 2)
    np.testing.assert_allclose(cyl.detachment_angle(at, args), at, rtol=1e-15)
    traj = _roll_off(jnp.asarray(0.5), theta0)
    assert traj.result == cjax.RESULTS.successful
    assert bool(traj.release.released) and float(traj.release.time) == 0.0
    np.testing.assert_allclose(traj.release.q[1], theta0, rtol=1e-12)


def test_vmap_matches_a_single_run(roll_offs):
    alpha, theta0, batched = roll_offs
    single = _roll_off(alpha[4], theta0[4])
    np.testing.assert_allclose(batched.q[4], single.q, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(batched.release.time[4], single.release.time, rtol=1e-12)


@pytest.mark.parametrize("theta0", [0.3, 1.0])
def test_closed_form_time_against_quadrature(theta0):
    """The elliptic-integral time against SciPy's quadrature of dt = dtheta/thetadot
    (substituting theta = theta0 + s^2 to remove the endpoint singularity)."""
    args = cyl.default_args(alpha=0.5)
    theta_star = float(cyl.detachment_angle(theta0, args))

    def integrand(s):
        theta = theta0 + s * s
        return 2 * s / np.sqrt(float(cyl.angular_velocity_squared(theta, theta0, args)))

    reference, _ = scipy.integrate.quad(
        integrand, 0.0, np.sqrt(theta_star - theta0), epsabs=1e-13, epsrel=1e-13
    )
    np.testing.assert_allclose(cyl.detachment_time(theta0, args), reference, rtol=1e-11)


@pytest.mark.parametrize(
    "solver, controller, dt0, rtol",
    [
        # An implicit tableau: the dummy multiplier component rides through the
        # stage root-finds (`_WatchedSolver` reads it from the stages).
        (diffrax.Kvaerno5(), diffrax.PIDController(rtol=1e-8, atol=1e-8), None, 1e-8),
        # Fixed steps with two stages: the dense output fills the gap (0.3 of a step).
        (diffrax.Heun(), diffrax.ConstantStepSize(), 1e-3, 1e-6),
    ],
)
def test_release_angle_with_other_tableaus(solver, controller, dt0, rtol):
    args = cyl.default_args()
    theta0 = jnp.asarray(0.3)
    q0, qd0 = cyl.state(theta0, jnp.zeros_like(theta0), args)
    traj = cjax.simulate(
        cyl.contact_system(),
        (0.0, 2.0),
        q0,
        qd0,
        args,
        solver=solver,
        stepsize_controller=controller,
        dt0=dt0,
        saveat=cjax.SaveAt(t1=True),
    )
    assert traj.release.released
    np.testing.assert_allclose(
        traj.release.q[1], cyl.detachment_angle(theta0, args), rtol=rtol
    )


def test_balanced_on_top_never_releases():
    """theta0 = 0 exactly: an equilibrium; it stays on top and is never released."""
    args = cyl.default_args()
    q0, qd0 = cyl.state(jnp.asarray(0.0), jnp.asarray(0.0), args)
    traj = _contact_run(
        args, q0, qd0, jnp.asarray(3.0), jnp.array([0.0, 1.0, 2.0, 3.0])
    )
    assert traj.result == cjax.RESULTS.successful
    assert not traj.release.released
    assert traj.release.time == 3.0
    # theta1 and theta2 stay exactly put; r to round-off (XLA's fused arithmetic in
    # the compiled structured solve leaves rddot ~ 3e-16 instead of an exact 0).
    np.testing.assert_array_equal(traj.q[-1, 1:], q0[1:])
    np.testing.assert_allclose(traj.q[-1], q0, rtol=0, atol=4 * np.finfo(float).eps)
    np.testing.assert_allclose(traj.multipliers[-1, 0], args["M"] * args["g"])


def test_start_past_detachment_releases_at_once():
    """Moving too fast for the normal force to hold (M g cos theta < M (R+a)
    thetadot^2): released at t0, clearly reported, and the whole run is free flight,
    a projectile for the centre and a constant spin for theta2."""
    args = cyl.default_args()
    theta, thetadot = jnp.asarray(1.0), jnp.asarray(3.0)
    q0, qd0 = cyl.state(theta, thetadot, args)
    assert cyl.normal_force(theta, theta, args) > 0  # from rest it would hold...
    assert args["g"] * jnp.cos(theta) < (args["R"] + args["a"]) * thetadot**2
    ts = jnp.array([0.0, 0.1, 0.2, 0.4])
    traj = _contact_run(args, q0, qd0, jnp.asarray(0.4), ts)
    assert traj.result == cjax.RESULTS.successful
    rel = traj.release
    assert rel.released and rel.at_start and rel.time == 0.0
    np.testing.assert_array_equal(rel.q, q0)
    r0 = q0[0]
    x0, y0 = r0 * jnp.sin(theta), r0 * jnp.cos(theta)
    vx, vy = r0 * thetadot * jnp.cos(theta), -r0 * thetadot * jnp.sin(theta)
    r, th = traj.q[:, 0], traj.q[:, 1]
    np.testing.assert_allclose(r * jnp.sin(th), x0 + vx * ts, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(
        r * jnp.cos(th), y0 + vy * ts - args["g"] * ts**2 / 2, rtol=1e-9, atol=1e-10
    )
    np.testing.assert_allclose(traj.q[:, 2], q0[2] + qd0[2] * ts, rtol=1e-10)


@pytest.mark.slow
def test_gradients_through_the_release_match_finite_differences():
    """d/d(alpha, theta0, R) of the release time, the angle and rate at release, and
    the distance r at t1 (in free flight after release)."""

    def outputs(p):
        args = cyl.default_args(alpha=p[0], R=p[2])
        q0, qd0 = cyl.state(p[1], jnp.zeros_like(p[1]), args)
        traj = cjax.simulate(
            cyl.contact_system(),
            (0.0, 1.2),
            q0,
            qd0,
            args,
            stepsize_controller=TIGHT,
            saveat=cjax.SaveAt(
                t1=True, multipliers=False, energy=False, violation=False
            ),
        )
        rel = traj.release
        return jnp.stack([rel.time, rel.q[1], rel.qd[1], traj.q[-1, 0]])

    p = jnp.array([0.5, 0.3, 1.0])
    jac = jax.jit(jax.jacrev(outputs))(p)
    outputs_jit = jax.jit(outputs)
    for i in range(4):
        fd = finite_difference_grad(lambda x, i=i: outputs_jit(x)[i], p, rel_step=1e-5)
        np.testing.assert_allclose(jac[i], fd, rtol=2e-5, atol=1e-8)
    # And the release time's gradient against the closed form's.
    closed = jax.grad(
        lambda p: cyl.detachment_time(p[1], cyl.default_args(alpha=p[0], R=p[2]))
    )(p)
    np.testing.assert_allclose(jac[0], closed, rtol=1e-6)


def _lifted_particle():
    """A particle on the floor y >= 0 (contact multiplier = normal force >= 0), lifted
    by a force pulse F(t) = A m g u e^(1 - u), u = t / tau (peak A m g at t = tau):
    released when F = m g, it flies and lands again (re-contact, y back to 0)."""

    def lagrangian(q, qd, t, args):
        return 0.5 * args["m"] * jnp.dot(qd, qd) - args["m"] * args["g"] * q[1]

    def forces(q, qd, t, args):
        u = t / args["tau"]
        lift = args["A"] * args["m"] * args["g"] * u * jnp.exp(1 - u)
        return jnp.stack([jnp.zeros_like(lift), lift])

    floor = cjax.Unilateral(
        cjax.Holonomic(lambda q, t, args: q[1]), sign=1.0, gap=lambda q, t, a: q[1]
    )
    return cjax.LagrangianSystem(lagrangian, floor, forces)


def _release_and_landing(A, tau, g=9.81):
    """Release: A u e^(1-u) = 1 on the rising branch (u < 1). Flight: y'' = F/m - g
    from rest at y = 0, integrated in closed form with
    P(t) = A g tau^2 (u + 2) e^(1-u) (P'' = A g u e^(1-u))."""
    u_r = scipy.optimize.brentq(
        lambda u: A * u * np.exp(1 - u) - 1, 0.0, 1.0, xtol=1e-16
    )
    t_r = tau * u_r

    def p(t):
        u = t / tau
        return A * g * tau**2 * (u + 2) * np.exp(1 - u)

    def dp(t):
        u = t / tau
        return -A * g * tau * (u + 1) * np.exp(1 - u)

    def height(t):
        return p(t) - p(t_r) - dp(t_r) * (t - t_r) - g * (t - t_r) ** 2 / 2

    t_land = scipy.optimize.brentq(height, t_r + 1e-3, t_r + 100.0, xtol=1e-15)
    return t_r, u_r, t_land


def test_release_and_recontact_of_a_lifted_particle():
    system = _lifted_particle()

    @jax.jit
    def run(a, tau):
        args = {"m": jnp.asarray(2.0), "g": jnp.asarray(9.81), "A": a, "tau": tau}
        return cjax.simulate(
            system,
            (0.0, 20.0),
            jnp.array([0.0, 0.0]),
            jnp.array([1.0, 0.0]),
            args,
            stepsize_controller=TIGHT,
            saveat=cjax.SaveAt(ts=jnp.array([0.05, 19.0])),
            throw=False,
        )

    a, tau = jnp.asarray(3.0), jnp.asarray(0.5)
    traj = run(a, tau)
    # The run stops at the landing, before t1: not `successful` (the save at
    # t = 19 is inf), and the status says why.
    assert traj.result == cjax.RESULTS.recontact
    t_release, u_release, t_landing = _release_and_landing(3.0, 0.5)
    rel = traj.release
    assert rel.released and rel.recontact and not rel.at_start
    np.testing.assert_allclose(rel.time, t_release, rtol=1e-9)
    np.testing.assert_allclose(rel.recontact_time, t_landing, rtol=1e-7)
    # Before release the normal force is m g - F; after landing nothing is computed.
    u = 0.05 / 0.5
    np.testing.assert_allclose(
        traj.multipliers[0, 0], 2.0 * 9.81 * (1 - 3.0 * u * np.exp(1 - u)), rtol=1e-9
    )
    assert np.all(np.isinf(traj.q[1]))
    # d t_release / dA = -tau u / (A (1 - u)), from A u e^(1-u) = 1.
    grad = jax.grad(lambda a: run(a, tau).release.time)(a)
    np.testing.assert_allclose(
        grad, -0.5 * u_release / (3.0 * (1 - u_release)), rtol=1e-7
    )


def test_bad_unilateral_constraints():
    rows = cjax.Pfaffian(cyl.pfaffian_rows)
    with pytest.raises(ValueError, match="sign"):
        cjax.Unilateral(rows, sign=2.0)
    with pytest.raises(ValueError, match="Holonomic"):
        cjax.Unilateral(lambda q, t, a: q[0])
    contact = cjax.Pfaffian(lambda q, t, a: cyl.pfaffian_rows(q, t, a)[:1])
    no_slip = cjax.Pfaffian(lambda q, t, a: cyl.pfaffian_rows(q, t, a)[1:])
    two = cjax.LagrangianSystem(
        cyl.lagrangian, (cjax.Unilateral(contact), cjax.Unilateral(no_slip))
    )
    args = cyl.default_args()
    q0, qd0 = cyl.state(jnp.asarray(0.3), jnp.asarray(0.0), args)
    with pytest.raises(ValueError, match="one `cjax.Unilateral`"):
        cjax.simulate(two, (0.0, 1.0), q0, qd0, args)
