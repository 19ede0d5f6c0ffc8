"""The nonholonomic and rheonomic scenes, simulated, against their closed forms and
invariants."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import constrained_jax as cjax
from constrained_jax.scenes import rolling_disk as disk, rotating_hoop as hoop


TIGHT = diffrax.PIDController(rtol=1e-10, atol=1e-10)


def test_rolling_disk_moves_on_a_circle():
    args = disk.default_args()
    theta0, nu, omega = 0.3, 2.0, 0.7
    q0, qd0 = disk.initial_state(jnp.asarray(theta0), nu, omega, args)
    ts = jnp.linspace(0.0, 6.0, 7)
    traj = cjax.simulate(
        disk.system(),
        (0.0, 6.0),
        q0,
        qd0,
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(ts=ts),
    )
    q_ref, lam_ref = disk.closed_form(ts, theta0, nu, omega, args)
    np.testing.assert_allclose(traj.q, q_ref, atol=1e-8)
    np.testing.assert_allclose(traj.multipliers, lam_ref, atol=1e-8)
    # No holonomic constraint: no position violation to report; velocity one holds.
    assert traj.violation["position"].shape == (7, 0)
    np.testing.assert_allclose(traj.violation["velocity"], 0.0, atol=1e-9)
    np.testing.assert_allclose(traj.energy, traj.energy[0], rtol=1e-9)


def test_rotating_hoop_acceleration_and_jacobi_integral():
    args = hoop.default_args(omega=6.0, rho=0.5)
    theta0, t0 = 0.4, 0.0
    q0, qd0 = hoop.state(theta0, 0.0, t0, args)
    qdd, _ = hoop.system().accelerations(q0, qd0, t0, args)
    # Second derivative of the position along the hoop at thetadot = 0:
    # d^2/dt^2 position(theta(t), t) = dposition/dtheta thetaddot + d^2position/dt^2.
    thdd = hoop.angular_acceleration(theta0, args)
    d_theta = jax.jacfwd(hoop.position)(jnp.asarray(theta0), jnp.asarray(t0), args)
    d_tt = jax.jacfwd(jax.jacfwd(hoop.position, argnums=1), argnums=1)(
        jnp.asarray(theta0), jnp.asarray(t0), args
    )
    np.testing.assert_allclose(qdd, d_theta * thdd + d_tt, atol=1e-12)

    ts = jnp.linspace(0.0, 3.0, 13)
    traj = cjax.simulate(
        hoop.system(),
        (0.0, 3.0),
        q0,
        qd0,
        args,
        stepsize_controller=TIGHT,
        stabilization=cjax.Projection(),
        saveat=cjax.SaveAt(ts=ts),
    )
    theta = jax.vmap(lambda q, t: hoop.angle(q, t, args))(traj.q, ts)
    thetadot = jax.vmap(
        lambda q, qd, t: jax.jvp(
            lambda q_, t_: hoop.angle(q_, t_, args), (q, t), (qd, 1.0)
        )[1]
    )(traj.q, traj.qd, ts)
    h = hoop.jacobi_integral(theta, thetadot, args)
    np.testing.assert_allclose(h, h[0], atol=1e-8 * float(jnp.abs(h[0])))
    # The inertial energy is not conserved: the drive does work.
    assert float(jnp.max(traj.energy) - jnp.min(traj.energy)) > 1e-3
    # The bead oscillates about cos(theta*) = g/(rho omega^2), not about the bottom.
    theta_star = np.arccos(args["g"] / (args["rho"] * args["omega"] ** 2))
    assert float(jnp.min(theta)) < theta_star < float(jnp.max(theta))
