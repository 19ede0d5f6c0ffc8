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

import abc
import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.scipy as jsp
import lineax as lx
from jaxtyping import Array, Bool, Float, Int, PyTree

from ._linalg import (
    dense_factor,
    dense_solve,
    DenseLU,
    ldl_factor_unrolled,
    ldl_solve_unrolled,
)
from ._results import RESULTS


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
# Saddle-point solves of mechanics: [[M, -A^T], [A, 0]] [x; lambda] = [f; -b]
# ---------------------------------------------------------------------------------


class AbstractSaddlePointSolver(eqx.Module):
    """A method for the saddle-point system of constrained mechanics,

        M x - A^T lambda = f,    A x = -b,

    with `M` (n x n) symmetric and `A` (k x n). The system is nonsingular exactly when
    `A` has full row rank and `M` is positive definite on the null space of `A`; `M`
    itself may be singular.

    **Free gauge directions.** A direction `v` with `M v = 0` and `A v = 0` (no
    inertia, and free of the constraints: a massless coordinate that nothing couples
    to, like the spin of the rolling cylinder with `I = 0` once it has let go) makes
    the system singular, but it need not make it unsolvable. If no force acts along it
    (`f . v = 0` to round-off) the equations hold for every component of `x` along `v`:
    such a direction is a free gauge, and the solvers return the solution whose
    unknown at the vanishing pivot is zero (for a massless coordinate: its
    acceleration is zero, so its velocity is held). If a force acts along it
    (`f . v != 0`, e.g. a potential gradient on a massless coordinate) the equations
    are inconsistent and the solve reports `singular`. Redundant constraints (`A`
    rank-deficient) are always reported `singular`: their multipliers are not unique.
    """

    @abc.abstractmethod
    def solve(
        self,
        mass: Float[Array, "n n"],
        jac: Float[Array, "k n"],
        rhs: Float[Array, " n"],
        bias: Float[Array, " k"],
    ) -> tuple[Float[Array, " n"], Float[Array, " k"], Bool[Array, ""]]:
        """Returns `(x, lambda, singular)`; when `singular`, `x` and `lambda` are 0.

        `singular` is false for a free gauge direction (no inertia, no force, see the
        class docstring): `x` is then the solution with zero component at its pivot.
        """


def _lu_solve_gauge(lu, perm, zero, b, unrolled: bool):
    """Solve `P K x = L U x = b[perm]` given an LU factorisation whose pivots `zero`
    vanish: those unknowns are set to 0 and their rows of `U x = y` are dropped (the
    caller checks the residual)."""
    m = lu.shape[-1]
    if unrolled:
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
            xs[i] = jnp.where(zero[i], 0.0, s / jnp.where(zero[i], 1.0, lu[i, i]))
        return jnp.stack(xs)
    y = jsp.linalg.solve_triangular(lu, b[perm], lower=True, unit_diagonal=True)
    y = jnp.where(zero, 0.0, y)
    upper = jnp.where(zero[:, None], jnp.eye(m, dtype=lu.dtype), jnp.triu(lu))
    return jsp.linalg.solve_triangular(upper, y, lower=False)


