"""The vector field that `simulate` integrates, `(q, qdot) -> (qdot, qddot)`, and the
divergence check of its steps.

`qddot` comes from the KKT solve of [`constrained_jax.LagrangianSystem`][], with the
rows that hold in the current contact mode (`LagrangianSystem.with_active`); the
stabilization adds its bias correction.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from ._misc import all_finite
from ._system import solve_dynamics


# A state is taken as diverged when a constraint residual, as a distance (the residual
# over the row norm of the constraint Jacobian at the start of the phase), exceeds
# this fraction of the size of the state: not drift but a trajectory that has left
# the manifold (or is about to overflow).
_DIVERGED = 0.25


def solve_accelerations(system, q, qd, t, args, bias_correction=None):
    """`(qddot, lambda, singular)`, traced once per system and shapes, with `qddot`
    NaN where `singular` (a NaN derivative makes the step fail).

    Each trace of the equations of motion adds a copy of the derivatives of the
    Lagrangian to the traced program; one run calls them at many places (the vector
    field in diffrax's initial step and in the stages, the events, the watched
    multiplier, the saved multipliers, the singular check), some of which diffrax
    traces more than once. Under `jit` the later calls reuse the first trace (and XLA
    inlines the calls, so the compiled program is the same). `t` is cast to the dtype
    of `q` (not weakly typed) so that every call site has the same signature."""
    t = jnp.asarray(t, q.dtype)
    return _jit_solve_accelerations(system, q, qd, t, args, bias_correction)


@eqx.filter_jit
def _jit_solve_accelerations(system, q, qd, t, args, bias_correction):
    return solve_dynamics(system, q, qd, t, args, bias_correction, fill=jnp.nan)


def field_and_multipliers(system, stabilization):
    """`(t, (q, qdot), args) -> ((qdot, qddot), lambda)`: one KKT solve.

    (A `jax.tree_util.Partial`, not a closure: the arrays of `system`, a Lagrangian
    module's parameters or its contact mode say, are leaves of the vector field, so
    the solve's adjoint sees no closed-over array and traces the solve once, see
    `_adjoint.py`.)"""
    return jax.tree_util.Partial(_field, system, stabilization)


def _field(system, stabilization, t, y, args):
    q, qd = y
    correction = stabilization.bias_correction(system, q, qd, t, args)
    # A singular KKT matrix makes the step fail: `qdd` is then NaN, which the
    # controller rejects (set inside the solve, where XLA fuses it); the status is
    # recovered afterwards at the saved states.
    qdd, lam, _ = solve_accelerations(system, q, qd, t, args, correction)
    return (qd, qdd), lam


def vector_field(system, stabilization):
    """`(t, (q, qdot), args) -> (qdot, qddot)` (see `field_and_multipliers`)."""
    return jax.tree_util.Partial(_derivative, system, stabilization)


def _derivative(system, stabilization, t, y, args):
    return _field(system, stabilization, t, y, args)[0]


def diverged_condition(system, q_ref, t_ref, args):
    """A boolean event: non-finite state, or residuals of the rows that hold beyond
    `_DIVERGED`.

    Checked by diffrax at every accepted step (fixed steps included, where diffrax
    checks nothing). The residuals are scaled by the row norms of `A` at `q_ref`, so
    that the bound reads as a distance and does not depend on how `G` is written.
    Rows that do not hold in the contact mode (a released contact's gap) are not
    checked.

    (A `jax.tree_util.Partial`, not a closure: the row norms are a leaf of the event,
    so the solve's adjoint sees no closed-over array, see `_adjoint.py`.)
    """
    jac = system.constraint_jacobian(q_ref, t_ref, args)
    row_norms = None
    if jac.shape[0]:
        tiny = jnp.finfo(q_ref.dtype).tiny
        row_norms = jnp.maximum(jnp.linalg.norm(jac, axis=1), tiny)
    return jax.tree_util.Partial(_diverged, system, row_norms)


def _diverged(system, row_norms, t, y, args, **kwargs):
    del kwargs
    q, qd = y
    bad = jnp.invert(all_finite((q, qd)))
    if row_norms is not None:
        position = system.position_residual(q, t, args) / row_norms
        velocity = system.velocity_residual(q, qd, t, args) / row_norms
        if system.active is not None:
            position = jnp.where(system.active, position, 0.0)
            velocity = jnp.where(system.active, velocity, 0.0)
        bad = (
            bad
            | jnp.any(jnp.abs(position) > _DIVERGED * (1 + jnp.max(jnp.abs(q))))
            | jnp.any(jnp.abs(velocity) > _DIVERGED * (1 + jnp.max(jnp.abs(qd))))
        )
    return bad
