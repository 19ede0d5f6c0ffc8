"""Keeping a simulation on the constraint manifold.

Integrating the index-1 (acceleration-level) equations enforces the constraints only
through their second derivative, so round-off and truncation errors make `G` and
`A qdot + a` drift. Three strategies, each an object passed to `simulate`:

- [`constrained_jax.Unstabilized`][]: nothing; the drift is reported in
  `Trajectory.violation`.
- [`constrained_jax.Baumgarte`][]: replace `A qddot + bias = 0` by
  `A qddot + bias + 2 alpha (A qdot + a) + beta^2 G = 0`, a damped oscillator for the
  violation (J. Baumgarte, Comput. Methods Appl. Mech. Eng. 1 (1972) 1-16).
- [`constrained_jax.Projection`][]: after every step, project `q` onto `G = 0` and
  `qdot` onto `A qdot + a = 0`, each in the metric of `M` (the closest admissible
  state in kinetic-energy norm), by a wrapped diffrax solver. The projections solve
  the same KKT matrix as the dynamics, so a singular `M` is fine.
"""

import abc
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._system import project
from ._wrapped_solver import AbstractForwardingSolver, prepare_to_wrap


class AbstractStabilization(eqx.Module):
    """How `simulate` keeps the constraints satisfied (see the module docstring).

    The protocol is the three places where a strategy can act: the vector field
    (`bias_correction`), the diffrax solver (`wrap_solver`) and the saved states
    (`project_saved`).
    """

    @abc.abstractmethod
    def bias_correction(self, system, q, qd, t, args) -> Float[Array, " k"] | None:
        """The term added to the constraint bias of the acceleration solve,
        `A qddot + bias + correction = 0`, shape `(k,)`; or `None` for none."""

    @abc.abstractmethod
    def wrap_solver(
        self,
        solver: diffrax.AbstractSolver,
        system,
        stepsize_controller: diffrax.AbstractStepSizeController,
        adjoint: diffrax.AbstractAdjoint,
    ) -> diffrax.AbstractSolver:
        """The diffrax solver that integrates `system` with this stabilization."""

    @abc.abstractmethod
    def project_saved(
        self,
        system,
        q: Float[Array, "T n"],
        qd: Float[Array, "T n"],
        ts,
        args,
        active: Bool[Array, "T k"] | None = None,
    ) -> tuple[Float[Array, "T n"], Float[Array, "T n"]]:
        """The states saved at the times `ts` (interpolated between steps), as the
        trajectory reports them; `active`, if given, holds the rows of `system` that
        held at each save time (a contact mode, see
        `LagrangianSystem.with_active`)."""


class Unstabilized(AbstractStabilization):
    """Integrate the acceleration-level equations as they are."""

    def bias_correction(self, system, q, qd, t, args):
        return None

    def wrap_solver(self, solver, system, stepsize_controller, adjoint):
        return solver

    def project_saved(self, system, q, qd, ts, args, active=None):
        return q, qd


class Baumgarte(AbstractStabilization):
    """Baumgarte stabilization with rates `alpha` (velocity) and `beta` (position).

    The constraint violation then obeys `e'' + 2 alpha e' + beta^2 e = 0`: choose
    `alpha = beta` (critical damping) of the order of the inverse time scale of the
    motion. Too large values make the equations stiff.
    """

    alpha: float = 1.0
    beta: float = 1.0

    def bias_correction(self, system, q, qd, t, args) -> Float[Array, " k"]:
        velocity = system.velocity_residual(q, qd, t, args)
        position = system.position_residual(q, t, args)
        return 2 * self.alpha * velocity + self.beta**2 * position

    def wrap_solver(self, solver, system, stepsize_controller, adjoint):
        return solver

    def project_saved(self, system, q, qd, ts, args, active=None):
        return q, qd


class Projection(AbstractStabilization):
    """Project onto the constraint manifold after each step, in the metric of `M`.

    Positions: `iterations` Gauss-Newton steps of
    `[[M, A^T], [A, 0]] [dq; mu] = [0; -G]` (Pfaffian rows get `0`: the correction is
    a virtual displacement). Velocities: one solve of
    `[[M, A^T], [A, 0]] [dv; mu] = [0; -(A qdot + a)]`.

    Works with any diffrax solver, explicit or implicit. A first-same-as-last solver
    (Tsit5, Dopri5) re-evaluates the vector field at the projected state at the start
    of each step (one more evaluation per step), so no stale derivative is reused.
    The saved states, interpolated between steps, are projected as well.
    """

    iterations: int = 3

    def bias_correction(self, system, q, qd, t, args):
        return None

    def wrap_solver(self, solver, system, stepsize_controller, adjoint):
        solver = prepare_to_wrap(solver, stepsize_controller, adjoint)
        return ProjectedSolver(solver, system, self.iterations)

    def project_saved(self, system, q, qd, ts, args, active=None):
        def one(q_, qd_, t_, active_=None):
            held = system if active_ is None else system.with_active(active_)
            return project_state(held, q_, qd_, t_, args, self.iterations)

        if active is None:
            return jax.vmap(one)(q, qd, ts)
        return jax.vmap(one)(q, qd, ts, active)


def project_state(system, q, qd, t, args, iterations: int):
    """The closest admissible `(q, qd)` in the kinetic-energy metric
    (`constrained_jax._system.project`): NaN where a solve is singular or a detected
    pattern misses an entry at one of the states, which the solver then rejects."""
    q, qd, _, singular = project(system, q, qd, t, args, iterations)
    return jnp.where(singular, jnp.nan, q), jnp.where(singular, jnp.nan, qd)


class ProjectedSolver(AbstractForwardingSolver):
    """A diffrax solver followed by a projection onto the constraint manifold.

    Built by `simulate` for `Projection()`; wraps any diffrax solver (explicit or
    implicit). The state is `(q, qd)`; `args` is the simulation's `args`.
    """

    solver: diffrax.AbstractSolver
    system: Any
    iterations: int

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        # `made_jump=True`: the state was moved by the previous projection, so a
        # first-same-as-last solver (Tsit5, Dopri5) must not reuse the derivative it
        # stored at the unprojected state. Costs one more evaluation per step.
        del made_jump
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, True
        )
        q, qd = y1
        y1 = project_state(self.system, q, qd, t1, args, self.iterations)
        return y1, y_error, dense_info, solver_state, result
