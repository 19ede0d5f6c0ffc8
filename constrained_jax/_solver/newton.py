"""[`constrained_jax.Newton`][]: Newton's method on a smooth KKT residual, with an
affine-covariant line search."""

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool

from .._results import RESULTS
from .dense_lu import DenseLU
from .kkt_solver import AbstractKKTSolver
from .semismooth_newton import SemismoothNewton


class _NewtonState(eqx.Module):
    done: Bool[Array, ""]
    result: RESULTS


def _rms(x: Array) -> Array:
    return jnp.sqrt(jnp.mean(jnp.square(x))) if x.size else jnp.zeros((), x.dtype)


class Newton(AbstractKKTSolver):
    """Newton's method on the full KKT system, globalised by an affine-covariant
    line search.

    Each step solves `K dz = -r` with the KKT matrix `K` (the Jacobian of the residual
    `r`, built by autodiff) through Lineax. The step length `a` is halved until the
    *natural monotonicity test* holds: the simplified Newton correction at the trial
    point, `dz' = -K^{-1} r(z + a dz)` (same factorisation), must shrink,
    `|dz'| <= (1 - a/4) |dz|`, in the scaled norm `rms(v / (atol + rtol |z|))`.
    Unlike a test on `|r|`, this is invariant under rescaling of the equations and of
    the unknowns, so badly scaled problems (lengths of 1e3 next to heights of 1e-1)
    take full Newton steps. It converges from any start whose path avoids singular
    `K`; otherwise it stops and says why (`RESULTS.singular_kkt`,
    `RESULTS.line_search_failed`, `RESULTS.nonfinite_objective` where `F` or `G` or
    their derivatives are NaN or inf, `RESULTS.linear_solve_failed` where an
    iterative linear solver did not converge).

    Converged when the full Newton step is within tolerance, `|dz| < 1` in that
    scaled norm; the step is then taken (so the error is of the order of the square
    of the tolerance). Tolerances below `100 eps` of the dtype are raised to it: a
    Newton step computed from a residual at round-off is the round-off amplified by
    the conditioning of `K`, and a tighter test can stall there (the float32 sphere
    geodesic, `Chebyshev(24)`, stalled with steps of about `120 eps` of the unknowns
    under a `10 eps` floor). Float32: `100 eps = 1.2e-5`, the accuracy float32 can
    promise; float64: `2.2e-14`, far below the default `1e-10`.

    The default `linear_solver` is [`constrained_jax.DenseLU`][], which forms `K`.
    For large problems use a matrix-free one,
    `Newton(linear_solver=constrained_jax.MINRES(rtol=1e-11, atol=0.0))`: each
    Krylov iteration is then one Hessian-vector product, and no matrix is formed.

    With inequality constraints the KKT residual is only semismooth; `Newton` then
    hands the solve to the [`constrained_jax.SemismoothNewton`][] of its `rtol`,
    `atol`, `linear_solver` and `max_backtracks` (`complementarity_solver`).

    **Reference:** P. Deuflhard, *Newton Methods for Nonlinear Problems: Affine
    Invariance and Adaptive Algorithms*, Springer (2004), section 3.3 (NLEQ-ERR).
    """

    rtol: float = 1e-10
    atol: float = 1e-10
    linear_solver: lx.AbstractLinearSolver = DenseLU()
    max_backtracks: int = 40

    def __check_init__(self):
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if isinstance(value, (int, float)) and not value >= 0:
                raise ValueError(f"`Newton({name}=...)` must be non-negative.")
        if (
            isinstance(self.rtol, (int, float))
            and isinstance(self.atol, (int, float))
            and self.rtol == 0
            and self.atol == 0
        ):
            raise ValueError("`Newton` needs a positive `rtol` or `atol`.")

    def _tolerances(self, dtype):
        floor = 100 * jnp.finfo(dtype).eps
        rtol = jnp.maximum(jnp.asarray(self.rtol, dtype), floor)
        atol = jnp.asarray(self.atol, dtype)
        atol = jnp.where(atol > 0, jnp.maximum(atol, floor), atol)
        return rtol, atol

    def init(self, residual, z, args):
        del residual, args
        return _NewtonState(done=jnp.array(False), result=RESULTS.successful)

    def step(self, residual, z, args, state):
        dtype = z.dtype
        rtol, atol = self._tolerances(dtype)
        structure = jax.ShapeDtypeStruct(z.shape, dtype)
        solver = self.linear_solver
        r, lin = jax.linearize(lambda z_: residual(z_, args), z)
        operator = lx.FunctionLinearOperator(lin, structure, lx.symmetric_tag)
        linear_state = solver.init(operator, {})

        def newton_direction(rhs):
            sol = lx.linear_solve(
                operator, rhs, solver, state=linear_state, throw=False
            )
            return sol.value, sol.result

        dz, lin_result = newton_direction(-r)
        # F, G or their derivatives undefined at z: said so, whatever the linear
        # solver makes of a NaN right-hand side.
        defined = jnp.all(jnp.isfinite(r))
        lin_ok = (
            defined & (lin_result == lx.RESULTS.successful) & jnp.all(jnp.isfinite(dz))
        )
        dz = jnp.where(lin_ok, dz, 0.0)
        scale = atol + rtol * jnp.abs(z)
        norm = lambda v: _rms(v / scale)
        dz_norm = norm(dz)
        converged = jnp.all(r == 0) | (lin_ok & (dz_norm < 1))

        def contraction(alpha):
            # A trial point where the residual is not finite (outside the domain of
            # F or G) is rejected before any linear solve sees it, for every linear
            # solver alike.
            r_trial = residual(z + alpha * dz, args)
            simplified, _ = newton_direction(-r_trial)
            theta = norm(simplified) / dz_norm
            ok = jnp.all(jnp.isfinite(r_trial)) & jnp.isfinite(theta)
            return jnp.where(ok, theta, jnp.inf)

        def ls_cond(c):
            alpha, theta, it = c
            return jnp.invert(theta <= 1 - alpha / 4) & (it < self.max_backtracks)

        def ls_body(c):
            alpha, _, it = c
            alpha = 0.5 * alpha
            return alpha, contraction(alpha), it + 1

        one = jnp.ones((), dtype)
        alpha, theta, _ = lax.while_loop(
            ls_cond, ls_body, (one, contraction(one), jnp.array(0))
        )
        ls_ok = theta <= 1 - alpha / 4
        alpha = jnp.where(converged, one, alpha)
        z_new = z + alpha * dz
        finite = jnp.all(jnp.isfinite(z_new))
        # Why the Newton step could not be computed: NaN or inf in the residual or
        # the matrix (F or G undefined there: a non-finite residual is checked
        # here, and DenseLU and MINRES report a non-finite matrix as
        # `nonfinite_input`); a singular KKT matrix; otherwise an iterative solver
        # that did not converge.
        failed_result = RESULTS.where(
            jnp.invert(defined) | (lin_result == lx.RESULTS.nonfinite_input),
            RESULTS.nonfinite_objective,
            RESULTS.where(
                lin_result == lx.RESULTS.singular,
                RESULTS.singular_kkt,
                RESULTS.linear_solve_failed,
            ),
        )
        result = RESULTS.where(
            converged,
            RESULTS.successful,
            RESULTS.where(
                jnp.invert(lin_ok),
                failed_result,
                RESULTS.where(
                    jnp.invert(ls_ok), RESULTS.line_search_failed, state.result
                ),
            ),
        )
        moved = converged | (lin_ok & ls_ok)
        # (A step that is not taken keeps the status that says why.)
        result = RESULTS.where(moved & jnp.invert(finite), RESULTS.nonfinite, result)
        z_new = jnp.where(moved & finite, z_new, z)
        done = converged | (result != RESULTS.successful)
        return z_new, _NewtonState(done=done, result=result)

    def terminate(self, residual, z, args, state):
        del residual, z, args
        return state.done, state.result

    def postprocess(self, residual, z, args, state):
        del residual, args, state
        return z, {}

    def complementarity_solver(self) -> SemismoothNewton:
        """With inequality constraints: the [`constrained_jax.SemismoothNewton`][]
        with this solver's `rtol`, `atol`, `linear_solver` and `max_backtracks`."""
        return SemismoothNewton(
            rtol=self.rtol,
            atol=self.atol,
            linear_solver=self.linear_solver,
            max_backtracks=self.max_backtracks,
        )


Newton.__init__.__doc__ = """**Arguments:**

- `rtol`, `atol`: relative and absolute tolerance on the unknowns `z = (x, lambda)`.
- `linear_solver`: a Lineax solver for `K dz = -r` (and for the backward pass).
    [`constrained_jax.DenseLU`][] (default) forms `K`;
    [`constrained_jax.MINRES`][] is matrix-free.
- `max_backtracks`: halvings of the step before the line search gives up.
"""
