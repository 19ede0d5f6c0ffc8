"""MINRES: a matrix-free Lineax solver for symmetric (possibly indefinite) operators
such as a KKT matrix. Needs only matrix-vector products, i.e. Hessian-vector products
by autodiff, so an n x n matrix is never formed.
"""

from typing import Any

import jax
import jax.lax as lax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float, PyTree

from .._compat import lineax_internal as lxi


class MINRES(lx.AbstractLinearSolver):
    """Minimal-residual Krylov solver for symmetric (possibly indefinite) operators,
    with a diagonal preconditioner.

    The natural Krylov method for a KKT matrix `K = [[H, J^T], [J, 0]]`, which is
    symmetric but indefinite, so that conjugate gradients do not apply. Only
    matrix-vector products are used: with a `lineax.JacobianLinearOperator` these are
    Hessian-vector products by forward-over-reverse autodiff, and no matrix is formed.

    **Preconditioning.** MINRES needs a symmetric positive definite preconditioner
    (Wathen and Silvester). This one is diagonal, `D = diag(d)` with `d_i` the
    Euclidean norm of row `i` of the operator, estimated from `probes` products with
    fixed random sign vectors `v`: `d_i^2 = mean (A v)_i^2`, whose expectation is
    `sum_j A_ij^2` (Bekas, Kokiopoulou and Saad). On the rows of `x` of a KKT matrix
    whose Hessian dominates its rows (the ill-conditioned case, e.g. `1/x_i` of an
    entropy) `d_i` is `|H_ii|`, the Jacobi preconditioner of the Hessian block; on the
    rows of `lambda` it is `|grad G_j|`. The estimate is exact for a diagonal operator
    whatever `probes`, and within a factor of about `1 + sqrt(2 / probes)` otherwise.
    MINRES runs on the symmetrically scaled operator `D^{-1/2} A D^{-1/2}`.
    `probes=0` turns the preconditioner off.

    Terminates when the *true* residual satisfies `||A x - b|| <= atol + rtol ||b||`,
    with `rtol` raised to `100 eps` of the dtype where it is below (as in
    [`constrained_jax.Newton`][]: a residual cannot be computed more accurately than
    its round-off, so that `rtol=1e-12` in float32 means `1.2e-5`); failure to do so
    within `max_steps` is reported as `lineax.RESULTS.max_steps_reached`. NaN or inf
    in the operator or the right-hand side is never turned into a number: the
    solution is then NaN and the status `lineax.RESULTS.nonfinite_input`.

    **References:** C. C. Paige and M. A. Saunders, *Solution of sparse indefinite
    systems of linear equations*, SIAM J. Numer. Anal. 12 (1975) 617-629.
    A. J. Wathen and D. J. Silvester, *Fast iterative solution of stabilised Stokes
    systems. Part I*, SIAM J. Numer. Anal. 30 (1993) 630-649. C. Bekas,
    E. Kokiopoulou and Y. Saad, *An estimator for the diagonal of a matrix*, Appl.
    Numer. Math. 57 (2007) 1214-1229.
    """

    rtol: float
    atol: float
    max_steps: int = 1000
    probes: int = 16

    def __check_init__(self):
        if isinstance(self.probes, int) and self.probes < 0:
            raise ValueError("`MINRES(probes=...)` must be a non-negative integer.")

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("`MINRES` may only be used with square operators.")
        if not lx.is_symmetric(operator):
            raise ValueError(
                "`MINRES` requires a symmetric operator: tag it with "
                "`lineax.symmetric_tag`."
            )
        operator = lx.linearise(operator)
        packed = lxi.pack_structures(operator)
        scale = _row_norm_scale(_flat_matvec(operator, packed), operator, self.probes)
        return operator, packed, scale

    def compute(self, state, vector: PyTree[Array], options: dict[str, Any]):
        del options
        operator, packed, scale = state
        b = lxi.ravel_vector(vector, packed)
        rtol = jnp.maximum(
            jnp.asarray(self.rtol, b.dtype), 100 * jnp.finfo(b.dtype).eps
        )
        x, num_steps, converged = minres(
            _flat_matvec(operator, packed),
            b,
            rtol=rtol,
            atol=self.atol,
            max_steps=self.max_steps,
            scale=scale,
        )
        result = lx.RESULTS.where(
            converged, lx.RESULTS.successful, lx.RESULTS.max_steps_reached
        )
        result = lx.RESULTS.where(
            jnp.all(jnp.isfinite(x)), result, lx.RESULTS.nonfinite_input
        )
        return lxi.unravel_solution(x, packed), result, {"num_steps": num_steps}

    def transpose(self, state, options: dict[str, Any]):
        # Symmetric: the transpose has the same row norms.
        operator, packed, scale = state
        return (
            operator.transpose(),
            lxi.transpose_packed_structures(packed),
            scale,
        ), {}

    def conj(self, state, options: dict[str, Any]):
        operator, packed, scale = state
        return (lx.conj(operator), packed, scale), {}

    def assume_full_rank(self):
        return True


