"""The structured saddle-point solve for large systems: a block-diagonal mass matrix
and a sparse constraint Jacobian, solved by the range-space method with a sparse
`L D L^T` of the Schur complement in levels of independent pivots
([`constrained_jax.SparseSchur`][]).

Everything that depends on the sparsity patterns (the blocks of `M`, the pattern of
`S = A M^-1 A^T`, the elimination order, its fill and its levels) is planned once, at
trace time, in numpy; the numeric phase is a few vectorized gathers and scatter-adds
per level, so the program grows like the number of levels, not like the size.
"""

import functools

import jax.numpy as jnp
import numpy as np

from .saddle_point import (
    AbstractSaddlePointSolver,
    FullKKTLU,
    ldl_factor_unrolled,
    ldl_solve_unrolled,
)
from .sparse import as_dense, SparseMatrix


# The largest block of `M` factored by unrolled elimination (trace and compile time
# grow like the cube of the block size); a mass matrix with a larger block is solved
# densely.
_BLOCK_MAX = 12


def _blocks(n, rows, cols):
    """The blocks of `M`: the connected components of its (symmetrized) pattern, as
    sorted coordinate lists, or None if a diagonal entry is structurally zero."""
    rows, cols = np.asarray(rows, int), np.asarray(cols, int)
    if not np.all(np.isin(np.arange(n), rows[rows == cols])):
        return None
    parent = np.arange(n)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
        pr, pc = find(r), find(c)
        if pr != pc:
            parent[max(pr, pc)] = min(pr, pc)
    roots = np.array([find(i) for i in range(n)])
    groups: dict[int, list[int]] = {}
    for i, root in enumerate(roots.tolist()):
        groups.setdefault(root, []).append(i)
    return list(groups.values())


def _elimination_levels(k, edges):
    """A fill-reducing elimination order of a symmetric pattern in levels of
    independent pivots (multiple minimum degree: each level eliminates a maximal
    independent set of nodes whose degree is at most `max(2, min degree)`). On a path
    this is odd-even (cyclic) reduction, `log2(k)` levels; on a tree, leaves and
    chain interiors first.

    Returns `levels` (lists of pivots), `fill` (the edges of the filled graph, as
    `(i, j)` with `i < j`) and, per level, the pivots' neighbours at elimination.
    """
    adjacency = [set() for _ in range(k)]
    for i, j in edges:
        adjacency[i].add(j)
        adjacency[j].add(i)
    fill = {(min(i, j), max(i, j)) for i, j in edges}
    remaining = set(range(k))
    levels, neighbours = [], []
    while remaining:
        degree = {i: len(adjacency[i]) for i in remaining}
        bound = max(2, min(degree.values()))
        level, blocked = [], set()
        for i in sorted(remaining, key=lambda i: (degree[i], i)):
            if degree[i] > bound:
                break
            if i not in blocked:
                level.append(i)
                blocked.update(adjacency[i])
        level.sort()
        levels.append(level)
        neighbours.append([sorted(adjacency[p]) for p in level])
        for p, nbrs in zip(level, neighbours[-1], strict=True):
            for a in nbrs:
                adjacency[a].discard(p)
                for b in nbrs:
                    if a < b and b not in adjacency[a]:
                        adjacency[a].add(b)
                        adjacency[b].add(a)
                        fill.add((a, b))
        remaining.difference_update(level)
    return levels, sorted(fill), neighbours


