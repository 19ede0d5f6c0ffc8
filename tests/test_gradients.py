"""Gradients through `simulate` with the adjoint chosen per case (`adjoint=None`):
against central finite differences, against forward mode, and through the release
event against the closed form of the detachment time."""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax._adjoint import default_adjoint, ForwardJacobianAdjoint
from constrained_jax.scenes import two_cylinders as cyl

from .helpers import finite_difference_grad


TIGHT = diffrax.PIDController(rtol=1e-11, atol=1e-11)
FINAL = cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False)


def test_default_adjoint_is_chosen_per_case():
    mine = diffrax.RecursiveCheckpointAdjoint(checkpoints=7)
    assert default_adjoint(mine) is mine
    chosen = default_adjoint(None)
    assert isinstance(chosen, ForwardJacobianAdjoint)
    assert isinstance(chosen.fallback, diffrax.RecursiveCheckpointAdjoint)
    with pytest.raises(ValueError, match="diffrax adjoint"):
        default_adjoint("backsolve")


def _theta1(adjoint, t1=0.5):
    def fn(p):
        args = {**cyl.default_args(), "I": p[0]}
        q0, qd0 = cyl.state(p[1], jnp.zeros_like(p[1]), args)
        traj = cjax.simulate(
            cyl.system(),
            (0.0, t1),
            q0,
            qd0,
            args,
            stepsize_controller=TIGHT,
            saveat=FINAL,
            adjoint=adjoint,
        )
        return traj.q[-1, 1]

    return fn


def test_attached_gradient_matches_finite_differences_and_forward_mode():
    """d theta1(t1) / d(I, theta0), attached motion: reverse mode (the default
    adjoint) against central differences and against forward mode
    (`adjoint=diffrax.ForwardMode()` with `jax.jacfwd`, the cheaper way to a few
    derivatives)."""
    p = jnp.array([cyl.default_args()["I"], 0.3])
    grad = jax.jit(jax.grad(_theta1(None)))(p)
    fd = finite_difference_grad(jax.jit(_theta1(None)), p, rel_step=1e-5)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)
    assert grad[0] < 0  # more rotational inertia rolls off more slowly
    forward = jax.jit(jax.jacfwd(_theta1(diffrax.ForwardMode())))(p)
    np.testing.assert_allclose(grad, forward, rtol=1e-12, atol=1e-15)


def test_release_time_gradient_matches_the_closed_form():
    """d t_release / d(I, theta0) through the release event, against the derivative
    of the closed form `time_to_angle(arccos(2 cos theta0 / (3 + alpha)), theta0)`;
    and d r(t1) / dI in free flight after the release, against finite differences."""

    def outputs(p):
        args = {**cyl.default_args(), "I": p[0]}
        q0, qd0 = cyl.state(p[1], jnp.zeros_like(p[1]), args)
        traj = cjax.simulate(
            cyl.contact_system(),
            (0.0, 1.2),
            q0,
            qd0,
            args,
            stepsize_controller=TIGHT,
            saveat=FINAL,
        )
        return jnp.stack([traj.release.time, traj.q[-1, 0]])

    p = jnp.array([cyl.default_args()["I"], 0.3])
    jac = jax.jit(jax.jacrev(outputs))(p)
    closed = jax.grad(
        lambda p: cyl.detachment_time(p[1], {**cyl.default_args(), "I": p[0]})
    )(p)
    np.testing.assert_allclose(jac[0], closed, rtol=1e-6)
    outputs_jit = jax.jit(outputs)
    fd = finite_difference_grad(lambda x: outputs_jit(x)[1], p, rel_step=1e-5)
    np.testing.assert_allclose(jac[1], fd, rtol=2e-5, atol=1e-8)


def _pendulum_x(t1, g, throw, adjoint=None):
    """`x(t1)` of the pendulum released at 1 rad, with a step budget of 24: enough
    for `t1 = 0.2`, not for `t1 = 5`."""
    from constrained_jax.scenes import pendulum as pend

    args = pend.default_args(g=g)
    q0, qd0 = pend.state(jnp.asarray(1.0), jnp.asarray(0.0), args)
    traj = cjax.simulate(
        pend.system(),
        (0.0, t1),
        q0,
        qd0,
        args,
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8),
        saveat=FINAL,
        max_steps=24,
        throw=throw,
        adjoint=adjoint,
    )
    return traj.q[-1, 0], traj.result


# (Module-level: both parametrizations share their programs.)
_pendulum_results = jax.jit(jax.vmap(lambda t1, g: _pendulum_x(t1, g, False)[1]))
_pendulum_x_value = jax.jit(lambda g: _pendulum_x(0.2, g, False)[0])


