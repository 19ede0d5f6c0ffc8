"""Linear solvers for the saddle-point (KKT) systems of the library, as Lineax solvers.

Two strategies, both usable wherever Lineax takes a solver (Newton steps, the implicit
function theorem in the backward pass):

- [`constrained_jax.DenseLU`][]: materialises the matrix. Systems of up to
  `unroll_max` unknowns are factored by Gaussian elimination with partial pivoting
  *unrolled at trace time*, which XLA fuses into straight-line code: on CPU a LAPACK
  call on a 3x3 matrix costs far more than its arithmetic: a vmapped batch of 10,000
  cylinder extremizations runs 4-7x faster than with LAPACK's LU
  (`DenseLU(unroll_max=0)`; `benchmarks/extremize.py`). Larger systems use
  LAPACK's LU. Singular matrices are reported (`lineax.RESULTS.singular`), never
  returned as NaN; matrices with NaN or inf entries as
  `lineax.RESULTS.nonfinite_input`.
- [`constrained_jax.MINRES`][]: matrix-free, for symmetric (possibly indefinite)
  operators such as a KKT matrix. Needs only matrix-vector products, i.e. Hessian-vector
  products by autodiff, so an n x n matrix is never formed.
"""

import functools
from typing import Any

import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.scipy as jsp
import lineax as lx
import lineax.internal as lxi
from jaxtyping import Array, Bool, Float, Int, PyTree


def _singular_threshold(a: Float[Array, "m m"]) -> Float[Array, ""]:
    """A pivot below this (relative to the largest entry) counts as zero."""
    m = a.shape[-1]
    eps = jnp.finfo(a.dtype).eps
    return 10 * m * eps * jnp.max(jnp.abs(a))


def lu_factor_unrolled(
    a: Float[Array, "m m"],
) -> tuple[Float[Array, "m m"], Int[Array, " m"], Bool[Array, ""]]:
    """LU factorisation with partial pivoting, unrolled over the (static) size.

    Returns `(lu, perm, singular)` with `a[perm] = L @ U`, `L` unit lower triangular
    stored below the diagonal of `lu` and `U` on and above it. Pivot rows are selected
    with one-hot arithmetic rather than dynamic indexing, so the whole factorisation
    is elementwise work that XLA fuses (also under `jax.vmap`).
    """
    m = a.shape[-1]
    idx = jnp.arange(m)
    perm = idx
    lu = a
    threshold = _singular_threshold(a)
    singular = jnp.array(False)
    for k in range(m):
        col = jnp.where(idx >= k, jnp.abs(lu[:, k]), -1.0)
        p = jnp.argmax(col)
        onehot = (idx == p).astype(a.dtype)
        row_p = onehot @ lu
        row_k = lu[k]
        perm_p = jnp.sum(jnp.where(idx == p, perm, 0))
        perm_k = perm[k]
        # Swap rows k and p (p >= k).
        lu = lu + onehot[:, None] * (row_k - row_p)[None, :]
        lu = lu.at[k].set(row_p)
        perm = jnp.where(idx == p, perm_k, perm).at[k].set(perm_p)
        pivot = lu[k, k]
        small = jnp.abs(pivot) <= threshold
        singular = singular | small
        safe_pivot = jnp.where(small, 1.0, pivot)
        below = idx > k
        factors = jnp.where(below, lu[:, k] / safe_pivot, 0.0)
        right = idx > k
        update = factors[:, None] * jnp.where(right, lu[k], 0.0)[None, :]
        lu = lu - update
        lu = lu.at[:, k].set(jnp.where(below, factors, lu[:, k]))
    return lu, perm, singular


def lu_solve_unrolled(
    lu: Float[Array, "m m"], perm: Int[Array, " m"], b: Float[Array, " m"]
) -> Float[Array, " m"]:
    """Solves `a x = b` given `lu_factor_unrolled(a)`."""
    m = lu.shape[-1]
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
        xs[i] = s / lu[i, i]
    return jnp.stack(xs)


