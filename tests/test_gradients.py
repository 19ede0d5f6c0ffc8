"""Gradients through `simulate` with the adjoint chosen per case (`adjoint=None`):
against central finite differences, against forward mode, and through the release
event against the closed form of the detachment time."""

import diffrax
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
