"""Simulation of constrained systems: closed forms, invariants, drift, convergence."""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import pendulum, two_cylinders as cyl2

from .helpers import finite_difference_grad, tree_allclose


TIGHT = diffrax.PIDController(rtol=1e-10, atol=1e-10)


def _pendulum_run(stabilization, periods=1.0, num_saves=5):
    @jax.jit
    def run(theta0, args):
        q0, qd0 = pendulum.state(theta0, jnp.zeros_like(theta0), args)
        t1 = periods * pendulum.period(theta0, args)
        return cjax.simulate(
            pendulum.system(),
            (0.0, t1),
            q0,
            qd0,
            args,
            stabilization=stabilization,
            stepsize_controller=TIGHT,
            saveat=cjax.SaveAt(ts=jnp.linspace(0.0, 1.0, num_saves) * t1),
        )

    return run


@pytest.fixture(scope="module")
def pendulum_runs():
    return {
        name: _pendulum_run(stab, periods=10.0, num_saves=11)
        for name, stab in [
            ("unstabilized", cjax.Unstabilized()),
            ("baumgarte", cjax.Baumgarte(alpha=10.0, beta=10.0)),
            ("projection", cjax.Projection()),
        ]
    }


@pytest.mark.parametrize("name", ["unstabilized", "baumgarte", "projection"])
def test_pendulum_period_and_energy(pendulum_runs, name):
    """After each whole period 4 sqrt(l/g) K(sin(theta0/2)) the pendulum is back at
    its start; the energy is conserved."""
    args = pendulum.default_args(l=0.8)
    theta0 = jnp.asarray(1.2)
    traj = pendulum_runs[name](theta0, args)
    assert traj.result == cjax.RESULTS.successful
    q0, _ = pendulum.state(theta0, 0.0, args)
    np.testing.assert_allclose(traj.q, np.broadcast_to(q0, traj.q.shape), atol=1e-7)
    np.testing.assert_allclose(traj.qd, 0.0, atol=1e-6)
    # Runge-Kutta energy error grows like (local tolerance) x (steps): 1e-10 x ~2000
    # steps over these 10 periods bounds it by a few 1e-7.
    np.testing.assert_allclose(traj.energy, traj.energy[0], rtol=1e-6)


def test_constraint_drift_per_stabilization(pendulum_runs):
    """Projection holds G = 0 to round-off; Baumgarte damps the drift that the
    unstabilized index-1 formulation accumulates."""
    args = pendulum.default_args(l=0.8)
    drift = {
        name: float(jnp.max(jnp.abs(run(jnp.asarray(1.2), args).violation["position"])))
        for name, run in pendulum_runs.items()
    }
    assert drift["projection"] <= 1e-13
    assert drift["baumgarte"] < drift["unstabilized"]
    assert drift["unstabilized"] < 1e-6  # drift, not divergence, at this tolerance


@pytest.fixture(scope="module")
def cylinder_run():
    @jax.jit
    def run(theta0, args):
        q0, qd0 = cyl2.state(theta0, jnp.zeros_like(theta0), args)
        return cjax.simulate(
            cyl2.system(),
            (0.0, 0.8),
            q0,
            qd0,
            args,
            stepsize_controller=TIGHT,
            saveat=cjax.SaveAt(ts=jnp.linspace(0.0, 0.8, 9)),
        )

    return run


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
def test_two_cylinders_normal_force_along_trajectory(cylinder_run, alpha):
    """Q_r(theta1(t)) and theta1dot^2 along the attached phase match the closed forms
    (alpha = 0: singular mass matrix)."""
    args = cyl2.default_args(alpha=alpha)
    theta0 = jnp.asarray(0.3)
    traj = cylinder_run(theta0, args)
    theta = traj.q[:, 1]
    assert float(theta[-1]) > float(theta0) + 0.3  # it really rolled
    np.testing.assert_allclose(
        traj.multipliers[:, 0], cyl2.normal_force(theta, theta0, args), atol=1e-7
    )
    np.testing.assert_allclose(
        traj.qd[:, 1] ** 2,
        cyl2.angular_velocity_squared(theta, theta0, args),
        atol=1e-8,
    )
    # Contact and no slip hold; the force of constraint on r is the normal force.
    np.testing.assert_allclose(traj.q[:, 0], args["R"] + args["a"], rtol=1e-9)
    np.testing.assert_allclose(traj.constraint_forces[:, 0], traj.multipliers[:, 0])