def ldl_factor_unrolled(
    a: list[list[Array]],
) -> tuple[list[list[Array]], list[Array], Bool[Array, ""]]:
    """`a = L D L^T` without pivoting, on a symmetric matrix given as nested lists of
    scalars, unrolled at trace time.

    Returns `(L, d, breakdown)`: `L[i][j]` for `j < i` (unit diagonal implied), the
    diagonal `d`, and a flag raised when a pivot is smaller than `10 m eps max|a|`
    (then that pivot is replaced by 1 so that nothing is NaN). Working on scalars keeps
    every operation elementwise: under `jax.vmap` the whole factorisation fuses into a
    few loops over the batch (matrix slicing and `@` would become batched `dot`s and
    gathers, which XLA on CPU does not fuse).

    Without pivoting this is backward stable for positive definite `a`; for an
    indefinite `a` it works whenever no leading principal minor vanishes.
    """
    m = len(a)
    scale = functools.reduce(jnp.maximum, [jnp.abs(x) for row in a for x in row])
    threshold = 10 * m * jnp.finfo(jnp.result_type(scale)).eps * scale
    lower: list[list[Array]] = [[] for _ in range(m)]
    d: list[Array] = []
    breakdown = jnp.array(False)
    for j in range(m):
        s = a[j][j]
        for p in range(j):
            s = s - lower[j][p] * lower[j][p] * d[p]
        small = jnp.abs(s) <= threshold
        breakdown = breakdown | small
        d.append(jnp.where(small, jnp.ones_like(s), s))
        for i in range(j + 1, m):
            t = a[i][j]
            for p in range(j):
                t = t - lower[i][p] * lower[j][p] * d[p]
            lower[i].append(t / d[j])
    return lower, d, breakdown


def ldl_solve_unrolled(
    lower: list[list[Array]], d: list[Array], b: list[Array]
) -> list[Array]:
    """Solve `L D L^T x = b` given `ldl_factor_unrolled` (lists of scalars)."""
    m = len(d)
    y: list[Array] = []
    for i in range(m):
        s = b[i]
        for p in range(i):
            s = s - lower[i][p] * y[p]
        y.append(s)
    x: list = [None] * m
    for i in reversed(range(m)):
        s = y[i] / d[i]
        for p in range(i + 1, m):
            s = s - lower[p][i] * x[p]
        x[i] = s
    return x


def dense_factor(a: Float[Array, "m m"], unroll_max: int):
    """Factor a square matrix: unrolled for `m <= unroll_max`, LAPACK otherwise."""
    m = a.shape[-1]
    if m <= unroll_max:
        return lu_factor_unrolled(a)
    lu, piv = jsp.linalg.lu_factor(a)
    singular = jnp.any(jnp.abs(jnp.diagonal(lu)) <= _singular_threshold(a))
    perm = lax.linalg.lu_pivots_to_permutation(piv, m)
    return lu, perm, singular


def dense_solve(factors, b: Float[Array, " m"], unroll_max: int) -> Float[Array, " m"]:
    """Solve with the output of `dense_factor`; singular systems give zeros."""
    lu, perm, singular = factors
    m = lu.shape[-1]
    safe_lu = jnp.where(singular, jnp.eye(m, dtype=lu.dtype), lu)
    if m <= unroll_max:
        x = lu_solve_unrolled(safe_lu, perm, b)
    else:
        y = jsp.linalg.solve_triangular(
            safe_lu, b[perm], lower=True, unit_diagonal=True
        )
        x = jsp.linalg.solve_triangular(safe_lu, y, lower=False)
    return jnp.where(singular, 0.0, x)


_DenseLUState = tuple[Any, Any, lxi.PackedStructures, Any]


