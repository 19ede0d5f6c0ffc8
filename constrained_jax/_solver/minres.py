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
