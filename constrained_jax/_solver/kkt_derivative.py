"""The derivative of a saddle-point solve, without differentiating the elimination.

The solution `z = [x; lambda]` of

    K z = [f; -b],    K = [[M, -A^T], [A, 0]],

moves with its inputs as `K dz = [df - dM x + dA^T lambda; -(db + dA x)]`: the tangent
solves the same system with another right-hand side. `solve` wraps any
[`constrained_jax.AbstractSaddlePointSolver`][] (a black box) in a `jax.custom_jvp`
with that rule, so that neither forward nor reverse mode differentiates the
factorisation (the unrolled elimination, its pivots and `where`s): both apply the
solver's own map from right-hand side to solution, linearised at the primal
right-hand side (`jax.linearize` with `M` and `A` fixed), to the tangent right-hand
side. That map is linear in the right-hand side (the pivot tests, the gauge and
singularity flags are primal values), so it is transposed for reverse mode as it
stands; only the factorisation is computed, once, in the forward pass.

The rule reproduces the plain derivative of the elimination to round-off, including
its conventions:

- **Singular** systems (the solution is zero): zero tangents.
- **Free gauge directions** (a direction `v` with `M v = 0`, `A v = 0` and no force
    along it, whose unknown at the vanishing pivot is set to zero): the solution solves
    the system with that unknown removed, and so does its tangent (the linearised map
    drops the right-hand side's component at the pivot as the solve does).

Second derivatives differentiate the rule itself: correct, but they go through the
elimination once more (none of the library's own paths takes them).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .saddle_point import AbstractSaddlePointSolver
from .sparse import matvec as _matvec


def solve(
    solver: AbstractSaddlePointSolver,
    mass,
    jac,
    rhs: Float[Array, " n"],
    bias,
    nan_x: bool = False,
) -> tuple[Float[Array, " n"], Float[Array, " k"], Bool[Array, ""]]:
    """`solver.solve(mass, jac, rhs, bias)`, differentiated by the implicit rule (see
    the module's docstring) instead of through the elimination.

    **Arguments:**

    - `solver`: a saddle-point solver (its `solve` is used as a black box).
    - `mass`, `jac`: `M` (`n x n`) and `A` (`k x n`), dense or `SparseMatrix`es.
    - `rhs`, `bias`: `f` (shape `(n,)`) and `b` (shape `(k,)`).
    - `nan_x`: a `singular` solve has `x` NaN instead of zero (`solver._solve_nan_x`).

    **Returns:** `(x, lambda, singular)`, as `solver.solve`.
    """
    return _solve(solver, nan_x, mass, jac, rhs, bias)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _solve(solver, nan_x, mass, jac, rhs, bias):
    if nan_x:
        return solver._solve_nan_x(mass, jac, rhs, bias)
    return solver.solve(mass, jac, rhs, bias)


@_solve.defjvp
def _solve_jvp(solver, nan_x, primals, tangents):
    mass, jac, rhs, bias = primals
    d_mass, d_jac, d_rhs, d_bias = tangents

    def solution(rhs_, bias_):
        x, lam, singular = solver.solve(mass, jac, rhs_, bias_)
        return (x, lam), singular

    (x, lam), linear, singular = jax.linearize(solution, rhs, bias, has_aux=True)
    # K dz = [df - dM x + dA^T lambda; -(db + dA x)]
    tangent_rhs = d_rhs - _matvec(d_mass, x) + _matvec(d_jac, lam, transpose=True)
    tangent_bias = d_bias + _matvec(d_jac, x)
    dx, dlam = linear(tangent_rhs, tangent_bias)
    dx, dlam = (jnp.where(singular, 0.0, d) for d in (dx, dlam))
    d_singular = np.zeros(singular.shape, jax.dtypes.float0)
    if nan_x:
        x = jnp.where(singular, jnp.nan, x)
    return (x, lam, singular), (dx, dlam, d_singular)
