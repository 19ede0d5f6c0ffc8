"""Reduced coordinates agree with the full constrained system; linearisation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import pendulum, two_cylinders as cyl2


def _pendulum_embedding(s, t, args):
    return args["l"] * jnp.stack([jnp.sin(s[0]), -jnp.cos(s[0])])


def _cylinder_embedding(s, t, args):
    ratio = 1 + args["R"] / args["a"]
    return jnp.stack([args["R"] + args["a"] + 0.0 * s[0], s[0], ratio * s[0]])


def test_pendulum_reduced_equation_and_tension():
    """r = l eliminated: sddot = -(g/l) sin s; the tension comes back from the
    residual of the full Cartesian equations."""
    reduction = cjax.reduce(pendulum.system(), _pendulum_embedding)
    args = pendulum.default_args(m=1.3, l=0.9)
    s, sd = jnp.array([0.7]), jnp.array([1.1])
    sdd, lam = reduction.system.accelerations(s, sd, 0.0, args)
    assert lam.shape == (0,)
    np.testing.assert_allclose(
        sdd, pendulum.angular_acceleration(0.7, args), rtol=1e-13
    )
    full_lam = reduction.full_multipliers(s, sd, 0.0, args)
    np.testing.assert_allclose(
        full_lam, [-pendulum.tension(0.7, 1.1, args)], rtol=1e-12
    )


@pytest.mark.parametrize("alpha", [0.0, 0.6])
def test_two_cylinders_reduced_agrees_with_full(alpha):
    args = cyl2.default_args(alpha=alpha)
    reduction = cjax.reduce(cyl2.system(), _cylinder_embedding)
    theta0, theta1 = 0.2, 0.5
    thd = jnp.sqrt(cyl2.angular_velocity_squared(theta1, theta0, args))
    s, sd = jnp.array([theta1]), jnp.stack([thd])
    sdd, _ = reduction.system.accelerations(s, sd, 0.0, args)
    np.testing.assert_allclose(
        sdd, [cyl2.angular_acceleration(theta1, args)], rtol=1e-12
    )
    lam = reduction.full_multipliers(s, sd, 0.0, args)
    q, qd = cyl2.state(jnp.asarray(theta1), thd, args)
    _, lam_full = cyl2.system().accelerations(q, qd, 0.0, args)
    np.testing.assert_allclose(lam, lam_full, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(
        lam[0], cyl2.normal_force(theta1, theta0, args), rtol=1e-10
    )


def test_reduced_and_full_trajectories_agree():
    args = cyl2.default_args(alpha=0.5)
    reduction = cjax.reduce(cyl2.system(), _cylinder_embedding)
    ts = jnp.linspace(0.0, 0.6, 4)
    saveat = cjax.SaveAt(ts=ts, multipliers=False)
    reduced = cjax.simulate(
        reduction.system,
        (0.0, 0.6),
        jnp.array([0.3]),
        jnp.array([0.0]),
        args,
        saveat=saveat,
    )
    q0, qd0 = cyl2.state(jnp.asarray(0.3), jnp.asarray(0.0), args)
    full = cjax.simulate(cyl2.system(), (0.0, 0.6), q0, qd0, args, saveat=saveat)
    np.testing.assert_allclose(reduced.q[:, 0], full.q[:, 1], rtol=1e-7)
    lifted = jax.vmap(lambda s, sd, t: reduction.lift(s, sd, t, args))(
        reduced.q, reduced.qd, ts
    )
    np.testing.assert_allclose(lifted[0], full.q, rtol=1e-7)


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
def test_linearized_growth_rate_at_the_top(alpha):
    """At the top of the fixed cylinder the rolling one is unstable with growth rate
    sqrt(g / ((1 + alpha)(R + a)))."""
    args = cyl2.default_args(alpha=alpha, a=0.4, R=1.1)
    holonomic = cjax.LagrangianSystem(
        cyl2.lagrangian,
        cjax.Holonomic(
            lambda q, t, p: jnp.stack(
                [q[0] - p["R"] - p["a"], (p["R"] + p["a"]) * q[1] - p["a"] * q[2]]
            )
        ),
    )
    q, qd = cyl2.state(jnp.asarray(0.0), jnp.asarray(0.0), args)
    lin = cjax.linearize(holonomic, q, qd, args=args)
    rate = np.sqrt(args["g"] / ((1 + alpha) * (args["R"] + args["a"])))
    np.testing.assert_allclose(
        np.sort(np.asarray(lin.eigenvalues).real), [-rate, rate], rtol=1e-10
    )
    np.testing.assert_allclose(np.asarray(lin.eigenvalues).imag, 0.0, atol=1e-12)


def test_linearized_pendulum_frequency():
    args = pendulum.default_args(l=0.5)
    lin = cjax.linearize(
        pendulum.system(), jnp.array([0.0, -0.5]), jnp.zeros(2), args=args
    )
    omega = np.sqrt(args["g"] / args["l"])
    np.testing.assert_allclose(
        np.sort(np.asarray(lin.eigenvalues).imag), [-omega, omega], rtol=1e-10
    )
    np.testing.assert_allclose(np.asarray(lin.eigenvalues).real, 0.0, atol=1e-10)


@jax.jit
def _pendulum_eigenvalues(q, qd, args):
    """One compiled `linearize` of the pendulum for the careless inputs below."""
    return cjax.linearize(pendulum.system(), q, qd, args=args).eigenvalues


@pytest.mark.parametrize(
    "case, message",
    [
        ("off the rod (r = 1.3 l)", "violates the constraints"),
        ("radial velocity", "violates the constraints"),
        ("NaN in args", "NaN or inf"),
        ("inf in q", "NaN or inf"),
    ],
)
def test_linearize_refuses_points_it_cannot_linearize(case, message):
    """A point off the constraints (it used to give the frequency of a pendulum of
    length 1.3 l, sqrt(g / 1.3 l), with no word), and non-finite inputs (it used to
    give eigenvalues 0 for a NaN gravity): refused at run time, also under `jit`.
    The valid point through the same program: sqrt(g / l)."""
    args = pendulum.default_args()
    q, qd = jnp.array([0.0, -1.0]), jnp.zeros(2)
    if case.startswith("off"):
        q = 1.3 * q
    elif case.startswith("radial"):
        qd = jnp.array([0.0, 0.5])
    elif case.startswith("NaN"):
        args = dict(args, g=jnp.asarray(jnp.nan))
    else:
        q = q.at[0].set(jnp.inf)
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(_pendulum_eigenvalues(q, qd, args))
    good = pendulum.default_args()
    eigenvalues = _pendulum_eigenvalues(jnp.array([0.0, -1.0]), jnp.zeros(2), good)
    np.testing.assert_allclose(
        np.sort(np.asarray(eigenvalues).imag), [-np.sqrt(9.81), np.sqrt(9.81)]
    )


def test_linearize_refuses_a_singular_kkt_matrix():
    """A massless coordinate with a force on it (the equations of motion have no
    solution): it used to give eigenvalues 0; refused. Without the force (a free
    gauge) the pendulum's frequency, and a zero mode for the gauge."""

    def system(force):
        def lagrangian(q, qd, t, args):
            return pendulum.lagrangian(q[:2], qd[:2], t, args) - force * q[2]

        rod = cjax.Holonomic(lambda q, t, args: pendulum.rod(q[:2], t, args))
        return cjax.LagrangianSystem(lagrangian, rod)

    args = pendulum.default_args()
    q, qd = jnp.array([0.0, -1.0, 0.0]), jnp.zeros(3)
    with pytest.raises(Exception, match="singular"):
        cjax.linearize(system(2.0), q, qd, args=args)
    eigenvalues = np.asarray(cjax.linearize(system(0.0), q, qd, args=args).eigenvalues)
    omega = np.sqrt(9.81)
    np.testing.assert_allclose(
        np.sort(eigenvalues.imag), [-omega, 0, 0, omega], atol=1e-9
    )