class FullKKTLU(AbstractSaddlePointSolver):
    """Forms the `(n + k)` square KKT matrix and factors it by LU with partial
    pivoting (unrolled up to `unroll_max` unknowns, LAPACK above).

    Needs nothing but a nonsingular KKT matrix, so it also handles Lagrangians whose
    `M` is indefinite. Under `jax.vmap` the pivoting (row selection, permutation)
    becomes batched `dot`s and gathers that XLA on CPU does not fuse: for small
    systems it costs several times [`constrained_jax.RangeSpaceLDL`][].

    A pivot below `10 m eps` of the largest entry counts as zero. Zero pivots in the
    columns of `x` are free gauge directions (see
    [`constrained_jax.AbstractSaddlePointSolver`][]): their unknowns are set to zero
    and the solution is accepted only if it satisfies the whole system to round-off
    (`|K z - r| <= 100 m eps (|K| |z|_1 + |r|)`), i.e. if no force acts along them.
    Zero pivots in the columns of `lambda` (redundant constraints) are `singular`.
    Partial pivoting is not rank-revealing: for a gauge direction that is not along a
    coordinate it may leave the dependent row where a later column needs it, and then
    reports `singular` (never a wrong answer); [`constrained_jax.RangeSpaceLDL`][]
    solves those. A massless coordinate that nothing couples to (a zero row and
    column) is always handled.
    """

    unroll_max: int = 12

    def solve(self, mass, jac, rhs, bias):
        n, k = mass.shape[0], jac.shape[0]
        if k == 0:
            matrix, vector = mass, rhs
        else:
            zeros = jnp.zeros((k, k), mass.dtype)
            matrix = jnp.block([[mass, -jac.T], [jac, zeros]])
            vector = jnp.concatenate([rhs, -bias])
        m = n + k
        lu, perm, _ = dense_factor(matrix, self.unroll_max)
        eps = jnp.finfo(matrix.dtype).eps
        scale = jnp.max(jnp.abs(matrix))
        zero = jnp.abs(jnp.diagonal(lu)) <= 10 * m * eps * scale
        sol = _lu_solve_gauge(lu, perm, zero, vector, m <= self.unroll_max)
        # With vanishing pivots the dropped rows are consistency conditions: the
        # solution stands only if the whole system holds to round-off.
        residual = jnp.max(jnp.abs(matrix @ sol - vector))
        size = scale * jnp.sum(jnp.abs(sol)) + jnp.max(jnp.abs(vector))
        consistent = residual <= 100 * m * eps * size
        singular = jnp.any(zero[n:]) | (jnp.any(zero) & jnp.invert(consistent))
        singular = singular | jnp.invert(jnp.all(jnp.isfinite(sol)))
        sol = jnp.where(singular, 0.0, sol)
        return sol[:n], sol[n:], singular


def _ldl_factor_gauge(a: list[list[Array]]):
    """`a = L D L^T` without pivoting (symmetric `a` as nested lists of scalars,
    unrolled), allowing zero pivots with a zero column: a positive semidefinite `a`
    with null directions.

    Returns `(L, d, null, breakdown)`: `L[i][j]` (`j < i`), the pivots `d[j]` (1 at a
    zero pivot), `null[j]` (the pivot is below `10 m eps max|a|`), and
    `breakdown`: a zero pivot whose column is not zero
    (impossible for positive semidefinite `a`, where `|t| <= sqrt(d_i d_j)`): an
    indefinite matrix that needs pivoting. A zero pivot's column of `L` is 0, so the
    factorisation is that of `a` with its null directions split off: forward
    substitution gives, at a zero pivot `j`, the component `b . v_j` of the
    right-hand side along the null vector `v_j = L^-T e_j` (`a v_j = 0`).
    """
    m = len(a)
    scale = functools.reduce(jnp.maximum, [jnp.abs(x) for row in a for x in row])
    threshold = 10 * m * jnp.finfo(jnp.result_type(scale)).eps * scale
    column_threshold = 2 * jnp.sqrt(threshold * scale)
    lower: list[list[Array]] = [[] for _ in range(m)]
    d: list[Array] = []
    null: list[Array] = []
    breakdown = jnp.array(False)
    for j in range(m):
        s = a[j][j]
        for p in range(j):
            s = s - lower[j][p] * lower[j][p] * d[p]
        small = jnp.abs(s) <= threshold
        null.append(small)
        safe = jnp.where(small, jnp.ones_like(s), s)
        d.append(safe)
        for i in range(j + 1, m):
            t = a[i][j]
            for p in range(j):
                t = t - lower[i][p] * lower[j][p] * d[p]
            breakdown = breakdown | (small & (jnp.abs(t) > column_threshold))
            lower[i].append(jnp.where(small, jnp.zeros_like(t), t / safe))
    return lower, d, null, breakdown


