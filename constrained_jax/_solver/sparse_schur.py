"""STUB (issue 12, helper h12-sparse replaces this): the structured saddle-point
solve for large systems with a (block-)diagonal mass matrix and a sparse constraint
Jacobian. Until then it forms the dense matrices and calls LAPACK."""

from .saddle_point import AbstractSaddlePointSolver, FullKKTLU
from .sparse import as_dense


class SparseSchur(AbstractSaddlePointSolver):
    """Range-space method on sparse matrices (stub: dense LAPACK LU)."""

    def solve(self, mass, jac, rhs, bias):
        return FullKKTLU(unroll_max=0).solve(as_dense(mass), as_dense(jac), rhs, bias)
