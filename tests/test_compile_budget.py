"""Structural facts of the compiled `simulate` program (no timings: those are in
benchmarks/compile_time.py), and that the smaller program gives the same answers."""

import diffrax
import equinox as eqx
import jax
import jax.extend as jex
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import pendulum, two_cylinders as cyl2


def _run(saveat, max_steps=4096, dt0=None, throw=False):
    args = pendulum.default_args()
    q0, qd0 = pendulum.state(jnp.asarray(0.5), jnp.asarray(0.0), args)

    def run(q0, qd0, args):
        return cjax.simulate(
            pendulum.system(),
            (0.0, 1.3),
            q0,
            qd0,
            args,
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            saveat=saveat,
            max_steps=max_steps,
            dt0=dt0,
            throw=throw,
        )

    return run, (q0, qd0, args)


def _num_while(jaxpr) -> int:
    """`while` loops in a closed jaxpr, nested ones included."""
    count = 0
    for eqn in jaxpr.eqns:
        count += eqn.primitive.name == "while"
        for sub in jex.core.jaxprs_in_params(eqn.params):
            count += _num_while(sub)
    return count


def test_saving_only_the_ends_has_no_save_loop():
    # `SaveAt(t0=True, t1=True)` uses diffrax's own end saves, not the loop that
    # interpolates at save times: one `while` fewer than the same times as `ts`.
    ends, inputs = _run(cjax.SaveAt(t0=True, t1=True))
    grid, _ = _run(cjax.SaveAt(ts=jnp.asarray([0.0, 1.3])))
    num_ends = _num_while(jax.make_jaxpr(ends)(*inputs).jaxpr)
    num_grid = _num_while(jax.make_jaxpr(grid)(*inputs).jaxpr)
    assert num_ends == num_grid - 1


def test_saving_only_the_ends_matches_the_grid():
    # A full run, one stopped at `max_steps`, and one stopped before its first
    # accepted step (both ends `inf`, as diffrax leaves save times not reached).
    for max_steps, dt0 in ((4096, None), (3, None), (1, 1.0)):
        ends, inputs = _run(cjax.SaveAt(t0=True, t1=True), max_steps, dt0)
        grid, _ = _run(cjax.SaveAt(ts=jnp.asarray([0.0, 1.3])), max_steps, dt0)
        a, b = jax.jit(ends)(*inputs), jax.jit(grid)(*inputs)
        assert a.result == b.result
        assert (a.result == cjax.RESULTS.successful) == (max_steps > 3)
        assert np.all(np.isinf(a.q[0])) == (dt0 is not None)
        np.testing.assert_array_equal(a.ts, b.ts)
        for x, y in [
            (a.q, b.q),
            (a.qd, b.qd),
            (a.multipliers, b.multipliers),
            (a.energy, b.energy),
            (a.violation["position"], b.violation["position"]),
        ]:
            # The end not reached is `inf` in both.
            np.testing.assert_array_equal(np.isinf(x), np.isinf(y))
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)
        # Only the ends: `t1` alone too.
        last, _ = _run(cjax.SaveAt(t1=True), max_steps, dt0)
        c = jax.jit(last)(*inputs)
        np.testing.assert_allclose(c.q, a.q[1:], rtol=1e-12, atol=1e-12)


def _fresh(system):
    """`system` with a new Lagrangian function object: nothing of it is cached yet."""

    def lagrangian(q, qd, t, args):
        return system.lagrangian(q, qd, t, args)

    return eqx.tree_at(lambda s: s.lagrangian, system, lagrangian)


def _count_equations(monkeypatch, fn, *inputs) -> int:
    """How many times tracing `fn` traces the equations of motion of a system."""
    calls = []
    original = cjax.LagrangianSystem.saddle_point_system

    def counted(self, *args):
        calls.append(None)
        return original(self, *args)

    monkeypatch.setattr(cjax.LagrangianSystem, "saddle_point_system", counted)
    # (In JAX's default promotion mode: diffrax checks the vector field in the
    # "standard" one, which would otherwise be a second trace under the tests'
    # "strict" mode.)
    with jax.numpy_dtype_promotion("standard"):
        jax.make_jaxpr(fn)(*inputs)
    return len(calls)


def test_equations_traced_once_per_system(monkeypatch):
    # Each trace of the equations adds a copy of the derivatives of the Lagrangian to
    # the traced program: the vector field (diffrax's initial step, the stages), the
    # release event, the watched multiplier, the saved multipliers and the singular
    # check all reuse one trace per system: a release run traces the attached system,
    # the free one (without the contact's rows) and, for the quantities at the
    # saves, the system with the rows held at each save as data.
    args = cyl2.default_args()
    q0, qd0 = cyl2.state(jnp.asarray(0.2), jnp.asarray(0.0), args)
    controller = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    for system, num_systems in ((cyl2.system(), 1), (cyl2.contact_system(), 3)):
        system = _fresh(system)

        def run(q0, qd0, args, system=system):
            return cjax.simulate(
                system,
                (0.0, 1.5),
                q0,
                qd0,
                args,
                stepsize_controller=controller,
                saveat=cjax.SaveAt(ts=jnp.linspace(0.0, 1.5, 4)),
                throw=False,
            )

        assert _count_equations(monkeypatch, run, q0, qd0, args) == num_systems