class DenseLU(lx.AbstractLinearSolver):
    """Dense LU solver with partial pivoting that reports singular matrices.

    For matrices of size at most `unroll_max` the factorisation is unrolled at trace
    time (fast for the tiny KKT systems of mechanics and small extremizations, batched
    with `jax.vmap`); larger ones use LAPACK. A pivot smaller than
    `10 m eps max|A|` marks the matrix singular: the solve then returns
    `lineax.RESULTS.singular` (and zeros, never NaN). A matrix with NaN or inf
    entries (e.g. a Hessian evaluated outside the domain of the function) is reported
    as `lineax.RESULTS.nonfinite_input` instead, so that the caller can tell a
    singular matrix from an undefined one.
    """

    unroll_max: int = 12

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("`DenseLU` may only be used with square operators.")
        matrix = operator.as_matrix()
        packed = lxi.pack_structures(operator)
        return self._state(matrix, packed)

    def _state(self, matrix, packed) -> _DenseLUState:
        finite = jnp.all(jnp.isfinite(matrix))
        return matrix, dense_factor(matrix, self.unroll_max), packed, finite

    def compute(self, state: _DenseLUState, vector: PyTree[Array], options):
        del options
        _, factors, packed, finite = state
        b = lxi.ravel_vector(vector, packed)
        x = dense_solve(factors, b, self.unroll_max)
        singular = factors[2]
        result = lx.RESULTS.where(singular, lx.RESULTS.singular, lx.RESULTS.successful)
        result = lx.RESULTS.where(finite, result, lx.RESULTS.nonfinite_input)
        return lxi.unravel_solution(x, packed), result, {}

    def transpose(self, state: _DenseLUState, options: dict[str, Any]):
        matrix, _, packed, _ = state
        return self._state(matrix.T, lxi.transpose_packed_structures(packed)), {}

    def conj(self, state: _DenseLUState, options: dict[str, Any]):
        matrix, _, packed, _ = state
        return self._state(matrix.conj(), packed), {}

    def assume_full_rank(self):
        return True


DenseLU.__init__.__doc__ = """**Arguments:**

- `unroll_max`: the largest size factored by unrolled elimination; larger systems use
    LAPACK. Unrolling costs trace and compile time growing like `m**3`, so keep it
    small.
"""


class MINRES(lx.AbstractLinearSolver):
    """Minimal-residual Krylov solver for symmetric, possibly indefinite, operators.

    The natural Krylov method for a KKT matrix `[[H, J^T], [J, 0]]`, which is symmetric
    but indefinite, so that conjugate gradients do not apply. Only matrix-vector
    products are used: with a `lineax.JacobianLinearOperator` these are
    Hessian-vector products by forward-over-reverse autodiff, and no matrix is formed.

    Terminates when the residual estimate satisfies
    `||A x - b|| <= atol + rtol ||b||`; failure to do so within `max_steps` is
    reported as `lineax.RESULTS.max_steps_reached`, and a non-finite iterate (NaN or
    inf in the operator or the right-hand side) as `lineax.RESULTS.nonfinite_input`.

    !!! note

        Unpreconditioned: the number of iterations grows with the condition number of
        the operator restricted to the Krylov space. Well-scaled problems need tens of
        iterations whatever their size.

    **Reference:** C. C. Paige and M. A. Saunders, *Solution of sparse indefinite
    systems of linear equations*, SIAM J. Numer. Anal. 12 (1975) 617-629.
    """

    rtol: float
    atol: float
    max_steps: int = 1000

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("`MINRES` may only be used with square operators.")
        if not lx.is_symmetric(operator):
            raise ValueError(
                "`MINRES` requires a symmetric operator: tag it with "
                "`lineax.symmetric_tag`."
            )
        return lx.linearise(operator), lxi.pack_structures(operator)

    def compute(self, state, vector: PyTree[Array], options: dict[str, Any]):
        del options
        operator, packed = state
        b = lxi.ravel_vector(vector, packed)
        unravel_in = lambda v: lxi.unravel_solution(v, packed)

        def matvec(v):
            out = operator.mv(unravel_in(v))
            return jnp.concatenate(
                [jnp.ravel(leaf) for leaf in jax.tree_util.tree_leaves(out)]
            )

        x, num_steps, converged = minres(
            matvec, b, rtol=self.rtol, atol=self.atol, max_steps=self.max_steps
        )
        result = lx.RESULTS.where(
            converged, lx.RESULTS.successful, lx.RESULTS.max_steps_reached
        )
        result = lx.RESULTS.where(
            jnp.all(jnp.isfinite(x)), result, lx.RESULTS.nonfinite_input
        )
        return unravel_in(x), result, {"num_steps": num_steps}

    def transpose(self, state, options: dict[str, Any]):
        operator, packed = state
        return (operator.transpose(), lxi.transpose_packed_structures(packed)), {}

    def conj(self, state, options: dict[str, Any]):
        operator, packed = state
        return (lx.conj(operator), packed), {}

    def assume_full_rank(self):
        return True


