"""Matrices with a static sparsity pattern, as the structured KKT path passes them.

The pattern (`rows`, `cols`, `shape`) is Python data, fixed at trace time; only the
nonzero `values` are arrays (batched under `jax.vmap`). So a solver can plan its
elimination once, at trace time, and the memory of a state is `O(nnz)`, not `O(n^2)`.
"""

import functools
import operator

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


# Up to this many nonzeros, products are written on scalars with static indices: no
# gather or scatter, which XLA:CPU never compiles into the single function of a
# small loop (`constrained_jax.use_loop_kernels`), so that a gradient through
# `simulate` of a small system stays one function per step.
_UNROLL = 64


class SparseMatrix(eqx.Module):
    """`values[p]` at `(rows[p], cols[p])` of a `shape` matrix, zero elsewhere.

    The pattern is static (tuples of Python ints, part of the tree structure); entries
    listed in the pattern may still be zero at run time.
    """

    values: Float[Array, " nnz"]
    rows: tuple[int, ...] = eqx.field(static=True)
    cols: tuple[int, ...] = eqx.field(static=True)
    shape: tuple[int, int] = eqx.field(static=True)

    def todense(self) -> Float[Array, "m n"]:
        out = jnp.zeros(self.shape, self.values.dtype)
        if not self.rows:
            return out
        return out.at[np.asarray(self.rows), np.asarray(self.cols)].set(self.values)

    @classmethod
    def from_dense(cls, dense, pattern) -> "SparseMatrix":
        """The entries of `dense` at the nonzeros of the boolean `pattern`."""
        pattern = np.asarray(pattern, bool)
        rows, cols = np.nonzero(pattern)
        values = jnp.asarray(dense)[rows, cols]
        return cls(
            values,
            tuple(int(r) for r in rows),
            tuple(int(c) for c in cols),
            tuple(int(s) for s in pattern.shape),
        )

    def pattern(self) -> np.ndarray:
        out = np.zeros(self.shape, bool)
        out[np.asarray(self.rows, int), np.asarray(self.cols, int)] = True
        return out


def as_dense(matrix) -> Float[Array, "m n"]:
    """A dense array from a dense array or a `SparseMatrix`."""
    if isinstance(matrix, SparseMatrix):
        return matrix.todense()
    return matrix


def matvec(matrix, vector, transpose: bool = False) -> Array:
    """`matrix @ vector` (`matrix.T @ vector` if `transpose`) for a dense array or a
    `SparseMatrix` (on its nonzeros only)."""
    if not isinstance(matrix, SparseMatrix):
        return (matrix.T if transpose else matrix) @ vector
    rows, cols = np.asarray(matrix.rows, int), np.asarray(matrix.cols, int)
    size = matrix.shape[1] if transpose else matrix.shape[0]
    if transpose:
        rows, cols = cols, rows
    dtype = jnp.result_type(matrix.values, vector)
    out = jnp.zeros((size,), dtype)
    if rows.size == 0:
        return out
    if rows.size <= _UNROLL:
        terms: list[list] = [[] for _ in range(size)]
        for p, (r, c) in enumerate(zip(rows.tolist(), cols.tolist(), strict=True)):
            terms[r].append(matrix.values[p] * vector[c])
        zero = jnp.zeros((), dtype)
        return jnp.stack(
            [functools.reduce(operator.add, t).astype(dtype) if t else zero
             for t in terms]
        )  # fmt: skip
    return out.at[rows].add(matrix.values * vector[cols])