@pytest.mark.parametrize("throw", [False, True])
def test_failed_run_has_nan_gradient(throw):
    """A run that spends its step budget has no derivative: `jax.grad` gives NaN,
    also with `throw=True` (whose check rides on the trajectory, which a program
    keeping only the gradient drops), and under `jax.vmap` only for the failed
    member of a batch; the successful member's gradient matches finite
    differences."""
    loss = lambda t1, g: _pendulum_x(t1, g, throw)[0]
    grad = jax.jit(jax.vmap(jax.grad(loss, argnums=1)))
    t1s, g = jnp.array([0.2, 5.0]), jnp.array([9.81, 9.81])
    grads = np.asarray(grad(t1s, g))
    assert np.isnan(grads[1])
    assert np.isfinite(grads[0])
    codes = np.asarray(_pendulum_results(t1s, g)._value)
    assert codes[0] == cjax.RESULTS.successful._value
    assert codes[1] == cjax.RESULTS.max_steps_reached._value
    step = 1e-4
    fd = (_pendulum_x_value(9.81 + step) - _pendulum_x_value(9.81 - step)) / (2 * step)
    np.testing.assert_allclose(grads[0], fd, rtol=1e-5)
    # Forward mode too (`jax.jvp` keeps the primal, so `throw=True` raises there).
    forward = lambda g: _pendulum_x(5.0, g, throw, diffrax.ForwardMode())[0]
    if throw:
        with pytest.raises(Exception, match="max_steps|maximum number of"):
            jax.jvp(forward, (9.81,), (1.0,))
    else:
        _, tangent = jax.jvp(forward, (9.81,), (1.0,))
        assert np.isnan(tangent)


def test_may_hold_tracers_finds_closed_over_values():
    """The adjoint closure-converts its loops only when a tracer is reachable from
    their non-array parts; anything it cannot look into counts as reachable."""
    from constrained_jax._adjoint import may_hold_tracers

    found = {}

    @jax.jit
    def probe(x):
        scale = 2 * x
        closure = lambda y: y * scale
        nested = {"f": [functools.partial(lambda a, b: a + b, scale)]}

        class Holder:
            def __init__(self):
                self.value = (1, scale)

            def method(self, y):
                return y

        found["closure"] = may_hold_tracers(closure)
        found["partial"] = may_hold_tracers(nested)
        found["method"] = may_hold_tracers(Holder().method)
        found["default"] = may_hold_tracers(lambda y, s=scale: y * s)
        found["plain"] = may_hold_tracers((jnp.sin, lambda y: y, np.ones(2), 3.0))
        found["module"] = may_hold_tracers(cyl.system())
        found["opaque"] = may_hold_tracers(object())
        return x

    probe(1.0)
    assert found == {
        "closure": True,
        "partial": True,
        "method": True,
        "default": True,
        "plain": False,
        "module": False,
        "opaque": True,
    }


class _PendulumLagrangian(eqx.Module):
    """The pendulum's Lagrangian as a module holding `g` (an array field)."""

    g: jax.Array

    def __call__(self, q, qd, t, args):
        return 0.5 * args["m"] * jnp.dot(qd, qd) - args["m"] * self.g * q[1]


def _closed_over_g(g, adjoint, closed):
    """`x(t1)` of the pendulum released at 1 rad, with `g` closed over by the
    Lagrangian (`closed=True`), a field of a Lagrangian module (`"module"`) or
    passed through `args` (`False`)."""
    from constrained_jax.scenes import pendulum as pend

    args = pend.default_args()
    if closed == "module":
        rod = pend.system().constraints
        system = cjax.LagrangianSystem(_PendulumLagrangian(g), constraints=rod)
    elif closed:

        def lagrangian(q, qd, t, args_):
            return 0.5 * args_["m"] * jnp.dot(qd, qd) - args_["m"] * g * q[1]

        rod = pend.system().constraints
        system = cjax.LagrangianSystem(lagrangian, constraints=rod)
    else:
        system, args = pend.system(), {**args, "g": g}
    q0, qd0 = pend.state(jnp.asarray(1.0), jnp.asarray(0.0), args)
    traj = cjax.simulate(
        system,
        (0.0, 0.3),
        q0,
        qd0,
        args,
        stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
        saveat=FINAL,
        adjoint=adjoint,
    )
    return traj.q[-1, 0]


def test_gradient_through_a_closed_over_parameter():
    """A Lagrangian that closes over the differentiated value (not through `args`):
    the adjoint finds the tracer in the closure and converts it to an input, so the
    gradient is the one with the value in `args` (which matches finite
    differences), in forward mode and by the fallback (`max_tangents=0`; the same
    fallback with `args` is checked in `test_kkt_derivative.py`). The value as an
    array field of a Lagrangian module is a leaf of the vector field (no
    conversion): the same gradient."""
    fallback = ForwardJacobianAdjoint(max_tangents=0)
    closed = jax.jit(jax.grad(lambda g: _closed_over_g(g, None, True)))(9.81)
    closed_fallback = jax.jit(jax.grad(lambda g: _closed_over_g(g, fallback, True)))(
        9.81
    )
    module = jax.jit(jax.grad(lambda g: _closed_over_g(g, None, "module")))(9.81)
    passed = jax.jit(jax.grad(lambda g: _closed_over_g(g, None, False)))(9.81)
    value = jax.jit(lambda g: _closed_over_g(g, None, False))
    h = 1e-4
    fd = (value(9.81 + h) - value(9.81 - h)) / (2 * h)
    assert np.isfinite(passed) and passed != 0
    np.testing.assert_allclose(passed, fd, rtol=1e-6)
    np.testing.assert_allclose(closed, passed, rtol=1e-10)
    np.testing.assert_allclose(closed_fallback, passed, rtol=1e-10)
    np.testing.assert_allclose(module, passed, rtol=1e-10)
