"""The protocol of the nonlinear solvers of a KKT residual, `AbstractKKTSolver`, and
the loop that runs one, `iterate` (as optimistix's `AbstractIterativeSolver` and
`iterative_solve`). The solvers are [`constrained_jax.Newton`][] (`newton.py`) and
[`constrained_jax.SemismoothNewton`][] (`semismooth_newton.py`)."""

import abc
import functools as ft
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
import lineax as lx
from jaxtyping import Array, Bool, Float, PyTree

from .._results import RESULTS


_ResidualFn = Callable[[Float[Array, " m"], PyTree], Float[Array, " m"]]


class KKTResidual(eqx.Module):
    """A KKT residual `(grad F*, G, phi)` of unknowns `z = (x, lambda, mu)` together
    with the layout a regularised step needs: `n` unknowns `x` first, and the sense
    `sign` (`+1` to minimize, `-1` to maximize) in which the stationarity rows are
    the gradient of the objective; with `bounds`, also `k` (the constraint rows after
    the `n` stationarity rows) and the promise that every complementarity row is a
    bound: the rows after the first `n + k` come in blocks of `n`, row `i` of a
    block depending on `x_i` and its own multiplier alone, so that their Jacobian is
    diagonal (`SemismoothNewton` then solves a reduced system of `n + k` unknowns).

    Called like the residual itself; a solver that does not use the layout sees a
    plain residual function.
    """

    fn: _ResidualFn
    n: int = eqx.field(static=True)
    sign: float = eqx.field(static=True)
    k: int = eqx.field(static=True, default=0)
    bounds: bool = eqx.field(static=True, default=False)

    def __call__(self, z, args):
        return self.fn(z, args)

    def proximal_signs(self, z: Float[Array, " m"]) -> Float[Array, " m"]:
        """`sign` on the rows of `x`, zero on those of the multipliers: the diagonal
        `D` of the proximal term `rho D (z - z_c)` (the gradient of
        `sign rho |x - x_c|^2 / 2`), which adds `rho` to the curvature of the
        objective in the direction of `sense`."""
        return jnp.zeros_like(z).at[: self.n].set(self.sign)


class AbstractKKTSolver(eqx.Module):
    """A method for finding a root of a KKT residual (for extremization and
    functionals a symmetric one: the Jacobian is the KKT matrix).

    The protocol is that of optimistix's `AbstractIterativeSolver`: `init` makes the
    solver state, `step` takes one step, `terminate` says whether to stop and with
    which status, `postprocess` finishes. The loop, `max_steps`, the check of the
    start and the status after too many steps are written once, in
    `constrained_jax._solver.kkt_solver.iterate`. `linear_solver` is also used by the
    implicit function theorem in the backward pass, so that derivatives cost one more
    linear solve of the same kind (never an unrolled iteration).

    A KKT system with complementarity rows (inequality constraints) is not smooth:
    `complementarity_solver` names the solver that takes this one's place there.
    """

    linear_solver: eqx.AbstractVar[lx.AbstractLinearSolver]

    @abc.abstractmethod
    def init(self, residual: _ResidualFn, z: Float[Array, " m"], args: PyTree) -> Any:
        """The solver state before the first step from `z`."""

    @abc.abstractmethod
    def step(
        self, residual: _ResidualFn, z: Float[Array, " m"], args: PyTree, state: Any
    ) -> tuple[Float[Array, " m"], Any]:
        """One step: the new iterate and state."""

    @abc.abstractmethod
    def terminate(
        self, residual: _ResidualFn, z: Float[Array, " m"], args: PyTree, state: Any
    ) -> tuple[Bool[Array, ""], RESULTS]:
        """`(done, result)`: whether to stop, and the status so far (successful while
        the iteration goes on or after it converged)."""

    @abc.abstractmethod
    def postprocess(
        self, residual: _ResidualFn, z: Float[Array, " m"], args: PyTree, state: Any
    ) -> tuple[Float[Array, " m"], dict[str, Any]]:
        """The root returned, and the solver's own statistics."""

    def complementarity_solver(self) -> "AbstractKKTSolver":
        """The solver that takes this one's place on a KKT system with
        complementarity rows (inequality constraints), whose residual is only
        semismooth.

        By default there is none, and this raises a `ValueError`;
        [`constrained_jax.Newton`][] answers with the
        [`constrained_jax.SemismoothNewton`][] of its tolerances and linear solver,
        and `SemismoothNewton` with itself.
        """
        raise ValueError(
            f"`{type(self).__name__}` cannot solve a KKT system with inequality "
            "constraints (its complementarity rows are only semismooth): pass "
            "`solver=cjax.SemismoothNewton(rtol=..., atol=..., linear_solver=...)`, "
            "or a `cjax.Newton`, whose tolerances and linear solver it takes."
        )


def iterate(
    solver: AbstractKKTSolver,
    residual: _ResidualFn,
    z0: Float[Array, " m"],
    args: PyTree,
    max_steps: int,
    start_ok: Bool[Array, ""],
    unrolled: int = 0,
) -> tuple[Float[Array, " m"], RESULTS, dict[str, Any]]:
    """Find `z` with `residual(z, args) = 0` by `solver`, starting at `z0`: one
    `lax.while_loop` over `solver.step` until `solver.terminate` or `max_steps`.
    The first `unrolled` steps are straight-line code before the loop, which XLA
    fuses with the code around it (for small systems solved inside another loop).

    `start_ok` is false when the inputs are not finite: no step is taken and the
    status is `RESULTS.invalid_input`. An iteration still going after `max_steps`
    steps is `RESULTS.nonlinear_max_steps_reached`.

    **Returns:** `(z, result, stats)`, `stats` with `num_steps` and the solver's own.
    """

    def cond(carry):
        z, num_steps, state = carry
        done, _ = solver.terminate(residual, z, args, state)
        return start_ok & jnp.invert(done) & (num_steps < max_steps)

    def body(carry):
        z, num_steps, state = carry
        z, state = solver.step(residual, z, args, state)
        return z, num_steps + 1, state

    carry = (z0, jnp.array(0), solver.init(residual, z0, args))
    for _ in range(unrolled):
        carry = jtu.tree_map(ft.partial(jnp.where, cond(carry)), body(carry), carry)
    z, num_steps, state = lax.while_loop(cond, body, carry)
    done, result = solver.terminate(residual, z, args, state)
    result = RESULTS.where(
        (result == RESULTS.successful) & jnp.invert(done),
        RESULTS.nonlinear_max_steps_reached,
        result,
    )
    result = RESULTS.where(start_ok, result, RESULTS.invalid_input)
    z, stats = solver.postprocess(residual, z, args, state)
    return z, result, {"num_steps": num_steps, **stats}
