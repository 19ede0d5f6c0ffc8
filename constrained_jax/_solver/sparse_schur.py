"""The structured saddle-point solve for large systems: a block-diagonal mass matrix
and a sparse constraint Jacobian, solved by the range-space method with a sparse
`L D L^T` of the Schur complement, sequential along a band (`lax.scan`) or in levels
of independent pivots ([`constrained_jax.SparseSchur`][]).

Everything that depends on the sparsity patterns (the blocks of `M`, the pattern of
`S = A M^-1 A^T`, the elimination order, its fill and its levels) is planned once, at
trace time, in numpy; the numeric phase is a few vectorized gathers per level (sums
over scattered entries are written as padded gathers: batched scatters are slow on
CPU), so the program grows like the number of levels, not like the size.
"""

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .full_kkt_lu import FullKKTLU
from .ldl import ldl_factor_unrolled, ldl_solve_unrolled
from .saddle_point import AbstractSaddlePointSolver, KKTForm


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


def _band_order(k, edges):
    """A bandwidth-reducing order of a symmetric pattern: the natural order or the
    reverse Cuthill-McKee order (breadth first from a node of least degree, component
    by component), whichever has the smaller bandwidth. Returns the order and its
    bandwidth (at least 1)."""
    adjacency = [[] for _ in range(k)]
    for i, j in edges:
        adjacency[i].append(j)
        adjacency[j].append(i)
    degree = [len(a) for a in adjacency]
    order, seen = [], [False] * k
    for start in sorted(range(k), key=lambda i: (degree[i], i)):
        if seen[start]:
            continue
        seen[start], queue, head = True, [start], 0
        while head < len(queue):
            v, head = queue[head], head + 1
            for u in sorted(adjacency[v], key=lambda u: (degree[u], u)):
                if not seen[u]:
                    seen[u] = True
                    queue.append(u)
        order.extend(queue)

    def bandwidth(order):
        position = np.empty(k, int)
        position[np.asarray(order, int)] = np.arange(k)
        return max([abs(position[i] - position[j]) for i, j in edges] + [1])

    natural, reverse = list(range(k)), order[::-1]
    if bandwidth(natural) <= bandwidth(reverse):
        return np.asarray(natural, int), int(bandwidth(natural))
    return np.asarray(reverse, int), int(bandwidth(reverse))


# The largest bandwidth (under the order of `_band_order`) for which `method="auto"`
# eliminates `S` sequentially (see `SparseSchur`).
_BAND_MAX = 8


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
        nnz_a = len(a_rows)
        self.m_rows = _sum_index(m_rows, n, nnz_m)
        self.m_cols = np.asarray(m_cols, int)
        self.a_by_row = _sum_index(a_rows, k, nnz_a)  # A v
        self.a_by_col = _sum_index(a_cols, n, nnz_a)  # A^T v
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
        # The sequential elimination: per pivot (in the band order), the positions
        # of its column S[t + i, t], i = 0..w (the zero slot outside the pattern).
        order, self.band_width = _band_order(k, edges)
        self.band_order, self.band_inverse = order, np.argsort(order)
        keys = [(i, i) for i in range(k)] + sorted(edges)
        position = {key: q for q, key in enumerate(keys)}
        self.band_index = np.array(
            [
                [
                    position.get(
                        (min(order[t], order[t + i]), max(order[t], order[t + i])),
                        len(keys),
                    )
                    if t + i < k
                    else len(keys)
                    for i in range(self.band_width + 1)
                ]
                for t in range(k)
            ],
            int,
        )
        levels, _, neighbours = _elimination_levels(k, edges)
        # The active entries of S (diagonal and edges among the nodes not yet
        # eliminated, `(a, b)` with `a <= b`) are stored compactly level by level,
        # and the active nodes too: every step is a gather, none a scatter (batched
        # scatters are slow on CPU).
        self.s_keys = keys
        t = np.array([(e1, mi, e2) for e1, mi, e2, _ in triples], int).reshape(-1, 3)
        self.s_a1, self.s_minv, self.s_a2 = t.T
        position = {key: q for q, key in enumerate(keys)}
        self.s_sum = _sum_index(
            [position[sk] for *_, sk in triples], len(keys), len(triples)
        )
        nodes = list(range(k))
        self.levels = []
        for level, nbrs in zip(levels, neighbours, strict=True):
            position = {key: q for q, key in enumerate(keys)}
            node_position = {v: q for q, v in enumerate(nodes)}
            pivots = set(level)
            next_nodes = [v for v in nodes if v not in pivots]
            next_position = {v: q for q, v in enumerate(next_nodes)}
            # Column entries S[p, i] of this level and the Schur updates
            # S[a, b] -= S[a, p] S[b, p] / d_p over neighbours b <= a of each pivot.
            col_pivot, col_entry, col_row = [], [], []
            upd_a, upd_b = [], []
            updates: dict[tuple[int, int], list[int]] = {}
            num_updates = 0
            for q, (p, nb) in enumerate(zip(level, nbrs, strict=True)):
                start = len(col_entry)
                for i in nb:
                    col_pivot.append(q)
                    col_entry.append(position[(min(p, i), max(p, i))])
                    col_row.append(next_position[i])
                for x, a in enumerate(nb):
                    for y, b in enumerate(nb[: x + 1]):
                        updates.setdefault((b, a), []).append(num_updates)
                        upd_a.append(start + x)
                        upd_b.append(start + y)
                        num_updates += 1
            next_keys = [
                key for key in keys if key[0] not in pivots and key[1] not in pivots
            ]
            next_keys += sorted(set(updates) - set(next_keys))
            by_pivot = [[] for _ in level]
            for e, q in enumerate(col_pivot):
                by_pivot[q].append(e)
            self.levels.append(
                _Level(
                    pivots=np.array([node_position[p] for p in level], int),
                    diag=np.array([position[(p, p)] for p in level], int),
                    col_pivot=np.asarray(col_pivot, int),
                    col_entry=np.asarray(col_entry, int),
                    col_row=np.asarray(col_row, int),
                    upd_a=np.asarray(upd_a, int),
                    upd_b=np.asarray(upd_b, int),
                    keep=np.array(
                        [position.get(key, len(keys)) for key in next_keys], int
                    ),
                    update_sum=_pad(
                        [updates.get(key, []) for key in next_keys], num_updates
                    ),
                    keep_nodes=np.array([node_position[v] for v in next_nodes], int),
                    row_sum=_sum_index(col_row, len(next_nodes), len(col_row)),
                    pivot_sum=_pad(by_pivot, len(col_row)),
                    merge=_merge(level, next_nodes, nodes),
                )
            )
            keys, nodes = next_keys, next_nodes


