"""Dense LU after Ruiz equilibration, for badly scaled KKT matrices."""

from typing import Any

import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

from .dense_lu import dense_factor, dense_solve


def _equilibrate(a: Float[Array, "m m"], iterations: int = 4):
    """Ruiz scaling: `R^{-1} A C^{-1}` with every row and column of max-norm ~1."""
    m = a.shape[-1]
    row = jnp.ones((m,), a.dtype)
    col = jnp.ones((m,), a.dtype)
    for _ in range(iterations):
        r = jnp.sqrt(jnp.max(jnp.abs(a), axis=1))
        c = jnp.sqrt(jnp.max(jnp.abs(a), axis=0))
        r = jnp.where(r > 0, r, 1.0)
        c = jnp.where(c > 0, c, 1.0)
        a = a / r[:, None] / c[None, :]
        row = row * r
        col = col * c
    return a, row, col


class EquilibratedDenseLU(lx.AbstractLinearSolver):
    """Dense LU with partial pivoting after Ruiz equilibration of rows and columns.

    KKT matrices of discretized functionals are badly scaled: the Hessian block grows
    like `N^2` (spectral: `N^4`) while a constraint row may be tiny (the length
    constraint of a nearly taut rope has gradient `~ y' ~ 1e-3`). Scaling rows and
    columns to unit max-norm first (`A = R A_s C`) makes the pivot threshold of
    `DenseLU` (`10 m eps max|A|`) mean "numerically singular" rather than "badly
    scaled". Singular matrices are reported as `lineax.RESULTS.singular`.

    **Arguments:**

    - `unroll_max`: the largest size factored by the unrolled elimination of
        `DenseLU` (fused straight-line code, the faster one for batches of small
        systems under `jax.vmap`); larger ones by LAPACK's LU, which compiles faster.

    **Reference:** D. Ruiz, *A scaling algorithm to equilibrate both rows and columns
    norms in matrices*, RAL-TR-2001-034 (2001).
    """

    unroll_max: int = 12

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("`EquilibratedDenseLU` needs a square operator.")
        matrix = operator.as_matrix()
        scaled, row, col = _equilibrate(matrix)
        return matrix, scaled, row, col, dense_factor(scaled, self.unroll_max)

    def compute(self, state, vector, options: dict[str, Any]):
        del options
        _, _, row, col, factors = state
        x = dense_solve(factors, vector / row, self.unroll_max) / col
        singular = factors[2]
        result = lx.RESULTS.where(singular, lx.RESULTS.singular, lx.RESULTS.successful)
        return x, result, {}

    def transpose(self, state, options: dict[str, Any]):
        matrix, scaled, row, col, _ = state
        scaled_t = scaled.T
        return (
            matrix.T,
            scaled_t,
            col,
            row,
            dense_factor(scaled_t, self.unroll_max),
        ), options

    def conj(self, state, options: dict[str, Any]):
        return state, options

    def assume_full_rank(self):
        return True