def test_derived_quantities_at_saves_are_the_systems(cylinder_run):
    """What `simulate` derives at the saved states (the multipliers by a loop of the
    unbatched KKT solve, the rest batched; at a single save by plain calls) is what
    the system's own methods give at those states."""
    args = cyl2.default_args(alpha=0.5)
    system = cyl2.system()

    @jax.jit
    def one_save(theta0, args):
        q0, qd0 = cyl2.state(theta0, jnp.zeros_like(theta0), args)
        return cjax.simulate(
            system, (0.0, 0.8), q0, qd0, args, stepsize_controller=TIGHT,
            saveat=cjax.SaveAt(ts=jnp.array([0.5])),
        )  # fmt: skip

    theta0 = jnp.asarray(0.3)
    for traj in (cylinder_run(theta0, args), one_save(theta0, args)):
        assert traj.result == cjax.RESULTS.successful
        for i in range(traj.ts.shape[0]):
            q, qd, t = traj.q[i], traj.qd[i], traj.ts[i]
            _, lam = system.accelerations(q, qd, t, args)
            np.testing.assert_allclose(traj.multipliers[i], lam, rtol=1e-12)
            np.testing.assert_allclose(
                traj.constraint_forces[i],
                system.constraint_forces(q, qd, t, args),
                rtol=1e-12,
                atol=1e-12,
            )
            np.testing.assert_allclose(
                traj.energy[i], system.energy(q, qd, t, args), rtol=1e-13
            )
            np.testing.assert_allclose(
                traj.violation["position"][i],
                system.holonomic_residual(q, t, args),
                atol=1e-15,
            )
            np.testing.assert_allclose(
                traj.violation["velocity"][i],
                system.velocity_residual(q, qd, t, args),
                atol=1e-15,
            )
    assert one_save(theta0, args).multipliers.shape == (1, 2)


def test_vmap_matches_loop(cylinder_run):
    args = cyl2.default_args(alpha=0.5)
    thetas = jnp.array([0.1, 0.2, 0.3])
    batched = jax.vmap(lambda th: cylinder_run(th, args))(thetas)
    for i, th in enumerate(thetas):
        single = cylinder_run(th, args)
        assert tree_allclose(batched.q[i], single.q, rtol=1e-12, atol=1e-13)
        assert tree_allclose(
            batched.multipliers[i], single.multipliers, rtol=1e-12, atol=1e-13
        )


def test_gradient_wrt_parameters_matches_finite_differences():
    """d theta1(t) / d alpha through the whole simulation."""

    def final_angle(p):
        args = cyl2.default_args(alpha=p[0], R=p[1])
        q0, qd0 = cyl2.state(jnp.asarray(0.3), jnp.asarray(0.0), args)
        traj = cjax.simulate(
            cyl2.system(),
            (0.0, 0.5),
            q0,
            qd0,
            args,
            stepsize_controller=TIGHT,
            saveat=cjax.SaveAt(t1=True, multipliers=False),
        )
        return traj.q[-1, 1]

    p = jnp.array([0.5, 1.0])
    grad = jax.grad(final_angle)(p)
    fd = finite_difference_grad(final_angle, p, rel_step=1e-5)
    np.testing.assert_allclose(grad, fd, rtol=1e-5)
    assert grad[0] < 0  # more rotational inertia rolls off more slowly