def _ldl_solve_gauge(lower, d, null, b: list[Array], size=None):
    """Solve `L D L^T x = b` from `_ldl_factor_gauge`, with `x`'s entries at zero
    pivots set to 0. Returns `(x, inconsistent)`: `inconsistent` when `b` has a
    component along a null direction beyond round-off (`|b . v_j| > 100 m eps
    size`, `size = max|b|` unless given): no solution exists."""
    m = len(d)
    y: list[Array] = []
    for i in range(m):
        s = b[i]
        for p in range(i):
            s = s - lower[i][p] * y[p]
        y.append(s)
    if size is None:
        size = functools.reduce(jnp.maximum, [jnp.abs(v) for v in b])
    tol = 100 * m * jnp.finfo(jnp.result_type(size)).eps * size
    inconsistent = functools.reduce(
        jnp.logical_or, [null[j] & (jnp.abs(y[j]) > tol) for j in range(m)]
    )
    x: list = [None] * m
    for i in reversed(range(m)):
        s = jnp.where(null[i], jnp.zeros_like(y[i]), y[i] / d[i])
        for p in range(i + 1, m):
            s = s - lower[p][i] * x[p]
        x[i] = s
    return x, inconsistent


class RangeSpaceLDL(AbstractSaddlePointSolver):
    """The range-space (Schur complement) method on the augmented mass matrix.

    Adding `rho A^T (A x + b) = 0` to the first block row gives the equivalent system

        M~ x - A^T lambda = f - rho A^T b,   M~ = M + rho A^T A,

    and `M~` is positive definite whenever `M` is positive semidefinite and the KKT
    matrix is nonsingular, even when `M` is singular (a massless direction that the
    constraints fix, as for the rolling cylinder with `I = 0`). Then

        (A M~^-1 A^T) lambda = -b - A M~^-1 (f - rho A^T b),
        x = M~^-1 (f - rho A^T b + A^T lambda),

    with `M~` and the Schur complement factored by `L D L^T` without pivoting,
    `rho = tr M / tr(A A^T)` (same units as `M`, so the scaling of the problem is kept).
    Every operation is written on scalars and unrolled, so that under `jax.vmap` it
    fuses into a few elementwise loops: on the scenes of `benchmarks/dynamics.py` it is
    several times faster than [`constrained_jax.FullKKTLU`][] and close to hand-written
    equations. Systems with `n + k > unroll_max` use `FullKKTLU`.

    **Free gauge directions.** For positive semidefinite `M`, `M~` is singular exactly
    when some `v != 0` has `M v = 0` and `A v = 0` (see
    [`constrained_jax.AbstractSaddlePointSolver`][]). Its pivot vanishes (below
    `10 m eps` of the largest entry, with a zero column): the unknown at that pivot is
    set to zero, after checking that the right-hand side `f` and the rows of `A` have
    no component along `v` beyond round-off; otherwise the system is `singular` (a
    force along a direction without inertia). So the rolling cylinder with `I = 0`
    keeps its spin rate once it flies free, and a massless coordinate with a
    potential gradient on it is refused.

    !!! note

        A pivot below `10 m eps` of the largest entry with a nonzero column counts as
        a breakdown and the system is reported singular. For positive semidefinite `M`
        (every kinetic energy) that never happens. For an *indefinite* `M` (not a
        kinetic energy) the elimination may break down on a nonsingular KKT matrix:
        use [`constrained_jax.FullKKTLU`][]. A vanishing pivot of the Schur complement
        (redundant constraints) is reported singular.

    **Reference:** J. Nocedal and S. J. Wright, *Numerical Optimization*, 2nd ed.,
    Springer (2006), sections 16.2-16.3 (range-space method, augmented Lagrangian).
    """

    unroll_max: int = 12

    def solve(self, mass, jac, rhs, bias):
        n, k = mass.shape[0], jac.shape[0]
        if n + k > self.unroll_max:
            return FullKKTLU(unroll_max=0).solve(mass, jac, rhs, bias)
        m = [[mass[i, j] for j in range(n)] for i in range(n)]
        a = [[jac[r, i] for i in range(n)] for r in range(k)]
        f = [rhs[i] for i in range(n)]
        b = [bias[r] for r in range(k)]
        if k > 0:
            trace_m = sum(jnp.abs(m[i][i]) for i in range(n))
            trace_a = sum(a[r][i] * a[r][i] for r in range(k) for i in range(n))
            one = jnp.ones_like(trace_m)
            rho = jnp.where(trace_m > 0, trace_m, one) / jnp.where(
                trace_a > 0, trace_a, one
            )
            m = [
                [
                    m[i][j] + rho * sum(a[r][i] * a[r][j] for r in range(k))
                    for j in range(n)
                ]
                for i in range(n)
            ]
            f = [f[i] - rho * sum(a[r][i] * b[r] for r in range(k)) for i in range(n)]
        lower, d, null, singular = _ldl_factor_gauge(m)
        u, inconsistent = _ldl_solve_gauge(lower, d, null, f)
        singular = singular | inconsistent
        if k == 0:
            x = jnp.stack(u)
            return jnp.where(singular, 0.0, x), jnp.zeros((0,), x.dtype), singular
        y = []  # M~^-1 A^T
        size_a = functools.reduce(jnp.maximum, [jnp.abs(v) for row in a for v in row])
        for r in range(k):
            y_r, inconsistent = _ldl_solve_gauge(lower, d, null, a[r], size_a)
            y.append(y_r)
            singular = singular | inconsistent
        schur = [
            [sum(a[r][i] * y[s][i] for i in range(n)) for s in range(k)]
            for r in range(k)
        ]
        lower_s, d_s, singular_s = ldl_factor_unrolled(schur)
        lam = ldl_solve_unrolled(
            lower_s,
            d_s,
            [-b[r] - sum(a[r][i] * u[i] for i in range(n)) for r in range(k)],
        )
        x = [u[i] + sum(y[r][i] * lam[r] for r in range(k)) for i in range(n)]
        singular = singular | singular_s
        x, lam = jnp.stack(x), jnp.stack(lam)
        return jnp.where(singular, 0.0, x), jnp.where(singular, 0.0, lam), singular