class _Plan:
    """The symbolic analysis of `(M, A)` patterns: static index arrays only."""

    def __init__(self, mass_pattern, jac_pattern):
        m_rows, m_cols, (n, _) = mass_pattern
        a_rows, a_cols, (k, _) = jac_pattern
        self.n, self.k = n, k
        blocks = _blocks(n, m_rows, m_cols)
        self.dense = blocks is None or max(map(len, blocks)) > _BLOCK_MAX
        if self.dense:
            return
        # `M`'s blocks, grouped by size; `mass_index[g][i][j]` is the position in
        # `mass.values` of entry (i, j) of every block of group g (nnz if absent).
        position = {
            (r, c): p for p, (r, c) in enumerate(zip(m_rows, m_cols, strict=True))
        }
        nnz_m = len(m_rows)
        by_size: dict[int, list[list[int]]] = {}
        for block in blocks:
            by_size.setdefault(len(block), []).append(block)
        self.groups = []  # (coordinates (nb, s), mass_index (s, s, nb))
        for s in sorted(by_size):
            coords = np.array(by_size[s], int)
            index = np.array(
                [
                    [
                        [position.get((b[i], b[j]), nnz_m) for b in coords]
                        for j in range(s)
                    ]
                    for i in range(s)
                ],
                int,
            )
            self.groups.append((coords, index))
        order = np.concatenate([c.reshape(-1) for c, _ in self.groups])
        self.block_order = order  # the coordinates, block by block
        self.block_inverse = np.argsort(order)
        # Where each coordinate's row of M^-1 lives in the flat vector of the blocks
        # of M^-1 (group by group, each (s, s, nb) flattened).
        offset, minv_pos = 0, {}
        for coords, _ in self.groups:
            nb, s = coords.shape
            for b in range(nb):
                for i in range(s):
                    for j in range(s):
                        minv_pos[(coords[b, i], coords[b, j])] = (
                            offset + (i * s + j) * nb + b
                        )
            offset += s * s * nb
        self.a_rows, self.a_cols = np.asarray(a_rows, int), np.asarray(a_cols, int)
        if k == 0:
            return
        # The pattern of S = A M^-1 A^T, and each of its entries as a sum of
        # A[r, i] M^-1[i, j] A[s, j] over the blocks both rows touch.
        block_id = np.empty(n, int)
        for b, block in enumerate(blocks):
            block_id[block] = b
        entries_of_block: dict[int, list[int]] = {}
        for e, c in enumerate(self.a_cols.tolist()):
            entries_of_block.setdefault(int(block_id[c]), []).append(e)
        edges = set()
        triples = []  # (A entry, M^-1 entry, A entry, S key)
        for es in entries_of_block.values():
            for e1 in es:
                r, i = self.a_rows[e1], self.a_cols[e1]
                for e2 in es:
                    s_, j = self.a_rows[e2], self.a_cols[e2]
                    if r < s_:
                        continue
                    if r != s_:
                        edges.add((int(s_), int(r)))
                    triples.append((e1, minv_pos[(i, j)], e2, (int(s_), int(r))))
        levels, fill, neighbours = _elimination_levels(k, edges)
        # S's values: the diagonal (positions 0..k-1) then the filled edges.
        key = {(i, i): i for i in range(k)}
        for p, edge in enumerate(fill):
            key[edge] = k + p
        self.nnz_s = k + len(fill)
        t = np.array([(e1, mi, e2, key[sk]) for e1, mi, e2, sk in triples], int)
        self.s_a1, self.s_minv, self.s_a2, self.s_target = t.T
        self.levels = []
        for level, nbrs in zip(levels, neighbours, strict=True):
            # Column entries (p, i) of this level: the pivot's local index and the
            # position of S[p, i]; the Schur updates S[a, b] -= S[a, p] S[b, p] / d_p
            # over pairs of neighbours a <= b of each pivot.
            col_pivot, col_entry, col_row = [], [], []
            upd_a, upd_b, upd_target = [], [], []
            for q, (p, nb) in enumerate(zip(level, nbrs, strict=True)):
                start = len(col_entry)
                for i in nb:
                    col_pivot.append(q)
                    col_entry.append(key[(min(p, i), max(p, i))])
                    col_row.append(i)
                for x, a in enumerate(nb):
                    for y, b in enumerate(nb[: x + 1]):
                        upd_a.append(start + x)
                        upd_b.append(start + y)
                        upd_target.append(key[(b, a)])
            self.levels.append(
                tuple(
                    np.asarray(v, int)
                    for v in (
                        level,
                        col_pivot,
                        col_entry,
                        col_row,
                        upd_a,
                        upd_b,
                        upd_target,
                    )
                )
            )


@functools.lru_cache(maxsize=64)
def _plan(mass_pattern, jac_pattern) -> _Plan:
    return _Plan(mass_pattern, jac_pattern)


def _factor_mass(plan, values, threshold):
    """The blocks of `M^-1`, flat (group by group, each `(s, s, nb)`), by unrolled
    `L D L^T` vectorized over the blocks of a size; `bad`: a pivot at or below
    `threshold` (zero or negative mass)."""
    values = jnp.concatenate([values, jnp.zeros((1,), values.dtype)])
    parts, bad = [], jnp.array(False)
    for coords, index in plan.groups:
        s = coords.shape[1]
        a = [[values[index[i, j]] for j in range(s)] for i in range(s)]
        if s == 1:
            small = a[0][0] <= threshold
            bad = bad | jnp.any(small)
            parts.append(1 / jnp.where(small, 1.0, a[0][0]))
            continue
        lower, d, _, breakdown = ldl_factor_unrolled(a)
        bad = bad | jnp.any(breakdown)
        for dj in d:
            bad = bad | jnp.any(dj <= threshold)
        one, zero = jnp.ones_like(a[0][0]), jnp.zeros_like(a[0][0])
        columns = [
            ldl_solve_unrolled(lower, d, [one if i == j else zero for i in range(s)])[0]
            for j in range(s)
        ]
        parts.append(jnp.stack([columns[j][i] for i in range(s) for j in range(s)]))
    return jnp.concatenate([p.reshape(-1) for p in parts]), bad