class _Level(NamedTuple):
    """One level of independent pivots (positions are in the level's compact
    storage of the active entries of `S` and of the active nodes)."""

    pivots: np.ndarray  # the pivots among the active nodes
    diag: np.ndarray  # their diagonal entries
    col_pivot: np.ndarray  # per column entry S[p, i]: the pivot's index in the level
    col_entry: np.ndarray  # ... its position
    col_row: np.ndarray  # ... i among the next level's nodes
    upd_a: np.ndarray  # per Schur update: the column entries S[a, p], S[b, p]
    upd_b: np.ndarray
    keep: np.ndarray  # per next entry: its position now (or the zero slot: fill)
    update_sum: np.ndarray  # per next entry: its updates (padded)
    keep_nodes: np.ndarray  # per next node: its position now
    row_sum: np.ndarray  # per next node: the column entries in its row (padded)
    pivot_sum: np.ndarray  # per pivot: its column entries (padded)
    merge: np.ndarray  # per active node: its index in [pivots, next nodes]


def _merge(level, next_nodes, nodes):
    where = {p: q for q, p in enumerate(level)}
    where.update({v: len(level) + q for q, v in enumerate(next_nodes)})
    return np.array([where[v] for v in nodes], int)


def _pad(lists, pad):
    """A `(len(lists), width)` index array of the lists, padded with `pad`."""
    width = max([len(x) for x in lists] + [1])
    out = np.full((len(lists), width), pad, int)
    for q, x in enumerate(lists):
        out[q, : len(x)] = x
    return out


def _sum_index(targets, size, pad):
    """For sources with the given `targets` (in `range(size)`): per target, its
    sources, padded with `pad` (see `_gather_sum`)."""
    lists = [[] for _ in range(size)]
    for e, t in enumerate(targets):
        lists[int(t)].append(e)
    return _pad(lists, pad)


def _take(values, index):
    """`values[index]` for a static integer array `index` (along the first axis): a
    slice where the positions are evenly spaced (the identity, a range, a stride),
    else a gather. Most index arrays of a plan are such ranges for diagonal blocks
    (the identity of `M`'s pattern, its blocks in order), and a slice compiles to
    less than a gather with a constant index."""
    index = np.asarray(index)
    flat = index.reshape(-1)
    if flat.size == 0:
        return values[index]
    start = int(flat[0])
    step = int(flat[1] - flat[0]) if flat.size > 1 else 1
    if step >= 1 and np.array_equal(flat, start + step * np.arange(flat.size)):
        stop = start + step * (flat.size - 1) + 1
        if start == 0 and step == 1 and stop == values.shape[0]:
            out = values
        else:
            out = jax.lax.slice_in_dim(values, start, stop, step)
        return out.reshape(index.shape + values.shape[1:])
    return values[index]


