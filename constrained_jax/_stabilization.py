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

from typing import Any

import diffrax
import equinox as eqx
import jax.numpy as jnp
from diffrax._root_finder import use_stepsize_tol
from jaxtyping import Array, Float


class AbstractStabilization(eqx.Module):
    """How `simulate` keeps the constraints satisfied (see the module docstring)."""


class Unstabilized(AbstractStabilization):
    """Integrate the acceleration-level equations as they are."""


class Baumgarte(AbstractStabilization):
    """Baumgarte stabilization with rates `alpha` (velocity) and `beta` (position).

    The constraint violation then obeys `e'' + 2 alpha e' + beta^2 e = 0`: choose
    `alpha = beta` (critical damping) of the order of the inverse time scale of the
    motion. Too large values make the equations stiff.
    """

    alpha: float = 1.0
    beta: float = 1.0

    def bias_correction(self, system, q, qd, t, args) -> Float[Array, " k"]:
        velocity = system.velocity_violation(q, qd, t, args)
        position = system.position_rows(q, t, args)
        return 2 * self.alpha * velocity + self.beta**2 * position


class Projection(AbstractStabilization):
    """Project onto the constraint manifold after each step, in the metric of `M`.

    Positions: `iterations` Gauss-Newton steps of
    `[[M, A^T], [A, 0]] [dq; mu] = [0; -G]` (Pfaffian rows get `0`: the correction is
    a virtual displacement). Velocities: one solve of
    `[[M, A^T], [A, 0]] [dv; mu] = [0; -(A qdot + a)]`.

    Works with any diffrax solver, explicit or implicit. A first-same-as-last solver
    (Tsit5, Dopri5) re-evaluates the vector field at the projected state at the start
    of each step (one more evaluation per step), so no stale derivative is reused.
    """

    iterations: int = 3


def project_state(system, q, qd, t, args, iterations: int):
    """The closest admissible `(q, qd)` in the kinetic-energy metric."""
    n = q.shape[0]
    mass = system.mass_matrix(q, qd, t, args)

    def kkt_solve(jac, rhs_lower):
        # [[M, A^T], [A, 0]] [dq; mu] = [0; r] is the system's saddle-point problem
        # with f = 0 and bias = -r (and lambda = -mu).
        zeros = jnp.zeros((n,), q.dtype)
        return system.linear_solver.solve(mass, jac, zeros, -rhs_lower)[0]

    for _ in range(iterations):
        jac = system.constraint_jacobian(q, t, args)
        q = q + kkt_solve(jac, -system.position_rows(q, t, args))
    jac = system.constraint_jacobian(q, t, args)
    qd = qd + kkt_solve(jac, -system.velocity_violation(q, qd, t, args))
    return q, qd


def resolve_implicit_tolerances(solver, stepsize_controller):
    """Give an implicit solver's root finder the step-size controller's tolerances.

    What `diffrax.diffeqsolve` does itself for a bare implicit solver, done before
    wrapping it in `ProjectedSolver` (diffrax cannot reach into the wrapper).
    """
    if not isinstance(solver, diffrax.AbstractImplicitSolver) or not isinstance(
        stepsize_controller, diffrax.AbstractAdaptiveStepSizeController
    ):
        return solver
    names = [
        name
        for name in ("rtol", "atol", "norm")
        if getattr(solver.root_finder, name) is use_stepsize_tol
    ]
    return eqx.tree_at(
        lambda s: tuple(getattr(s.root_finder, name) for name in names),
        solver,
        tuple(getattr(stepsize_controller, name) for name in names),
    )


class ProjectedSolver(diffrax.AbstractWrappedSolver):
    """A diffrax solver followed by a projection onto the constraint manifold.

    Built by `simulate` for `Projection()`; wraps any diffrax solver (explicit or
    implicit). The state is `(q, qd)`; `args` is the simulation's `args`.
    """

    solver: diffrax.AbstractSolver
    system: Any
    iterations: int

    @property
    def term_structure(self):
        return self.solver.term_structure

    @property
    def scan_kind(self):
        return getattr(self.solver, "scan_kind", None)

    @property
    def root_finder(self):
        # diffrax forwards `isinstance(..., AbstractImplicitSolver)` to the wrapped
        # solver and then reads `root_finder`; `simulate` has already filled in its
        # tolerances (`resolve_implicit_tolerances`).
        return self.solver.root_finder

    @property
    def interpolation_cls(self):  # pyright: ignore
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

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

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)