def test_convergence_order_is_the_solvers():
    """Fixed steps of Heun's method (order 2): the error at a generic time falls like
    dt^2 (slope of log error against log dt), against a tight Tsit5 reference.
    (At a whole period the pendulum is at rest, where a phase error costs only its
    square: a generic time avoids that superconvergence.)"""
    args = pendulum.default_args()
    theta0 = jnp.asarray(0.8)
    q0, qd0 = pendulum.state(theta0, 0.0, args)
    t1 = 0.3 * pendulum.period(theta0, args)
    reference = cjax.simulate(
        pendulum.system(),
        (0.0, t1),
        q0,
        qd0,
        args,
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
        saveat=cjax.SaveAt(t1=True),
    ).q[-1]

    steps = np.array([50, 100, 200, 400])

    # The step traced and one `max_steps` for all: one compiled program for the four
    # step sizes (fixed steps: `max_steps` only bounds the loop, the steps taken are
    # `num_steps` whatever it is).
    @jax.jit
    def final_q(dt0):
        traj = cjax.simulate(
            pendulum.system(),
            (0.0, t1),
            q0,
            qd0,
            args,
            solver=diffrax.Heun(),
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=dt0,
            max_steps=int(steps.max()) + 1,
            saveat=cjax.SaveAt(t1=True, multipliers=False, energy=False),
        )
        return traj.q[-1]

    def error(num_steps):
        return float(jnp.linalg.norm(final_q(t1 / num_steps) - reference))

    errors = np.array([error(int(s)) for s in steps])
    slope = np.polyfit(np.log(1.0 / steps), np.log(errors), 1)[0]
    assert 1.8 < slope < 2.3, (errors, slope)


def test_inconsistent_initial_state():
    system = pendulum.system()
    args = pendulum.default_args()
    q0 = jnp.array([0.3, -0.9])  # |q0| != l
    qd0 = jnp.array([0.5, 0.2])  # not tangent
    traj = cjax.simulate(system, (0.0, 0.1), q0, qd0, args, throw=False)
    assert traj.result == cjax.RESULTS.inconsistent_initial_state
    with pytest.raises(eqx.EquinoxRuntimeError, match="consistent_initial_state"):
        cjax.simulate(system, (0.0, 0.1), q0, qd0, args)
    q0c, qd0c = cjax.consistent_initial_state(system, q0, qd0, 0.0, args)
    np.testing.assert_allclose(jnp.linalg.norm(q0c), args["l"], rtol=1e-12)
    np.testing.assert_allclose(jnp.dot(q0c, qd0c), 0.0, atol=1e-12)
    # The projected state is the closest one: q0c is along q0 (the metric is m I).
    np.testing.assert_allclose(q0c / jnp.linalg.norm(q0c), q0 / jnp.linalg.norm(q0))
    traj = cjax.simulate(system, (0.0, 0.1), q0c, qd0c, args)
    assert traj.result == cjax.RESULTS.successful


def test_consistent_initial_state_refuses_what_it_cannot_project():
    """At the origin the rod's Jacobian vanishes and no Gauss-Newton step moves: the
    origin used to come back unchanged (G = -l) without a word. Refused at run time,
    also under `jit`; from a far start (|q0| = 1e6 l) it converges."""
    system = pendulum.system()
    args = pendulum.default_args()
    project = jax.jit(
        lambda q0, qd0: cjax.consistent_initial_state(system, q0, qd0, 0.0, args)
    )
    with pytest.raises(Exception, match="still violates"):
        jax.block_until_ready(project(jnp.zeros(2), jnp.array([0.3, 0.4])))
    q0c, qd0c = project(jnp.array([1e6, -1e6]), jnp.array([0.3, 0.4]))
    np.testing.assert_allclose(jnp.linalg.norm(q0c), args["l"], rtol=1e-12)
    np.testing.assert_allclose(q0c, jnp.array([1.0, -1.0]) / jnp.sqrt(2.0))
    np.testing.assert_allclose(jnp.dot(q0c, qd0c), 0.0, atol=1e-12)