FullKKTLU.__init__.__doc__ = RangeSpaceLDL.__init__.__doc__ = """**Arguments:**

- `unroll_max`: the largest `n + k` solved by unrolled elimination (trace and compile
    time grow like `(n + k)**3`); larger systems use LAPACK's LU on the full matrix.
"""


# ---------------------------------------------------------------------------------
# Solvers
# ---------------------------------------------------------------------------------


class AbstractKKTSolver(eqx.Module):
    """A method for finding a root of a symmetric KKT residual.

    Subclasses implement `solve`; `linear_solver` is also used by the implicit function
    theorem in the backward pass, so that derivatives cost one more linear solve of
    the same kind (never an unrolled iteration).
    """

    linear_solver: eqx.AbstractVar[lx.AbstractLinearSolver]

    @abc.abstractmethod
    def solve(
        self,
        residual: Callable[[Float[Array, " m"], PyTree], Float[Array, " m"]],
        z0: Float[Array, " m"],
        args: PyTree,
        max_steps: int,
        start_ok: Bool[Array, ""],
    ) -> tuple[Float[Array, " m"], RESULTS, dict[str, Int[Array, ""]]]:
        """Find `z` with `residual(z, args) = 0`, starting at `z0`.

        `start_ok` is false when the inputs are not finite: no step is taken and the
        status is `RESULTS.invalid_input`.
        """


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
    of the tolerance). Tolerances below `10 eps` of the dtype (unreachable in
    floating point) are raised to it.

    The default `linear_solver` is [`constrained_jax.DenseLU`][], which forms `K`.
    For large problems use a matrix-free one,
    `Newton(linear_solver=constrained_jax.MINRES(rtol=1e-11, atol=0.0))`: each
    Krylov iteration is then one Hessian-vector product, and no matrix is formed.

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

    def solve(self, residual, z0, args, max_steps, start_ok):
        dtype = z0.dtype
        floor = 10 * jnp.finfo(dtype).eps
        rtol = jnp.maximum(jnp.asarray(self.rtol, dtype), floor)
        atol = jnp.asarray(self.atol, dtype)
        atol = jnp.where(atol > 0, jnp.maximum(atol, floor), atol)
        structure = jax.ShapeDtypeStruct(z0.shape, dtype)
        solver = self.linear_solver

        def cond(carry):
            _, step, result, done = carry
            return jnp.invert(done) & (step < max_steps)

        def body(carry):
            z, step, result, _ = carry
            r, lin = jax.linearize(lambda z_: residual(z_, args), z)
            operator = lx.FunctionLinearOperator(lin, structure, lx.symmetric_tag)
            state = solver.init(operator, {})

            def newton_direction(rhs):
                sol = lx.linear_solve(operator, rhs, solver, state=state, throw=False)
                return sol.value, sol.result

            dz, lin_result = newton_direction(-r)
            lin_ok = (lin_result == lx.RESULTS.successful) & jnp.all(jnp.isfinite(dz))
            dz = jnp.where(lin_ok, dz, 0.0)
            scale = atol + rtol * jnp.abs(z)
            norm = lambda v: _rms(v / scale)
            dz_norm = norm(dz)
            converged = jnp.all(r == 0) | (lin_ok & (dz_norm < 1))

            def contraction(alpha):
                simplified, _ = newton_direction(-residual(z + alpha * dz, args))
                theta = norm(simplified) / dz_norm
                return jnp.where(jnp.isfinite(theta), theta, jnp.inf)

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
            # Why the Newton step could not be computed: a singular KKT matrix; NaN
            # or inf in the residual or the matrix (F or G undefined there: DenseLU
            # and MINRES report it as `nonfinite_input`, and Lineax does so when the
            # right-hand side is not finite); otherwise an iterative solver that did
            # not converge.
            failed_result = RESULTS.where(
                lin_result == lx.RESULTS.singular,
                RESULTS.singular_kkt,
                RESULTS.where(
                    lin_result == lx.RESULTS.nonfinite_input,
                    RESULTS.nonfinite_objective,
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
                        jnp.invert(ls_ok), RESULTS.line_search_failed, result
                    ),
                ),
            )
            moved = converged | (lin_ok & ls_ok)
            # (A step that is not taken keeps the status that says why.)
            result = RESULTS.where(
                moved & jnp.invert(finite), RESULTS.nonfinite, result
            )
            z_new = jnp.where(moved & finite, z_new, z)
            done = converged | (result != RESULTS.successful)
            return z_new, step + 1, result, done

        init_result = RESULTS.where(start_ok, RESULTS.successful, RESULTS.invalid_input)
        init = (z0, jnp.array(0), init_result, jnp.invert(start_ok))
        z, num_steps, result, done = lax.while_loop(cond, body, init)
        result = RESULTS.where(
            (result == RESULTS.successful) & jnp.invert(done),
            RESULTS.nonlinear_max_steps_reached,
            result,
        )
        return z, result, {"num_steps": num_steps}


Newton.__init__.__doc__ = """**Arguments:**

- `rtol`, `atol`: relative and absolute tolerance on the unknowns `z = (x, lambda)`.
- `linear_solver`: a Lineax solver for `K dz = -r` (and for the backward pass).
    [`constrained_jax.DenseLU`][] (default) forms `K`;
    [`constrained_jax.MINRES`][] is matrix-free.
- `max_backtracks`: halvings of the step before the line search gives up.
"""
