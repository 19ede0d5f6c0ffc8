"""The constrained solve shared by every nonlinear solve of the library.

Every such problem is a root `z = (x, lambda, mu)` of KKT conditions: `n` unknowns
`x`, `k` equality multipliers `lambda`, `m` inequality multipliers `mu`,

    e(z, args) = 0                                    (n + k equations)
    s mu_i >= 0,  H_i(x, args) <= 0,  mu_i H_i = 0    (m complementarity rows)

(`s = +1` to minimize, `-1` to maximize). For a Lagrangian `F* = F + lambda . G +
mu . H` the equations are its stationarity, `(grad F + J^T lambda + A^T mu, G)`,
whose Jacobian (`m = 0`) is the symmetric saddle-point matrix

    K = [[Hess F*, J^T],
         [J,       0  ]],

`J = dG/dx`, `A = dH/dx`; `m = 0` is the equality-constrained case. This module holds

- `KKTProblem`: those conditions as a value (the equations, `H`, the layout `n, k, m`,
  the sign `s`); `lagrangian_problem` builds one from `F`, `G`, `H`;
- `kkt_solve`: the one constrained solve (an `AbstractKKTSolver` run to convergence
  by `iterate`, the complementarity check, derivatives by the implicit function
  theorem, the final residual), used by [`constrained_jax.extremize`][],
  [`constrained_jax.solve_functional`][] and the variational integrator;
- `kkt_residual`: `(grad F + J^T lambda, G)` by one reverse-mode pass;
- `constraint_jacobian`, `tangent_projector`: the constraint geometry;
- `reduced_hessian_extremes`: the Hessian of `F*` restricted to the tangent space of
  the constraints (formed for small `n`, Lanczos beyond), which decides minimum /
  maximum / saddle.
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
from ._inequalities import complementarity_check, fischer_burmeister
from ._misc import check_max_steps
from ._results import RESULTS
from ._solver.dense_lu import dense_factor, dense_solve
from ._solver.kkt_solver import AbstractKKTSolver, iterate, KKTResidual


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

    Up to `n = num_steps` unknowns the restricted Hessian is formed instead (`n`
    Hessian-vector products in one batch, an orthonormal basis of the range of the
    projector from its eigendecomposition) and its extreme eigenvalues taken
    directly: the same eigenvalues as the exact Lanczos run, from a program with no
    loop, which compiles faster.

    Returns `[nan, nan]` when the tangent space is `{0}` (`k == n`, or a projector
    onto `{0}`).
    """
    m = min(n - k, num_steps)
    if m <= 0:
        return jnp.full((2,), jnp.nan, dtype)
    if n <= num_steps:
        return _dense_extremes(hvp, project, n, dtype)
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


def _dense_extremes(hvp, project, n: int, dtype) -> Float[Array, "2"]:
    """`reduced_hessian_extremes` for small `n`, from the formed matrix."""
    eye = jnp.eye(n, dtype=dtype)
    proj = jax.vmap(project)(eye)
    proj = 0.5 * (proj + proj.T)
    # The range of the orthogonal projector: its eigenvectors of eigenvalue one.
    levels, vecs = jnp.linalg.eigh(proj)
    inside = levels > 0.5
    hess = vecs.T @ jax.vmap(hvp)(vecs.T).T
    hess = 0.5 * (hess + hess.T)
    hess = jnp.where(inside[:, None] & inside[None, :], hess, 0.0)
    # Directions outside the range moved beyond the spectrum (on either side), so
    # that the extreme eigenvalues are those of the restricted Hessian.
    big = 2 * jnp.max(jnp.sum(jnp.abs(hess), axis=1)) + 1
    shift = jnp.where(inside, 0.0, big)
    lo = jnp.linalg.eigvalsh(hess + jnp.diag(shift))[0]
    hi = jnp.linalg.eigvalsh(hess - jnp.diag(shift))[-1]
    return jnp.where(jnp.any(inside), jnp.stack([lo, hi]), jnp.nan)


