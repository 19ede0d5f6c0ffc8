"""Sharp edges of issue 11: free gauge directions, and float32 (no `jax_enable_x64`).

- two cylinders, alpha in {0, 0.5, 1} (vmap), released and flown past release:
  `successful`; detachment at arccos(2 cos theta0 / (3 + alpha)); the centre follows
  the projectile from the closed-form release state; the spin rate is held (alpha = 0:
  a free gauge, zero acceleration).
- pendulum + a massless coordinate that nothing acts on (both saddle-point solvers):
  the pendulum's closed-form accelerations and tension, the massless coordinate's
  acceleration 0; simulated, its velocity is held.
- the same massless coordinate with a potential gradient on it: `accelerations`
  raises "singular", `solve_accelerations` flags it, `simulate` returns
  `singular_dynamics` (never a made-up answer).
- a gauge direction that is not a coordinate (`M = m [[1, 1], [1, 1]]`, force along
  (1, 1)): a solution of `M qdd = f` with zero at the vanishing pivot; a force with a
  component along (1, -1): singular.
- random saddle-point systems with a gauge direction in ker M and ker A: consistent
  right-hand side -> a solution of the KKT equations with the unique multipliers
  (`RangeSpaceLDL` always; `FullKKTLU` either that or `singular`: its partial pivoting
  may refuse a gauge that is not along a coordinate); a force along the gauge ->
  singular; redundant constraints (even consistent) -> singular.
- float32 (subprocess, JAX_ENABLE_X64=0): exactly one UserWarning naming float32 and
  `jax_enable_x64`; every scene runs with its defaults and meets its closed form at
  the documented float32 tolerances (1e-4 relative for dynamics, 1e-5 for the
  extremum); an explicit `PIDController(rtol=1e-9, atol=1e-9)` is warned about.
- float64: explicit tolerances float64 can reach give no warning, defaults unchanged.
"""

import json
import textwrap
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import pendulum, two_cylinders as cyl

from .helpers import run_python, solve_with


TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
SOLVERS = [cjax.RangeSpaceLDL(), cjax.FullKKTLU()]
SOLVER_IDS = ["range-space", "full-lu"]


# ---------------------------------------------------------------------------------
# (A) Free gauge directions
# ---------------------------------------------------------------------------------


@jax.jit
def _fly(alpha):
    """Released from rest at theta0 = 0.3 and flown 0.3 s and 0.6 s past the
    closed-form detachment time."""
    args = cyl.default_args(alpha=alpha)
    theta0 = jnp.asarray(0.3)
    q0, qd0 = cyl.state(theta0, jnp.zeros_like(theta0), args)
    ts = cyl.detachment_time(theta0, args) + jnp.array([0.3, 0.6])
    return cjax.simulate(
        cyl.contact_system(),
        (0.0, ts[-1]),
        q0,
        qd0,
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(ts=ts),
        throw=False,
    )