def _apply_blocks(plan, minv, v):
    """`M^-1 v` from the flat blocks of `M^-1`."""
    out, offset = [], 0
    for coords, _ in plan.groups:
        nb, s = coords.shape
        blocks = minv[offset : offset + s * s * nb].reshape(s, s, nb)
        out.append(jnp.sum(blocks * v[coords.T][None], axis=1).T.reshape(-1))
        offset += s * s * nb
    return jnp.concatenate(out)[plan.block_inverse]


def _spmv(values, rows, cols, v, size):
    """`B v` for the sparse `B` with `values` at `(rows, cols)` and `size` rows."""
    return jnp.zeros((size,), v.dtype).at[rows].add(values * v[cols])


def _schur_solve(plan, s_values, g, threshold):
    """Solve `S y = g` by `L D L^T` in the plan's levels of independent pivots; `bad`:
    a pivot at or below `threshold` (redundant constraints, or an indefinite `S`)."""
    factors, bad = [], jnp.array(False)
    for level, col_pivot, col_entry, _, upd_a, upd_b, upd_target in plan.levels:
        d = s_values[level]
        small = d <= threshold
        bad = bad | jnp.any(small)
        d = jnp.where(small, 1.0, d)
        column = s_values[col_entry]
        lower = column / d[col_pivot]
        if upd_target.size:
            s_values = s_values.at[upd_target].add(-column[upd_a] * lower[upd_b])
        factors.append((d, lower))
    y = g
    for (level, col_pivot, _, col_row, *_), (_, lower) in zip(
        plan.levels, factors, strict=True
    ):
        if col_row.size:
            y = y.at[col_row].add(-lower * y[level][col_pivot])
    for (level, col_pivot, _, col_row, *_), (d, lower) in reversed(
        list(zip(plan.levels, factors, strict=True))
    ):
        x = y[level] / d
        if col_row.size:
            x = x - jnp.zeros_like(x).at[col_pivot].add(lower * y[col_row])
        y = y.at[level].set(x)
    return y, bad