def test_nan_parameters_and_step_budget():
    system = pendulum.system()
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)
    bad = dict(args, g=jnp.asarray(jnp.nan))
    traj = cjax.simulate(system, (0.0, 0.1), q0, qd0, bad, throw=False)
    assert traj.result == cjax.RESULTS.invalid_input
    traj = cjax.simulate(system, (0.0, 10.0), q0, qd0, args, max_steps=5, throw=False)
    assert traj.result == cjax.RESULTS.max_steps_reached


def test_bad_arguments():
    system = pendulum.system()
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)
    with pytest.raises(ValueError, match="stabilization"):
        cjax.simulate(system, (0.0, 1.0), q0, qd0, args, stabilization="projection")
    with pytest.raises(ValueError, match="saves nothing"):
        cjax.SaveAt()
    with pytest.raises(ValueError, match="same shape"):
        cjax.simulate(system, (0.0, 1.0), q0, qd0[:1], args)


def test_singular_dynamics_is_reported():
    """A constraint stated twice makes the KKT matrix singular: the run fails with
    `RESULTS.singular_dynamics` (also when nothing but the final state is saved),
    never with NaN states reported as success."""
    base = pendulum.system()
    system = cjax.LagrangianSystem(
        base.lagrangian, (base.constraints[0], base.constraints[0])
    )
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)
    for saveat in (cjax.SaveAt(t1=True, multipliers=False), cjax.SaveAt(t1=True)):
        traj = cjax.simulate(
            system, (0.0, 1.0), q0, qd0, args, saveat=saveat, max_steps=64, throw=False
        )
        assert traj.result == cjax.RESULTS.singular_dynamics
    with pytest.raises(eqx.EquinoxRuntimeError, match="singular"):
        cjax.simulate(system, (0.0, 1.0), q0, qd0, args, max_steps=64)


@pytest.mark.parametrize("stabilization", [cjax.Unstabilized(), cjax.Projection()])
def test_saved_multipliers_at_t1_alone(stabilization):
    """`SaveAt(t1=True)` computes the multipliers and the singular check with one
    solve (the saved state is the last one reached): the same as the general path of
    `SaveAt(ts=[t1])` (a solve at the saved state and one at the end state), for a
    run that gets to `t1`, for one that stops
    short (`max_steps`: not reached, zeros) and for one refused (`invalid_input`);
    against the closed-form normal force too."""
    args = cyl2.default_args(alpha=0.5)

    @functools.partial(jax.jit, static_argnames=("alone", "max_steps"))
    def run(theta0, args, alone, max_steps=4096):
        q0, qd0 = cyl2.state(theta0, jnp.zeros_like(theta0), args)
        saveat = cjax.SaveAt(t1=True) if alone else cjax.SaveAt(ts=jnp.array([0.8]))
        return cjax.simulate(
            cyl2.system(), (0.0, 0.8), q0, qd0, args, stabilization=stabilization,
            stepsize_controller=TIGHT, saveat=saveat, max_steps=max_steps,
            throw=False,
        )  # fmt: skip

    theta0 = jnp.asarray(0.2)
    for max_steps, arg in ((4096, theta0), (3, theta0), (4096, jnp.nan)):
        alone = run(arg, args, True, max_steps)
        batched = run(arg, args, False, max_steps)
        assert alone.result == batched.result
        np.testing.assert_allclose(
            alone.multipliers, batched.multipliers, rtol=1e-12, atol=1e-12
        )
        np.testing.assert_allclose(
            alone.constraint_forces, batched.constraint_forces, rtol=1e-12, atol=1e-12
        )
    assert run(theta0, args, True, 3).result == cjax.RESULTS.max_steps_reached
    assert run(jnp.nan, args, True).result == cjax.RESULTS.invalid_input
    ok = run(theta0, args, True)
    assert ok.result == cjax.RESULTS.successful
    theta = ok.q[-1, 1]
    np.testing.assert_allclose(
        ok.multipliers[-1, 0], cyl2.normal_force(theta, theta0, args), atol=1e-7
    )


