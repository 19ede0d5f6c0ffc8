"""The globalisation shared by [`constrained_jax.SemismoothNewton`][]'s two steps (the
dense one, and the bound step of `bound_step.py`): the natural monotonicity test on
the Newton direction, else Levenberg-Marquardt with an Armijo search on the weighted
merit; and the matrix-free conjugate gradients and least-eigenvalue estimate both
use."""

import jax.lax as lax
import jax.numpy as jnp


def tolerances(solver, dtype):
    """`(rtol, atol)` of `solver`, each raised to `100 eps` of `dtype`."""
    floor = 100 * jnp.finfo(dtype).eps
    rtol = jnp.maximum(jnp.asarray(solver.rtol, dtype), floor)
    atol = jnp.maximum(jnp.asarray(solver.atol, dtype), floor)
    return rtol, atol


def conjugate_gradient_mv(apply, shift, rhs, max_steps: int):
    """Solve `(A + shift I) d = rhs`, `A` symmetric positive semidefinite given by
    `apply`, by conjugate gradients from `d = 0`, at most `max_steps` steps, to a
    relative residual of `sqrt(eps)`. Every iterate descends the quadratic model, so
    stopping early still gives a descent direction."""
    tol = jnp.sqrt(jnp.finfo(rhs.dtype).eps) * jnp.linalg.norm(rhs)

    def cond(c):
        _, _, _, rr, it = c
        return (it < max_steps) & (jnp.sqrt(rr) > tol)

    def body(c):
        d, r, p, rr, it = c
        ap = apply(p) + shift * p
        pap = jnp.dot(p, ap)
        alpha = jnp.where(pap > 0, rr / jnp.where(pap > 0, pap, 1.0), 0.0)
        d = d + alpha * p
        r = r - alpha * ap
        rr_new = jnp.dot(r, r)
        p = r + rr_new / jnp.where(rr > 0, rr, 1.0) * p
        it = jnp.where(pap > 0, it + 1, max_steps)
        return d, r, p, rr_new, it

    zero = jnp.zeros_like(rhs)
    d, *_ = lax.while_loop(cond, body, (zero, rhs, rhs, jnp.dot(rhs, rhs), 0))
    return d


def least_eigenvalue_mv(matvec, size: int, dtype, bound, num_steps: int = 32):
    """An estimate of the least eigenvalue of a symmetric operator, by power
    iteration on `bound I - A` from a fixed start (`bound` at least the spectral
    radius); the Rayleigh quotient bounds it from above."""
    v = 1.0 + jnp.arange(size, dtype=dtype) / size
    v = v / jnp.linalg.norm(v)

    def body(_, v):
        w = bound * v - jnp.where(jnp.isfinite(av := matvec(v)), av, 0.0)
        norm = jnp.linalg.norm(w)
        return jnp.where(norm > 0, w / jnp.where(norm > 0, norm, 1.0), v)

    v = lax.fori_loop(0, num_steps, body, v)
    return jnp.dot(v, matvec(v))


def levenberg_marquardt_damping(psi, gram_max, eps):
    """The damping `nu` of the Levenberg-Marquardt direction, from the merit `psi`
    and the largest diagonal entry of the (weighted) Gram matrix `J^T W^2 J`:
    `min(sqrt(2 psi), 1) max(gram_max, 1)`, at least `1e3 eps gram_max` (for a
    positive semidefinite Gram matrix its largest entry is on the diagonal)."""
    nu = jnp.minimum(jnp.sqrt(2 * psi), 1.0) * jnp.maximum(gram_max, 1.0)
    return jnp.maximum(nu, 1e3 * eps * gram_max)


def globalized_step(
    z,
    r,
    res,
    finite,
    weight,
    psi,
    grad_psi,
    newton_solve,
    matvec,
    check_rtol,
    lm_direction,
    rtol,
    atol,
    max_backtracks: int,
):
    """One globalised step from `z` (residual `r`, proximal residual `res`).

    The Newton direction `newton_solve(-r)` counts where it is finite and solves the
    system to `check_rtol` (`|matvec(dz) + r| <= check_rtol |r|`). Deuflhard's natural
    monotonicity test (as in `Newton`: the simplified correction at the trial point
    must shrink, in the scaled norm `rms(v / (atol + rtol |z|))`) decides its length;
    where it fails, `lm_direction()` (a descent direction of the merit
    `Psi = |weight r|^2 / 2`, gradient `grad_psi`) with an Armijo search on `Psi`.
    Converged where the full Newton step is within tolerance (it is then taken).

    **Returns:** `(z_new, converged, moved)`.
    """
    dtype = z.dtype
    one = jnp.ones((), dtype)
    dz_newton = newton_solve(-r)
    check = jnp.linalg.norm(matvec(dz_newton) + r)
    newton_ok = (
        finite
        & jnp.all(jnp.isfinite(dz_newton))
        & (check <= check_rtol * jnp.linalg.norm(r) + jnp.finfo(dtype).tiny)
    )
    dz_newton = jnp.where(newton_ok, dz_newton, 0.0)
    scale = atol + rtol * jnp.abs(z)
    norm = lambda v: jnp.sqrt(jnp.mean(jnp.square(v / scale)))
    step_norm = norm(dz_newton)
    converged = (psi == 0) | (newton_ok & (step_norm < 1))

    def contraction(alpha):
        simplified = newton_solve(-res(z + alpha * dz_newton))
        theta = norm(simplified) / jnp.where(step_norm > 0, step_norm, 1.0)
        return jnp.where(jnp.isfinite(theta), theta, jnp.inf)

    def nm_cond(c):
        alpha, theta, it = c
        return jnp.invert(theta <= 1 - alpha / 4) & (it < max_backtracks) & newton_ok

    def nm_body(c):
        alpha, _, it = c
        alpha = 0.5 * alpha
        return alpha, contraction(alpha), it + 1

    # Converged: no trial point is needed.
    theta0 = lax.cond(converged, lambda: jnp.zeros((), dtype), lambda: contraction(one))
    alpha_n, theta, _ = lax.while_loop(nm_cond, nm_body, (one, theta0, 0))
    ok_n = newton_ok & (theta <= 1 - alpha_n / 4)

    def merit(z_):
        r_ = weight * res(z_)
        value = 0.5 * jnp.dot(r_, r_)
        return jnp.where(jnp.isfinite(value), value, jnp.inf)

    def armijo():
        dz = lm_direction()
        slope = jnp.dot(grad_psi, dz)
        descent = slope < 0

        def accept(alpha):
            return merit(z + alpha * dz) <= psi + 1e-4 * alpha * slope

        def cond(c):
            alpha, ok, it = c
            return jnp.invert(ok) & (it < max_backtracks) & descent

        def body(c):
            alpha, _, it = c
            alpha = 0.5 * alpha
            return alpha, accept(alpha), it + 1

        alpha, ok, _ = lax.while_loop(cond, body, (one, accept(one), 0))
        return alpha * dz, ok & descent

    dz_lm, ok_lm = lax.cond(
        ok_n | converged | jnp.invert(finite),
        lambda: (jnp.zeros_like(z), jnp.array(False)),
        armijo,
    )
    dz = jnp.where(ok_n, alpha_n * dz_newton, dz_lm)
    dz = jnp.where(converged, dz_newton, dz)
    moved = converged | ok_n | ok_lm
    return jnp.where(moved, z + dz, z), converged, moved
