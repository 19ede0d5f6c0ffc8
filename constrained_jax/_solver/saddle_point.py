"""Solvers for the saddle-point systems of constrained mechanics,

    [[M, -A^T], [A, 0]] [x; lambda] = [f; -b],

by the full KKT matrix ([`constrained_jax.FullKKTLU`][]) or by the range-space method
on scalars ([`constrained_jax.RangeSpaceLDL`][]); both handle free gauge directions.
"""

import abc
import functools

import equinox as eqx
import jax.numpy as jnp
import jax.scipy as jsp
import numpy as np
from jaxtyping import Array, Bool, Float

from .dense_lu import dense_factor, lu_solve_unrolled
from .sparse import as_dense, SparseMatrix


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

    **Non-finite values.** The library's solvers also report a solution that is not
    finite (NaN or inf in the inputs, or an overflow) as `singular`, with zeros, and
    say so by `reports_non_finite()`; `LagrangianSystem` then refuses a solve by a NaN
    right-hand side. A solver of your own need not (the default is `False`): the
    system then masks its solution itself.
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

    def structured(self) -> bool:
        """Whether `solve` takes `M` and `A` as `SparseMatrix`es with patterns
        detected at trace time (`LagrangianSystem` then builds them so, checking the
        patterns at run time); if `False` it gets dense arrays and no pattern."""
        return False

    def reports_non_finite(self) -> bool:
        """Whether `solve` reports a solution that is not finite as `singular`, with
        zeros (a NaN right-hand side then refuses a solve). `False` by default:
        `LagrangianSystem` then masks the solution itself."""
        return False

    def unrolled(self, n: int, k: int) -> bool:
        """Whether `solve` is unrolled scalar code for `n` unknowns and `k`
        constraints, which XLA fuses under `jax.vmap`. `LagrangianSystem` then writes
        its assembly of `M`, `A` and the bias on scalars too (for up to 24 entries),
        so that a batch of states runs as one fused loop; otherwise on arrays, which
        compiles to a smaller program. `True` by default."""
        return True

    def _solve_nan_x(self, mass, jac, rhs, bias):
        """`solve`, with `x` NaN (not zero) when `singular`: what `simulate`'s vector
        field wants (a NaN derivative makes the step fail). A solver that branches
        may set it inside its branches, where XLA fuses it into the solve
        (`Automatic`: a single two-cylinder trajectory 3.9 -> 3.4 us per step), not
        as a `where` on the branch's output."""
        return nan_on_singular(self.solve)(mass, jac, rhs, bias)


def nan_on_singular(solve):
    """`solve`, with `x` NaN (not zero) where the solve is `singular`."""

    def filled(*args):
        x, lam, singular = solve(*args)
        return jnp.where(singular, jnp.nan, x), lam, singular

    return filled


