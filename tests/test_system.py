"""Equations of motion and multipliers of constrained Lagrangian systems, against the
lecture's closed forms."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import pendulum, two_cylinders as cyl2

from .helpers import tree_allclose


@pytest.fixture(scope="module")
def cylinder_accelerations():
    system = cyl2.system()
    return jax.jit(system.accelerations)


@pytest.fixture(scope="module")
def pendulum_accelerations():
    return jax.jit(pendulum.system().accelerations)


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("theta0, theta1", [(0.1, 0.4), (0.5, 0.7), (1e-3, 0.2)])
def test_two_cylinders_multipliers(cylinder_accelerations, alpha, theta0, theta1):
    """Q_r = M g ((3+alpha) cos th - 2 cos th0)/(1+alpha), lambda_2 = -(I/a^2)(R+a)thdd,
    with thetadot^2 from energy conservation; alpha = 0 has a singular mass matrix."""
    args = cyl2.default_args(M=2.0, alpha=alpha, a=0.3, R=1.2)
    theta1dot = jnp.sqrt(cyl2.angular_velocity_squared(theta1, theta0, args))
    q, qd = cyl2.state(jnp.asarray(theta1), theta1dot, args)
    qdd, lam = cylinder_accelerations(q, qd, 0.0, args)
    thdd = cyl2.angular_acceleration(theta1, args)
    ratio = 1 + args["R"] / args["a"]
    np.testing.assert_allclose(qdd, [0.0, thdd, ratio * thdd], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        lam[0], cyl2.normal_force(theta1, theta0, args), rtol=1e-12
    )
    np.testing.assert_allclose(
        lam[1], cyl2.no_slip_multiplier(theta1, args), rtol=1e-12, atol=1e-14
    )


def test_two_cylinders_mass_matrix_singular_at_alpha_zero():
    args = cyl2.default_args(alpha=0.0)
    q, qd = cyl2.state(jnp.asarray(0.3), jnp.asarray(0.1), args)
    mass = cyl2.system().mass_matrix(q, qd, 0.0, args)
    assert np.linalg.matrix_rank(np.asarray(mass)) == 2


def test_two_cylinders_constraint_forces(cylinder_accelerations):
    """Q^c = A^T lambda = (Q_r, (R+a) lambda_2, -a lambda_2), the lecture's right-hand
    sides of the three equations of motion."""
    args = cyl2.default_args(alpha=0.4)
    theta0, theta1 = 0.2, 0.5
    thd = jnp.sqrt(cyl2.angular_velocity_squared(theta1, theta0, args))
    q, qd = cyl2.state(jnp.asarray(theta1), thd, args)
    forces = cyl2.system().constraint_forces(q, qd, 0.0, args)
    lam2 = cyl2.no_slip_multiplier(theta1, args)
    expected = [
        cyl2.normal_force(theta1, theta0, args),
        (args["R"] + args["a"]) * lam2,
        -args["a"] * lam2,
    ]
    np.testing.assert_allclose(forces, expected, rtol=1e-12)


@pytest.mark.parametrize("theta0, theta", [(0.3, 0.1), (1.2, -0.5), (2.5, 2.0)])
def test_pendulum_tension_and_acceleration(pendulum_accelerations, theta0, theta):
    args = pendulum.default_args(m=1.5, g=9.81, l=0.7)
    thd2 = 2 * args["g"] * (jnp.cos(theta) - jnp.cos(theta0)) / args["l"]
    thd = jnp.sqrt(thd2)
    q, qd = pendulum.state(jnp.asarray(theta), thd, args)
    qdd, lam = pendulum_accelerations(q, qd, 0.0, args)
    np.testing.assert_allclose(lam, [-pendulum.tension(theta, thd, args)], rtol=1e-12)
    # Cartesian acceleration of circular motion: l (thdd e_theta - thd^2 e_r).
    thdd = pendulum.angular_acceleration(theta, args)
    e_r = jnp.array([jnp.sin(theta), -jnp.cos(theta)])
    e_theta = jnp.array([jnp.cos(theta), jnp.sin(theta)])
    expected = args["l"] * (thdd * e_theta - thd2 * e_r)
    np.testing.assert_allclose(qdd, expected, rtol=1e-11, atol=1e-12)


def test_energy_function_is_the_hamiltonian_for_natural_systems():
    args = pendulum.default_args()
    q, qd = pendulum.state(jnp.asarray(0.4), jnp.asarray(1.3), args)
    energy = pendulum.system().energy(q, qd, 0.0, args)
    expected = 0.5 * args["m"] * jnp.dot(qd, qd) + args["m"] * args["g"] * q[1]
    np.testing.assert_allclose(energy, expected, rtol=1e-14)


def test_energy_rate_vanishes_along_the_constrained_motion():
    """d/dt h = dh/dq qdot + dh/dqdot qddot = 0 for the two cylinders (ideal
    constraints do no work), at a state away from the closed-form path."""
    system = cyl2.system()
    args = cyl2.default_args(alpha=0.7)
    q, qd = cyl2.state(jnp.asarray(0.9), jnp.asarray(-0.8), args)
    qdd, _ = system.accelerations(q, qd, 0.0, args)
    _, rate = jax.jvp(
        lambda q_, qd_: system.energy(q_, qd_, 0.0, args), (q, qd), (qd, qdd)
    )
    np.testing.assert_allclose(rate, 0.0, atol=1e-12)


def test_holonomic_and_pfaffian_forms_agree():
    """The lecture's two-cylinder constraints written as G = (r - R - a,
    (R+a) theta1 - a theta2) give the same accelerations and multipliers."""
    holonomic = cjax.LagrangianSystem(
        cyl2.lagrangian,
        cjax.Holonomic(
            lambda q, t, p: jnp.stack(
                [q[0] - p["R"] - p["a"], (p["R"] + p["a"]) * q[1] - p["a"] * q[2]]
            )
        ),
    )
    args = cyl2.default_args(alpha=0.3)
    q, qd = cyl2.state(jnp.asarray(0.4), jnp.asarray(0.6), args)
    out_h = holonomic.accelerations(q, qd, 0.0, args)
    out_p = cyl2.system().accelerations(q, qd, 0.0, args)
    assert tree_allclose(out_h, out_p, rtol=1e-13, atol=1e-13)


def test_rheonomic_bead_on_rotating_hoop():
    """A bead on a hoop of radius rho spinning at omega about the vertical axis, in
    Cartesian coordinates with time-dependent constraints. The reduced equation is
    thdd = sin th (omega^2 cos th - g/rho) (theta from the bottom)."""
    rho, omega, g, m = 0.8, 3.0, 9.81, 0.4

    def lagrangian(q, qd, t, args):
        return 0.5 * m * jnp.dot(qd, qd) - m * g * q[2]

    def hoop(q, t, args):
        # The hoop lies in the vertical plane through the axis at angle omega t.
        normal = jnp.stack([-jnp.sin(omega * t), jnp.cos(omega * t), 0.0 * t])
        return jnp.stack([jnp.dot(q, q) - rho**2, jnp.dot(normal, q)])

    system = cjax.LagrangianSystem(lagrangian, cjax.Holonomic(hoop))
    th, thd, t = 0.7, 0.3, 0.4
    e_h = np.array(
        [np.cos(omega * t), np.sin(omega * t), 0.0]
    )  # horizontal direction in the hoop's plane

    def position(th, t):
        e = jnp.stack([jnp.cos(omega * t), jnp.sin(omega * t), 0.0 * t])
        return rho * jnp.sin(th) * e - rho * jnp.cos(th) * jnp.array([0.0, 0.0, 1.0])

    q = position(th, t)
    _, qd = jax.jvp(
        position,
        (jnp.asarray(th), jnp.asarray(t)),
        (jnp.asarray(thd), jnp.asarray(1.0)),
    )
    qdd, _ = system.accelerations(q, qd, t, args=None)
    thdd = np.sin(th) * (omega**2 * np.cos(th) - g / rho)
    # Inertial acceleration along the hoop's tangent: rho thdd plus the projection of
    # the centripetal acceleration -omega^2 rho sin(th) e_h onto the tangent.
    e_t = np.cos(th) * e_h + np.sin(th) * np.array([0.0, 0.0, 1.0])
    expected = rho * thdd - omega**2 * rho * np.sin(th) * np.cos(th)
    np.testing.assert_allclose(np.dot(qdd, e_t), expected, rtol=1e-12)
    # And the constraints hold at acceleration level: A qdd + bias = 0.
    jac = system.constraint_jacobian(q, jnp.asarray(t), None)
    bias = system.acceleration_bias(q, qd, jnp.asarray(t), None)
    np.testing.assert_allclose(jac @ qdd + bias, 0.0, atol=1e-12)


def test_vmap_matches_loop(cylinder_accelerations):
    args = cyl2.default_args(alpha=0.5)
    thetas = jnp.linspace(0.1, 0.8, 5)
    states = jax.vmap(lambda th: cyl2.state(th, 0.3 * th, args))(thetas)
    batched = jax.vmap(lambda q, qd: cylinder_accelerations(q, qd, 0.0, args))(*states)
    for i in range(5):
        single = cylinder_accelerations(states[0][i], states[1][i], 0.0, args)
        assert tree_allclose((batched[0][i], batched[1][i]), single, rtol=1e-14)


def test_gradient_of_normal_force_wrt_alpha():
    """d Q_r / d alpha from autodiff through the KKT solve vs the closed form."""
    theta0, theta1 = 0.2, 0.6

    def normal(alpha):
        args = cyl2.default_args(alpha=alpha)
        thd = jnp.sqrt(cyl2.angular_velocity_squared(theta1, theta0, args))
        q, qd = cyl2.state(jnp.asarray(theta1), thd, args)
        return cyl2.system().accelerations(q, qd, 0.0, args)[1][0]

    def closed(alpha):
        return cyl2.normal_force(theta1, theta0, cyl2.default_args(alpha=alpha))

    for al in (0.0, 0.3, 1.0):
        np.testing.assert_allclose(
            jax.grad(normal)(al), jax.grad(closed)(al), rtol=1e-11
        )


# ------------------------------------------------------------------ bad input


def test_non_scalar_lagrangian():
    system = cjax.LagrangianSystem(lambda q, qd, t, a: qd**2)
    with pytest.raises(ValueError, match="scalar"):
        system.accelerations(jnp.zeros(2), jnp.zeros(2), 0.0)


def test_constraint_not_wrapped():
    with pytest.raises(ValueError, match="Holonomic"):
        cjax.LagrangianSystem(pendulum.lagrangian, constraints=(pendulum.rod,))


def test_pfaffian_of_wrong_shape():
    system = cjax.LagrangianSystem(
        pendulum.lagrangian, cjax.Pfaffian(lambda q, t, a: jnp.ones(3))
    )
    args = pendulum.default_args()
    with pytest.raises(ValueError, match=r"\(k, n\)"):
        system.accelerations(jnp.array([0.0, -1.0]), jnp.zeros(2), 0.0, args)


def test_singular_kkt_matrix_raises():
    """L has no kinetic term in y and no constraint fixes y: where the force -2y on y
    is nonzero there is no solution; where it vanishes (y = 0) y is a free gauge and
    gets zero acceleration."""
    system = cjax.LagrangianSystem(lambda q, qd, t, a: 0.5 * qd[0] ** 2 - q[1] ** 2)
    with pytest.raises(eqx.EquinoxRuntimeError, match="singular"):
        system.accelerations(jnp.array([0.0, 1.0]), jnp.zeros(2), 0.0)
    qdd, _ = system.accelerations(jnp.zeros(2), jnp.zeros(2), 0.0)
    np.testing.assert_array_equal(qdd, 0.0)


def test_redundant_constraints_raise():
    doubled = cjax.Holonomic(lambda q, t, a: jnp.stack([pendulum.rod(q, t, a)[0]] * 2))
    system = cjax.LagrangianSystem(pendulum.lagrangian, doubled)
    args = pendulum.default_args()
    q, qd = pendulum.state(jnp.asarray(0.3), jnp.asarray(0.1), args)
    with pytest.raises(eqx.EquinoxRuntimeError, match="singular"):
        system.accelerations(q, qd, 0.0, args)


def test_more_constraints_than_coordinates():
    system = cjax.LagrangianSystem(
        pendulum.lagrangian,
        cjax.Holonomic(lambda q, t, a: jnp.stack([q[0], q[1], q[0] + q[1]])),
    )
    with pytest.raises(ValueError, match="more constraints"):
        system.accelerations(jnp.zeros(2), jnp.zeros(2), 0.0, pendulum.default_args())