def test_gradient_wrt_initial_state_matches_finite_differences():
    """d x(t1) / d(q0, qd0) through the simulation, along admissible perturbations
    (the initial state is built from (theta0, thetadot0), so it stays consistent)."""
    args = pendulum.default_args()

    @jax.jit
    def final_x(p):
        q0, qd0 = pendulum.state(p[0], p[1], args)
        traj = cjax.simulate(
            pendulum.system(),
            (0.0, 0.7),
            q0,
            qd0,
            args,
            stepsize_controller=TIGHT,
            saveat=cjax.SaveAt(t1=True, multipliers=False, energy=False),
        )
        return traj.q[-1, 0] + 0.3 * traj.qd[-1, 1]

    p = jnp.array([0.6, -0.4])
    grad = jax.jit(jax.grad(final_x))(p)
    fd = finite_difference_grad(final_x, p, rel_step=1e-5)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-8)


def test_projection_with_an_implicit_solver():
    """`Projection` wraps an implicit diffrax solver (Kvaerno5): after a whole
    closed-form period the pendulum is back at its start, and the constraint holds to
    round-off at every saved time."""
    args = pendulum.default_args()
    theta0 = jnp.asarray(0.9)
    q0, qd0 = pendulum.state(theta0, jnp.asarray(0.0), args)
    t1 = pendulum.period(theta0, args)
    traj = cjax.simulate(
        pendulum.system(),
        (0.0, t1),
        q0,
        qd0,
        args,
        solver=diffrax.Kvaerno5(),
        stabilization=cjax.Projection(),
        stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9),
        saveat=cjax.SaveAt(ts=jnp.linspace(0.0, 1.0, 6) * t1, multipliers=False),
    )
    np.testing.assert_allclose(traj.q[-1], q0, atol=1e-6)
    assert np.max(np.abs(traj.violation["position"])) < 1e-13
    assert np.max(np.abs(traj.violation["velocity"])) < 1e-12


def test_float32_simulation():
    """Float32 inputs run in float32 end to end, at float32 accuracy: a quarter of a
    closed-form period later the released pendulum is at the bottom, x = 0."""
    args = {k: jnp.asarray(v, jnp.float32) for k, v in pendulum.default_args().items()}
    theta0 = jnp.asarray(0.5, jnp.float32)
    q0, qd0 = pendulum.state(theta0, jnp.zeros_like(theta0), args)
    quarter = 0.25 * pendulum.period(theta0, args)
    traj = cjax.simulate(
        pendulum.system(),
        (jnp.zeros_like(quarter), quarter),
        q0,
        qd0,
        args,
        stabilization=cjax.Projection(),
        stepsize_controller=diffrax.PIDController(rtol=1e-5, atol=1e-5),
        saveat=cjax.SaveAt(t1=True),
    )
    assert traj.q.dtype == jnp.float32 and traj.multipliers.dtype == jnp.float32
    assert traj.result == cjax.RESULTS.successful
    np.testing.assert_allclose(traj.q[-1, 0], 0.0, atol=1e-4)
    np.testing.assert_allclose(traj.q[-1, 1], -args["l"], rtol=1e-5)
    # The tension at the bottom, m g (3 - 2 cos theta0), is the multiplier's magnitude.
    tension = args["m"] * args["g"] * (3 - 2 * jnp.cos(theta0))
    np.testing.assert_allclose(-traj.multipliers[-1, 0], tension, rtol=1e-4)


def test_fixed_step_blow_up_is_not_success():
    """Explicit Euler with far too large fixed steps on the pendulum blows up to
    inf/NaN; diffrax does not check fixed steps, `simulate` does."""
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(1.0), jnp.asarray(0.0), args)
    traj = cjax.simulate(
        pendulum.system(),
        (0.0, 2000.0),
        q0,
        qd0,
        args,
        solver=diffrax.Euler(),
        stepsize_controller=diffrax.ConstantStepSize(),
        dt0=0.5,
        saveat=cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False),
        throw=False,
    )
    assert not np.all(np.isfinite(traj.q))
    # Stopped at the first accepted step off the manifold (issue 11), before inf.
    assert traj.result == cjax.RESULTS.diverged


