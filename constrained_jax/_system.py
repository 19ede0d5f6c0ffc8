"""Constrained Lagrangian mechanics: the equations of motion and the multipliers.

For a Lagrangian `L(q, qdot, t)` with constraints `A(q, t) qdot + a(q, t) = 0` (see
`_constraints.py`) and generalised forces `Q(q, qdot, t)`, the lecture's equations

    d/dt (dL/dqdot_sigma) - dL/dq_sigma = sum_j lambda_j g_{j sigma} + Q_sigma

expand, with `M = d^2 L / dqdot^2` and `c = (dp/dq) qdot + dp/dt - dL/dq`
(`p = dL/dqdot`), into the saddle-point system

    [[M, -A^T], [A, 0]] [qddot; lambda] = [Q - c; -(Adot qdot + adot)].

`M` may be singular (a massless direction) as long as the KKT matrix is not, i.e. `M`
is positive definite on the null space of `A`. A direction with no inertia that the
constraints leave free and that no force acts on is a free gauge: its acceleration is
set to zero (see `LagrangianSystem.accelerations`). The force of constraint is
`Q^c = A^T lambda`.
"""

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._constraints import AbstractConstraint
from ._misc import inexact_asarray
from ._solver.saddle_point import AbstractSaddlePointSolver, RangeSpaceLDL


