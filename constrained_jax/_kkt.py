"""Saddle-point (KKT) machinery shared by every pillar of the library.

Every problem here reduces to finding a root `z = (x, lambda)` of a KKT residual whose
Jacobian is the symmetric saddle-point matrix

    K = [[H, J^T],
         [J, 0  ]],

with `H` the Hessian of the Lagrangian `F* = F + lambda . G` and `J = dG/dx`. This
module holds

- `kkt_residual`: `(grad F + J^T lambda, G)` by one reverse-mode pass;
- `constraint_jacobian`, `tangent_projector`: the constraint geometry;
- `reduced_hessian_extremes`: the Hessian of `F*` restricted to the tangent space of
  the constraints, by Lanczos, which decides minimum / maximum / saddle;
- `kkt_solve`: the one constrained solve (start check, an `AbstractKKTSolver` from
  `_solver/newton.py` run to convergence, derivatives by the implicit function
  theorem, the final residual) that every pillar calls.
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool, Float, PyTree

from ._implicit import implicit_jvp
from ._misc import check_max_steps
from ._results import RESULTS
from ._solver.dense_lu import dense_factor, dense_solve
from ._solver.newton import AbstractKKTSolver, iterate


# ---------------------------------------------------------------------------------
# Residual and geometry
# ---------------------------------------------------------------------------------


def kkt_residual(
    objective: Callable,
    constraints: Callable | None,
    z: Float[Array, " n+k"],
    args: PyTree,
    n: int,
) -> Float[Array, " n+k"]:
    """The KKT residual of `F* = F + lambda . G` at `z = (x, lambda)`.

    Returns the concatenation of `grad F(x) + J(x)^T lambda` (`n` entries, the
    stationarity of `F*` in `x`) and `G(x)` (`k` entries, its stationarity in
    `lambda`), computed with one forward and one reverse pass.
    """
    x, lam = z[:n], z[n:]
    if constraints is None:
        return jax.grad(objective)(x, args)

    def both(x_):
        return objective(x_, args), constraints(x_, args)

    (f, g), vjp = jax.vjp(both, x)
    (grad_star,) = vjp((jnp.ones_like(f), lam))
    return jnp.concatenate([grad_star, g])


def constraint_jacobian(
    constraints: Callable, x: Float[Array, " n"], args: PyTree
) -> Float[Array, "k n"]:
    """`J = dG/dx`, one reverse pass per constraint (cheap when `k` is small)."""
    return jax.jacrev(constraints)(x, args)


def gram_factors(jac: Float[Array, "k n"]):
    """Factor `J J^T`; its `singular` flag says the constraints are dependent."""
    return dense_factor(jac @ jac.T, unroll_max=12)


def tangent_projector(jac: Float[Array, "k n"], factors) -> Callable:
    """`P v = v - J^T (J J^T)^{-1} J v`: orthogonal projection onto `ker J`."""
    return lambda v: v - jac.T @ dense_solve(factors, jac @ v, unroll_max=12)


def least_squares_multipliers(
    grad_f: Float[Array, " n"], jac: Float[Array, "k n"], factors
) -> Float[Array, " k"]:
    """The `lambda` minimising `|grad F + J^T lambda|`: `-(J J^T)^{-1} J grad F`."""
    return -dense_solve(factors, jac @ grad_f, unroll_max=12)


def reduced_hessian_extremes(
    hvp: Callable[[Float[Array, " n"]], Float[Array, " n"]],
    project: Callable[[Float[Array, " n"]], Float[Array, " n"]],
    n: int,
    k: int,
    dtype,
    num_steps: int = 64,
) -> Float[Array, "2"]:
    """Smallest and largest eigenvalue of the Hessian restricted to `ker J`.

    Lanczos with full reorthogonalisation on `v -> P H P v`, started from a fixed
    pseudo-random vector. When `n - k <= num_steps` the Krylov space is the whole
    tangent space and the eigenvalues are exact up to round-off; otherwise they are
    the extreme Ritz values (which approach the true extremes from inside the
    spectrum).

    Returns `[nan, nan]` when the tangent space is `{0}` (`k == n`).
    """
    m = min(n - k, num_steps)
    if m <= 0:
        return jnp.full((2,), jnp.nan, dtype)
    start = jax.random.normal(jax.random.key(0), (n,), dtype)
    v = project(start)
    v = v / jnp.linalg.norm(v)
    basis = jnp.zeros((m, n), dtype).at[0].set(v)
    alphas = jnp.zeros((m,), dtype)
    betas = jnp.zeros((m,), dtype)
    eps = jnp.finfo(dtype).eps

    def body(j, carry):
        basis, alphas, betas, broken = carry
        vj = basis[j]
        w = project(hvp(project(vj)))
        alpha = jnp.dot(w, vj)
        # Full reorthogonalisation (twice is enough) against the basis so far.
        # Rows of `basis` past j are still zero, so no masking is needed.
        for _ in range(2):
            w = w - basis.T @ (basis @ w)
        w = project(w)
        beta = jnp.linalg.norm(w)
        scale = jnp.maximum(jnp.max(jnp.abs(alphas)), jnp.abs(alpha))
        new_broken = broken | (beta <= 100 * eps * jnp.maximum(scale, 1.0))
        # After a breakdown the Krylov space is invariant: it already holds every
        # distinct eigenvalue (the start vector is generic). Pad with decoupled
        # copies of the first Ritz value so that no spurious eigenvalue appears.
        alpha = jnp.where(broken, alphas[0], alpha)
        alphas = alphas.at[j].set(alpha)
        betas = betas.at[j].set(jnp.where(new_broken, 0.0, beta))
        safe = jnp.where(new_broken, 1.0, beta)
        next_v = jnp.where(new_broken, 0.0, w / safe)
        basis = lax.cond(
            j + 1 < m, lambda b: b.at[j + 1].set(next_v), lambda b: b, basis
        )
        return basis, alphas, betas, new_broken

    basis, alphas, betas, _ = lax.fori_loop(
        0, m, body, (basis, alphas, betas, jnp.array(False))
    )
    if m == 1:
        return jnp.stack([alphas[0], alphas[0]])
    off = betas[: m - 1]
    tri = jnp.diag(alphas) + jnp.diag(off, 1) + jnp.diag(off, -1)
    eigs = jnp.linalg.eigvalsh(tri)
    return jnp.stack([eigs[0], eigs[-1]])


# ---------------------------------------------------------------------------------
# The constrained solve
# ---------------------------------------------------------------------------------


def check_kkt_solver(solver: AbstractKKTSolver, max_steps: int) -> None:
    """Trace-time checks of the arguments of every constrained solve."""
    if not isinstance(solver, AbstractKKTSolver):
        raise ValueError(
            f"`solver` must be a constrained_jax solver such as `cjax.Newton()`, got "
            f"{type(solver).__name__}."
        )
    check_max_steps(max_steps)


def _primal(inputs):
    objective, constraints, solver, z0, args, n, max_steps, start_ok, strategy = inputs
    residual = lambda z, a: kkt_residual(objective, constraints, z, a, n)
    solve = lambda res, z_start, ok: iterate(solver, res, z_start, args, max_steps, ok)
    if strategy is None:
        z, result, stats = solve(residual, z0, start_ok)
    else:
        z, result, stats = strategy(solve, residual, z0, args, start_ok)
    return z, (result, stats)


def _rewrite(z, aux, inputs):
    del aux
    objective, constraints, _, _, args, n, _, _, _ = inputs
    return kkt_residual(objective, constraints, z, args, n)


def kkt_solve(
    objective: Callable,
    constraints: Callable | None,
    x0: Float[Array, " n"],
    lam0: Float[Array, " k"],
    args: PyTree,
    solver: AbstractKKTSolver,
    max_steps: int,
    start_ok: Bool[Array, ""],
    strategy: Callable | None = None,
) -> tuple[Float[Array, " n+k"], RESULTS, dict[str, Any], Float[Array, " n+k"]]:
    """The constrained solve shared by [`constrained_jax.extremize`][] and
    [`constrained_jax.solve_functional`][]: a root `z = (x, lambda)` of the KKT
    residual of `F* = F + lambda . G`, differentiable by the implicit function theorem.

    **Arguments:**

    - `objective`, `constraints`: `F(x, args)`, `G(x, args)` on flat `x` (`G` may be
        `None`); closure-converted here, so they may close over traced arrays.
    - `x0`, `lam0`: the start; not differentiated. Where not `start_ok` it is returned
        as it is.
    - `args`: the parameters, differentiated through the implicit function theorem.
    - `solver`, `max_steps`: run by `constrained_jax._solver.newton.iterate`.
    - `start_ok`: false when the start is not usable (no step is taken, the status is
        `RESULTS.invalid_input`).
    - `strategy`: `None`, or a pytree callable `strategy(solve, residual, z0, args,
        start_ok) -> (z, result, stats)` that drives the solve (e.g. continuation),
        with `solve(residual, z_start, start_ok)` one run of the solver.

    **Returns:** `(z, result, stats, residual)`: the root, with derivatives (NaN where
    the solve failed, see `constrained_jax._implicit`); its status; `num_steps`,
    `max_steps` and `kkt_residual` (root mean square); the KKT residual at `z`
    (not differentiated).
    """
    n = x0.shape[0]
    objective = eqx.filter_closure_convert(objective, x0, args)
    if constraints is not None:
        constraints = eqx.filter_closure_convert(constraints, x0, args)
    z0 = lax.stop_gradient(jnp.concatenate([x0, lam0]))
    inputs = (
        objective,
        constraints,
        solver,
        z0,
        args,
        n,
        max_steps,
        start_ok,
        strategy,
    )
    tags = frozenset({lx.symmetric_tag})
    z, (result, stats) = implicit_jvp(
        _primal, _rewrite, inputs, tags, solver.linear_solver
    )
    residual = kkt_residual(objective, constraints, lax.stop_gradient(z), args, n)
    stats = {
        **stats,
        "max_steps": max_steps,
        "kkt_residual": jnp.sqrt(jnp.mean(jnp.square(residual))),
    }
    return z, result, stats, residual
