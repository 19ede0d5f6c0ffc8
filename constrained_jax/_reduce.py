"""Reducing coordinates where a constraint can be solved, and linearising.

`reduce(system, embedding)`: when the constraints can be solved as `q = phi(s, t)` (for
the pendulum `(x, y) = l (sin s, -cos s)`; for the two cylinders
`(r, theta1, theta2) = (R + a, s, (1 + R/a) s)`), the reduced Lagrangian is

    L_s(s, sdot, t) = L(phi(s, t), (dphi/ds) sdot + dphi/dt, t),

with generalised forces `(dphi/ds)^T Q`. The multipliers of the eliminated constraints
are not lost: as the lecture does for the two cylinders, they follow from the residual
of the full equations along the reduced motion, `A^T lambda = M qddot + c - Q`.

`linearize(system, q_eq, qd_eq, t, args)`: the linearised dynamics on the constraint
manifold about an equilibrium, and its eigenvalues.
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from ._constraints import AbstractConstraint
from ._custom_types import Args, ScalarLike
from ._misc import (
    all_finite,
    check_consistency_tol,
    CONSISTENCY_TOLERANCE,
    default_float_dtype,
    float_tolerance,
    full_precision,
)
from ._results import error_if
from ._solver.saddle_point import solve as solve_saddle_point
from ._system import LagrangianSystem, off_constraints, PATTERN_MISMATCH_MESSAGE


class Reduction(eqx.Module):
    """A system in reduced coordinates `s`, with the way back to the full one.

    **Attributes:**

    - `system`: the [`constrained_jax.LagrangianSystem`][] in `s` (simulate it).
    - `full`: the original system in `q`.
    - `embedding`: `phi(s, t, args) -> q`.
    """

    system: LagrangianSystem
    full: LagrangianSystem
    embedding: Callable

    def lift(self, s, sd, t, args=None):
        """`(q, qdot)` from `(s, sdot)`: `q = phi`, `qdot = dphi/ds sdot + dphi/dt`."""
        t = jnp.asarray(t, jnp.result_type(s))
        fn = lambda s_, t_: self.embedding(s_, t_, args)
        return jax.jvp(fn, (s, t), (sd, jnp.ones_like(t)))

    def full_multipliers(
        self, s, sd, t, args=None, *, consistency_tol: float | None = None
    ) -> Float[Array, " k"]:
        """The multipliers of the full system along the reduced motion.

        `lambda` is the full system's, from its saddle-point solve at the lifted
        state; `qddot` comes from the reduced equations lifted by the embedding, and
        the full equations are checked along it: `A^T lambda = M qddot - (Q - c)`.

        Raises (at run time, also under `jit`) where these would not be the
        multipliers of the full system: the lifted motion violates the full
        system's constraints at the position, velocity or acceleration level (an
        embedding that does not satisfy the constraints it eliminates, e.g. the
        pendulum's circle drawn with the wrong radius), or `A^T lambda` cannot
        balance `M qddot - (Q - c)` (the reduced motion does not satisfy the full
        equations: a constraint eliminated that the full system does not have).
        Tolerance: `consistency_tol` (`None`: `1e-8` in float64, as in
        [`constrained_jax.simulate`][]), relative to the size of each quantity's
        terms.
        """
        t = jnp.asarray(t, jnp.result_type(s))
        sdd, _ = self.system.accelerations(s, sd, t, args)

        def q_dot(s_, sd_, t_):
            return self.lift(s_, sd_, t_, args)[1]

        q, qd = self.lift(s, sd, t, args)
        if consistency_tol is None:
            consistency_tol = float_tolerance(*CONSISTENCY_TOLERANCE, q.dtype)
        else:
            consistency_tol = check_consistency_tol(consistency_tol)
        # qddot = d/dt (qdot) along (sdot, sddot, 1).
        _, qdd = jax.jvp(q_dot, (s, sd, t), (sd, sdd, jnp.ones_like(t)))
        kkt = self.full.saddle_point_system(q, qd, t, args)
        _, lam, singular = solve_saddle_point(self.full.saddle_point_solver, kkt)
        mass, jac = kkt.mass.todense(), kkt.jac.todense()
        rhs, bias = kkt.rhs, kkt.bias
        residual = mass @ qdd - rhs
        # (Each check is attached to `qdd` too: `error_if` on an empty `lam` alone,
        # a system without constraints, would never fire.)
        if kkt.mismatch is not None:
            lam, qdd = error_if((lam, qdd), kkt.mismatch, PATTERN_MISMATCH_MESSAGE)
        lam, qdd = error_if(
            (lam, qdd),
            singular,
            "`Reduction.full_multipliers`: the full system's KKT matrix "
            "[[M, -A^T], [A, 0]] is singular at this state (redundant constraints, "
            "or a force along a direction without inertia): its multipliers are not "
            "defined.",
        )
        # The lifted motion on the full constraints: positions and velocities as
        # `simulate` checks a start, accelerations (`A qddot + bias = 0`) and the
        # balance of forces row by row, each against the size of its terms.
        acceleration = jac @ qdd + bias
        acceleration_scale = jnp.abs(jac) @ jnp.abs(qdd) + jnp.abs(bias)
        balance = jac.T @ lam - residual
        # (Each multiplier at the size of the largest: the round-off of the solve,
        # which a row whose own terms vanish, a massless coordinate, would
        # otherwise be held to.)
        lam_size = jnp.full_like(lam, jnp.max(jnp.abs(lam), initial=0.0))
        balance_scale = (
            jnp.abs(mass) @ jnp.abs(qdd) + jnp.abs(rhs) + jnp.abs(jac.T) @ lam_size
        )
        off = off_constraints(self.full, q, qd, t, args, consistency_tol) | jnp.any(
            jnp.abs(acceleration) > consistency_tol * acceleration_scale
        )
        lam, qdd = error_if(
            (lam, qdd),
            off,
            "`Reduction.full_multipliers`: the lifted motion q = phi(s, t) violates "
            "the full system's constraints (at the position, velocity or "
            "acceleration level, beyond `consistency_tol`): the embedding does not "
            "satisfy the constraints it eliminates, so the reduced motion is not a "
            "motion of the full system. Check `phi` (e.g. the radius of a circle).",
        )
        lam, _ = error_if(
            (lam, qdd),
            jnp.any(jnp.abs(balance) > consistency_tol * balance_scale),
            "`Reduction.full_multipliers`: no multipliers balance the full "
            "equations along the reduced motion (A^T lambda != M qddot - (Q - c) "
            "beyond `consistency_tol`): the reduced motion does not satisfy the full "
            "equations of motion (the embedding removes freedom that no constraint "
            "of the full system removes).",
        )
        return lam


@full_precision
def reduce(
    system: LagrangianSystem,
    embedding: Callable,
    constraints: AbstractConstraint | tuple[AbstractConstraint, ...] = (),
) -> Reduction:
    """Eliminate constraints by an explicit parametrisation `q = phi(s, t, args)`.

    **Arguments:**

    - `system`: the full [`constrained_jax.LagrangianSystem`][].
    - `embedding`: `phi(s, t, args) -> q`; must satisfy the constraints it eliminates
        identically in `s` and `t`.
    - `constraints`: constraints that remain, written in `s` (e.g. a nonholonomic one
        that no parametrisation removes).

    **Returns:** a [`constrained_jax.Reduction`][].
    """
    if not callable(embedding):
        raise ValueError("`embedding` must be a callable phi(s, t, args) -> q.")

    def lift(s, sd, t, args):
        fn = lambda s_, t_: embedding(s_, t_, args)
        return jax.jvp(fn, (s, t), (sd, jnp.ones_like(t)))

    def lagrangian(s, sd, t, args):
        q, qd = lift(s, sd, t, args)
        return system.lagrangian(q, qd, t, args)

    forces = None
    if system.forces is not None:

        def forces(s, sd, t, args):
            q, qd = lift(s, sd, t, args)
            jac = jax.jacfwd(embedding)(s, t, args)
            return jac.T @ system.forces(q, qd, t, args)

    reduced = LagrangianSystem(lagrangian, constraints, forces)
    return Reduction(system=reduced, full=system, embedding=embedding)


class Linearization(eqx.Module):
    """Linearised dynamics on the constraint manifold about an equilibrium.

    **Attributes:**

    - `matrix`: `A_lin` with `d/dt (xi, eta) = A_lin (xi, eta)`, where
        `delta q = position_basis xi` and `delta qdot = velocity_basis eta`.
    - `eigenvalues`: of `matrix` (growth rates and frequencies).
    - `position_basis`: orthonormal basis of the admissible position perturbations
        (the null space of the holonomic constraint Jacobian), shape `(n, n - k_h)`.
    - `velocity_basis`: of the admissible velocities (null space of `A`), shape
        `(n, n - k)`.
    """

    matrix: Float[Array, "m m"]
    eigenvalues: Complex[Array, " m"]
    position_basis: Float[Array, "n p"]
    velocity_basis: Float[Array, "n v"]


def _null_space(jac: Float[Array, "k n"]) -> Float[Array, "n m"]:
    n, k = jac.shape[1], jac.shape[0]
    if k == 0:
        return jnp.eye(n, dtype=jac.dtype)
    _, _, vt = jnp.linalg.svd(jac, full_matrices=True)
    return vt[k:].T


@full_precision
def linearize(
    system: LagrangianSystem,
    q_eq: Float[ArrayLike, " n"],
    qd_eq: Float[ArrayLike, " n"],
    t: ScalarLike = 0.0,
    args: Args = None,
    *,
    consistency_tol: float | None = None,
) -> Linearization:
    """Linearise the constrained dynamics about `(q_eq, qd_eq)` at time `t`.

    Position perturbations are restricted to the tangent space of the holonomic
    constraints and velocity perturbations to the null space of all constraint rows
    `A` (assumed of full rank `k`): the spurious zero modes of the index-1 equations
    (drift off the manifold) are excluded. Non-autonomous systems are linearised at the
    frozen time `t`.

    **Arguments:**

    - `system`: a [`constrained_jax.LagrangianSystem`][].
    - `q_eq`, `qd_eq`: the equilibrium, shape `(n,)`, on the constraints.
    - `t`: the time at which a non-autonomous system is frozen.
    - `args`: parameters passed to every user function.
    - `consistency_tol`: how far `(q_eq, qd_eq)` may be from the constraints
        (relative to `1 + |q_eq|`, `1 + |qd_eq|`); `None` (default) follows the
        dtype as in [`constrained_jax.simulate`][]: `1e-8` in float64.

    **Returns:** a [`constrained_jax.Linearization`][].

    Raises (at run time, also under `jit`) where the linearisation would not describe
    the system: NaN or inf in the inputs; a point off the constraints (`G(q_eq) != 0`
    or `A qd_eq + a != 0` beyond `consistency_tol`: project it first with
    [`constrained_jax.consistent_initial_state`][]); a singular KKT matrix there (the
    equations of motion have no solution, see
    [`constrained_jax.LagrangianSystem.accelerations`][]); a non-finite result.
    Whether the point is an equilibrium is not checked: a moving constraint (the
    rotating hoop in Cartesian coordinates) has equilibria with nonzero `qd_eq` and
    `qddot`.
    """
    q_eq = jnp.asarray(q_eq, default_float_dtype())
    qd_eq = jnp.asarray(qd_eq, default_float_dtype())
    system.check(q_eq, qd_eq, t, args)
    if consistency_tol is None:
        consistency_tol = float_tolerance(*CONSISTENCY_TOLERANCE, q_eq.dtype)
    else:
        consistency_tol = check_consistency_tol(consistency_tol)
    t = jnp.asarray(t, q_eq.dtype)
    finite = all_finite((q_eq, qd_eq, t, args))
    q_eq, qd_eq = error_if(
        (q_eq, qd_eq),
        jnp.invert(finite),
        "`linearize`: `q_eq`, `qd_eq`, `t` or `args` contain NaN or inf.",
    )
    off = off_constraints(system, q_eq, qd_eq, t, args, consistency_tol)
    q_eq, qd_eq = error_if(
        (q_eq, qd_eq),
        off,
        "`linearize`: the point (q_eq, qd_eq) violates the constraints (G(q_eq, t) "
        "!= 0 or A qd_eq + a != 0 beyond `consistency_tol`): the linearisation on "
        "the constraint manifold needs a point on it. Project it first with "
        "`cjax.consistent_initial_state(system, q_eq, qd_eq, t, args)`.",
    )
    jac_h = jax.jacfwd(system.holonomic_residual)(q_eq, t, args)
    z_pos = _null_space(jac_h)
    z_vel = _null_space(system.constraint_jacobian(q_eq, t, args))

    def qdd(q, qd):
        qdd_, _, singular = system.solve_accelerations(q, qd, t, args)
        return qdd_, singular

    (d_q, d_qd), singular = jax.jacfwd(qdd, argnums=(0, 1), has_aux=True)(q_eq, qd_eq)
    d_q = error_if(
        d_q,
        singular,
        "`linearize`: the KKT matrix [[M, -A^T], [A, 0]] is singular at (q_eq, qd_eq): "
        "the equations of motion have no unique solution there (a force along a "
        "direction without inertia that the constraints leave free, or redundant "
        "constraints), so they have no linearisation. See "
        "`cjax.LagrangianSystem.accelerations`.",
    )
    top = jnp.concatenate(
        [jnp.zeros((z_pos.shape[1], z_pos.shape[1]), q_eq.dtype), z_pos.T @ z_vel], 1
    )
    bottom = jnp.concatenate([z_vel.T @ d_q @ z_pos, z_vel.T @ d_qd @ z_vel], 1)
    matrix = jnp.concatenate([top, bottom], 0)
    matrix = error_if(
        matrix,
        jnp.invert(jnp.all(jnp.isfinite(matrix))),
        "`linearize`: the linearised matrix is not finite (the equations of motion "
        "or their derivatives overflow or are NaN at (q_eq, qd_eq)).",
    )
    return Linearization(
        matrix=matrix,
        eigenvalues=jnp.linalg.eigvals(matrix),
        position_basis=z_pos,
        velocity_basis=z_vel,
    )
