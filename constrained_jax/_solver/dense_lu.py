"""Dense LU with partial pivoting that reports singular matrices, as a Lineax solver.

Systems of up to `unroll_max` unknowns are factored by Gaussian elimination with
partial pivoting *unrolled at trace time*, which XLA fuses into straight-line code: on
CPU a LAPACK call on a 3x3 matrix costs far more than its arithmetic, so a vmapped
batch of small problems runs several times faster than with LAPACK's LU
(`DenseLU(unroll_max=0)`; `benchmarks/extremize.py`). Larger systems use LAPACK's LU.
Singular matrices are reported (`lineax.RESULTS.singular`), never returned as NaN;
matrices with NaN or inf entries as `lineax.RESULTS.nonfinite_input`.
"""

from typing import Any

import jax.lax as lax
import jax.numpy as jnp
import jax.scipy as jsp
import lineax as lx
from jaxtyping import Array, Bool, Float, Int, PyTree

from .._compat import lineax_internal as lxi


def _singular_threshold(a: Float[Array, "m m"]) -> Float[Array, ""]:
    """A pivot below this (relative to the largest entry) counts as zero."""
    m = a.shape[-1]
    eps = jnp.finfo(a.dtype).eps
    return 10 * m * eps * jnp.max(jnp.abs(a))


def lu_factor_unrolled(
    a: Float[Array, "m m"],
) -> tuple[Float[Array, "m m"], Int[Array, " m"], Bool[Array, ""]]:
    """LU factorisation with partial pivoting, unrolled over the (static) size.

    Returns `(lu, perm, singular)` with `a[perm] = L @ U`, `L` unit lower triangular
    stored below the diagonal of `lu` and `U` on and above it. Pivot rows are selected
    with one-hot arithmetic rather than dynamic indexing, so the whole factorisation
    is elementwise work that XLA fuses (also under `jax.vmap`).
    """
    m = a.shape[-1]
    idx = jnp.arange(m)
    perm = idx
    lu = a
    threshold = _singular_threshold(a)
    singular = jnp.array(False)
    for k in range(m):
        col = jnp.where(idx >= k, jnp.abs(lu[:, k]), -1.0)
        p = jnp.argmax(col)
        onehot = (idx == p).astype(a.dtype)
        row_p = onehot @ lu
        row_k = lu[k]
        perm_p = jnp.sum(jnp.where(idx == p, perm, 0))
        perm_k = perm[k]
        # Swap rows k and p (p >= k).
        lu = lu + onehot[:, None] * (row_k - row_p)[None, :]
        lu = lu.at[k].set(row_p)
        perm = jnp.where(idx == p, perm_k, perm).at[k].set(perm_p)
        pivot = lu[k, k]
        small = jnp.abs(pivot) <= threshold
        singular = singular | small
        safe_pivot = jnp.where(small, 1.0, pivot)
        below = idx > k
        factors = jnp.where(below, lu[:, k] / safe_pivot, 0.0)
        right = idx > k
        update = factors[:, None] * jnp.where(right, lu[k], 0.0)[None, :]
        lu = lu - update
        lu = lu.at[:, k].set(jnp.where(below, factors, lu[:, k]))
    return lu, perm, singular


def lu_solve_unrolled(
    lu: Float[Array, "m m"],
    perm: Int[Array, " m"],
    b: Float[Array, " m"],
    zero: Bool[Array, " m"] | None = None,
) -> Float[Array, " m"]:
    """Solves `a x = b` given `lu_factor_unrolled(a)`.

    With `zero` (flags of vanishing pivots) those unknowns are set to 0 and their rows
    of `U x = y` are dropped (the caller checks the residual)."""
    m = lu.shape[-1]
    y = b[perm]
    ys = []
    for i in range(m):
        s = y[i]
        for j in range(i):
            s = s - lu[i, j] * ys[j]
        ys.append(s)
    xs = [None] * m
    for i in reversed(range(m)):
        s = ys[i]
        for j in range(i + 1, m):
            s = s - lu[i, j] * xs[j]
        if zero is None:
            xs[i] = s / lu[i, i]
        else:
            pivot = jnp.where(zero[i], 1.0, lu[i, i])
            xs[i] = jnp.where(zero[i], 0.0, s / pivot)
    return jnp.stack(xs)