def test_two_cylinders_alpha_sweep_includes_zero_and_flies_free():
    alphas = jnp.array([0.0, 0.5, 1.0])
    traj = jax.vmap(_fly)(alphas)
    np.testing.assert_array_equal(traj.result._value, cjax.RESULTS.successful._value)
    assert np.all(traj.release.released) and not np.any(traj.release.recontact)
    theta0 = 0.3
    for i, alpha in enumerate(alphas):
        args = cyl.default_args(alpha=alpha)
        theta_s = cyl.detachment_angle(theta0, args)
        np.testing.assert_allclose(
            theta_s, np.arccos(2 * np.cos(theta0) / (3 + float(alpha))), rtol=1e-14
        )
        np.testing.assert_allclose(traj.release.q[i, 1], theta_s, rtol=1e-9)
        t_s = cyl.detachment_time(theta0, args)
        np.testing.assert_allclose(traj.release.time[i], t_s, rtol=1e-8)
        # Free flight from the closed-form release state: r = R + a, rdot = 0.
        thetadot_s = jnp.sqrt(cyl.angular_velocity_squared(theta_s, theta0, args))
        r = args["R"] + args["a"]
        dt = traj.ts[i] - t_s
        x = r * jnp.sin(theta_s) + r * thetadot_s * jnp.cos(theta_s) * dt
        y = (
            r * jnp.cos(theta_s)
            - r * thetadot_s * jnp.sin(theta_s) * dt
            - args["g"] * dt**2 / 2
        )
        q = traj.q[i]
        np.testing.assert_allclose(q[:, 0] * jnp.sin(q[:, 1]), x, rtol=1e-8)
        np.testing.assert_allclose(q[:, 0] * jnp.cos(q[:, 1]), y, rtol=1e-8, atol=1e-9)
        assert np.all(q[:, 0] > r)
        # The spin: no torque (alpha > 0) or no inertia and no force (alpha = 0, a
        # free gauge with zero acceleration): the rolling rate at release is held.
        spin = (1 + args["R"] / args["a"]) * thetadot_s
        np.testing.assert_allclose(traj.qd[i, :, 2], spin, rtol=1e-8)
        np.testing.assert_allclose(q[:, 2], traj.release.q[i, 2] + spin * dt, rtol=1e-8)
        np.testing.assert_array_equal(traj.multipliers[i], 0.0)


def _pendulum_with_massless(potential: float, solver):
    """The Cartesian pendulum, plus a coordinate phi with no kinetic energy and
    potential `potential * phi` (a force -potential on it)."""

    def lagrangian(q, qd, t, args):
        return pendulum.lagrangian(q[:2], qd[:2], t, args) - potential * q[2]

    rod = cjax.Holonomic(lambda q, t, args: pendulum.rod(q[:2], t, args))
    return cjax.LagrangianSystem(lagrangian, rod, saddle_point_solver=solver)


def _pendulum_state(theta, thetadot, args, phi=0.7, phidot=0.4):
    q, qd = pendulum.state(jnp.asarray(theta), jnp.asarray(thetadot), args)
    return jnp.append(q, phi), jnp.append(qd, phidot)


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
def test_massless_free_coordinate_is_a_gauge(solver):
    system = _pendulum_with_massless(0.0, solver)
    args = pendulum.default_args()
    theta, thetadot = 0.6, 1.3
    q, qd = _pendulum_state(theta, thetadot, args)
    qdd, lam = jax.jit(system.accelerations)(q, qd, 0.0, args)
    # Circular motion: l (thdd e_theta - thd^2 e_r), e_r = (sin, -cos).
    thdd = pendulum.angular_acceleration(theta, args)
    l = args["l"]
    e_r = jnp.array([jnp.sin(theta), -jnp.cos(theta)])
    e_theta = jnp.array([jnp.cos(theta), jnp.sin(theta)])
    expected = l * (thdd * e_theta - thetadot**2 * e_r)
    np.testing.assert_allclose(qdd[:2], expected, rtol=1e-12, atol=1e-12)
    assert qdd[2] == 0.0
    np.testing.assert_allclose(
        lam, [-pendulum.tension(theta, thetadot, args)], rtol=1e-12
    )
    # Simulated: the pendulum as without phi; phi's velocity is held.
    ts = jnp.array([0.5, 1.0])
    traj = cjax.simulate(
        system,
        (0.0, 1.0),
        q,
        qd,
        args,
        stepsize_controller=TIGHT,
        saveat=cjax.SaveAt(ts=ts),
    )
    np.testing.assert_allclose(traj.qd[:, 2], qd[2], rtol=1e-14)
    np.testing.assert_allclose(traj.q[:, 2], q[2] + qd[2] * ts, rtol=1e-12)
    np.testing.assert_allclose(traj.energy, traj.energy[0], rtol=1e-9)


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
def test_massless_coordinate_with_a_force_is_refused(solver):
    system = _pendulum_with_massless(2.0, solver)
    args = pendulum.default_args()
    q, qd = _pendulum_state(0.6, 1.3, args)
    _, _, singular = jax.jit(system.solve_accelerations)(q, qd, 0.0, args)
    assert singular
    with pytest.raises(eqx.EquinoxRuntimeError, match="no inertia"):
        system.accelerations(q, qd, 0.0, args)
    traj = cjax.simulate(system, (0.0, 1.0), q, qd, args, throw=False)
    assert traj.result == cjax.RESULTS.singular_dynamics


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
def test_gauge_direction_not_along_a_coordinate(solver):
    """L = m (xd + yd)^2 / 2 - V: the direction (1, -1) has no inertia. With
    V = m g (x + y) no force acts along it (a gauge); with V = m g x one does."""
    m, g = 2.0, 9.81
    kinetic = lambda qd: 0.5 * m * (qd[0] + qd[1]) ** 2
    gauge = cjax.LagrangianSystem(
        lambda q, qd, t, a: kinetic(qd) - m * g * (q[0] + q[1]),
        saddle_point_solver=solver,
    )
    q, qd = jnp.array([0.3, -0.2]), jnp.array([0.5, 0.1])
    qdd, lam = gauge.accelerations(q, qd, 0.0)
    assert lam.shape == (0,)
    np.testing.assert_allclose(qdd[0] + qdd[1], -g, rtol=1e-14)
    assert jnp.min(jnp.abs(qdd)) == 0.0  # zero at the vanishing pivot
    forced = cjax.LagrangianSystem(
        lambda q, qd, t, a: kinetic(qd) - m * g * q[0], saddle_point_solver=solver
    )
    assert forced.solve_accelerations(q, qd, 0.0, None)[2]


