"""Saddle-point (KKT) machinery shared by every pillar of the library.

Every problem here reduces to finding a root `z = (x, lambda)` of a KKT residual whose
Jacobian is the symmetric saddle-point matrix

    K = [[H, J^T],
         [J, 0  ]],

with `H` the Hessian of the Lagrangian `F* = F + lambda . G` and `J = dG/dx`. This
module holds

- `kkt_residual`: `(grad F + J^T lambda, G)` by one reverse-mode pass;
- `constraint_jacobian`, `tangent_projector`: the constraint geometry;
- `AbstractKKTSolver` and its globalised `Newton` iteration, whose linear solves go
  through Lineax (dense [`constrained_jax.DenseLU`][] or matrix-free
  [`constrained_jax.MINRES`][]);
- `reduced_hessian_extremes`: the Hessian of `F*` restricted to the tangent space of
  the constraints, by Lanczos, which decides minimum / maximum / saddle.
"""

from collections.abc import Callable

import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ._solver.dense_lu import dense_factor, dense_solve


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