def dense_factor(a: Float[Array, "m m"], unroll_max: int):
    """Factor a square matrix: unrolled for `m <= unroll_max`, LAPACK otherwise."""
    m = a.shape[-1]
    if m <= unroll_max:
        return lu_factor_unrolled(a)
    lu, piv = jsp.linalg.lu_factor(a)
    singular = jnp.any(jnp.abs(jnp.diagonal(lu)) <= _singular_threshold(a))
    perm = lax.linalg.lu_pivots_to_permutation(piv, m)
    return lu, perm, singular


def dense_solve(factors, b: Float[Array, " m"], unroll_max: int) -> Float[Array, " m"]:
    """Solve with the output of `dense_factor`; singular systems give zeros."""
    lu, perm, singular = factors
    m = lu.shape[-1]
    safe_lu = jnp.where(singular, jnp.eye(m, dtype=lu.dtype), lu)
    if m <= unroll_max:
        x = lu_solve_unrolled(safe_lu, perm, b)
    else:
        y = jsp.linalg.solve_triangular(
            safe_lu, b[perm], lower=True, unit_diagonal=True
        )
        x = jsp.linalg.solve_triangular(safe_lu, y, lower=False)
    return jnp.where(singular, 0.0, x)


_DenseLUState = tuple[Any, Any, lxi.PackedStructures, Any]


class DenseLU(lx.AbstractLinearSolver):
    """Dense LU solver with partial pivoting that reports singular matrices.

    For matrices of size at most `unroll_max` the factorisation is unrolled at trace
    time (fast for the tiny KKT systems of mechanics and small extremizations, batched
    with `jax.vmap`); larger ones use LAPACK. A pivot smaller than
    `10 m eps max|A|` marks the matrix singular: the solve then returns
    `lineax.RESULTS.singular` (and zeros, never NaN). A matrix with NaN or inf
    entries (e.g. a Hessian evaluated outside the domain of the function) is reported
    as `lineax.RESULTS.nonfinite_input` instead, so that the caller can tell a
    singular matrix from an undefined one.
    """

    unroll_max: int = 12

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("`DenseLU` may only be used with square operators.")
        matrix = operator.as_matrix()
        packed = lxi.pack_structures(operator)
        return self._state(matrix, packed)

    def _state(self, matrix, packed) -> _DenseLUState:
        finite = jnp.all(jnp.isfinite(matrix))
        return matrix, dense_factor(matrix, self.unroll_max), packed, finite

    def compute(self, state: _DenseLUState, vector: PyTree[Array], options):
        del options
        _, factors, packed, finite = state
        b = lxi.ravel_vector(vector, packed)
        x = dense_solve(factors, b, self.unroll_max)
        singular = factors[2]
        result = lx.RESULTS.where(singular, lx.RESULTS.singular, lx.RESULTS.successful)
        result = lx.RESULTS.where(finite, result, lx.RESULTS.nonfinite_input)
        return lxi.unravel_solution(x, packed), result, {}

    def transpose(self, state: _DenseLUState, options: dict[str, Any]):
        matrix, _, packed, _ = state
        return self._state(matrix.T, lxi.transpose_packed_structures(packed)), {}

    def conj(self, state: _DenseLUState, options: dict[str, Any]):
        matrix, _, packed, _ = state
        return self._state(matrix.conj(), packed), {}

    def assume_full_rank(self):
        return True


DenseLU.__init__.__doc__ = """**Arguments:**

- `unroll_max`: the largest size factored by unrolled elimination; larger systems use
    LAPACK. Unrolling costs trace and compile time growing like `m**3`, so keep it
    small.
"""