def _gauge_problem(rng, n, k):
    """M positive semidefinite, A of full row rank, and a gauge direction v in
    ker M and ker A (so the KKT matrix is singular)."""
    v = rng.normal(size=n)
    v /= np.linalg.norm(v)
    proj = np.eye(n) - np.outer(v, v)
    basis = proj @ rng.normal(size=(n, n))
    mass = basis @ basis.T
    jac = rng.normal(size=(k, n)) @ proj
    return mass, jac, v


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
@pytest.mark.parametrize("n, k", [(3, 0), (3, 1), (4, 2)])
def test_saddle_point_gauge(solver, n, k):
    rng = np.random.default_rng(10 * n + k)
    mass, jac, v = _gauge_problem(rng, n, k)
    f = rng.normal(size=n)
    f_consistent = f - np.dot(f, v) * v
    bias = rng.normal(size=k)
    solve = jax.jit(solve_with(solver))
    x, lam, singular = solve(*map(jnp.asarray, (mass, jac, f_consistent, bias)))
    if isinstance(solver, cjax.FullKKTLU) and singular:
        # Right or refused: partial pivoting may leave the dependent row where a
        # later column needs it, for a gauge that is not along a coordinate.
        assert np.all(x == 0) and np.all(lam == 0)
        return
    assert not singular
    scale = 1 + np.max(np.abs(np.concatenate([x, lam])))
    np.testing.assert_allclose(mass @ x - jac.T @ lam, f_consistent, atol=1e-11 * scale)
    np.testing.assert_allclose(jac @ x, -bias, atol=1e-11 * scale)
    # The multipliers are unique (A has full rank): those of the system with the
    # gauge removed (x restricted to v-perp).
    basis = np.linalg.svd(np.eye(n) - np.outer(v, v))[0][:, : n - 1]
    reduced = np.block(
        [
            [basis.T @ mass @ basis, -(jac @ basis).T],
            [jac @ basis, np.zeros((k, k))],
        ]
    )
    ref = np.linalg.solve(reduced, np.concatenate([basis.T @ f_consistent, -bias]))
    np.testing.assert_allclose(lam, ref[n - 1 :], atol=1e-10 * scale)
    # A force along the gauge direction: no solution.
    x, lam, singular = solve(*map(jnp.asarray, (mass, jac, f_consistent + v, bias)))
    assert singular and np.all(x == 0) and np.all(lam == 0)


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
def test_consistent_redundant_constraints_stay_refused(solver):
    """A repeated constraint row with a consistent bias: the multipliers are not
    unique, so it is refused (not given one split of the force)."""
    rng = np.random.default_rng(7)
    basis = rng.normal(size=(3, 3))
    mass = basis @ basis.T
    row = rng.normal(size=3)
    jac = np.stack([row, row])
    bias = np.array([0.4, 0.4])
    _, _, singular = solve_with(solver)(
        *map(jnp.asarray, (mass, jac, rng.normal(size=3), bias))
    )
    assert singular