def _gather_sum(values, index):
    """`out[t] = sum(values[index[t]])`, with the padding index `len(values)` read
    as zero: a segment sum written as a gather."""
    if np.any(index >= values.shape[0]):
        values = jnp.concatenate([values, jnp.zeros((1,), values.dtype)])
    if index.shape[1] == 1:
        return _take(values, index[:, 0])
    return jnp.sum(_take(values, index), axis=1)


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
        a = [[_take(values, index[i, j]) for j in range(s)] for i in range(s)]
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
        out.append(jnp.sum(blocks * _take(v, coords.T)[None], axis=1).T.reshape(-1))
        offset += s * s * nb
    return _take(jnp.concatenate(out), plan.block_inverse)


def _spmv(values, cols, v, by_row):
    """`B v` for the sparse `B` with `values` at columns `cols`, summed by row."""
    return _gather_sum(values * _take(v, cols), by_row)


def _schur_solve(plan, s_values, g, threshold):
    """Solve `S y = g` by `L D L^T` in the plan's levels of independent pivots; `bad`:
    a pivot at or below `threshold` (redundant constraints, or an indefinite `S`)."""
    factors, bad = [], jnp.array(False)
    for level in plan.levels:
        d = _take(s_values, level.diag)
        small = d <= threshold
        bad = bad | jnp.any(small)
        d = jnp.where(small, 1.0, d)
        column = _take(s_values, level.col_entry)
        lower = column / _take(d, level.col_pivot)
        kept = jnp.concatenate([s_values, jnp.zeros((1,), s_values.dtype)])
        s_values = _take(kept, level.keep)
        if level.upd_a.size:
            delta = _take(column, level.upd_a) * _take(lower, level.upd_b)
            s_values = s_values - _gather_sum(delta, level.update_sum)
        factors.append((d, lower))
    # Forward substitution, the active nodes shrinking level by level.
    y, pivot_values = g, []
    for level, (_, lower) in zip(plan.levels, factors, strict=True):
        y_pivots = _take(y, level.pivots)
        pivot_values.append(y_pivots)
        y = _take(y, level.keep_nodes)
        if level.col_row.size:
            y = y - _gather_sum(lower * _take(y_pivots, level.col_pivot), level.row_sum)
    # Back substitution, the active nodes growing back.
    x = y
    for level, (d, lower), y_pivots in reversed(
        list(zip(plan.levels, factors, pivot_values, strict=True))
    ):
        x_pivots = y_pivots / d
        if level.col_row.size:
            x_pivots = x_pivots - _gather_sum(
                lower * _take(x, level.col_row), level.pivot_sum
            )
        x = _take(jnp.concatenate([x_pivots, x]), level.merge)
    return x, bad


def _band_solve(plan, s_values, g, threshold):
    """Solve `S y = g` by a sequential band `L D L^T` (`lax.scan` over the pivots in
    the band order, each step the same `w x w` update: for a chain, `w = 1`, the
    Thomas algorithm); `bad` as in `_schur_solve`."""
    w = plan.band_width
    dtype = s_values.dtype
    padded = jnp.concatenate([s_values, jnp.zeros((1,), dtype)])
    columns = _take(padded, plan.band_index)  # (k, w + 1)
    last = jnp.zeros((1,), dtype)

    def factor(carry, inputs):
        # `update`, `z`: the previous pivots' Schur updates of S and corrections of
        # g on the next w nodes.
        update, z = carry
        column, g_t = inputs
        column = column - jnp.concatenate([update[:, 0], last])
        small = column[0] <= threshold
        d = jnp.where(small, 1.0, column[0])
        lower = column[1:] / d
        y = g_t - z[0]
        update = d * lower[:, None] * lower[None, :]
        z = lower * y
        if w > 1:  # the next w - 1 nodes' updates move up one place
            update = update + jnp.pad(carry[0][1:, 1:], ((0, 1), (0, 1)))
            z = z + jnp.concatenate([carry[1][1:], last])
        return (update, z), (d, lower, y, small)

    natural = np.array_equal(plan.band_order, np.arange(len(plan.band_order)))
    init = (jnp.zeros((w, w), dtype), jnp.zeros((w,), dtype))
    inputs = (columns, g if natural else _take(g, plan.band_order))
    _, (d, lower, y, small) = jax.lax.scan(factor, init, inputs)

    def back(window, inputs):
        d, lower, y = inputs
        x = y / d - jnp.sum(lower * window)
        if w > 1:
            return jnp.concatenate([x[None], window[:-1]]), x
        return x[None], x

    _, x = jax.lax.scan(back, jnp.zeros((w,), dtype), (d, lower, y), reverse=True)
    return (x if natural else _take(x, plan.band_inverse)), jnp.any(small)


