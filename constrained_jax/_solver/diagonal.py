"""The range-space method for a structurally diagonal mass matrix, `M = D`:

    (A D^-1 A^T) lambda = -b - A D^-1 f,    x = D^-1 (f + A^T lambda),

with the reciprocals `1 / D_ii` computed once and every operation written on scalars
(unrolled at trace time on the nonzeros of `A`), so that under `jax.vmap` XLA fuses
it into about as many loops over the batch as hand-written equations of motion.

A mass that vanishes at run time (set through `args`, say) has no reciprocal. If its
column of `A` is structurally zero, the coordinate is a free gauge (see
[`constrained_jax.AbstractSaddlePointSolver`][]) and its reciprocal is taken as 0.
If the constraints couple it (the rolling cylinder with `I = 0`), the system may
still be nonsingular, and it is solved by a general method instead: under `jax.vmap`
the general method runs only when some state of the batch needs it (a custom
batching rule with one `lax.cond` for the whole batch), so a batch of positive
masses costs only the fast path.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array

from .ldl import (
    dot,
    inactive_pivots,
    mask_inactive_rows,
    max_abs,
    minus_sum,
    schur_solve_unrolled,
)


def is_diagonal(mass) -> bool:
    """Whether the pattern of `mass` (a `SparseMatrix`) lies on the diagonal."""
    return not mass.is_dense and all(
        i == j for i, j in zip(mass.rows, mass.cols, strict=True)
    )


def _diagonal(mass, n: int) -> list:
    """The diagonal entries of a diagonal `SparseMatrix` (`None`: structural zero)."""
    out: list = [None] * n
    for p, i in enumerate(mass.rows):
        out[i] = mass.values[p]
    return out


def coupled_columns(jac, n: int) -> np.ndarray:
    """The columns of `A` that are not structurally zero (trace-time booleans)."""
    return np.any(jac.pattern(), axis=0) if jac.shape[0] else np.zeros((n,), bool)


def _zero_mass_threshold(d: list, n: int):
    """`10 n eps max|D|`: a diagonal mass at or below it counts as zero (`None` when
    every entry is a structural zero)."""
    present = [v for v in d if v is not None]
    if not present:
        return None
    scale = max_abs(present)
    return 10 * n * jnp.finfo(scale.dtype).eps * scale


def needs_general(mass, jac, n: int):
    """Whether the fast path cannot solve this system: a mass coupled by `A` that is
    not positive beyond round-off (`D_ii <= 10 n eps max|D|`)."""
    d = _diagonal(mass, n)
    coupled = coupled_columns(jac, n)
    threshold = _zero_mass_threshold(d, n)
    if threshold is None:
        return jnp.asarray(bool(np.any(coupled)))
    flags = [
        jnp.asarray(True) if d[i] is None else d[i] <= threshold
        for i in range(n)
        if coupled[i]
    ]
    if not flags:
        return jnp.asarray(False)
    return functools.reduce(jnp.logical_or, flags)


def free_gauges(mass, jac, n: int) -> list:
    """For each coordinate, whether it is a free gauge: a column of `A` that is
    structurally zero and a mass that vanishes (`|D_ii| <= 10 n eps max|D|`, or a
    structural zero). Trace-time `True`/`False` where structure decides, else a
    traced boolean."""
    d = _diagonal(mass, n)
    coupled = coupled_columns(jac, n)
    threshold = _zero_mass_threshold(d, n)
    return [
        False if coupled[i] else (True if d[i] is None else jnp.abs(d[i]) <= threshold)
        for i in range(n)
    ]


def stack_by_select(values: list) -> Array:
    """`jnp.stack(values)` for scalars, written as a chain of `where`s on an index.

    The same values, exactly. Under `jax.vmap` a stack of per-state scalars is a
    concatenate along the minor axis, which XLA:CPU writes in the transposed layout
    and then copies into the output's; the `where`s are elementwise and write the
    output in place (one pass over the batch fewer). On a single state the plain
    `jnp.stack` is the cheaper, so the batched path alone uses this.
    """
    index = lax.iota(np.int32, len(values))
    out = jnp.broadcast_to(values[-1], (len(values),))
    for i in range(len(values) - 2, -1, -1):
        out = jnp.where(index == i, values[i], out)
    return out


def reciprocals(mass, jac, n: int) -> tuple[list, list]:
    """`(inv, small)`, per coordinate: `inv[i] = 1 / D_ii` (`None` for a structural
    zero that `A` does not couple) and `small[i]`, for a coordinate that `A` does not
    couple, whether it is a free gauge (its mass vanishes; its reciprocal is then 0),
    `None` for a coupled one."""
    values, index, small = _reciprocal_vector(mass, jac, n)
    return [None if p is None else values[p] for p in index], small


def _reciprocal_vector(mass, jac, n: int):
    """`reciprocals` as one vector: `(values, index, small)`, `inv[i]` being
    `values[index[i]]` (`None` where `index[i]` is). One divide for all the masses,
    where the scalars of `reciprocals` are each a kernel of XLA's (a divide feeding
    two fusions is not duplicated)."""
    d = _diagonal(mass, n)
    coupled = coupled_columns(jac, n)
    gauges = free_gauges(mass, jac, n)
    present = [i for i in range(n) if d[i] is not None]
    index: list = [None] * n
    for p, i in enumerate(present):
        index[i] = p
    small = [None if coupled[i] else jnp.asarray(gauges[i]) for i in range(n)]
    if not present:
        return None, index, small
    values = jnp.stack([d[i] for i in present])
    if all(small[i] is None for i in present):
        return 1 / values, index, small
    flag = jnp.stack(
        [jnp.zeros((), bool) if small[i] is None else small[i] for i in present]
    )
    inv = jnp.where(flag, jnp.zeros_like(values), 1 / jnp.where(flag, 1, values))
    return inv, index, small


def diagonal_range_space(
    mass, jac, rhs, bias, active=None, stack=jnp.stack, fill=0.0, recip=None
):
    """The fast path, assuming `needs_general` is false: `(x, lambda, singular)`.

    `singular` flags a vanishing pivot of `A D^-1 A^T` (below `10 k eps` of its
    largest entry: redundant constraints), a force on a massless coordinate that
    nothing couples to (`|f_i| > 100 n eps max|f|`) and a non-finite result; `x` is
    then `fill` and `lambda` zero.
    `stack` assembles `x` and `lambda` from their entries (`stack_by_select` under
    `jax.vmap`). `recip`: `reciprocals(mass, jac, n)`, if computed already (`mass`
    is then not read). `active`: the rows that hold (`None`: all), the others
    solved as `lambda_j = 0` (see `AbstractSaddlePointSolver`), on the scalars.
    """
    n, k = rhs.shape[0], bias.shape[0]
    a = jac.entries()
    inv, small = reciprocals(mass, jac, n) if recip is None else recip
    f = [rhs[i] for i in range(n)]
    zero = jnp.zeros_like(rhs[0])
    tol = 100 * n * jnp.finfo(rhs.dtype).eps * max_abs(f)
    inconsistent = jnp.array(False)
    for i in range(n):
        if small[i] is not None:
            inconsistent = inconsistent | (small[i] & (jnp.abs(f[i]) > tol))
    zeros_lam = jnp.zeros((0,), rhs.dtype)
    if k == 0:
        lam: list = []
        x = [zero if v is None else f[i] * v for i, v in enumerate(inv)]
        singular = inconsistent
    else:
        b = None
        if active is not None:
            a, b = mask_inactive_rows(a, [bias[r] for r in range(k)], active)
        # D^-1 A^T, row by row of A.
        y = [[None if v is None else v * inv[i] for i, v in enumerate(r)] for r in a]
        schur = [[dot(y[r], a[s]) for s in range(k)] for r in range(k)]
        if active is not None:
            schur = inactive_pivots(schur, active, rhs.dtype)
        # Its non-finite solutions are reported below (one constraint: no pivot
        # test, see `schur_solve_unrolled`).
        lam, breakdown = schur_solve_unrolled(
            schur,
            [
                minus_sum(-(bias[r] if b is None else b[r]), [dot(y[r], f)])
                for r in range(k)
            ],
        )
        lam = [zero if v is None else v for v in lam]
        x = []
        for i in range(n):
            if inv[i] is None:
                x.append(zero)
                continue
            coupling = dot([a[r][i] for r in range(k)], lam)
            x.append((f[i] if coupling is None else f[i] + coupling) * inv[i])
        singular = breakdown | inconsistent
    # Elementwise on the scalars: a reduction over a stacked array would cost XLA
    # separate passes over the batch.
    finite = [jnp.isfinite(v) for v in x + lam]
    singular = singular | jnp.invert(functools.reduce(jnp.logical_and, finite))
    fill = zero if fill == 0 else jnp.full_like(zero, fill)
    x = stack([jnp.where(singular, fill, v) for v in x])
    lam = stack([jnp.where(singular, zero, v) for v in lam]) if k else zeros_lam
    return x, lam, singular


def _batched(fn, axis_size, in_batched, args):
    """`jax.vmap(fn)` over the batched arguments only."""
    axes = tuple(0 if any(jax.tree.leaves(b)) else None for b in in_batched)
    return jax.vmap(fn, in_axes=axes, axis_size=axis_size)(*args)


def _batch_last(args, in_batched):
    """`(moved, back)`: the batched arrays of `args` (of rank 2 and more) with their
    batch axis moved last, and the function that moves it back to the front.

    An operand of a `lax.cond` is passed in XLA's default layout (the last axis
    fastest). The entries of a batched `A` (shape `(N, k, n)`), of `f` and of the bias
    are computed as separate loops over the batch, each written as a contiguous run:
    the layout of shape `(k, n, N)`. Passed as `(N, k, n)`, the branch copies it into
    the default layout first (one pass over the batch per operand); passed as
    `(k, n, N)`, it is the same memory and XLA drops the transposes."""
    flags = jax.tree.leaves(in_batched)
    leaves, treedef = jax.tree.flatten(args)
    moves = [bool(b) and np.ndim(x) >= 2 for x, b in zip(leaves, flags, strict=True)]
    moved = [
        jnp.moveaxis(x, 0, -1) if m else x for x, m in zip(leaves, moves, strict=True)
    ]

    def back(moved_leaves):
        out = [
            jnp.moveaxis(x, -1, 0) if m else x
            for x, m in zip(moved_leaves, moves, strict=True)
        ]
        return jax.tree.unflatten(treedef, out)

    return moved, back


def diagonal_solve(mass, jac, rhs, bias, general, fill=0.0, active=None):
    """Solves the saddle-point system for a diagonal `SparseMatrix` `mass`: the fast
    path where it applies, else `general(mass, jac, rhs, bias, active)` (which
    applies `fill` itself), one `lax.cond` per call (per batch under `jax.vmap`).
    `active`: the rows that hold (`None`: all; see `AbstractSaddlePointSolver`).

    A `singular` solve has `x = fill`, set inside the branches, where XLA fuses it
    into the solve (a `where` on the `lax.cond`'s output would be a kernel more per
    call, and the branches would output the flag apart).

    Differentiable in forward and reverse mode: the tangents solve the same system
    (`lax.custom_linear_solve`, so that they transpose). On a free gauge coordinate
    (see `free_gauges`) the solve sets the unknown to 0 and ignores its right-hand
    side; the tangent solves do the same (their right-hand side is projected before
    the solve, so that a cotangent on the gauge is not taken for a force on a
    massless coordinate), which makes the map `P S P` and its transpose `P S^T P`.
    Inactive rows likewise: the solve ignores their right-hand side and returns
    their multipliers zero, the operator has those rows of `A` masked.
    """
    n = rhs.shape[0]
    fast_path = functools.partial(diagonal_range_space, fill=fill)
    filled = fill != 0

    def general_branch(mass, recip, jac, rhs, bias, active):
        del recip
        return general(*lax.optimization_barrier((mass, jac, rhs, bias, active)))

    @jax.custom_batching.custom_vmap
    def core(mass, jac, rhs, bias, active):
        values, index, small = _reciprocal_vector(mass, jac, n)

        def fast_branch(mass, recip, jac, rhs, bias, active):
            del mass
            jac, rhs, bias, active, (values, small) = lax.optimization_barrier(
                (jac, rhs, bias, active, recip)
            )
            inv = [None if p is None else values[p] for p in index]
            return fast_path(None, jac, rhs, bias, active, recip=(inv, small))

        # The reciprocals of the masses before the `lax.cond`, where XLA hoists
        # those that depend on `args` only out of `simulate`'s loop (or folds them,
        # for constant `args`); the operands cross into the branches behind
        # optimization barriers, so that their entries are read inside, fused into
        # the solve, and not each sliced out before the `lax.cond` as a kernel of
        # its own (the reciprocals as one vector: one kernel in all).
        return lax.cond(
            needs_general(mass, jac, n),
            general_branch,
            fast_branch,
            mass,
            (values, small),
            jac,
            rhs,
            bias,
            active,
        )

    @core.def_vmap
    def _(axis_size, in_batched, mass, jac, rhs, bias, active):
        args = (mass, jac, rhs, bias, active)
        flags = _batched(
            lambda m, a: needs_general(m, a, n), axis_size, in_batched[:2], args[:2]
        )
        fast = functools.partial(fast_path, stack=stack_by_select)
        # The batched operands cross into the `lax.cond` with the batch axis last:
        # the layout in which XLA:CPU computes them (each entry a contiguous run over
        # the batch), so that they need no transposing copy in the branch (see
        # `_batch_last`).
        moved, back = _batch_last(args, in_batched)
        out = lax.cond(
            jnp.any(flags),
            lambda m: _batched(general, axis_size, in_batched, back(m)),
            lambda m: _batched(fast, axis_size, in_batched, back(m)),
            moved,
        )
        return out, (True, True, True)

    @jax.custom_jvp
    def solve(mass, jac, rhs, bias, active):
        return core(mass, jac, rhs, bias, active)

    @solve.defjvp
    def _(primals, tangents):
        mass, jac, rhs, bias, active = primals
        dmass, djac, drhs, dbias, _ = tangents
        x_out, lam, singular = solve(mass, jac, rhs, bias, active)
        if active is not None:
            # The operator and its tangent without the inactive rows (the solves
            # below ignore those rows' right-hand sides and zero their multipliers).
            jac, djac = jac.mask_rows(active), djac.mask_rows(active)
        # The solution with zeros where singular (not `fill`), so that no NaN
        # enters the tangents (nor, transposed, the cotangents).
        x = jnp.where(singular, 0.0, x_out) if filled else x_out
        # K z = r, K = [[M, -A^T], [A, 0]]: K dz = dr - dK z.
        dr = jnp.concatenate(
            [
                drhs - dmass.matvec(x) + djac.matvec(lam, transpose=True),
                -dbias - djac.matvec(x),
            ]
        )

        def matvec(z):
            return jnp.concatenate(
                [
                    mass.matvec(z[:n]) - jac.matvec(z[n:], transpose=True),
                    jac.matvec(z[:n]),
                ]
            )

        gauges = free_gauges(mass, jac, n)
        if any(g is not False for g in gauges):
            project = lambda r: jnp.where(
                jnp.stack([jnp.asarray(g) for g in gauges]), 0.0, r
            )
        else:
            project = lambda r: r

        def zeroed(x_, lam_, singular_):
            return jnp.where(singular_, 0.0, x_) if filled else x_, lam_

        def kkt_solve(_, r):
            dx, dlam = zeroed(*solve(mass, jac, project(r[:n]), -r[n:], active))
            return jnp.concatenate([dx, dlam])

        def kkt_transpose_solve(_, r):
            # K^T = [[M, A^T], [-A, 0]]: K^T w = r is K (w1, -w2) = (r1, -r2).
            w1, w2 = zeroed(*solve(mass, jac, project(r[:n]), r[n:], active))
            return jnp.concatenate([w1, -w2])

        dz = lax.custom_linear_solve(
            matvec, dr, kkt_solve, kkt_transpose_solve, has_aux=False
        )
        dz = jnp.where(singular, 0.0, dz)
        dsingular = np.zeros(np.shape(singular), jax.dtypes.float0)
        return (x_out, lam, singular), (dz[:n], dz[n:], dsingular)

    return solve(mass, jac, rhs, bias, active)