# ---------------------------------------------------------------------------------
# The problem
# ---------------------------------------------------------------------------------


class _Stationarity(eqx.Module):
    """`e(z, args) = (grad F + J^T lambda + A^T mu, G)`, the stationarity of
    `F* = F + lambda . G + mu . H` in `(x, lambda)`, by one reverse-mode pass."""

    objective: Callable
    constraints: Callable | None
    inequalities: Callable | None
    n: int = eqx.field(static=True)
    k: int = eqx.field(static=True)

    def __call__(self, z, args):
        if self.inequalities is None:
            return kkt_residual(self.objective, self.constraints, z, args, self.n)
        n, k = self.n, self.k
        x, lam, mu = z[:n], z[n : n + k], z[n + k :]

        def values(x_):
            f = self.objective(x_, args)
            if self.constraints is None:
                g = jnp.zeros((0,), x_.dtype)
            else:
                g = self.constraints(x_, args)
            return f, g, self.inequalities(x_, args)

        (f, g, _), vjp = jax.vjp(values, x)
        (grad_star,) = vjp((jnp.ones_like(f), lam, mu))
        return jnp.concatenate([grad_star, g])


class KKTProblem(eqx.Module):
    """The KKT conditions of a constrained solve, as a value.

    The unknowns are `z = (x, lambda, mu)`, of sizes `n`, `k`, `m`; the conditions are

        equations(z, args) = 0                                      (n + k rows)
        s mu_i >= 0,  -inequalities(x, args)_i >= 0,  mu_i H_i = 0   (m rows)

    with `s = sign`. `m = 0` is the smooth (equality) case, whose residual is the
    equations themselves; otherwise the complementarity rows are written with the
    Fischer-Burmeister function, `phi(s mu, -H) = 0`, which vanishes exactly where
    they hold (`constrained_jax._inequalities`). `symmetric` says whether the
    Jacobian of the equations is symmetric (a KKT matrix) or not (the variational
    integrator's steps), which the implicit derivative passes to the linear solver.
    `bounds` says that every inequality is a bound: `H` comes in blocks of `n` rows,
    row `i` of a block depending on `x_i` alone (`lower - x`, `x - upper`), so that
    `dH/dx` is diagonal in each block and never needs to be formed.
    """

    equations: Callable
    inequalities: Callable | None
    n: int = eqx.field(static=True)
    k: int = eqx.field(static=True)
    m: int = eqx.field(static=True, default=0)
    sign: float = eqx.field(static=True, default=1.0)
    symmetric: bool = eqx.field(static=True, default=True)
    bounds: bool = eqx.field(static=True, default=False)

    def bound_derivatives(self, x, args):
        """`dH/dx` of a problem whose inequalities are bounds, as its diagonals,
        shape `(m // n, n)`: `-1` on the rows `lower - x`, `+1` on `x - upper`, `0`
        for an infinite bound (one product with a vector of ones)."""
        ones = jnp.ones_like(x)
        _, diag = jax.jvp(lambda x_: self.inequalities(x_, args), (x,), (ones,))
        return diag.reshape(self.m // self.n, self.n)

    def split(self, z):
        """`(x, lambda, mu)`."""
        n, k = self.n, self.k
        return z[:n], z[n : n + k], z[n + k :]

    def residual(self, z, args):
        """The residual whose root the solver finds: the equations, then
        `phi(s mu, -H)` for the complementarity rows."""
        if not self.m:
            return self.equations(z, args)
        x, _, mu = self.split(z)
        h = self.inequalities(x, args)
        return jnp.concatenate(
            [self.equations(z, args), fischer_burmeister(self.sign * mu, -h)]
        )

    def rewrite(self, z, strict, args):
        """The equations the implicit function theorem differentiates: the equations,
        with the strictly active inequalities (`strict`) as equalities `H_i = 0` and
        the others as `mu_i = 0`. For a Lagrangian their Jacobian is symmetric,

            [[Hess_x F*, J^T, A_S^T, 0],
             [J,         0,   0,     0],
             [A_S,       0,   0,     0],
             [0,         0,   0,     I]]

        (`A_S` the strictly active rows of `dH/dx`), so the solver's own (symmetric,
        possibly matrix-free) `linear_solver` solves the tangent system."""
        if not self.m:
            return self.equations(z, args)
        weight = strict.astype(z.dtype)
        x, lam, mu = self.split(z)
        e = self.equations(jnp.concatenate([x, lam, mu * weight]), args)
        h = self.inequalities(x, args)
        # A blend, not `jnp.where`: reverse mode then carries the NaN cotangents of a
        # failed solve into every input (`where` would send them a zero).
        return jnp.concatenate([e, weight * h + (1 - weight) * mu])


def lagrangian_problem(
    objective: Callable,
    constraints: Callable | None,
    inequalities: Callable | None,
    x0: Float[Array, " n"],
    args: PyTree,
    sign: float = 1.0,
    bounds: bool = False,
) -> KKTProblem:
    """The `KKTProblem` of extremizing `F(x, args)` subject to `G(x, args) = 0` and
    `H(x, args) <= 0` (`G`, `H` may be `None`), on flat `x` shaped like `x0`
    (`bounds`: `H` is bounds only, see `KKTProblem`).

    The functions are closure-converted here, so they may close over traced arrays,
    which are then differentiated like `args`."""
    n = x0.shape[0]
    objective = eqx.filter_closure_convert(objective, x0, args)
    k = m = 0
    if constraints is not None:
        constraints = eqx.filter_closure_convert(constraints, x0, args)
        k = eqx.filter_eval_shape(constraints, x0, args).shape[0]
    if inequalities is not None:
        inequalities = eqx.filter_closure_convert(inequalities, x0, args)
        m = eqx.filter_eval_shape(inequalities, x0, args).shape[0]
    equations = _Stationarity(objective, constraints, inequalities, n, k)
    return KKTProblem(equations, inequalities, n, k, m, sign, bounds=bounds)


# ---------------------------------------------------------------------------------
# The constrained solve
# ---------------------------------------------------------------------------------


class KKTSolution(eqx.Module):
    """The result of `kkt_solve`.

    - `z`: the root `(x, lambda, mu)`, with derivatives by the implicit function
        theorem (NaN where the solve failed, see `constrained_jax._implicit`).
    - `result`: the status of the iteration (not yet judged by the caller's
        diagnostics).
    - `residual`: the residual at `z` (not differentiated).
    - `stats`: `num_steps`, `max_steps`, `kkt_residual` (root mean square of
        `residual`), the solver's own; with complementarity rows also
        `kkt_violation` (the largest relative violation of the KKT conditions) and
        `kkt_tolerance` (the tolerance it is judged by).
    - `active`, `strict`: where `H_i = 0`, and where also `mu_i != 0` (shape `(m,)`).
    - `infeasibility`: the largest relative `H_i > 0` (zero without inequalities).
    """

    z: Float[Array, " N"]
    result: RESULTS
    residual: Float[Array, " N"]
    stats: dict[str, Any]
    active: Bool[Array, " m"]
    strict: Bool[Array, " m"]
    infeasibility: Float[Array, ""]


def check_kkt_solver(solver: AbstractKKTSolver, max_steps: int) -> None:
    """Trace-time checks of the arguments of every constrained solve."""
    if not isinstance(solver, AbstractKKTSolver):
        raise ValueError(
            f"`solver` must be a constrained_jax solver such as `cjax.Newton()`, got "
            f"{type(solver).__name__}."
        )
    check_max_steps(max_steps)


def _primal(inputs):
    problem, solver, z0, args, max_steps, start_ok, strategy, unrolled, tol = inputs

    def solve(residual, z_start, ok):
        return iterate(solver, residual, z_start, args, max_steps, ok, unrolled)

    if strategy is None:
        residual = problem.residual
        if problem.m:
            # The layout lets the semismooth solver regularise its steps.
            residual = KKTResidual(
                residual, problem.n, problem.sign, problem.k, problem.bounds
            )
        z, result, stats = solve(residual, z0, start_ok)
    else:
        z, result, stats = strategy(solve, problem.residual, z0, args, start_ok)
    if problem.m:
        check = complementarity_check(problem, z, args, tol)
        stats = {**stats, **check}
    return z, (result, stats)


def _rewrite(z, aux, inputs):
    problem, args = inputs[0], inputs[3]
    _, stats = aux
    return problem.rewrite(z, stats.get("strict"), args)


def kkt_solve(
    problem: KKTProblem,
    solver: AbstractKKTSolver,
    z0: Float[Array, " N"],
    args: PyTree,
    max_steps: int,
    start_ok: Bool[Array, ""],
    *,
    strategy: Callable | None = None,
    unrolled: int = 0,
) -> KKTSolution:
    """A root of the KKT conditions of `problem`, differentiable by the implicit
    function theorem: the constrained solve of [`constrained_jax.extremize`][],
    [`constrained_jax.solve_functional`][] and the variational integrator.

    **Arguments:**

    - `problem`: the [`KKTProblem`][]; arrays it closes over (closure-converted) are
        differentiated like `args`.
    - `solver`: an `AbstractKKTSolver`. With complementarity rows (`problem.m > 0`)
        its `complementarity_solver()` runs instead, a
        [`constrained_jax.SemismoothNewton`][] whose `rtol`, `atol` also set the
        tolerance of the check of the KKT conditions, `sqrt(max(rtol, atol,
        100 eps))`.
    - `z0`: the start `(x0, lambda0, mu0)`; not differentiated. Where not `start_ok`
        it is returned as it is.
    - `args`: the parameters, differentiated through the implicit function theorem.
    - `max_steps`: the most steps of `constrained_jax._solver.kkt_solver.iterate`.
    - `start_ok`: false when the start is not usable (no step is taken, the status is
        `RESULTS.invalid_input`).
    - `strategy`: `None`, or a pytree callable `strategy(solve, residual, z0, args,
        start_ok) -> (z, result, stats)` that drives the solve (e.g. continuation),
        with `solve(residual, z_start, start_ok)` one run of the solver.
    - `unrolled`: steps of the iteration written as straight-line code before its
        loop (see `iterate`).

    **Returns:** a `KKTSolution`.
    """
    dtype = z0.dtype
    if problem.m:
        solver = solver.complementarity_solver()
        floor = 100 * float(jnp.finfo(dtype).eps)
        rtol = jnp.asarray(solver.rtol, dtype)
        tol = jnp.sqrt(jnp.maximum(jnp.maximum(rtol, solver.atol), floor)).astype(dtype)
    else:
        tol = None
    z0 = lax.stop_gradient(z0)
    inputs = (problem, solver, z0, args, max_steps, start_ok, strategy, unrolled, tol)
    tags = frozenset({lx.symmetric_tag}) if problem.symmetric else frozenset()
    z, (result, stats) = implicit_jvp(
        _primal, _rewrite, inputs, tags, solver.linear_solver
    )
    residual = problem.residual(lax.stop_gradient(z), args)
    stats = dict(stats)
    if problem.m:
        active = stats.pop("active")
        strict = stats.pop("strict")
        infeasibility = stats.pop("infeasibility")
        stats["kkt_violation"] = stats.pop("violation")
        stats["kkt_tolerance"] = tol
    else:
        active = strict = jnp.zeros((0,), bool)
        infeasibility = jnp.zeros((), dtype)
    stats = {
        **stats,
        "max_steps": max_steps,
        "kkt_residual": jnp.sqrt(jnp.mean(jnp.square(residual))),
    }
    return KKTSolution(z, result, residual, stats, active, strict, infeasibility)