def _wrong_radius(s, t, args):
    return 1.1 * _pendulum_embedding(s, t, args)


def _horizontal_line(s, t, args):
    # On the rod only at s = 0, where position and velocity hold but the
    # acceleration does not (no centripetal term).
    return jnp.stack([s[0], -args["l"] + 0.0 * s[0]])


@pytest.mark.parametrize(
    "embedding, s, message",
    [
        (_wrong_radius, 0.7, "violates the full system's constraints"),
        (_horizontal_line, 0.0, "violates the full system's constraints"),
    ],
)
def test_full_multipliers_refuse_an_embedding_off_the_constraints(
    embedding, s, message
):
    """The multipliers from an embedding that does not satisfy the constraints it
    eliminates used to come back without a word (-8.83 for a circle of radius 1.1 l,
    against the tension's -8.71): refused."""
    args = pendulum.default_args()
    reduction = cjax.reduce(pendulum.system(), embedding)
    with pytest.raises(Exception, match=message):
        reduction.full_multipliers(jnp.array([s]), jnp.array([1.1]), 0.0, args)


def test_full_multipliers_refuse_a_motion_the_full_system_does_not_have():
    """A falling particle held on a horizontal line by an embedding that no
    constraint of the full system imposes: no multipliers balance gravity."""
    free = cjax.LagrangianSystem(lambda q, qd, t, a: 0.5 * qd @ qd - 9.81 * q[1])
    reduction = cjax.reduce(free, lambda s, t, a: jnp.stack([s[0], 0.0 * s[0]]))
    with pytest.raises(Exception, match="no multipliers balance"):
        reduction.full_multipliers(jnp.array([0.3]), jnp.array([1.0]), 0.0)
