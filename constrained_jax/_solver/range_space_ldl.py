"""The saddle-point system by the range-space method on scalars
([`constrained_jax.RangeSpaceLDL`][])."""

import jax.numpy as jnp

from .full_kkt_lu import FullKKTLU
from .ldl import (
    add,
    dot,
    inactive_pivots,
    ldl_factor_unrolled,
    ldl_solve_unrolled,
    mask_inactive_rows,
    max_abs,
    minus_sum,
    schur_solve_unrolled,
)
from .saddle_point import AbstractSaddlePointSolver, KKTForm, mask_singular


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
    fuses into a few elementwise loops: for small systems it is several times faster
    than [`constrained_jax.FullKKTLU`][] and close to hand-written equations
    (`benchmarks/dynamics.py`). Systems with `n + k > unroll_max` use `FullKKTLU`.

    **Structure.** With `sparse=True` (the default) `M` and `A` come with the
    patterns detected at trace time (see [`constrained_jax.KKTForm`][]): the
    structural zeros of `M~`, of its factor (fill-in tracked symbolically), of
    `M~^-1 A^T` and of the Schur complement are skipped; the arithmetic on the rest
    is the dense one.

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
    sparse: bool = True

    def form(self, n: int, k: int) -> KKTForm:
        return KKTForm(sparse=self.sparse, unroll=n + k <= self.unroll_max)

    def solve(self, system, fill):
        n, k = system.n, system.k
        if n + k > self.unroll_max:
            return FullKKTLU(unroll_max=0).solve(system, fill)
        rhs, bias = system.rhs, system.bias
        m = system.mass.entries()
        a = system.jac.entries()
        f = [rhs[i] for i in range(n)]
        b = [bias[r] for r in range(k)]
        active = system.active if k > 0 else None
        if active is not None:
            # Inactive rows: zero in `A` and `b`, and `c` on the Schur complement's
            # diagonal (see `AbstractSaddlePointSolver`).
            a, b = mask_inactive_rows(a, b, active)
        if k > 0:
            diag_m = [m[i][i] for i in range(n) if m[i][i] is not None]
            trace_m = (
                sum(jnp.abs(v) for v in diag_m) if diag_m else jnp.zeros_like(f[0])
            )
            trace_a = dot([v for row in a for v in row], [v for row in a for v in row])
            trace_a = jnp.zeros_like(trace_m) if trace_a is None else trace_a
            one = jnp.ones_like(trace_m)
            rho = jnp.where(trace_m > 0, trace_m, one) / jnp.where(
                trace_a > 0, trace_a, one
            )
            columns = [[a[r][i] for r in range(k)] for i in range(n)]
            m = [
                [add(m[i][j], dot(columns[i], columns[j]), rho) for j in range(n)]
                for i in range(n)
            ]
            f = [add(f[i], dot(columns[i], b), -rho) for i in range(n)]
        lower, d, null, breakdown = ldl_factor_unrolled(m, gauge=True)
        u, inconsistent = ldl_solve_unrolled(lower, d, f, null)
        singular = breakdown | inconsistent
        u = [jnp.zeros_like(rhs[0]) if v is None else v for v in u]
        if k == 0:
            x = jnp.stack(u)
            singular = singular | jnp.invert(jnp.all(jnp.isfinite(x)))
            return (
                mask_singular(x, n, singular, fill),
                jnp.zeros((0,), x.dtype),
                singular,
            )
        y = []  # M~^-1 A^T
        # The rows of A along a null direction v of M~ (the A-row check). For
        # positive semidefinite M it is redundant: v^T M~ v = v^T M v + rho |A v|^2
        # = 0 forces A v = 0. It stays for indefinite M, where the column check of
        # the factorisation need not fire: M = [[-1/2, -1/2], [-1/2, 1/2]],
        # A = [1, 1] (a nonsingular KKT matrix) gives rho = 1/2, M~ = diag(0, 1),
        # whose zero pivot has a zero column, but A v = 1: without this check the
        # solve would return a wrong answer instead of reporting `singular`. (Nor
        # can `M_ii >= 0` replace it for a diagonal M: in a nearly singular case,
        # M = diag(1, 0), A = (1, 1e-8), the pivot of M~ falls below the threshold
        # while A v is of order 1e-8, far above round-off; only this check refuses.)
        size_a = max_abs([v for row in a for v in row if v is not None])
        for r in range(k):
            y_r, inconsistent = ldl_solve_unrolled(lower, d, a[r], null, size_a)
            y.append(y_r)
            singular = singular | inconsistent
        schur = [[dot(a[r], y[s]) for s in range(k)] for r in range(k)]
        if active is not None:
            schur = inactive_pivots(schur, active, rhs.dtype)
        lam, singular_s = schur_solve_unrolled(
            schur, [minus_sum(-b[r], [dot(a[r], u)]) for r in range(k)]
        )
        lam = [jnp.zeros_like(rhs[0]) if v is None else v for v in lam]
        x = [add(u[i], dot([y[r][i] for r in range(k)], lam)) for i in range(n)]
        singular = singular | singular_s
        sol = jnp.stack(x + lam)
        # A non-finite input (NaN, inf) or an overflow: `singular`, as the other
        # solvers report it.
        singular = singular | jnp.invert(jnp.all(jnp.isfinite(sol)))
        # One `where` on both parts (XLA then evaluates the flag in fewer fusions).
        sol = mask_singular(sol, n, singular, fill)
        return sol[:n], sol[n:], singular


RangeSpaceLDL.__init__.__doc__ = """**Arguments:**

- `unroll_max`: the largest `n + k` solved by unrolled elimination (trace and compile
    time grow like `(n + k)**3`); larger systems use LAPACK's LU on the full matrix.
- `sparse`: take `M` and `A` with their detected sparsity patterns (skipping
    structural zeros), or dense (nothing detected, nothing checked).
"""