# ---------------------------------------------------------------------------------
# (B) float32
# ---------------------------------------------------------------------------------


_FLOAT32_SCRIPT = textwrap.dedent(
    """
    import json, warnings
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import diffrax, jax, jax.numpy as jnp
        import constrained_jax as cjax
        from constrained_jax.scenes import (catenary, cylinder_volume, dido,
            pendulum, rolling_disk, rotating_hoop, sphere_geodesic, two_cylinders)
        cyl = two_cylinders
        out = {"x64": bool(jax.config.jax_enable_x64)}
        ok = lambda r: bool(r == cjax.RESULTS.successful)
        def rel(a, b):
            a, b = jnp.asarray(a), jnp.asarray(b)
            return float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))

        # Pendulum from rest at 1 rad: back after one closed-form period; at the
        # bottom (T/4) the multiplier is -tension. Default tolerances throughout.
        args = pendulum.default_args()
        theta0 = jnp.asarray(1.0)
        q0, qd0 = pendulum.state(theta0, jnp.zeros_like(theta0), args)
        period = pendulum.period(theta0, args)
        traj = cjax.simulate(pendulum.system(), (0.0, period), q0, qd0, args,
            saveat=cjax.SaveAt(ts=jnp.stack([period / 4, period])), throw=False)
        speed = jnp.sqrt(2 * args["g"] * (1 - jnp.cos(theta0)) / args["l"])
        out["pendulum"] = {"ok": ok(traj.result), "dtype": str(traj.q.dtype),
            "period": rel(traj.q[-1], q0),
            "tension": rel(-traj.multipliers[0, 0],
                           pendulum.tension(0.0, speed, args))}

        # Two cylinders, alpha in {0, 0.5, 1} (vmap): detachment, free flight.
        def roll(alpha):
            a = cyl.default_args(alpha=alpha)
            th0 = jnp.asarray(0.3)
            q0, qd0 = cyl.state(th0, jnp.zeros_like(th0), a)
            t_s = cyl.detachment_time(th0, a)
            ts = t_s + jnp.asarray([0.3, 0.6])
            traj = cjax.simulate(cyl.contact_system(), (0.0, ts[-1]), q0, qd0, a,
                saveat=cjax.SaveAt(ts=ts), throw=False)
            th_s = cyl.detachment_angle(th0, a)
            thd_s = jnp.sqrt(cyl.angular_velocity_squared(th_s, th0, a))
            r, dt = a["R"] + a["a"], ts - t_s
            x = r * jnp.sin(th_s) + r * thd_s * jnp.cos(th_s) * dt
            y = r * jnp.cos(th_s) - r * thd_s * jnp.sin(th_s) * dt - a["g"] * dt**2 / 2
            q = traj.q
            centre = jnp.stack([q[:, 0] * jnp.sin(q[:, 1]),
                                q[:, 0] * jnp.cos(q[:, 1])], -1)
            spin = (1 + a["R"] / a["a"]) * thd_s
            return (traj.result._value, traj.release.q[1] / th_s - 1,
                    traj.release.time / t_s - 1,
                    jnp.max(jnp.abs(centre - jnp.stack([x, y], -1))) / r,
                    jnp.max(jnp.abs(traj.qd[:, 2] / spin - 1)))
        res, angle, time, flight, spin = jax.vmap(roll)(jnp.asarray([0.0, 0.5, 1.0]))
        out["two_cylinders"] = {
            "ok": bool(jnp.all(res == cjax.RESULTS.successful._value)),
            "angle": float(jnp.max(jnp.abs(angle))),
            "time": float(jnp.max(jnp.abs(time))),
            "flight": float(flight.max()), "spin": float(spin.max())}

        # Rolling disk: the closed-form circle and multipliers.
        args = rolling_disk.default_args()
        q0, qd0 = rolling_disk.initial_state(jnp.asarray(0.3), 2.0, 0.7, args)
        ts = jnp.linspace(0.0, 6.0, 4)
        traj = cjax.simulate(rolling_disk.system(), (0.0, 6.0), q0, qd0, args,
            saveat=cjax.SaveAt(ts=ts), throw=False)
        q_ref, lam_ref = rolling_disk.closed_form(ts, 0.3, 2.0, 0.7, args)
        out["rolling_disk"] = {"ok": ok(traj.result), "q": rel(traj.q, q_ref),
            "multipliers": rel(traj.multipliers, lam_ref)}

        # Rotating hoop (Projection): the Jacobi integral is conserved.
        args = rotating_hoop.default_args(omega=6.0, rho=0.5)
        q0, qd0 = rotating_hoop.state(0.4, 0.0, 0.0, args)
        ts = jnp.linspace(0.0, 3.0, 7)
        traj = cjax.simulate(rotating_hoop.system(), (0.0, 3.0), q0, qd0, args,
            stabilization=cjax.Projection(), saveat=cjax.SaveAt(ts=ts), throw=False)
        angle = lambda q, t: rotating_hoop.angle(q, t, args)
        theta = jax.vmap(angle)(traj.q, ts)
        thetadot = jax.vmap(lambda q, qd, t: jax.jvp(
            angle, (q, t), (qd, jnp.ones_like(t)))[1])(traj.q, traj.qd, ts)
        h = rotating_hoop.jacobi_integral(theta, thetadot, args)
        out["rotating_hoop"] = {"ok": ok(traj.result), "jacobi": rel(h, h[0])}

        # Cylinder volume (extremize).
        sol = cylinder_volume.solve(1.0, 1.0, throw=False)
        ref = cylinder_volume.closed_form(1.0, 1.0)
        out["cylinder_volume"] = {"ok": ok(sol.result),
            "x": rel(sol.x, jnp.stack([ref["a"], ref["h"]])),
            "volume": rel(sol.value, ref["volume"])}

        # Functionals against their closed-form values.
        refs = {"catenary": catenary.closed_form(0.0, 0.0, 1.0, 0.0, 1.5)["value"],
                "dido": dido.closed_form(1.0, 2.5)["value"],
                "sphere_geodesic": sphere_geodesic.closed_form(
                    sphere_geodesic.START, sphere_geodesic.END)["value"]}
        for name, module in [("catenary", catenary), ("dido", dido),
                             ("sphere_geodesic", sphere_geodesic)]:
            sol = module.solve(throw=False)
            out[name] = {"ok": ok(sol.result), "value": rel(sol.value, refs[name])}

        # An explicit controller float32 cannot reach: warned about, not changed.
        args = pendulum.default_args()
        q0, qd0 = pendulum.state(jnp.asarray(1.0), jnp.asarray(0.0), args)
        cjax.simulate(pendulum.system(), (0.0, 0.1), q0, qd0, args, throw=False,
            stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9))
    messages = [str(w.message) for w in caught if w.category is UserWarning]
    out["x64_warnings"] = sum(
        "jax_enable_x64" in m and "float32" in m and "stepsize" not in m[:30]
        for m in messages)
    out["controller_warnings"] = sum(
        "`stepsize_controller` has rtol=1e-09" in m for m in messages)
    print("RESULT" + json.dumps(out))
    """
)


