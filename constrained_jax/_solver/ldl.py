"""Unrolled elimination on scalars: the building blocks of the range-space solvers.

Every function here works on nested lists of scalars, unrolled at trace time, so that
under `jax.vmap` the whole elimination fuses into a few elementwise loops over the batch
(matrix slicing and `@` would become batched `dot`s and gathers, which XLA on CPU does
not fuse). `None` is a structural zero: it costs nothing, and so does every product
with it.
"""

import functools

import jax.numpy as jnp
from jaxtyping import Array


def max_abs(values: list) -> Array:
    return functools.reduce(jnp.maximum, [jnp.abs(v) for v in values])


def minus_sum(start, products: list):
    """`start - sum(products)`, where `None` is a structural zero (so is the
    result when every term is one)."""
    out = start
    for term in products:
        if term is not None:
            out = -term if out is None else out - term
    return out


def dot(u: list, v: list):
    """`sum_i u_i v_i` over the entries that are not structural zeros (`None`; so is
    the result when every term is one). The products are added in order, the first
    one alone: the values of `minus_sum(None, [-u_i v_i, ...])` bit for bit, without
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
    scale = max_abs(entries)
    threshold = 10 * m * jnp.finfo(jnp.result_type(scale)).eps * scale
    # The column test `|t| > 2 sqrt(threshold scale)`, squared: no square root.
    column_threshold_sq = 4 * threshold * scale
    zero = jnp.zeros_like(scale)
    lower: list[list] = [[] for _ in range(m)]
    d: list[Array] = []
    null: list[Array] = []
    breakdown = jnp.array(False)
    for j in range(m):
        s = minus_sum(
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
            t = minus_sum(
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
            minus_sum(
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
            size = max_abs([v for v in b if v is not None])
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
        x[i] = minus_sum(
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
    `breakdown` is false, with the same values and flag in the end, bit for bit
    (and no flag array, which XLA would write out under `jax.vmap` as a pass over
    the batch of its own).
    """
    if len(schur) == 1 and schur[0][0] is not None:
        s = schur[0][0]
        return [right[0] / jnp.where(jnp.isinf(s), jnp.nan, s)], jnp.array(False)
    lower, d, _, breakdown = ldl_factor_unrolled(schur)
    lam, _ = ldl_solve_unrolled(lower, d, right)
    return lam, breakdown


def add(value, term, factor=None):
    """`value + factor * term` (`value + term` without `factor`), with `None` as a
    structural zero."""
    if term is None:
        return value
    if factor is None:
        return term if value is None else value + term
    if value is None:
        return factor * term
    return value + factor * term


def mask_inactive_rows(a: list[list], b: list, active) -> tuple[list[list], list]:
    """`(a, b)` with the rows `r` where `active[r]` is false set to zero: `a` nested
    lists of scalars (a `k x n` block, `None` a structural zero, kept) and `b` a
    list of `k` scalars. One `where` per entry, so that whatever an inactive row
    holds (NaN included) is dropped."""
    flags = [active[r] for r in range(len(a))]
    a = [
        [None if v is None else jnp.where(flag, v, jnp.zeros_like(v)) for v in row]
        for row, flag in zip(a, flags, strict=True)
    ]
    b = [
        jnp.where(flag, v, jnp.zeros_like(v)) for v, flag in zip(b, flags, strict=True)
    ]
    return a, b


def inactive_pivots(schur: list[list], active, dtype) -> list[list]:
    """The Schur complement `S` of a range-space method (nested lists of scalars,
    its inactive rows and columns already zero) with `c` on the diagonal of the
    inactive rows: `S + C`, whose row `j` reads `c lambda_j = 0`.

    `c` is the largest diagonal entry of `S` (1 where it is not positive: every row
    inactive, or none coupled), in the units of `S`: a relative pivot test
    (`10 k eps max|S|`) keeps its scale, takes no active pivot for zero and no
    inactive one for a breakdown, whatever the units of the problem. `dtype`:
    that of `S`."""
    k = len(schur)
    diagonal = [schur[r][r] for r in range(k) if schur[r][r] is not None]
    one = jnp.ones((), dtype)
    if diagonal:
        largest = functools.reduce(jnp.maximum, diagonal)
        c = jnp.where(largest > 0, largest, one)
    else:
        c = one
    out = [list(row) for row in schur]
    for r in range(k):
        s = schur[r][r]
        out[r][r] = jnp.where(active[r], jnp.zeros_like(c) if s is None else s, c)
    return out