MINRES.__init__.__doc__ = """**Arguments:**

- `rtol`, `atol`: stop when `||A x - b|| <= atol + rtol ||b||`.
- `max_steps`: the most Krylov iterations (matrix-vector products).
"""


def minres(
    matvec, b: Float[Array, " m"], *, rtol, atol, max_steps: int, refinements: int = 3
):
    """MINRES for a symmetric operator `matvec`, with iterative refinement.

    MINRES stops on its recurrence estimate of the residual, which drifts from the true
    residual `b - A x` in floating point (by orders of magnitude for long runs). So the
    true residual is computed at the end and, while it misses the tolerance, MINRES is
    restarted on it (at most `refinements` times; a pass that is not needed costs one
    matrix-vector product). Returns `(x, num_steps, converged)`, `converged` judged on
    the true residual; `num_steps` counts every iteration, capped by `max_steps` in
    total.
    """
    tol = atol + rtol * jnp.linalg.norm(b)
    x, steps, _ = _minres_pass(matvec, b, tol, max_steps)
    for _ in range(refinements):
        r = b - matvec(x)
        dx, more, _ = _minres_pass(matvec, r, tol, max_steps - steps)
        x = x + dx
        steps = steps + more
    converged = jnp.linalg.norm(b - matvec(x)) <= tol
    return x, steps, converged


def _minres_pass(matvec, b: Float[Array, " m"], tol, max_steps):
    """One MINRES run from zero, until the recurrence residual is below `tol`.

    Follows SciPy's `minres` without preconditioning.
    """
    dtype = b.dtype
    eps = jnp.finfo(dtype).eps
    beta1 = jnp.linalg.norm(b)
    zero_vec = jnp.zeros_like(b)

    def cond(carry):
        (itn, _, _, _, _, _, _, _, _, _, _, _, _, phibar, done) = carry
        return (itn < max_steps) & jnp.invert(done) & (phibar > tol)

    def body(carry):
        (itn, x, r1, r2, y, w, w2, oldb, beta, dbar, epsln, cs, sn, phibar, _) = carry
        safe_beta = jnp.where(beta > 0, beta, 1.0)
        v = y / safe_beta
        y = matvec(v)
        safe_oldb = jnp.where(oldb > 0, oldb, 1.0)
        y = y - jnp.where(itn >= 1, beta / safe_oldb, 0.0) * r1
        alfa = jnp.dot(v, y)
        y = y - (alfa / safe_beta) * r2
        r1 = r2
        r2 = y
        oldb = beta
        beta = jnp.linalg.norm(y)
        oldeps = epsln
        delta = cs * dbar + sn * alfa
        gbar = sn * dbar - cs * alfa
        epsln = sn * beta
        dbar = -cs * beta
        gamma = jnp.maximum(jnp.hypot(gbar, beta), eps)
        cs = gbar / gamma
        sn = beta / gamma
        phi = cs * phibar
        phibar = sn * phibar
        w1 = w2
        w2 = w
        w = (v - oldeps * w1 - delta * w2) / gamma
        x = x + phi * w
        # beta == 0: the Krylov space is invariant and x is exact.
        done = beta <= eps * beta1
        return (
            itn + 1,
            x,
            r1,
            r2,
            y,
            w,
            w2,
            oldb,
            beta,
            dbar,
            epsln,
            cs,
            sn,
            phibar,
            done,
        )

    one = jnp.ones((), dtype)
    zero = jnp.zeros((), dtype)
    init = (
        jnp.array(0),
        zero_vec,
        b,
        b,
        b,
        zero_vec,
        zero_vec,
        zero,
        beta1,
        zero,
        zero,
        -one,
        zero,
        beta1,
        beta1 == 0,
    )
    out = lax.while_loop(cond, body, init)
    itn, x, phibar, done = out[0], out[1], out[13], out[14]
    converged = done | (phibar <= tol)
    return x, itn, converged