class SparseSchur(AbstractSaddlePointSolver):
    """The range-space method for a block-diagonal `M` and a sparse `A`, in `O(N)`
    for chains and trees:

        S lambda = -b - A M^-1 f,    S = A M^-1 A^T,    x = M^-1 (f + A^T lambda).

    It takes `M` and `A` with their detected sparsity patterns (full patterns are
    solved densely). At trace time, from the static patterns: the
    blocks of `M` (the connected components of its pattern), the pattern of `S`, and an
    elimination order of `S` in levels of independent pivots (multiple minimum
    degree: each level eliminates a maximal independent set of nodes of degree at
    most `max(2, min degree)`). On a chain, whose `S` is tridiagonal, this is odd-even
    (cyclic) reduction: `log2(k)` levels and `O(k)` fill. At run time: the
    blocks of `M` are factored by `L D L^T` vectorized over the blocks of equal size,
    `S` is assembled in `O(nnz)`, and each level of its `L D L^T` is a few vectorized
    gathers on the entries still active. Run time and memory are `O(nnz)` of the
    filled `S` (linear in the number of links for chains and trees); the program
    grows with the number of levels, not with the size. The elimination is Gaussian
    elimination without pivoting on a symmetric permutation of positive definite
    matrices, so it is backward stable.

    **Two eliminations of `S`.** `method="levels"` is the levelled elimination above.
    `method="scan"` is a sequential band `L D L^T`: the natural order of the rows of
    `A` or the reverse Cuthill-McKee order, whichever has the smaller bandwidth `w`,
    and one `lax.scan` step per pivot, each the same `w x w` update of a window that
    slides along the band (forward substitution in the same scan, back substitution
    in a second one): `O(k w^2)`, a program of fixed size whatever `k`. On a chain
    `w = 1` and it is the Thomas algorithm. `method="auto"` (the default) takes the
    scan where `w <= 8` and the levels otherwise (a star, whose hub is coupled to
    every row, or a wide tree): on a chain or a narrow truss the scan compiles and
    runs faster (the levels of a truss degenerate into many), on a wide tree far
    slower (`benchmarks/sparse_schur.py` measures both).

    **What it needs.** `M` block-diagonal (after a symmetric permutation) with a
    structurally nonzero diagonal and positive definite blocks, and `A` of full row
    rank. A pivot of a block of `M` at or below `10 n eps max|M|` (a zero or negative
    mass, e.g. set through `args`), a pivot of `S` at or below `10 k eps max|S|`
    (redundant constraints), or a non-finite result is reported `singular`: unlike
    [`constrained_jax.RangeSpaceLDL`][] it does not solve free gauge directions. Last,
    the whole KKT system is checked in `O(nnz)`, block row by block row: `max|M x - A^T
    lambda - f| <= 100 (n + k) eps max(|M||x| + |A^T||lambda| + |f|)` and `max|A x + b|
    <= 100 (n + k) eps max(|A| |M^-1| (|f| + |A^T||lambda|) + |b|)`; a solution that
    fails it is `singular`, so a breakdown of the pivot-free elimination (an indefinite
    `M`) never returns a wrong answer. A pattern whose `M` has a structurally zero
    diagonal or a block larger than 12 is solved densely by
    [`constrained_jax.FullKKTLU`][].

    **References:** J. Nocedal and S. J. Wright, *Numerical Optimization*, 2nd ed.,
    Springer (2006), section 16.2 (range-space method). D. Heller, "Some aspects of the
    cyclic reduction algorithm for block tridiagonal linear systems", *SIAM J. Numer.
    Anal.* 13 (1976); G. H. Golub and C. F. Van Loan, *Matrix Computations*, 4th ed.,
    section 4.5.4 (cyclic reduction). J. W. H. Liu, "Modification of the minimum-degree
    algorithm by multiple elimination", *ACM TOMS* 11 (1985). E. Cuthill and J.
    McKee, "Reducing the bandwidth of sparse symmetric matrices", *Proc. 24th ACM
    National Conference* (1969).

    **Arguments:**

    - `method`: `"auto"` (default), `"scan"` or `"levels"`: how `S` is eliminated
        (see above). All three keep the same checks and give the same answers to
        round-off.
    """

    method: str = eqx.field(default="auto", static=True)

    def form(self, n: int, k: int) -> KKTForm:
        return KKTForm(sparse=True, unroll=False)

    def solve(self, system, fill):
        mass, jac, rhs, bias = system.mass, system.jac, system.rhs, system.bias
        if mass.is_dense or jac.is_dense:
            return FullKKTLU(unroll_max=0).solve(system, fill)
        plan = _plan(
            (mass.rows, mass.cols, mass.shape), (jac.rows, jac.cols, jac.shape)
        )
        if plan.dense:
            return FullKKTLU(unroll_max=0).solve(system, fill)
        n, k = plan.n, plan.k
        dtype = jnp.result_type(mass.values, jac.values, rhs, bias)
        eps = jnp.finfo(dtype).eps
        m_values, a_values = mass.values, jac.values
        active = system.active if k > 0 else None
        if active is not None:
            a_values = jnp.where(_take(active, plan.a_rows), a_values, 0.0)
            bias = jnp.where(active, bias, 0.0)
        max_m = jnp.max(jnp.abs(m_values))
        minv, bad = _factor_mass(plan, m_values, 10 * n * eps * max_m)
        u = _apply_blocks(plan, minv, rhs)
        if k == 0:
            x, lam, at_lam = u, jnp.zeros((0,), dtype), jnp.zeros_like(u)
        else:
            s_values = _gather_sum(
                _take(a_values, plan.s_a1)
                * _take(minv, plan.s_minv)
                * _take(a_values, plan.s_a2),
                plan.s_sum,
            )
            if active is not None:
                # Inactive rows: `c` on the diagonal of `S` (its first `k`
                # entries), its largest entry (1 where zero), so that `c lambda_j
                # = 0` (see `AbstractSaddlePointSolver`).
                diagonal = s_values[:k]
                largest = jnp.max(diagonal)
                c = jnp.where(largest > 0, largest, 1.0)
                s_values = jnp.concatenate(
                    [jnp.where(active, diagonal, c), s_values[k:]]
                )
            g = -bias - _spmv(a_values, plan.a_cols, u, plan.a_by_row)
            threshold = 10 * k * eps * jnp.max(jnp.abs(s_values))
            method = self.method
            if method == "auto":
                method = "scan" if plan.band_width <= _BAND_MAX else "levels"
            if method == "scan":
                lam, bad_s = _band_solve(plan, s_values, g, threshold)
            elif method == "levels":
                lam, bad_s = _schur_solve(plan, s_values, g, threshold)
            else:
                raise ValueError(
                    f"SparseSchur(method={method!r}): expected 'auto', 'levels' or "
                    "'scan'."
                )
            bad = bad | bad_s
            at_lam = _spmv(a_values, plan.a_rows, lam, plan.a_by_col)
            x = u + _apply_blocks(plan, minv, at_lam)
        # The whole KKT system, to round-off (see the class docstring).
        tol = 100 * (n + k) * eps
        abs_m = jnp.abs(m_values)
        residual = _spmv(m_values, plan.m_cols, x, plan.m_rows) - at_lam - rhs
        size = _spmv(abs_m, plan.m_cols, jnp.abs(x), plan.m_rows) + jnp.abs(rhs)
        if k > 0:
            abs_a = jnp.abs(a_values)
            at_lam_size = _spmv(abs_a, plan.a_rows, jnp.abs(lam), plan.a_by_col)
            size = size + at_lam_size
        ok = jnp.max(jnp.abs(residual)) <= tol * jnp.max(size)
        if k > 0:
            residual = _spmv(a_values, plan.a_cols, x, plan.a_by_row) + bias
            x_size = _apply_blocks(plan, jnp.abs(minv), jnp.abs(rhs) + at_lam_size)
            size = _spmv(abs_a, plan.a_cols, x_size, plan.a_by_row) + jnp.abs(bias)
            ok = ok & (jnp.max(jnp.abs(residual)) <= tol * jnp.max(size))
        finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(lam))
        singular = bad | jnp.invert(ok) | jnp.invert(finite)
        fill_x = 0.0 if fill == 0 else jnp.asarray(fill, x.dtype)
        return jnp.where(singular, fill_x, x), jnp.where(singular, 0.0, lam), singular