class LagrangianSystem(eqx.Module):
    """A mechanical system: a Lagrangian, constraints and generalised forces.

    **Arguments:**

    - `lagrangian`: `L(q, qd, t, args) -> scalar`, any JAX function (not only `T - V`
        with a constant mass matrix).
    - `constraints`: a sequence of [`constrained_jax.Holonomic`][] and
        [`constrained_jax.Pfaffian`][] objects (or a single one). Their rows are stacked
        in the order given; so are the multipliers.
    - `forces`: `Q(q, qd, t, args) -> (n,)`, generalised non-conservative forces, or
        `None`.
    - `saddle_point_solver`: how the KKT system is solved, an
        `AbstractSaddlePointSolver`: [`constrained_jax.RangeSpaceLDL`][] (default;
        any positive semidefinite `M`, i.e. any kinetic energy, even a singular one)
        or [`constrained_jax.FullKKTLU`][] (pivoted LU of the whole KKT matrix, also
        for indefinite `M`, several times slower under `vmap`).

    Coordinates `q` are arrays of shape `(n,)`; `t` is a scalar.
    """

    lagrangian: Callable
    constraints: tuple[AbstractConstraint, ...] = ()
    forces: Callable | None = None
    saddle_point_solver: AbstractSaddlePointSolver = RangeSpaceLDL()

    def __init__(
        self,
        lagrangian: Callable,
        constraints: AbstractConstraint | Sequence[AbstractConstraint] = (),
        forces: Callable | None = None,
        *,
        saddle_point_solver: AbstractSaddlePointSolver = RangeSpaceLDL(),
    ):
        if not callable(lagrangian):
            raise ValueError("`lagrangian` must be a callable L(q, qd, t, args).")
        if isinstance(constraints, AbstractConstraint):
            constraints = (constraints,)
        constraints = tuple(constraints)
        for c in constraints:
            if not isinstance(c, AbstractConstraint):
                raise ValueError(
                    "Each constraint must be a `cjax.Holonomic(G)` or "
                    f"`cjax.Pfaffian(g, h)`, got {type(c).__name__}. Wrap a function "
                    "G(q, t, args) as `cjax.Holonomic(G)`."
                )
        if forces is not None and not callable(forces):
            raise ValueError("`forces` must be a callable Q(q, qd, t, args) or None.")
        self.lagrangian = lagrangian
        self.constraints = constraints
        if not isinstance(saddle_point_solver, AbstractSaddlePointSolver):
            raise ValueError(
                "`saddle_point_solver` must be `cjax.RangeSpaceLDL()` or "
                f"`cjax.FullKKTLU()`, got {type(saddle_point_solver).__name__}."
            )
        self.forces = forces
        self.saddle_point_solver = saddle_point_solver

    # ------------------------------------------------------------------ structure

    def check(self, q, qd, t, args) -> tuple[int, int]:
        """Validate shapes at trace time; return `(n, k)`."""
        q, qd = jnp.asarray(q), jnp.asarray(qd)
        if q.ndim != 1 or qd.shape != q.shape:
            raise ValueError(
                "Coordinates q and velocities qd must be arrays of the same shape "
                f"(n,); got {q.shape} and {qd.shape}."
            )
        n = q.shape[0]
        out = jax.eval_shape(self.lagrangian, q, qd, t, args)
        if not isinstance(out, jax.ShapeDtypeStruct) or out.shape != ():
            raise ValueError(
                "The Lagrangian L(q, qd, t, args) must return a scalar, got "
                f"{getattr(out, 'shape', type(out).__name__)}. Sum kinetic and "
                "potential energies into one number."
            )
        k = sum(c.num_constraints(n, args, q.dtype) for c in self.constraints)
        if k > n:
            raise ValueError(
                f"There are more constraints (k = {k}) than coordinates (n = {n}); at "
                "most n can be independent. Remove the redundant ones."
            )
        if self.forces is not None:
            f_out = jax.eval_shape(self.forces, q, qd, t, args)
            if getattr(f_out, "shape", None) != (n,):
                raise ValueError(
                    f"forces Q(q, qd, t, args) must return shape (n,) = ({n},), got "
                    f"{getattr(f_out, 'shape', type(f_out).__name__)}."
                )
        return n, k

    def without(self, index: int) -> "LagrangianSystem":
        """The same system with its constraint number `index` removed (released)."""
        constraints = self.constraints[:index] + self.constraints[index + 1 :]
        return LagrangianSystem(
            self.lagrangian,
            constraints,
            self.forces,
            saddle_point_solver=self.saddle_point_solver,
        )

    # ------------------------------------------------------------------ physics

    def momentum(self, q, qd, t, args) -> Float[Array, " n"]:
        """Generalised momenta `p = dL/dqdot`."""
        return jax.grad(self.lagrangian, argnums=1)(q, qd, t, args)

    def mass_matrix(self, q, qd, t, args) -> Float[Array, "n n"]:
        """`M = d^2 L / dqdot^2` (may be singular; see the module docstring)."""
        return jax.jacfwd(self.momentum, argnums=1)(q, qd, t, args)

    def energy(self, q, qd, t, args) -> Float[Array, ""]:
        """The energy function (Jacobi integral) `h = qdot . dL/dqdot - L`.

        Conserved when `L`, the constraints and the forces do not depend on `t` and
        the forces do no work (ideal constraints do none).
        """
        return jnp.dot(qd, self.momentum(q, qd, t, args)) - self.lagrangian(
            q, qd, t, args
        )

    def constraint_jacobian(self, q, t, args) -> Float[Array, "k n"]:
        """`A = (g_{j sigma})`, the stacked rows of every constraint."""
        n = q.shape[0]
        if not self.constraints:
            return jnp.zeros((0, n), q.dtype)
        return jnp.concatenate(
            [c.velocity_form(q, t, args)[0] for c in self.constraints]
        )

    def velocity_residual(self, q, qd, t, args) -> Float[Array, " k"]:
        """`A qdot + a` for every constraint (zero on admissible motions)."""
        if not self.constraints:
            return jnp.zeros((0,), q.dtype)
        return jnp.concatenate(
            [c.velocity_residual(q, qd, t, args) for c in self.constraints]
        )

    def holonomic_residual(self, q, t, args) -> Float[Array, " k_holonomic"]:
        """`G(q, t)` for the holonomic constraints (nonholonomic ones have none)."""
        parts = [c.holonomic_residual(q, t, args) for c in self.constraints]
        if not parts:
            return jnp.zeros((0,), q.dtype)
        return jnp.concatenate(parts)

    def acceleration_bias(self, q, qd, t, args) -> Float[Array, " k"]:
        """`Adot qdot + adot`: constraints at acceleration level read
        `A qddot + bias = 0`."""
        if not self.constraints:
            return jnp.zeros((0,), q.dtype)
        return jnp.concatenate(
            [c.acceleration_bias(q, qd, t, args) for c in self.constraints]
        )

    def _equations(self, q, qd, t, args):
        """`M`, the right-hand side `Q - c`, `A` and the acceleration bias."""
        lag = self.lagrangian
        grad_q = jax.grad(lag, argnums=0)(q, qd, t, args)
        mass = self.mass_matrix(q, qd, t, args)
        # (dp/dq) qdot + dp/dt, one forward pass at fixed qdot.
        p_along = lambda q_, t_: self.momentum(q_, qd, t_, args)
        _, dp = jax.jvp(p_along, (q, t), (qd, jnp.ones_like(t)))
        rhs = grad_q - dp
        if self.forces is not None:
            rhs = rhs + self.forces(q, qd, t, args)
        jac = self.constraint_jacobian(q, t, args)
        bias = self.acceleration_bias(q, qd, t, args)
        return mass, rhs, jac, bias

    def position_residual(self, q, t, args) -> Float[Array, " k"]:
        """`G_j(q, t)` for holonomic rows and `0` for Pfaffian ones, stacked like the
        rows of `A`: the position-level residual used by stabilization."""
        if not self.constraints:
            return jnp.zeros((0,), q.dtype)
        return jnp.concatenate(
            [c.position_residual(q, t, args) for c in self.constraints]
        )

    def solve_accelerations(
        self, q, qd, t, args, bias_correction=None
    ) -> tuple[Float[Array, " n"], Float[Array, " k"], Bool[Array, ""]]:
        """`(qddot, lambda, singular)`: the KKT solve without raising.

        `singular` flags a KKT system without a solution (then `qddot`, `lambda` are
        zeros); free gauge directions (no inertia, no force) are not singular, their
        accelerations are zero (see `accelerations`).
        The solve is `self.saddle_point_solver`'s (by default the range-space method,
        unrolled so that XLA fuses it: on CPU a LAPACK call on such a small matrix
        costs more than its arithmetic). `bias_correction` (shape `(k,)`) is added to
        the acceleration bias, as Baumgarte stabilization does.
        """
        t = jnp.asarray(t, q.dtype)
        mass, rhs, jac, bias = self._equations(q, qd, t, args)
        if bias_correction is not None:
            bias = bias + bias_correction
        return self.saddle_point_solver.solve(mass, jac, rhs, bias)

    def accelerations(self, q, qd, t, args=None):
        """Solve the equations of motion for `(qddot, multipliers)`.

        `[[M, -A^T], [A, 0]] [qddot; lambda] = [Q - c; -(Adot qdot + adot)]`, in the
        convention `d/dt(dL/dqdot) - dL/dq = A^T lambda + Q`.

        **Free gauge directions.** A velocity direction `v` with no inertia
        (`M v = 0`) that the constraints leave free (`A v = 0`) makes the KKT matrix
        singular. If no force acts along it (`(Q - c) . v = 0` to round-off), the
        equations hold whatever its acceleration: it is a free gauge, and its
        acceleration is set to zero (the unknown at the vanishing pivot of the
        elimination is 0; for a massless coordinate, e.g. the spin `theta2` of the
        rolling cylinder with `I = 0` after it lets go, `qddot` of that coordinate is
        0, so its velocity is held). See
        [`constrained_jax.AbstractSaddlePointSolver`][].

        Raises (at run time, also under `jit`) if the equations have no solution or
        no unique multipliers: a force acts along a direction without inertia that
        the constraints leave free (e.g. a massless coordinate with a potential
        gradient), or the constraints are redundant.
        """
        q, qd = inexact_asarray(q), inexact_asarray(qd)
        self.check(q, qd, t, args)
        qdd, lam, singular = self.solve_accelerations(q, qd, t, args)
        qdd, lam = eqx.error_if(
            (qdd, lam),
            singular,
            "The KKT matrix [[M, -A^T], [A, 0]] is singular and the equations of "
            "motion have no solution: a force acts along a velocity direction that "
            "has no inertia and that the constraints leave free (M is singular on "
            "the null space of A, e.g. a massless coordinate with a potential "
            "gradient), or the constraints are redundant. (A direction with no "
            "inertia and no force is a free gauge and gets zero acceleration.) Check "
            "the mass matrix and the forces, and remove dependent constraints.",
        )
        return qdd, lam

    def constraint_forces(self, q, qd, t, args=None) -> Float[Array, " n"]:
        """The generalised force of constraint `Q^c = A^T lambda`."""
        q, qd = inexact_asarray(q), inexact_asarray(qd)
        _, lam = self.accelerations(q, qd, t, args)
        jac = self.constraint_jacobian(q, jnp.asarray(t, q.dtype), args)
        return jac.T @ lam