def _compile_messages(*calls):
    """JAX's compile-log messages during each of `calls` (one list per call)."""
    import logging

    messages = []

    class _Collect(logging.Handler):
        def emit(self, record):
            messages.append(record.getMessage())

    handler = _Collect()
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    out = []
    try:
        with jax.log_compiles():
            for call in calls:
                start = len(messages)
                call()
                out.append(
                    [
                        m
                        for m in messages[start:]
                        if m.startswith("Finished XLA compilation")
                    ]
                )
    finally:
        logger.removeHandler(handler)
    return out


def test_throw_does_not_recompile_the_solve():
    """`throw` is applied after the compiled core of each solve: the same `simulate`
    with `throw=True` after `throw=False` compiles only the small check (no second
    copy of the run), and still raises on a failed run."""
    quiet, inputs = _run(cjax.SaveAt(t1=True))
    loud, _ = _run(cjax.SaveAt(t1=True), throw=True)
    first, second = _compile_messages(lambda: quiet(*inputs), lambda: loud(*inputs))
    assert any("_simulate" in m for m in first), first
    assert not any("_simulate" in m for m in second), second
    out_of_steps, _ = _run(cjax.SaveAt(t1=True), max_steps=3, throw=True)
    with pytest.raises(Exception, match="max_steps|maximum number of"):
        out_of_steps(*inputs)


def test_another_step_size_does_not_recompile():
    """`dt0` is traced: a second step size reuses the compiled `simulate` (a
    convergence study or a sweep over `dt0` compiles once), and gives another
    answer (it is used)."""
    coarse, inputs = _run(cjax.SaveAt(t1=True), dt0=0.01)
    fine, _ = _run(cjax.SaveAt(t1=True), dt0=0.02)
    out = {}
    first, second = _compile_messages(
        lambda: out.setdefault("coarse", coarse(*inputs)),
        lambda: out.setdefault("fine", fine(*inputs)),
    )
    assert any("_simulate" in m for m in first), first
    assert not any("_simulate" in m for m in second), second
    for traj in out.values():
        assert traj.result == cjax.RESULTS.successful
    assert out["coarse"].stats["num_steps"] != out["fine"].stats["num_steps"]


def _callbacks(jaxpr) -> list[str]:
    """The host-callback primitives in a closed jaxpr, nested ones included."""
    found = []
    for eqn in jaxpr.eqns:
        if "callback" in eqn.primitive.name:
            found.append(eqn.primitive.name)
        for sub in jex.core.jaxprs_in_params(eqn.params):
            found += _callbacks(sub)
    return found


def test_simulate_and_shooting_programs_have_no_host_callbacks(diffrax_patch):
    # JAX never writes a program with host callbacks to its persistent compilation
    # cache (`cjax.enable_compilation_cache`). diffrax checks traced save times with
    # `equinox.error_if`s (host callbacks); `simulate` checks them itself (a traced
    # bad grid is `RESULTS.invalid_time_grid`, test_sharp_edges_dynamics.py) and,
    # with the opt-in diffrax patch (`cjax.settings.use_diffrax_patch`), drops
    # diffrax's. Attached, release and contact-event runs, save times traced.
    from constrained_jax.scenes import bouncing_ball as ball

    assert diffrax_patch(True)

    ts = jnp.linspace(0.0, 1.0, 5)
    cases = []
    args = cyl2.default_args()
    q0, qd0 = cyl2.state(jnp.asarray(0.2), jnp.asarray(0.0), args)
    for system in (cyl2.system(), cyl2.contact_system()):
        cases.append((system, q0, qd0, args, {}))
    args = ball.default_args()
    q0, qd0 = ball.state(1.0, 0.1)
    cases.append((ball.system(), q0, qd0, args, {"max_events": 3}))
    for system, q0, qd0, args, options in cases:

        def run(q0, qd0, args, ts, system=system, options=options):
            return cjax.simulate(
                system,
                (0.0, 1.0),
                q0,
                qd0,
                args,
                saveat=cjax.SaveAt(ts=ts),
                throw=False,
                **options,
            )

        with jax.numpy_dtype_promotion("standard"):
            jaxpr = jax.make_jaxpr(run)(q0, qd0, args, ts)
        assert _callbacks(jaxpr.jaxpr) == []
    # The same for `solve_shooting`, which saves at its Chebyshev nodes.
    from constrained_jax.scenes import catenary

    def shoot(args):
        return cjax.solve_shooting(
            catenary.functional(-1.95, 0.0, 1.38, 0.5),
            args,
            slope0=jnp.asarray(-1.0),
            multipliers0=jnp.asarray([-1.0]),
            throw=False,
        ).y

    shooting = jax.make_jaxpr(shoot)({"rho_g": 2.5, "length": 4.0})
    assert _callbacks(shooting.jaxpr) == []
    # The library's own scoped change: diffrax's checks are back outside it.
    with jax.numpy_dtype_promotion("standard"):
        plain = jax.make_jaxpr(
            lambda ts: (
                diffrax.diffeqsolve(
                    diffrax.ODETerm(lambda t, y, args: -y),
                    diffrax.Tsit5(),
                    0.0,
                    1.0,
                    0.1,
                    jnp.ones(()),
                    saveat=diffrax.SaveAt(ts=ts),
                ).ys
            )
        )(ts)
    assert _callbacks(plain.jaxpr)
