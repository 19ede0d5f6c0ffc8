"""A Lineax solver that tries one solver and, where it fails, solves with another:
the default linear solver of [`constrained_jax.extremize`][] for KKT systems too
large to factor at every step but small enough to factor when the Krylov solve does
not converge."""

from typing import Any

import jax.lax as lax
import lineax as lx
from jaxtyping import Array, PyTree


class Fallback(lx.AbstractLinearSolver):
    """Solve with `first`; where it does not succeed, with `second`.

    `second` runs only where `first` reports a failure other than a non-finite input
    (NaN or inf in the operator or the right-hand side, which no solver can mend):
    `second` is then initialised (for [`constrained_jax.DenseLU`][] the matrix is
    formed and factored) and solves the same system, and its solution and status are
    returned. The choice is a `lax.cond`, so the unbatched solve pays for `second`
    only when `first` fails; under `jax.vmap` both run for the whole batch.

    **Arguments:**

    - `first`: the solver tried first, e.g. [`constrained_jax.MINRES`][].
    - `second`: the solver used where `first` fails, e.g. `DenseLU()`.
    """

    first: lx.AbstractLinearSolver
    second: lx.AbstractLinearSolver

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        return self.first.init(operator, options), operator

    def compute(self, state, vector: PyTree[Array], options: dict[str, Any]):
        first_state, operator = state
        x, result, stats = self.first.compute(first_state, vector, options)
        failed = (result != lx.RESULTS.successful) & (
            result != lx.RESULTS.nonfinite_input
        )

        def second(_):
            second_state = self.second.init(operator, options)
            x2, result2, _ = self.second.compute(second_state, vector, options)
            return x2, result2

        x, result = lax.cond(failed, second, lambda _: (x, result), None)
        return x, result, stats

    def transpose(self, state, options: dict[str, Any]):
        first_state, operator = state
        first_state, first_options = self.first.transpose(first_state, options)
        return (first_state, operator.transpose()), first_options

    def conj(self, state, options: dict[str, Any]):
        first_state, operator = state
        first_state, first_options = self.first.conj(first_state, options)
        return (first_state, lx.conj(operator)), first_options

    def assume_full_rank(self):
        return self.first.assume_full_rank() and self.second.assume_full_rank()