def test_progress_meter_reports_and_changes_nothing(capfd):
    """diffrax's progress meter is passed through: it prints, and the answer is the
    same as without it."""
    system = pendulum.system()
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)
    plain = cjax.simulate(system, (0.0, 1.0), q0, qd0, args)
    metered = cjax.simulate(
        system,
        (0.0, 1.0),
        q0,
        qd0,
        args,
        progress_meter=diffrax.TextProgressMeter(minimum_increase=0.5),
    )
    assert "100.00%" in capfd.readouterr().out
    assert tree_allclose(plain.q, metered.q, rtol=0.0, atol=0.0)
    with pytest.raises(ValueError, match="progress meter"):
        cjax.simulate(system, (0.0, 1.0), q0, qd0, args, progress_meter="tqdm")


def test_variational_integrator_refuses_a_progress_meter():
    """The variational integrator runs its own loop, not diffrax's: a progress meter
    is refused at trace time (not silently ignored), saying what to use instead."""
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)
    vi = dict(solver=cjax.VariationalIntegrator(), dt0=0.01)
    meter = diffrax.TextProgressMeter()
    with pytest.raises(ValueError, match="progress_meter.*variational integrator"):
        cjax.simulate(
            pendulum.system(), (0.0, 1.0), q0, qd0, args, progress_meter=meter, **vi
        )


def test_t1_floor_is_bitwise_diffrax(diffrax_patch):
    """With the opt-in diffrax patch (`cjax.settings.use_diffrax_patch`), diffrax's
    `t1 - 100 ULP` floor (100 chained `prevbefore`s) comes out of the patch's looped
    chain bit for bit, at the edges of the floating-point range too, under `jit`,
    `vmap` and `jvp`; and the program of a `simulate` with a traced `t1` holds a
    loop, not 100 unrolled `nextafter`s. Without it (the default), the program is
    plain diffrax's."""
    import equinox.internal as eqxi
    from diffrax import _integrate

    from constrained_jax import _compat as floor

    assert floor.diffrax_patch_available(), "the pinned diffrax should be patchable"

    def chain(prevbefore):
        def fn(t):
            for _ in range(100):
                t = prevbefore(t)
            return t

        return fn

    tiny = np.finfo(np.float64).tiny
    edges = [0.0, -0.0, 1.0, -1.0, 0.8, 3e-308, 5e-324, tiny, -tiny, 1e300]
    edges += [np.finfo(np.float64).max, np.inf, -np.inf, np.nan, 2.0**52, 1 + 2**-52]
    for dtype, view in ((np.float64, np.int64), (np.float32, np.int32)):
        with np.errstate(over="ignore"):  # float64's max is inf in float32
            x = jnp.asarray(np.asarray(edges, np.float64).astype(dtype))
        want = jax.jit(jax.vmap(chain(eqxi.prevbefore)))(x)
        got = jax.jit(jax.vmap(chain(floor.prevbefore)))(x)
        np.testing.assert_array_equal(
            np.asarray(got).view(view), np.asarray(want).view(view)
        )
        for xi in x[:6]:
            assert jax.jit(chain(floor.prevbefore))(xi) == jax.jit(
                chain(eqxi.prevbefore)
            )(xi)
    value, tangent = jax.jvp(chain(floor.prevbefore), (jnp.asarray(0.8),), (1.0,))
    assert value == chain(eqxi.prevbefore)(jnp.asarray(0.8)) and tangent == 1.0

    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)

    def run(t1):
        return cjax.simulate(
            pendulum.system(), (0.0, t1), q0, qd0, args, saveat=cjax.SaveAt(t1=True)
        ).q

    def next_afters(patch: bool) -> int:
        diffrax_patch(patch)
        text = jax.jit(run).lower(jnp.asarray(1.0)).as_text()
        assert _integrate.eqxi is eqxi  # diffrax is left as it was
        return text.count("next_after")

    # (The unrolled calls before the loop are traced, unused, and dropped by `jit`.)
    assert next_afters(True) < 10
    assert next_afters(False) >= 100
