"""Inequality constraints in [`constrained_jax.extremize`][]: the KKT conditions of

    extremize F(x)  subject to  G(x) = 0,  H(x) <= 0,

in the convention `grad F + lambda . grad G + mu . grad H = 0`, `mu . H = 0`, with
`s mu >= 0` (`s = +1` to minimize, `-1` to maximize), as a square nonsmooth system.

Complementarity `s mu_i >= 0, -H_i >= 0, s mu_i H_i = 0` holds exactly where the
Fischer-Burmeister function `phi(a, b) = a + b - sqrt(a^2 + b^2)` of `(s mu_i, -H_i)`
vanishes, so the unknowns `z = (x, lambda, mu)` solve the `n + k + m` equations

    grad F + J^T lambda + A^T mu = 0,    G = 0,    phi(s mu, -H) = 0

(`J = dG/dx`, `A = dH/dx`). They are solved by a semismooth Newton method whose
steps are damped by Deuflhard's natural monotonicity test (the globalisation of
[`constrained_jax.Newton`][]); where the Jacobian is singular (degenerate vertices,
dependent active constraints) or that test fails, a Levenberg-Marquardt step with an
Armijo line search on the merit `Psi = |r|^2 / 2`, which is continuously
differentiable for this `phi` (De Luca, Facchinei and Kanzow 1996). (An Armijo search
on `Psi` alone stalled at a local minimum of `|grad F|^2` on Rosenbrock's function
from (-1.2, 1); the monotonicity test, being affine invariant, does not.)

**References:** A. Fischer, *A special Newton-type optimization method*,
Optimization 24 (1992) 269-284; T. De Luca, F. Facchinei and C. Kanzow, *A semismooth
equation approach to the solution of nonlinear complementarity problems*,
Math. Programming 75 (1996) 407-439.
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.scipy as jsp
import lineax as lx
from jaxtyping import Array, Bool, Float, PyTree

from ._implicit import implicit_jvp
from ._results import RESULTS
from ._solver.newton import AbstractKKTSolver, iterate


# ---------------------------------------------------------------------------------
# The complementarity function
# ---------------------------------------------------------------------------------


@jax.custom_jvp
def fischer_burmeister(a: Array, b: Array) -> Array:
    """`phi(a, b) = a + b - sqrt(a^2 + b^2)`: zero exactly where `a >= 0`, `b >= 0`
    and `a b = 0`.

    Evaluated without cancellation (`2ab / (a + b + sqrt(a^2 + b^2))` where
    `a + b > 0`). Its derivative at the kink `a = b = 0` is taken as `(1, 0)`, the
    element of the B-subdifferential of an inactive constraint (`b > 0`, `a = 0`), so
    that it is always defined.
    """
    r = jnp.hypot(a, b)
    s = a + b
    safe = jnp.where(s > 0, s + r, 1.0)
    return jnp.where(s > 0, 2 * a * b / safe, s - r)


@fischer_burmeister.defjvp
def _fischer_burmeister_jvp(primals, tangents):
    a, b = primals
    ta, tb = tangents
    r = jnp.hypot(a, b)
    kink = r == 0
    safe = jnp.where(kink, 1.0, r)
    da = jnp.where(kink, 1.0, 1 - a / safe)
    db = jnp.where(kink, 0.0, 1 - b / safe)
    return fischer_burmeister(a, b), da * ta + db * tb


# ---------------------------------------------------------------------------------
# Residual
# ---------------------------------------------------------------------------------


class InequalityProblem(eqx.Module):
    """`F`, `G` (or `None`), `H` on flat `x`, the sizes and the sign `s` of `mu`."""

    objective: Callable
    constraints: Callable | None
    inequalities: Callable
    n: int = eqx.field(static=True)
    k: int = eqx.field(static=True)
    m: int = eqx.field(static=True)
    sign: float = eqx.field(static=True)

    def split(self, z):
        n, k = self.n, self.k
        return z[:n], z[n : n + k], z[n + k :]

    def values(self, x, args):
        f = self.objective(x, args)
        g = (
            jnp.zeros((0,), x.dtype)
            if self.constraints is None
            else self.constraints(x, args)
        )
        return f, g, self.inequalities(x, args)

    def stationarity(self, z, args, mu_weight=None):
        """`(grad F + J^T lambda + A^T mu, G, H)` by one reverse pass."""
        x, lam, mu = self.split(z)
        if mu_weight is not None:
            mu = mu * mu_weight
        (f, g, h), vjp = jax.vjp(lambda x_: self.values(x_, args), x)
        (grad_star,) = vjp((jnp.ones_like(f), lam, mu))
        return grad_star, g, h

    def residual(self, z, args):
        _, _, mu = self.split(z)
        grad_star, g, h = self.stationarity(z, args)
        return jnp.concatenate([grad_star, g, fischer_burmeister(self.sign * mu, -h)])


# ---------------------------------------------------------------------------------
# Semismooth Newton
# ---------------------------------------------------------------------------------


def _conjugate_gradient(matrix, shift, rhs):
    """Solve `(matrix + shift I) d = rhs` (symmetric positive definite) by conjugate
    gradients from `d = 0`, at most `len(rhs)` steps, to a relative residual of
    `sqrt(eps)`.

    Used for the Levenberg-Marquardt direction instead of a second factorisation:
    beside the Newton step's LU, a second batched LAPACK factorisation in the same
    loop body deadlocked XLA's CPU runtime under `jax.vmap` at a few hundred
    problems (every thread of its intra-op pool idle). Every conjugate-gradient
    iterate of an SPD system started at zero is a descent direction of its
    quadratic model, `rhs . d > 0`, so with `rhs = -grad Psi` the direction
    descends `Psi` however early the iteration stops.
    """
    size = rhs.shape[0]
    tol = jnp.sqrt(jnp.finfo(rhs.dtype).eps) * jnp.linalg.norm(rhs)

    def apply(v):
        return matrix @ v + shift * v

    def cond(c):
        _, r, _, rr, it = c
        return (it < size) & (jnp.sqrt(rr) > tol)

    def body(c):
        d, r, p, rr, it = c
        ap = apply(p)
        pap = jnp.dot(p, ap)
        alpha = rr / jnp.where(pap > 0, pap, 1.0)
        alpha = jnp.where(pap > 0, alpha, 0.0)
        d = d + alpha * p
        r = r - alpha * ap
        rr_new = jnp.dot(r, r)
        beta = rr_new / jnp.where(rr > 0, rr, 1.0)
        p = r + beta * p
        # A non-positive curvature (round-off) ends the iteration where it is.
        it = jnp.where(pap > 0, it + 1, size)
        return d, r, p, rr_new, it

    zero = jnp.zeros_like(rhs)
    rr0 = jnp.dot(rhs, rhs)
    d, *_ = lax.while_loop(cond, body, (zero, rhs, rhs, rr0, 0))
    return d


class _State(eqx.Module):
    done: Bool[Array, ""]
    result: RESULTS


class _SemismoothNewton(AbstractKKTSolver):
    """Semismooth Newton on `r(z) = 0`. Dense: the Jacobian is formed by
    forward-mode autodiff and LU-factored. The Newton step is damped by Deuflhard's
    natural monotonicity test (as in [`constrained_jax.Newton`][]); where the
    Jacobian is singular or that test fails, a Levenberg-Marquardt step with an
    Armijo line search on `Psi = |r|^2 / 2` is taken instead (a descent direction
    of `Psi` whenever `grad Psi = J^T r != 0`). Converged when a full Newton step is
    within `atol + rtol |z|` (root mean square of the scaled step below 1); the
    step is then taken."""

    rtol: float
    atol: float
    linear_solver: lx.AbstractLinearSolver
    max_backtracks: int = 40

    def init(self, residual, z, args):
        del residual, args
        return _State(done=jnp.array(False), result=RESULTS.successful)

    def step(self, residual, z, args, state):
        dtype = z.dtype
        eps = jnp.finfo(dtype).eps
        floor = 100 * eps
        rtol = jnp.maximum(jnp.asarray(self.rtol, dtype), floor)
        atol = jnp.maximum(jnp.asarray(self.atol, dtype), floor)
        res = lambda z_: residual(z_, args)
        r = res(z)
        jac = jax.jacfwd(res)(z)
        finite = jnp.all(jnp.isfinite(r)) & jnp.all(jnp.isfinite(jac))
        # The merit function of the fallback weighs each row of `r` by the
        # reciprocal of its row of the Jacobian (max-norm): stationarity (in the
        # units of grad F) and complementarity (in the units of H) would otherwise
        # differ by as many orders of magnitude as the multipliers are large, and
        # Levenberg-Marquardt would ignore the complementarity rows. (The Newton
        # step is invariant to this scaling.)
        row_size = jnp.max(jnp.abs(jnp.where(finite, jac, 0.0)), axis=1)
        weight = 1 / jnp.where(row_size > 0, row_size, 1.0)
        psi = 0.5 * jnp.dot(weight * r, weight * r)
        grad_psi = jac.T @ (weight**2 * r)
        one = jnp.ones((), dtype)

        # The Newton direction, if the Jacobian is (numerically) invertible; the
        # same factorisation gives the simplified Newton corrections.
        factors = jsp.linalg.lu_factor(jnp.where(finite, jac, 0.0))
        newton_solve = lambda rhs: jsp.linalg.lu_solve(factors, rhs)
        dz_newton = newton_solve(-r)
        check = jnp.linalg.norm(jac @ dz_newton + r)
        newton_ok = (
            finite
            & jnp.all(jnp.isfinite(dz_newton))
            & (check <= 1e-6 * jnp.linalg.norm(r) + jnp.finfo(dtype).tiny)
        )
        dz_newton = jnp.where(newton_ok, dz_newton, 0.0)
        scale = atol + rtol * jnp.abs(z)
        norm = lambda v: jnp.sqrt(jnp.mean(jnp.square(v / scale)))
        step_norm = norm(dz_newton)
        converged = (psi == 0) | (newton_ok & (step_norm < 1))

        # Deuflhard's natural monotonicity test on the Newton direction, as in
        # `Newton`: the simplified correction at the trial point must shrink.
        def contraction(alpha):
            simplified = newton_solve(-res(z + alpha * dz_newton))
            theta = norm(simplified) / jnp.where(step_norm > 0, step_norm, 1.0)
            return jnp.where(jnp.isfinite(theta), theta, jnp.inf)

        def nm_cond(c):
            alpha, theta, it = c
            return (
                jnp.invert(theta <= 1 - alpha / 4)
                & (it < self.max_backtracks)
                & newton_ok
            )

        def nm_body(c):
            alpha, _, it = c
            alpha = 0.5 * alpha
            return alpha, contraction(alpha), it + 1

        alpha_n, theta, _ = lax.while_loop(nm_cond, nm_body, (one, contraction(one), 0))
        ok_n = newton_ok & (theta <= 1 - alpha_n / 4)

        # Otherwise Levenberg-Marquardt, always a descent direction of Psi, with an
        # Armijo line search on Psi.
        scaled_jac = weight[:, None] * jac
        jtj = scaled_jac.T @ scaled_jac
        nu = jnp.minimum(jnp.sqrt(2 * psi), 1.0) * jnp.maximum(
            jnp.max(jnp.abs(jnp.diag(jtj))), 1.0
        )
        nu = jnp.maximum(nu, 1e3 * eps * jnp.max(jnp.abs(jtj)))
        dz_lm = _conjugate_gradient(
            jnp.where(finite, jtj, 0.0), jnp.where(finite, nu, 1.0), -grad_psi
        )
        dz_lm = jnp.where(jnp.all(jnp.isfinite(dz_lm)), dz_lm, 0.0)

        def merit(z_):
            r_ = weight * res(z_)
            value = 0.5 * jnp.dot(r_, r_)
            return jnp.where(jnp.isfinite(value), value, jnp.inf)

        def armijo(dz):
            slope = jnp.dot(grad_psi, dz)
            descent = slope < 0

            def accept(alpha):
                return merit(z + alpha * dz) <= psi + 1e-4 * alpha * slope

            def cond(c):
                alpha, ok, it = c
                return jnp.invert(ok) & (it < self.max_backtracks) & descent

            def body(c):
                alpha, _, it = c
                alpha = 0.5 * alpha
                return alpha, accept(alpha), it + 1

            alpha, ok, _ = lax.while_loop(cond, body, (one, accept(one), 0))
            return alpha, ok & descent

        alpha_lm, ok_lm = lax.cond(
            ok_n | converged,
            lambda: (jnp.zeros((), dtype), jnp.array(False)),
            lambda: armijo(dz_lm),
        )
        dz = jnp.where(ok_n, alpha_n * dz_newton, alpha_lm * dz_lm)
        dz = jnp.where(converged, dz_newton, dz)
        moved = converged | ok_n | ok_lm
        z_new = jnp.where(moved, z + dz, z)
        result = RESULTS.where(
            moved,
            RESULTS.successful,
            RESULTS.where(
                finite, RESULTS.line_search_failed, RESULTS.nonfinite_objective
            ),
        )
        done = converged | jnp.invert(moved)
        return z_new, _State(done=done, result=result)

    def terminate(self, residual, z, args, state):
        del residual, z, args
        return state.done, state.result

    def postprocess(self, residual, z, args, state):
        del residual, args, state
        return z, {}


# ---------------------------------------------------------------------------------
# The solve, its verification and its derivatives
# ---------------------------------------------------------------------------------


def _scales(problem, z, args):
    """Units in which the KKT conditions are checked: of the multipliers `mu`
    (`max(1, |mu|)`), of each `H_i` (`max(1, |x|) |grad H_i|`, floored at 1)
    and of the stationarity (`max(1, |grad F|)`), all max-norms."""
    x, _, mu = problem.split(z)
    jac_h = jax.jacrev(problem.inequalities)(x, args)
    grad_f = jax.grad(problem.objective)(x, args)
    x_scale = jnp.maximum(1.0, jnp.max(jnp.abs(x)))
    h_scale = jnp.maximum(1.0, x_scale * jnp.max(jnp.abs(jac_h), axis=1))
    mu_scale = jnp.maximum(1.0, jnp.max(jnp.abs(mu), initial=0.0))
    stat_scale = jnp.maximum(1.0, jnp.max(jnp.abs(grad_f)))
    return mu_scale, h_scale, stat_scale, jac_h


def _active_sets(problem, z, args, tol):
    """`(active, strict, violation, infeasible, jac_h)` at `z`, in the units of
    `_scales` (`a = s mu_i`, `b = -H_i`, each relative):

    - `active` where `H_i` is the zero of the complementary pair: `b <= max(a,
        tol^2)` (`tol^2` is the solver's own tolerance, `max(rtol, atol, 100 eps)`);
    - `strict` where also `a > tol^2`: active with a nonzero multiplier.
        `active & ~strict` are the weakly active (degenerate) inequalities;
    - `violation`: the largest violation of the KKT conditions (stationarity,
        `G = 0`, and `|min(a, b)|`, which covers feasibility, the sign of `mu` and
        complementarity);
    - `infeasible`: the largest `H_i > 0`.
    """
    _, _, mu = problem.split(z)
    mu_scale, h_scale, stat_scale, jac_h = _scales(problem, z, args)
    grad_star, g, h = problem.stationarity(z, args)
    a = problem.sign * mu / mu_scale
    b = -h / h_scale
    fine = tol * tol
    active = b <= jnp.maximum(a, fine)
    strict = active & (a > fine)
    complementarity = jnp.max(jnp.abs(jnp.minimum(a, b)), initial=0.0)
    stationarity = jnp.max(jnp.abs(grad_star)) / stat_scale
    x_scale = jnp.maximum(1.0, jnp.max(jnp.abs(problem.split(z)[0])))
    feasibility = jnp.max(jnp.abs(g), initial=0.0) / x_scale
    violation = jnp.maximum(jnp.maximum(complementarity, stationarity), feasibility)
    infeasible = jnp.max(-b, initial=0.0)
    return active, strict, violation, infeasible, jac_h


def _primal(inputs):
    problem, solver, z0, args, max_steps, start_ok, tol = inputs
    z, result, stats = iterate(solver, problem.residual, z0, args, max_steps, start_ok)
    active, strict, violation, infeasible, _ = _active_sets(problem, z, args, tol)
    aux = {
        **stats,
        "active": active,
        "strict": strict,
        "violation": violation,
        "infeasible": infeasible,
    }
    return z, (result, aux)


def _rewrite(z, residual, inputs):
    """The equations differentiated by the implicit function theorem: the strictly
    active inequalities as equalities `H_i = 0`, the others as `mu_i = 0`. Their
    Jacobian is symmetric,

        [[Hess_x F*, J^T, A_S^T, 0],
         [J,         0,   0,     0],
         [A_S,       0,   0,     0],
         [0,         0,   0,     I]],

    (`A_S` the rows of `dH/dx` that are strictly active), so the solver's own
    `linear_solver` (symmetric, possibly matrix-free) solves the tangent system."""
    problem, _, _, args, _, _, _ = inputs
    strict = residual[1]["strict"]
    weight = strict.astype(z.dtype)
    _, _, mu = problem.split(z)
    grad_star, g, h = problem.stationarity(z, args, mu_weight=weight)
    # A blend, not `jnp.where`: reverse mode then carries the NaN cotangents of a
    # failed solve into every input (`where` would send them a zero).
    return jnp.concatenate([grad_star, g, weight * h + (1 - weight) * mu])


def inequality_solve(
    problem: InequalityProblem,
    z0: Float[Array, " N"],
    args: PyTree,
    rtol: float,
    atol: float,
    linear_solver: lx.AbstractLinearSolver,
    max_steps: int,
    start_ok: Bool[Array, ""],
) -> tuple[Float[Array, " N"], RESULTS, dict[str, Any]]:
    """Solve the KKT system of `problem` from `z0 = (x0, lambda0, mu0)`.

    **Returns:** `(z, result, aux)`: the root, differentiable with respect to `args`
    (and to arrays closed over by `problem`) by the implicit function theorem on
    `_rewrite`; the status of the iteration (not yet verified); `aux` with
    `num_steps`, `active`, `strict`, `violation` (largest relative violation of
    the KKT conditions) and `infeasible` (largest relative `H_i > 0`).
    """
    dtype = z0.dtype
    floor = 100 * float(jnp.finfo(dtype).eps)
    tol = jnp.sqrt(
        jnp.maximum(jnp.maximum(jnp.asarray(rtol, dtype), atol), floor)
    ).astype(dtype)
    solver = _SemismoothNewton(rtol=rtol, atol=atol, linear_solver=linear_solver)
    inputs = (problem, solver, lax.stop_gradient(z0), args, max_steps, start_ok, tol)
    tags = frozenset({lx.symmetric_tag})
    z, (result, aux) = implicit_jvp(_primal, _rewrite, inputs, tags, linear_solver)
    return z, result, {**aux, "tolerance": tol}