MINRES.__init__.__doc__ = """**Arguments:**

- `rtol`, `atol`: stop when `||A x - b|| <= atol + rtol ||b||`.
- `max_steps`: the most Krylov iterations (matrix-vector products).
- `probes`: random products that estimate the diagonal preconditioner (`0`: none).
"""


def _flat_matvec(operator, packed):
    """`v -> A v` on flat vectors."""

    def matvec(v):
        out = operator.mv(lxi.unravel_solution(v, packed))
        return jnp.concatenate(
            [jnp.ravel(leaf) for leaf in jax.tree_util.tree_leaves(out)]
        )

    return matvec


def _row_norm_scale(matvec, operator, probes: int) -> Float[Array, " m"]:
    """`d^{-1/2}`, `d_i` the norm of row `i` of the operator estimated from `probes`
    products with fixed Rademacher vectors (ones where `probes = 0`). Rows whose
    estimate is zero or below `eps` of the largest are given that floor (an exactly
    zero row makes the operator singular, which MINRES then reports); a NaN estimate
    (a NaN operator) stays NaN, so that the solve is NaN."""
    size = operator.in_size()
    dtype = jnp.result_type(
        *[s.dtype for s in jax.tree_util.tree_leaves(operator.in_structure())]
    )
    if probes == 0:
        return jnp.ones((size,), dtype)
    signs = jax.random.rademacher(jax.random.key(0), (probes, size), dtype)
    d = jnp.sqrt(jnp.mean(jnp.square(jax.vmap(matvec)(signs)), axis=0))
    floor = jnp.maximum(jnp.finfo(dtype).eps * jnp.max(d), jnp.finfo(dtype).tiny)
    d = jnp.where(d > floor, d, floor)
    d = jnp.where(jnp.all(jnp.isfinite(d)), d, jnp.nan)
    return 1 / jnp.sqrt(d)


def minres(
    matvec,
    b: Float[Array, " m"],
    *,
    rtol,
    atol,
    max_steps: int,
    scale: Float[Array, " m"] | None = None,
    refinements: int = 3,
):
    """MINRES for a symmetric operator `matvec`, with iterative refinement.

    With `scale = s` MINRES runs on the scaled operator `S A S`, `S = diag(s)` (a
    diagonal preconditioner `D = S^{-2}`), and the solution is `x = S y`.

    MINRES stops on its recurrence estimate of the residual, which drifts from the true
    residual `b - A x` in floating point (by orders of magnitude for long runs), and
    with a preconditioner estimates the scaled residual, not `b - A x`. So the true
    residual is computed at the end and, while it misses the tolerance, MINRES is
    restarted on it (at most `refinements` times; a pass that is not needed costs one
    matrix-vector product), each pass aiming at the same relative reduction of the
    scaled residual. Returns `(x, num_steps, converged)`, `converged` judged on the
    true residual; `num_steps` counts every iteration, capped by `max_steps` in total.
    Where the operator or `b` is not finite, `x` is NaN (never zeros) and not
    converged.
    """
    if scale is None:
        scale = jnp.ones_like(b)
    scaled = lambda y: scale * matvec(scale * y)
    tol = atol + rtol * jnp.linalg.norm(b)

    def refine(x, r, steps):
        r_norm = jnp.linalg.norm(r)
        rs = scale * r
        ratio = jnp.linalg.norm(rs) / jnp.where(r_norm > 0, r_norm, 1.0)
        dy, more, _ = _minres_pass(scaled, rs, tol * ratio, max_steps - steps)
        return x + scale * dy, steps + more

    x, steps = refine(jnp.zeros_like(b), b, jnp.array(0))
    for _ in range(refinements):
        x, steps = refine(x, b - matvec(x), steps)
    r = b - matvec(x)
    finite = jnp.all(jnp.isfinite(r)) & jnp.all(jnp.isfinite(x))
    converged = finite & (jnp.linalg.norm(r) <= tol)
    # A NaN right-hand side leaves MINRES at its start, zero: report NaN instead.
    x = jnp.where(finite, x, jnp.nan)
    return x, steps, converged


def _minres_pass(matvec, b: Float[Array, " m"], tol, max_steps):
    """One MINRES run from zero, until the recurrence residual is below `tol`.

    Follows SciPy's `minres` without preconditioning (the caller scales).
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
