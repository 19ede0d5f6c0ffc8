"""Matrices with a static sparsity pattern: the blocks `M` and `A` of a saddle-point
system.

The pattern (`rows`, `cols`, `shape`) is Python data, fixed at trace time; only the
nonzero `values` are arrays (batched under `jax.vmap`). So a solver can plan its
elimination once, at trace time, and the memory of a state is `O(nnz)`, not `O(n^2)`.
A full pattern stores the dense array itself (`SparseMatrix.dense`), so a dense block
costs nothing to pass or to read back.
"""

import functools
import operator

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float


# Up to this many nonzeros, products are written on scalars with static indices: no
# gather or scatter, which XLA:CPU never compiles into the single function of a
# small loop, so that a gradient through `simulate` of a small system stays one
# function per step.
_UNROLL = 64


class SparseMatrix(eqx.Module):
    """`values[p]` at `(rows[p], cols[p])` of a `shape` matrix, zero elsewhere; or,
    with `rows` and `cols` `None` (the full pattern, `SparseMatrix.dense`), `values`
    is the dense matrix itself.

    The pattern is static (tuples of Python ints, part of the tree structure); entries
    listed in the pattern may still be zero at run time.
    """

    values: Float[Array, " nnz"] | Float[Array, "m n"]
    rows: tuple[int, ...] | None = eqx.field(static=True)
    cols: tuple[int, ...] | None = eqx.field(static=True)
    shape: tuple[int, int] = eqx.field(static=True)

    @classmethod
    def dense(cls, array) -> "SparseMatrix":
        """The full pattern: every entry may be nonzero."""
        array = jnp.asarray(array)
        return cls(array, None, None, tuple(int(s) for s in array.shape))

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

    @property
    def is_dense(self) -> bool:
        """Whether the pattern is full (`values` is the dense matrix)."""
        return self.rows is None

    def todense(self) -> Float[Array, "m n"]:
        if self.is_dense:
            return self.values
        out = jnp.zeros(self.shape, self.values.dtype)
        if not self.rows:
            return out
        return out.at[np.asarray(self.rows), np.asarray(self.cols)].set(self.values)

    def pattern(self) -> np.ndarray:
        """The boolean pattern (static)."""
        if self.is_dense:
            return np.ones(self.shape, bool)
        out = np.zeros(self.shape, bool)
        out[np.asarray(self.rows, int), np.asarray(self.cols, int)] = True
        return out

    def entries(self) -> list[list]:
        """Nested lists of scalars, `None` outside the pattern (a structural zero)."""
        rows, cols = self.shape
        if self.is_dense:
            return [[self.values[i, j] for j in range(cols)] for i in range(rows)]
        out: list[list] = [[None] * cols for _ in range(rows)]
        for p, (i, j) in enumerate(zip(self.rows, self.cols, strict=True)):
            out[i][j] = self.values[p]
        return out

    def mask_rows(self, keep: Bool[Array, " m"]) -> "SparseMatrix":
        """The same pattern with the rows `i` where `keep[i]` is false set to zero
        (`where`, so that whatever they held, NaN included, is dropped)."""
        if self.is_dense:
            return SparseMatrix.dense(jnp.where(keep[:, None], self.values, 0.0))
        if not self.rows:
            return self
        values = jnp.where(keep[np.asarray(self.rows)], self.values, 0.0)
        return SparseMatrix(values, self.rows, self.cols, self.shape)

    def matvec(self, vector, transpose: bool = False) -> Array:
        """`self @ vector` (`self.T @ vector` if `transpose`), on the nonzeros only."""
        if self.is_dense:
            return (self.values.T if transpose else self.values) @ vector
        rows, cols = np.asarray(self.rows, int), np.asarray(self.cols, int)
        size = self.shape[1] if transpose else self.shape[0]
        if transpose:
            rows, cols = cols, rows
        dtype = jnp.result_type(self.values, vector)
        out = jnp.zeros((size,), dtype)
        if rows.size == 0:
            return out
        if rows.size <= _UNROLL:
            terms: list[list] = [[] for _ in range(size)]
            for p, (r, c) in enumerate(zip(rows.tolist(), cols.tolist(), strict=True)):
                terms[r].append(self.values[p] * vector[c])
            zero = jnp.zeros((), dtype)
            return jnp.stack(
                [functools.reduce(operator.add, t).astype(dtype) if t else zero
                 for t in terms]
            )  # fmt: skip
        return out.at[rows].add(self.values * vector[cols])