class SparseSchur(AbstractSaddlePointSolver):
    """The range-space method for a block-diagonal `M` and a sparse `A`, in `O(N)`
    for chains and trees:

        S lambda = -b - A M^-1 f,    S = A M^-1 A^T,    x = M^-1 (f + A^T lambda).

    `mass` and `jac` are [`constrained_jax.SparseMatrix`][] (or dense arrays, for
    which this is dense). At trace time, from their static patterns: the blocks of
    `M` (the connected components of its pattern), the pattern of `S`, and an
    elimination order of `S` in levels of independent pivots (multiple minimum
    degree: each level eliminates a maximal independent set of nodes of degree at
    most `max(2, min degree)`). On a chain, whose `S` is tridiagonal, this is odd-even
    (cyclic) reduction: `log2(k)` levels, no fill beyond one band. At run time: the
    blocks of `M` are factored by `L D L^T` vectorized over the blocks of equal size,
    `S` is assembled in `O(nnz)`, and each level of its `L D L^T` is a few vectorized
    gathers and scatter-adds. Run time and memory are `O(nnz)` of the filled `S`
    (linear in the number of links for chains and trees); the program grows with the
    number of levels, not with the size. The elimination is Gaussian elimination
    without pivoting on the symmetric permutation of positive definite matrices, so
    it is backward stable.

    **What it needs.** `M` block-diagonal (after a symmetric permutation) with a
    structurally nonzero diagonal and positive definite blocks, and `A` of full row
    rank. A pivot of a block of `M` at or below `10 n eps max|M|` (a zero or negative
    mass, e.g. set through `args`), a pivot of `S` at or below `10 k eps max|S|`
    (redundant constraints), or a non-finite result is reported `singular` (zeros
    returned): unlike [`constrained_jax.RangeSpaceLDL`][] it does not solve free gauge
    directions. Last, the whole KKT system is checked in `O(nnz)`, block row by block
    row: `max|M x - A^T lambda - f| <= 100 (n + k) eps max(|M||x| + |A^T||lambda| +
    |f|)` and `max|A x + b| <= 100 (n + k) eps max(|A| |M^-1| (|f| + |A^T||lambda|) +
    |b|)`; a solution that fails it is `singular`, so a breakdown of the pivot-free
    elimination (an indefinite `M`) never returns a wrong answer. A pattern whose `M`
    has a structurally zero diagonal or a block larger than 12 is solved densely by
    [`constrained_jax.FullKKTLU`][].

    **References:** J. Nocedal and S. J. Wright, *Numerical Optimization*, 2nd ed.,
    Springer (2006), section 16.2 (range-space method). D. Heller, "Some aspects of the
    cyclic reduction algorithm for block tridiagonal linear systems", *SIAM J. Numer.
    Anal.* 13 (1976); G. H. Golub and C. F. Van Loan, *Matrix Computations*, 4th ed.,
    section 4.5.4 (cyclic reduction). J. W. H. Liu, "Modification of the minimum-degree
    algorithm by multiple elimination", *ACM TOMS* 11 (1985).
    """

    def solve(self, mass, jac, rhs, bias):
        if not (isinstance(mass, SparseMatrix) and isinstance(jac, SparseMatrix)):
            return FullKKTLU(unroll_max=0).solve(
                as_dense(mass), as_dense(jac), rhs, bias
            )
        plan = _plan(
            (mass.rows, mass.cols, mass.shape), (jac.rows, jac.cols, jac.shape)
        )
        if plan.dense:
            return FullKKTLU(unroll_max=0).solve(
                mass.todense(), jac.todense(), rhs, bias
            )
        n, k = plan.n, plan.k
        dtype = jnp.result_type(mass.values, jac.values, rhs, bias)
        eps = jnp.finfo(dtype).eps
        m_rows, m_cols = np.asarray(mass.rows, int), np.asarray(mass.cols, int)
        m_values, a_values = mass.values, jac.values
        max_m = jnp.max(jnp.abs(m_values))
        minv, bad = _factor_mass(plan, m_values, 10 * n * eps * max_m)
        u = _apply_blocks(plan, minv, rhs)
        if k == 0:
            x, lam, at_lam = u, jnp.zeros((0,), dtype), jnp.zeros_like(u)
        else:
            a_rows, a_cols = plan.a_rows, plan.a_cols
            s_values = (
                jnp.zeros((plan.nnz_s,), dtype)
                .at[plan.s_target]
                .add(a_values[plan.s_a1] * minv[plan.s_minv] * a_values[plan.s_a2])
            )
            g = -bias - _spmv(a_values, a_rows, a_cols, u, k)
            threshold = 10 * k * eps * jnp.max(jnp.abs(s_values))
            lam, bad_s = _schur_solve(plan, s_values, g, threshold)
            bad = bad | bad_s
            at_lam = _spmv(a_values, a_cols, a_rows, lam, n)
            x = u + _apply_blocks(plan, minv, at_lam)
        # The whole KKT system, to round-off (see the class docstring).
        tol = 100 * (n + k) * eps
        abs_m = jnp.abs(m_values)
        residual = _spmv(m_values, m_rows, m_cols, x, n) - at_lam - rhs
        size = _spmv(abs_m, m_rows, m_cols, jnp.abs(x), n) + jnp.abs(rhs)
        if k > 0:
            abs_a = jnp.abs(a_values)
            size = size + _spmv(abs_a, a_cols, a_rows, jnp.abs(lam), n)
        ok = jnp.max(jnp.abs(residual)) <= tol * jnp.max(size)
        if k > 0:
            residual = _spmv(a_values, a_rows, a_cols, x, k) + bias
            x_size = _apply_blocks(
                plan,
                jnp.abs(minv),
                jnp.abs(rhs) + _spmv(abs_a, a_cols, a_rows, jnp.abs(lam), n),
            )
            size = _spmv(abs_a, a_rows, a_cols, x_size, k) + jnp.abs(bias)
            ok = ok & (jnp.max(jnp.abs(residual)) <= tol * jnp.max(size))
        finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(lam))
        singular = bad | jnp.invert(ok) | jnp.invert(finite)
        return jnp.where(singular, 0.0, x), jnp.where(singular, 0.0, lam), singular