def _lu_solve_gauge(lu, perm, zero, b, unrolled: bool):
    """Solve `P K x = L U x = b[perm]` given an LU factorisation whose pivots `zero`
    vanish: those unknowns are set to 0 and their rows of `U x = y` are dropped (the
    caller checks the residual)."""
    m = lu.shape[-1]
    if unrolled:
        return lu_solve_unrolled(lu, perm, b, zero)
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

    The rows of `M` (and so the unknowns `lambda`) are first scaled by
    `max|A| / max|M|`, so that the two blocks have the same size whatever the units
    (a mass of `1e-300` next to an `A` of order 1 is not mistaken for zero; `lambda`
    is scaled back). A pivot below `10 m eps` of the largest entry counts as zero.
    Zero pivots in the columns of `x` are free gauge directions (see
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

    def reports_non_finite(self) -> bool:
        return True

    def unrolled(self, n: int, k: int) -> bool:
        return n + k <= self.unroll_max

    def solve(self, mass, jac, rhs, bias):
        mass, jac = as_dense(mass), as_dense(jac)
        n, k = mass.shape[0], jac.shape[0]
        if k == 0:
            matrix, vector = mass, rhs
            block_scale = None
        else:
            # (M x - A^T lambda) / s = f / s with s = max|M| / max|A|: the unknowns
            # are x and lambda / s.
            size_m, size_a = jnp.max(jnp.abs(mass)), jnp.max(jnp.abs(jac))
            ratio = size_m / size_a
            usable = (size_m > 0) & (size_a > 0) & (ratio > 0) & jnp.isfinite(ratio)
            block_scale = jnp.where(usable, ratio, 1.0)
            zeros = jnp.zeros((k, k), mass.dtype)
            matrix = jnp.block([[mass / block_scale, -jac.T], [jac, zeros]])
            vector = jnp.concatenate([rhs / block_scale, -bias])
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
        lam = sol[n:] if block_scale is None else sol[n:] * block_scale
        return sol[:n], lam, singular


def _max_abs(values: list) -> Array:
    return functools.reduce(jnp.maximum, [jnp.abs(v) for v in values])


def _minus_sum(start, products: list):
    """`start - sum(products)`, where `None` is a structural zero (so is the
    result when every term is one)."""
    out = start
    for term in products:
        if term is not None:
            out = -term if out is None else out - term
    return out


def _dot(u: list, v: list):
    """`sum_i u_i v_i` over the entries that are not structural zeros (`None`; so is
    the result when every term is one). The products are added in order, the first
    one alone: the values of `_minus_sum(None, [-u_i v_i, ...])` bit for bit, without
    its negations (a fifth of the traced operations of an unrolled solve)."""
    out = None
    for a, b in zip(u, v, strict=True):
        if a is not None and b is not None:
            out = a * b if out is None else out + a * b
    return out


def ldl_factor_unrolled(a: list[list], gauge: bool = False):
    """`a = L D L^T` without pivoting, on a symmetric matrix given as nested lists of
    scalars, unrolled at trace time.

    Working on scalars keeps every operation elementwise: under `jax.vmap` the whole
    factorisation fuses into a few loops over the batch (matrix slicing and `@` would
    become batched `dot`s and gathers, which XLA on CPU does not fuse). Without
    pivoting this is backward stable for positive definite `a`; for an indefinite `a`
    it works whenever no leading principal minor vanishes.

    Entries that are `None` are structural zeros: they cost nothing, and the fill-in
    is tracked symbolically (an entry of `L` is `None` when every term of it is), so
    a diagonal or banded `a` costs what its nonzeros cost. The arithmetic on the
    other entries is that of the dense elimination, so the results agree to the last
    bit. (A structurally zero diagonal entry is a zero pivot.)

    A pivot below `10 m eps max|a|` is a zero pivot (`null[j]`), replaced by 1 in `d`
    so that nothing is NaN. What it means depends on `gauge`:

    - `gauge=False`: any zero pivot is a `breakdown` (`a` is taken to be nonsingular).
    - `gauge=True`: zero pivots with a zero column are allowed (a positive
        semidefinite `a` with null directions). That column of `L` is set to 0, so the
        factorisation is that of `a` with its null directions split off: forward
        substitution gives, at a zero pivot `j`, the component `b . v_j` of the
        right-hand side along the null vector `v_j = L^-T e_j` (`a v_j = 0`).
        `breakdown` is a zero pivot whose column is not zero (beyond
        `2 sqrt(threshold max|a|)`): impossible for positive semidefinite `a`, where
        `t^2 <= d_i d_j`, so an indefinite matrix that needs pivoting.

    Returns `(L, d, null, breakdown)`: `L[i][j]` for `j < i` (unit diagonal implied;
    `None` where structurally zero), the pivots `d`, the zero-pivot flags `null` and
    the `breakdown` flag.
    """
    m = len(a)
    # `a` is symmetric: its lower triangle holds every entry.
    entries = [a[i][j] for i in range(m) for j in range(i + 1) if a[i][j] is not None]
    scale = _max_abs(entries)
    threshold = 10 * m * jnp.finfo(jnp.result_type(scale)).eps * scale
    # The column test `|t| > 2 sqrt(threshold scale)`, squared: no square root.
    column_threshold_sq = 4 * threshold * scale
    zero = jnp.zeros_like(scale)
    lower: list[list] = [[] for _ in range(m)]
    d: list[Array] = []
    null: list[Array] = []
    breakdown = jnp.array(False)
    for j in range(m):
        s = _minus_sum(
            a[j][j],
            [
                None if lower[j][p] is None else lower[j][p] * lower[j][p] * d[p]
                for p in range(j)
            ],
        )
        s = zero if s is None else s
        small = jnp.abs(s) <= threshold
        null.append(small)
        safe = jnp.where(small, jnp.ones_like(s), s)
        d.append(safe)
        column_big = []
        for i in range(j + 1, m):
            t = _minus_sum(
                a[i][j],
                [
                    None
                    if lower[i][p] is None or lower[j][p] is None
                    else lower[i][p] * lower[j][p] * d[p]
                    for p in range(j)
                ],
            )
            if t is None:
                lower[i].append(None)
            elif gauge:
                column_big.append(t * t > column_threshold_sq)
                lower[i].append(jnp.where(small, jnp.zeros_like(t), t / safe))
            else:
                lower[i].append(t / safe)
        if not gauge:
            breakdown = breakdown | small
        elif column_big:
            breakdown = breakdown | (
                small & functools.reduce(jnp.logical_or, column_big)
            )
    return lower, d, null, breakdown


def ldl_solve_unrolled(lower, d, b: list, null=None, size=None):
    """Solve `L D L^T x = b` given `ldl_factor_unrolled` (lists of scalars; `None`
    entries of `L` and `b` are structural zeros, and so are those of `x` that
    nothing fills).

    With the zero-pivot flags `null` of a `gauge=True` factorisation, `x`'s entries at
    zero pivots are set to 0, and `inconsistent` says that `b` has a component along
    a null direction beyond round-off (`|b . v_j| > 100 m eps size`, `size = max|b|`
    unless given): no solution exists. Without `null`, `inconsistent` is false.

    Returns `(x, inconsistent)`.
    """
    m = len(d)
    y: list = []
    for i in range(m):
        y.append(
            _minus_sum(
                b[i],
                [
                    None if lower[i][p] is None or y[p] is None else lower[i][p] * y[p]
                    for p in range(i)
                ],
            )
        )
    inconsistent = jnp.array(False)
    if null is not None:
        if size is None:
            size = _max_abs([v for v in b if v is not None])
        tol = 100 * m * jnp.finfo(jnp.result_type(size)).eps * size
        flags = [null[j] & (jnp.abs(y[j]) > tol) for j in range(m) if y[j] is not None]
        if flags:
            inconsistent = functools.reduce(jnp.logical_or, flags)
    x: list = [None] * m
    for i in reversed(range(m)):
        if y[i] is None:
            s = None
        elif null is None:
            s = y[i] / d[i]
        else:
            s = jnp.where(null[i], jnp.zeros_like(y[i]), y[i] / d[i])
        x[i] = _minus_sum(
            s,
            [
                None if lower[p][i] is None or x[p] is None else lower[p][i] * x[p]
                for p in range(i + 1, m)
            ],
        )
    return x, inconsistent


def schur_solve_unrolled(schur: list[list], right: list):
    """`(lam, breakdown)`: `S lam = right` for the symmetric Schur complement `S` of
    a range-space method (nested lists of scalars), by `ldl_factor_unrolled` and
    `ldl_solve_unrolled`; `breakdown` flags a vanishing pivot.

    For callers that report a solution that is not finite as `singular` (both
    range-space solvers). With one constraint, `S` is `1 x 1` and the pivot test,
    `|s| <= 10 eps |s|`, holds for `s = 0` and `s = +-inf` only: both make
    `right / s` not finite (`inf` is taken as NaN), so no test is made and
    `breakdown` is false, with the same values and flag in the end, bit for bit.
    Under `jax.vmap` the test was a flag array that XLA writes out as a pass over the
    batch of its own (the Cartesian pendulum, 1e4 states, one thread: 1.15x ->
    1.05x the hand-written equations, `benchmarks/README.md`).
    """
    if len(schur) == 1 and schur[0][0] is not None:
        s = schur[0][0]
        return [right[0] / jnp.where(jnp.isinf(s), jnp.nan, s)], jnp.array(False)
    lower, d, _, breakdown = ldl_factor_unrolled(schur)
    lam, _ = ldl_solve_unrolled(lower, d, right)
    return lam, breakdown


def _entries(matrix, shape) -> list[list]:
    """Nested lists of scalars, `None` outside the pattern of a `SparseMatrix`."""
    rows, cols = shape
    if isinstance(matrix, SparseMatrix):
        out: list[list] = [[None] * cols for _ in range(rows)]
        for p, (i, j) in enumerate(zip(matrix.rows, matrix.cols, strict=True)):
            out[i][j] = matrix.values[p]
        return out
    return [[matrix[i, j] for j in range(cols)] for i in range(rows)]


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

    **Structure.** Given `M` and `A` as sparse matrices (as `LagrangianSystem` passes
    them when `sparse=True`: patterns detected at trace time), the structural zeros
    of `M~`, of its factor (fill-in tracked symbolically), of `M~^-1 A^T` and of the
    Schur complement are skipped; the arithmetic on the rest is the dense one.

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

    def structured(self) -> bool:
        return self.sparse

    def reports_non_finite(self) -> bool:
        return True

    def unrolled(self, n: int, k: int) -> bool:
        return n + k <= self.unroll_max

    def solve(self, mass, jac, rhs, bias):
        n, k = rhs.shape[0], bias.shape[0]
        if n + k > self.unroll_max:
            return FullKKTLU(unroll_max=0).solve(mass, jac, rhs, bias)
        m = _entries(mass, (n, n))
        a = _entries(jac, (k, n))
        f = [rhs[i] for i in range(n)]
        b = [bias[r] for r in range(k)]
        if k > 0:
            diag_m = [m[i][i] for i in range(n) if m[i][i] is not None]
            trace_m = (
                sum(jnp.abs(v) for v in diag_m) if diag_m else jnp.zeros_like(f[0])
            )
            trace_a = _dot([v for row in a for v in row], [v for row in a for v in row])
            trace_a = jnp.zeros_like(trace_m) if trace_a is None else trace_a
            one = jnp.ones_like(trace_m)
            rho = jnp.where(trace_m > 0, trace_m, one) / jnp.where(
                trace_a > 0, trace_a, one
            )
            columns = [[a[r][i] for r in range(k)] for i in range(n)]
            m = [
                [_add(m[i][j], _dot(columns[i], columns[j]), rho) for j in range(n)]
                for i in range(n)
            ]
            f = [_add(f[i], _dot(columns[i], b), -rho) for i in range(n)]
        lower, d, null, breakdown = ldl_factor_unrolled(m, gauge=True)
        u, inconsistent = ldl_solve_unrolled(lower, d, f, null)
        singular = breakdown | inconsistent
        u = [jnp.zeros_like(rhs[0]) if v is None else v for v in u]
        if k == 0:
            x = jnp.stack(u)
            singular = singular | jnp.invert(jnp.all(jnp.isfinite(x)))
            return jnp.where(singular, 0.0, x), jnp.zeros((0,), x.dtype), singular
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
        size_a = _max_abs([v for row in a for v in row if v is not None])
        for r in range(k):
            y_r, inconsistent = ldl_solve_unrolled(lower, d, a[r], null, size_a)
            y.append(y_r)
            singular = singular | inconsistent
        schur = [[_dot(a[r], y[s]) for s in range(k)] for r in range(k)]
        lam, singular_s = schur_solve_unrolled(
            schur, [_minus_sum(-b[r], [_dot(a[r], u)]) for r in range(k)]
        )
        lam = [jnp.zeros_like(rhs[0]) if v is None else v for v in lam]
        x = [_add(u[i], _dot([y[r][i] for r in range(k)], lam)) for i in range(n)]
        singular = singular | singular_s
        sol = jnp.stack(x + lam)
        # A non-finite input (NaN, inf) or an overflow: `singular`, as the other
        # solvers report it.
        singular = singular | jnp.invert(jnp.all(jnp.isfinite(sol)))
        # One `where` on both parts (XLA then evaluates the flag in fewer fusions).
        sol = jnp.where(singular, 0.0, sol)
        return sol[:n], sol[n:], singular


def _add(value, term, factor=None):
    """`value + factor * term` (`value + term` without `factor`), with `None` as a
    structural zero."""
    if term is None:
        return value
    if factor is None:
        return term if value is None else value + term
    if value is None:
        return factor * term
    return value + factor * term


FullKKTLU.__init__.__doc__ = RangeSpaceLDL.__init__.__doc__ = """**Arguments:**

- `unroll_max`: the largest `n + k` solved by unrolled elimination (trace and compile
    time grow like `(n + k)**3`); larger systems use LAPACK's LU on the full matrix.
"""


class Automatic(AbstractSaddlePointSolver):
    """The default: a method chosen at trace time from the structure and size.

    - `n + k <= unroll_max` with a structurally diagonal `M` (Cartesian coordinates,
        the scenes' pendulum and cylinders): the range-space method with the
        reciprocals of the masses, unrolled on the nonzeros of `A`
        (`constrained_jax._solver.diagonal`; under `jax.vmap` about as fast as
        hand-written equations). A mass that vanishes at run time while `A` couples
        it (the rolling cylinder with `I = 0`) is solved by `RangeSpaceLDL` instead,
        for the whole batch, and only when some state of the batch needs it.
    - other `n + k <= unroll_max`: [`constrained_jax.RangeSpaceLDL`][], unrolled on
        the nonzeros of the detected patterns (fused under `jax.vmap`; the fastest
        for the small systems of the scenes).
    - larger, with a mass matrix that is block diagonal with a structurally nonzero
        diagonal (Cartesian and maximal coordinates, e.g. `scenes.chain`): the sparse
        range-space method `SparseSchur`, whose cost follows the nonzeros.
    - otherwise: [`constrained_jax.FullKKTLU`][] with LAPACK's LU.

    Every choice reports singular systems (never a wrong answer). The unrolled
    `RangeSpaceLDL` also solves free gauge directions (a massless coordinate that
    nothing couples to); `FullKKTLU` solves those along a coordinate; `SparseSchur`
    needs every mass pivot nonzero at run time and reports a zero mass (set through
    `args`, say) as singular: pass `saddle_point_solver=cjax.FullKKTLU()` for such
    systems. For an indefinite `M` (not a kinetic energy) choose `FullKKTLU()`
    explicitly.

    The threshold is measured (`n`-link chain, one trajectory, Tsit5, against
    LAPACK's LU): at `n + k = 6` the unrolled solve is faster to run (2.5x) and to
    compile; at `n + k = 9` and `12` it runs 1.8-1.9x slower for one trajectory and
    compiles 2-3x slower (under `jax.vmap` over 1,000 states it is still about 2x
    faster). So the default is never the slower one for a single trajectory; pass
    `RangeSpaceLDL()` (unrolled up to 12) for large batches of mid-sized systems.

    A subclass may override `choose` to return any solver, one of the user's
    included: it gets `M` and `A` as dense arrays unless it is `structured()`, and
    a solution of it that is not finite is reported as `singular` (with zeros), as
    `reports_non_finite()` promises.

    **Arguments:**

    - `unroll_max`: the largest `n + k` solved by the unrolled elimination.
    """

    unroll_max: int = 6

    def structured(self) -> bool:
        return True

    def reports_non_finite(self) -> bool:
        # Every solver `choose` returns does; `solve` masks the answer of one that
        # does not (a subclass whose `choose` returns a solver of the user's).
        return True

    def unrolled(self, n: int, k: int) -> bool:
        # Above `unroll_max`: `SparseSchur` or LAPACK's LU.
        return n + k <= self.unroll_max

    def choose(self, mass, n: int, k: int) -> AbstractSaddlePointSolver:
        """The solver used for a mass matrix `mass` (dense or `SparseMatrix`)."""
        if n + k <= self.unroll_max:
            return RangeSpaceLDL(unroll_max=self.unroll_max)
        if isinstance(mass, SparseMatrix) and _block_diagonal(mass.pattern()):
            from .sparse_schur import SparseSchur

            return SparseSchur()
        return FullKKTLU(unroll_max=0)

    def solve(self, mass, jac, rhs, bias):
        return self._solve(mass, jac, rhs, bias, nan_x=False)

    def _solve_nan_x(self, mass, jac, rhs, bias):
        return self._solve(mass, jac, rhs, bias, nan_x=True)

    def _solve(self, mass, jac, rhs, bias, nan_x: bool):
        n, k = rhs.shape[0], bias.shape[0]
        solver = self.choose(mass, n, k)
        general = solver.solve
        if not solver.structured():
            # LAPACK's LU, or a solver of the user's that takes dense arrays.
            general = functools.partial(_dense_inputs, general)
        if not solver.reports_non_finite():
            general = functools.partial(_report_non_finite, general)
        if self._diagonal_fast_path(mass, jac, n, k):
            from .diagonal import diagonal_solve

            return diagonal_solve(mass, jac, rhs, bias, general, nan_x=nan_x)
        return (nan_on_singular(general) if nan_x else general)(mass, jac, rhs, bias)

    def _diagonal_fast_path(self, mass, jac, n: int, k: int) -> bool:
        """Whether the unrolled diagonal range-space method applies: a structurally
        diagonal `M` whose every diagonal entry that `A` couples is structurally
        nonzero, with `n + k <= unroll_max`."""
        from .diagonal import coupled_columns, is_diagonal

        if n + k > self.unroll_max or not is_diagonal(mass):
            return False
        present = np.zeros((n,), bool)
        present[list(mass.rows)] = True
        return bool(np.all(present | ~coupled_columns(jac, n)))


def _dense_inputs(solve, mass, jac, rhs, bias):
    """`solve` on `M` and `A` as dense arrays."""
    return solve(as_dense(mass), as_dense(jac), rhs, bias)


def _report_non_finite(solve, mass, jac, rhs, bias):
    """`solve`, with a solution that is not finite reported as `singular` (zeros)."""
    x, lam, singular = solve(mass, jac, rhs, bias)
    n = x.shape[0]
    sol = jnp.concatenate([x, lam])
    singular = singular | jnp.invert(jnp.all(jnp.isfinite(sol)))
    sol = jnp.where(singular, 0.0, sol)
    return sol[:n], sol[n:], singular


def _block_diagonal(pattern: np.ndarray) -> bool:
    """Whether a symmetric pattern is block diagonal (its connected components are
    contiguous ranges of indices, each block not larger than 6) with a nonzero
    diagonal. Dense blocks are assumed (each is factored as a whole)."""
    n = pattern.shape[0]
    if not np.all(np.diagonal(pattern)):
        return False
    start = 0
    while start < n:
        end = start + 1
        while end < n and np.any(pattern[start:end, end:]):
            reach = np.nonzero(np.any(pattern[start:end], axis=0))[0]
            end = int(reach.max()) + 1
        if end - start > 6:
            return False
        start = end
    return True
