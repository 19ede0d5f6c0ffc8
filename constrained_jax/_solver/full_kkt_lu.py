"""The saddle-point system by LU of the whole KKT matrix
([`constrained_jax.FullKKTLU`][])."""

import jax.numpy as jnp
import jax.scipy as jsp

from .dense_lu import dense_factor, lu_solve_unrolled
from .saddle_point import AbstractSaddlePointSolver, KKTForm, mask_singular


def _lu_solve_gauge(lu, perm, zero, b, unrolled: bool):
    """Solve `P K x = L U x = b[perm]` given an LU factorisation whose pivots `zero`
    vanish: those unknowns are set to 0 and their rows of `U x = y` are dropped (the
    caller checks the residual)."""
    m = lu.shape[-1]
    if unrolled:
        return lu_solve_unrolled(lu, perm, b, zero)
    y = jsp.linalg.solve_triangular(lu, b[perm], lower=True, unit_diagonal=True)
    y = jnp.where(zero, 0.0, y)
    upper = jnp.where(zero[:, None], jnp.eye(m, dtype=lu.dtype), jnp.triu(lu))
    return jsp.linalg.solve_triangular(upper, y, lower=False)


class FullKKTLU(AbstractSaddlePointSolver):
    """Forms the `(n + k)` square KKT matrix and factors it by LU with partial
    pivoting (unrolled up to `unroll_max` unknowns, LAPACK above).

    Needs nothing but a nonsingular KKT matrix, so it also handles Lagrangians whose
    `M` is indefinite. Under `jax.vmap` the pivoting (row selection, permutation)
    becomes batched `dot`s and gathers that XLA on CPU does not fuse: for small
    systems it costs several times [`constrained_jax.RangeSpaceLDL`][].

    The rows of `M` (and so the unknowns `lambda`) are first scaled by
    `max|A| / max|M|`, so that the two blocks have the same size whatever the units
    (a mass of `1e-300` next to an `A` of order 1 is not mistaken for zero; `lambda`
    is scaled back). A pivot below `10 m eps` of the largest entry counts as zero.
    Zero pivots in the columns of `x` are free gauge directions (see
    [`constrained_jax.AbstractSaddlePointSolver`][]): their unknowns are set to zero
    and the solution is accepted only if it satisfies the whole system to round-off
    (`|K z - r| <= 100 m eps (|K| |z|_1 + |r|)`), i.e. if no force acts along them.
    Zero pivots in the columns of `lambda` (redundant constraints) are `singular`.
    Partial pivoting is not rank-revealing: for a gauge direction that is not along a
    coordinate it may leave the dependent row where a later column needs it, and then
    reports `singular` (never a wrong answer); [`constrained_jax.RangeSpaceLDL`][]
    solves those. A massless coordinate that nothing couples to (a zero row and
    column) is always handled.
    """

    unroll_max: int = 12

    def form(self, n: int, k: int) -> KKTForm:
        return KKTForm(sparse=False, unroll=n + k <= self.unroll_max)

    def solve(self, system, fill):
        mass, jac = system.mass.todense(), system.jac.todense()
        rhs, bias = system.rhs, system.bias
        n, k = mass.shape[0], jac.shape[0]
        active = system.active if k > 0 else None
        if active is not None:
            jac = jnp.where(active[:, None], jac, 0.0)
            bias = jnp.where(active, bias, 0.0)
        if k == 0:
            matrix, vector = mass, rhs
            block_scale = None
        else:
            # (M x - A^T lambda) / s = f / s with s = max|M| / max|A|: the unknowns
            # are x and lambda / s.
            size_m, size_a = jnp.max(jnp.abs(mass)), jnp.max(jnp.abs(jac))
            ratio = size_m / size_a
            usable = (size_m > 0) & (size_a > 0) & (ratio > 0) & jnp.isfinite(ratio)
            block_scale = jnp.where(usable, ratio, 1.0)
            corner = jnp.zeros((k, k), mass.dtype)
            if active is not None:
                # Inactive rows: `c (lambda_j / s) = 0`, `c` the largest entry of
                # the scaled matrix (1 where it is zero), so that neither an active
                # pivot nor an inactive one is taken for zero (see
                # `AbstractSaddlePointSolver`).
                largest = jnp.maximum(size_m / block_scale, size_a)
                c = jnp.where(largest > 0, largest, 1.0)
                corner = jnp.diag(jnp.where(active, 0.0, c))
            matrix = jnp.block([[mass / block_scale, -jac.T], [jac, corner]])
            vector = jnp.concatenate([rhs / block_scale, -bias])
        m = n + k
        lu, perm, _ = dense_factor(matrix, self.unroll_max)
        eps = jnp.finfo(matrix.dtype).eps
        scale = jnp.max(jnp.abs(matrix))
        zero = jnp.abs(jnp.diagonal(lu)) <= 10 * m * eps * scale
        sol = _lu_solve_gauge(lu, perm, zero, vector, m <= self.unroll_max)
        # With vanishing pivots the dropped rows are consistency conditions: the
        # solution stands only if the whole system holds to round-off.
        residual = jnp.max(jnp.abs(matrix @ sol - vector))
        size = scale * jnp.sum(jnp.abs(sol)) + jnp.max(jnp.abs(vector))
        consistent = residual <= 100 * m * eps * size
        singular = jnp.any(zero[n:]) | (jnp.any(zero) & jnp.invert(consistent))
        singular = singular | jnp.invert(jnp.all(jnp.isfinite(sol)))
        sol = mask_singular(sol, n, singular, fill)
        lam = sol[n:] if block_scale is None else sol[n:] * block_scale
        return sol[:n], lam, singular


FullKKTLU.__init__.__doc__ = """**Arguments:**

- `unroll_max`: the largest `n + k` solved by unrolled elimination (trace and compile
    time grow like `(n + k)**3`); larger systems use LAPACK's LU.
"""