def test_products_are_full_precision_on_every_backend():
    """Every matrix product of a public solve, the library's and the user's functions',
    is traced at `Precision.HIGHEST` (XLA:GPU's default for float32 is TF32, about
    1e-3 relative: enough to stall the float32 sphere geodesic's Newton solve).
    Checked on the lowered programs, so on a CPU too."""
    from constrained_jax.scenes import cylinder_volume, sphere_geodesic

    def precisions(fn, *inputs):
        text = jax.jit(fn).lower(*inputs).as_text()
        dots = [line for line in text.splitlines() if "dot_general" in line]
        return len(dots), sum("precision = [HIGHEST, HIGHEST]" in d for d in dots)

    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)

    def user_lagrangian(q, qd, t, args):  # a product of the user's own
        return 0.5 * qd @ jnp.diag(jnp.asarray([2.0, 1.0])) @ qd - q[1]

    free = cjax.LagrangianSystem(user_lagrangian)
    for fn, inputs in [
        (lambda: sphere_geodesic.solve(throw=False).value, ()),
        (lambda: cylinder_volume.solve(1.0, 1.0, throw=False).value, ()),
        (
            lambda t1: cjax.simulate(pendulum.system(), (0.0, t1), q0, qd0, args).q,
            (1.0,),
        ),
        (lambda q: free.accelerations(q, q, 0.0)[0], (jnp.ones(2),)),
    ]:
        total, highest = precisions(fn, *inputs)
        assert total > 0 and highest == total, (total, highest)


