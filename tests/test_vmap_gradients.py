"""Reverse-mode derivatives of contact runs under `jax.vmap`, whose lanes record
different numbers of events (a lane that is over waits for the others): `vmap(grad)`
and `grad(sum(vmap))` of a bouncing ball's second impact time against the closed
form, with the default adjoint's fallback taking over after the first phase (its
forward rule traced for two patterns of perturbed inputs inside one `lax.scan`) and
with `diffrax.RecursiveCheckpointAdjoint()`.

Both failed once inside the backward pass (Lineax's non-finite input: the phases of
the lanes already over ran with zero residuals); with two cylinders and friction,
`grad(sum(vmap))` gave NaN and `vmap(grad)` raised `StopIteration` in JAX's
`process_custom_vjp_call` (a program too long to compile for this suite)."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax._adjoint import ForwardJacobianAdjoint
from constrained_jax.scenes import bouncing_ball as ball


E, T1, MAX_EVENTS = 0.8, 1.5, 4
# Dropped from these heights the ball hits the floor 3, 2 and 2 times before T1
# (impact times t_k = t_1 + (2 v_1 / g)(e + ... + e^(k-1)), `ball.impact_time`).
HEIGHTS = jnp.asarray([0.5, 1.0, 1.5])
COUNTS = [3, 2, 2]
CONTROLLER = diffrax.PIDController(rtol=1e-10, atol=1e-10)
# (The default adjoint, forward mode through every phase of these runs, gave the
# right values before the fix too; `test_impacts.py` differentiates it under `vmap`.)
ADJOINTS = {
    # Forward mode for the first phase (one perturbed scalar, `e`), the fallback
    # for the next ones (their starting state is perturbed too).
    "fallback-after-first-phase": ForwardJacobianAdjoint(max_tangents=1),
    "checkpoint": diffrax.RecursiveCheckpointAdjoint(),
}


def _second_impact(e, h, adjoint):
    args = ball.default_args(e=e)
    q0, qd0 = ball.state(h)
    traj = cjax.simulate(
        ball.system(),
        (0.0, T1),
        q0,
        qd0,
        args,
        stepsize_controller=CONTROLLER,
        saveat=cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False),
        max_events=MAX_EVENTS,
        adjoint=adjoint,
        throw=False,
    )
    return traj.events.time[1], traj.events.count


def _closed_form():
    """`(t_2, d t_2 / d e)` per lane: `t_1 + 2 e v_1 / g` and `2 v_1 / g`."""
    args = ball.default_args(e=E)
    t1, v1 = (np.asarray(x) for x in ball.first_impact(np.asarray(HEIGHTS), args))
    g = float(args["g"])
    # A third impact before T1 in lane 0 only.
    assert list(t1 + 2 * v1 / g * (E + E**2) < T1) == [True, False, False]
    return t1 + 2 * E * v1 / g, 2 * v1 / g


def _program(adjoint, total: bool):
    """`vmap(value_and_grad)`, and `grad(sum(vmap))` if `total`, in one program."""

    def each(e):
        return jax.vmap(
            jax.value_and_grad(_second_impact, has_aux=True), in_axes=(None, 0, None)
        )(e, HEIGHTS, adjoint)

    def summed(e):
        return jnp.sum(jax.vmap(_second_impact, in_axes=(None, 0, None))(
            e, HEIGHTS, adjoint
        )[0])  # fmt: skip

    return jax.jit(lambda e: (each(e), jax.grad(summed)(e) if total else None))


# (`grad(sum(vmap))` through the checkpointed adjoint alone never failed.)
_PROGRAMS = {
    name: _program(adjoint, total=name != "checkpoint")
    for name, adjoint in ADJOINTS.items()
}


@pytest.mark.parametrize("adjoint", list(ADJOINTS))
def test_vmap_of_grad_and_grad_of_vmap(adjoint):
    ((values, counts), grads), total = _PROGRAMS[adjoint](jnp.asarray(E))
    t2, dt2 = _closed_form()
    np.testing.assert_array_equal(counts, COUNTS)
    np.testing.assert_allclose(values, t2, rtol=1e-8)
    np.testing.assert_allclose(grads, dt2, rtol=1e-6)
    if total is not None:
        np.testing.assert_allclose(total, np.sum(dt2), rtol=1e-6)