@pytest.fixture(scope="module")
def float32_run():
    proc = run_python(_FLOAT32_SCRIPT, timeout=1500, JAX_ENABLE_X64="0")
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT")]
    assert proc.returncode == 0 and lines, proc.stderr[-3000:]
    return json.loads(lines[-1][len("RESULT") :])


# Documented float32 tolerances (eps = 1.2e-7; default controller rtol = atol =
# 1.2e-5): 1e-4 relative for simulated closed forms, 1e-5 for the extremum, 1e-4 for
# the functionals' values.
def test_float32_scenes_meet_their_closed_forms(float32_run):
    out = float32_run
    assert out["x64"] is False
    assert out["pendulum"]["dtype"] == "float32"
    for scene in (
        "pendulum",
        "two_cylinders",
        "rolling_disk",
        "rotating_hoop",
        "cylinder_volume",
        "catenary",
        "dido",
        "sphere_geodesic",
    ):
        assert out[scene].pop("ok"), scene
    out["pendulum"].pop("dtype")
    for scene in (
        "pendulum",
        "two_cylinders",
        "rolling_disk",
        "rotating_hoop",
        "catenary",
        "dido",
        "sphere_geodesic",
    ):
        for name, error in out[scene].items():
            assert error < 1e-4, (scene, name, error)
    for name, error in out["cylinder_volume"].items():
        assert error < 1e-5, ("cylinder_volume", name, error)


def test_float32_warns_exactly_once(float32_run):
    assert float32_run["x64_warnings"] == 1
    assert float32_run["controller_warnings"] == 1


def test_float64_defaults_unchanged_and_no_warnings():
    """In float64 the defaults are the former ones (1e-8) and reachable explicit
    tolerances are not warned about; unreachable ones are."""
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(1.0), jnp.asarray(0.0), args)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        traj = cjax.simulate(
            pendulum.system(), (0.0, 0.1), q0, qd0, args, saveat=cjax.SaveAt(t1=True)
        )
    assert traj.result == cjax.RESULTS.successful
    with pytest.warns(UserWarning, match="below what float64 can reach"):
        cjax.simulate(
            pendulum.system(),
            (0.0, 0.1),
            q0,
            qd0,
            args,
            stepsize_controller=diffrax.PIDController(rtol=1e-17, atol=1e-17),
            max_steps=16,
            throw=False,
        )
    with pytest.warns(UserWarning, match="consistency_tol"):
        cjax.simulate(
            pendulum.system(),
            (0.0, 0.1),
            q0,
            qd0,
            args,
            consistency_tol=1e-17,
            throw=False,
        )
