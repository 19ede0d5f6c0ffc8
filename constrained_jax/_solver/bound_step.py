"""The step of [`constrained_jax.SemismoothNewton`][] on a KKT residual whose
complementarity rows are bounds (`KKTResidual.bounds`): the Jacobian of those rows is
diagonal, so the Newton system reduces to `n + k` unknowns, and no Jacobian of all
`n + k + m` unknowns is formed.

The residual is `r = (grad F* , G, phi_1, ..., phi_p)` in `z = (x, lambda, mu_1, ...,
mu_p)`, each `phi_b` a block of `n` rows `phi(s mu_b, -H_b(x))` whose row `i` depends
on `x_i` and `mu_b,i` alone (`H_b = lower - x` or `x - upper`). Its Jacobian is

    [[K,   J^T, C_1, ..., C_p],
     [J,   0,   0,   ..., 0  ],
     [B_1, 0,   A_1,      0  ],
     [...                    ],
     [B_p, 0,   0,   ..., A_p]]

with `K` the Hessian of `F*` (plus the proximal term), `J = dG/dx` and diagonal `C_b`
(`dH_b/dx`: `+-1`, or 0 for an infinite bound), `A_b`, `B_b` (the derivatives of
`phi`). Each row `i` of a block is either eliminated (`|A_b,i| >= |B_b,i|`, the bound
is inactive-ish: `dmu_b,i` from its row, a diagonal term `-C B / A` on `K`) or, for
the block of component `i` whose `|B|` is the largest where it exceeds `|A|` (the
active-ish bound), replaces the unknown `dx_i` by `u_i = C dmu_b,i`, with
`dx_i = (q_i - A dmu_b,i) / B`. What remains is exact, `n + k` unknowns
`y = (w, dlambda)` (`w_i = dx_i` or `u_i`):

    [[(K + D) S + M_A, J^T],  [[w      ],
     [J S,             0  ]]   [dlambda]]

`S = diag(-A C / B on the active-ish set, 1 elsewhere)`, `D` the diagonal of the
eliminated rows, `M_A` the mask of the active-ish set. It is formed and LU-factored
while it takes at most `DENSE_BYTES` (2 MiB: `n + k <= 512` in float64; a step then
costs `n + k` Jacobian-vector products and one LU factorisation). Above, `u_i` stays
an unknown of its own beside `dx_i` on the active-ish set, which makes the
symmetric system of `2n + k` unknowns of `BoundNewtonSystem.symmetric_mv`, solved by
[`constrained_jax.MINRES`][] (its diagonal preconditioner from random probes), each
product one Jacobian-vector product of the residual. Everything else the step needs
(the products with the whole Jacobian and its transpose for the Levenberg-Marquardt
fallback) comes from the linearised residual, with row and column sizes exact where
`K` is formed and estimated from random probes where it is not.
"""

import jax
import jax.lax as lax
import jax.numpy as jnp
import jax.scipy as jsp
import lineax as lx

from .globalization import (
    conjugate_gradient_mv,
    globalized_step,
    least_eigenvalue_mv,
    levenberg_marquardt_damping,
    tolerances,
)
from .minres import MINRES


# The reduced Newton matrix, (n + k)^2 entries, is formed and factored up to this
# size. A step factors it once and solves with it at every backtrack, and steps are
# more than in the equality case (the active set settles first): MINRES is the
# cheaper from here on.
DENSE_BYTES = 2**21
_PROBES = 8


class BoundNewtonSystem:
    """The linearised residual at `z` with the proximal term, its diagonal blocks,
    and the exact solve of its Newton system by the reduction of the module
    docstring. Built inside one step (not a pytree: it lives in a trace)."""

    def __init__(self, residual, z, args):
        n, k = residual.n, residual.k
        size = z.shape[0]
        p = (size - n - k) // n
        dtype = z.dtype
        self.n, self.k, self.p, self.size, self.dtype = n, k, p, size, dtype
        r, lin = jax.linearize(lambda z_: residual(z_, args), z)
        self.r, self.lin = r, lin
        self.sign = residual.sign
        self.proximal = jnp.zeros_like(z)
        self.transpose = jax.linear_transpose(lin, z)
        self.dense = (n + k) ** 2 * jnp.dtype(dtype).itemsize <= DENSE_BYTES

        # The diagonal blocks: one product per block of multipliers, one with x.
        def tangent(x=None, lam=None, blocks=None):
            t = jnp.zeros((size,), dtype)
            if x is not None:
                t = t.at[:n].set(x)
            if lam is not None:
                t = t.at[n : n + k].set(lam)
            if blocks is not None:
                t = t.at[n + k :].set(blocks.ravel())
            return t

        self.tangent = tangent
        eye_p = jnp.eye(p, dtype=dtype)
        ones = jnp.ones((n,), dtype)
        mu_cols = jax.vmap(lambda e: lin(tangent(blocks=e[:, None] * ones)))(eye_p)
        self.c = mu_cols[:, :n]  # (p, n): dH_b/dx
        self.a = mu_cols[:, n + k :].reshape(p, p, n)[jnp.arange(p), jnp.arange(p)]
        x_col = lin(tangent(x=ones))
        self.b = x_col[n + k :].reshape(p, n)
        # J^T as columns: one product per constraint.
        eye_k = jnp.eye(k, dtype=dtype)
        lam_cols = jax.vmap(lambda e: lin(tangent(lam=e)))(eye_k)  # (k, size)
        self.jt = lam_cols[:, :n].T  # (n, k)
        self.lam_cols = lam_cols
        if self.dense:
            eye_n = jnp.eye(n, dtype=dtype)
            x_cols = jax.vmap(lambda e: lin(tangent(x=e)))(eye_n)  # (n, size)
            self.x_cols = x_cols
            self.hess = x_cols[:, :n]  # symmetric: row i = column i
        self.finite = (
            jnp.all(jnp.isfinite(r))
            & jnp.all(jnp.isfinite(mu_cols))
            & jnp.all(jnp.isfinite(x_col))
            & jnp.all(jnp.isfinite(lam_cols))
        )
        if self.dense:
            self.finite = self.finite & jnp.all(jnp.isfinite(self.hess))

    def set_proximal(self, rho):
        """The proximal term `rho s` on the rows of `x`."""
        self.proximal = (
            jnp.zeros((self.size,), self.dtype).at[: self.n].set(self.sign * rho)
        )

    def mv(self, v):
        """`Jac v`, the proximal term included."""
        return self.lin(v) + self.proximal * v

    def rmv(self, w):
        """`Jac^T w`, the proximal term included."""
        return self.transpose(w)[0] + self.proximal * w

    # -- sizes of the rows and columns of the whole Jacobian -------------------------

    def hessian_matvec(self, v):
        """`K v`, the proximal term included."""
        return self.mv(self.tangent(x=v))[: self.n]

    def row_sizes(self):
        """The max-norm of each row of the Jacobian (rows of `K` by their 2-norm
        from random probes where `K` is not formed)."""
        n, k = self.n, self.k
        prox = self.proximal[:n]
        if self.dense:
            k_rows = jnp.max(jnp.abs(self.hess + jnp.diag(prox)), axis=1)
        else:
            signs = jax.random.rademacher(jax.random.key(0), (_PROBES, n), self.dtype)
            products = jax.vmap(self.hessian_matvec)(signs)
            k_rows = jnp.sqrt(jnp.mean(jnp.square(products), axis=0))
        stat = jnp.maximum(k_rows, jnp.max(jnp.abs(self.c), axis=0))
        if k:
            stat = jnp.maximum(stat, jnp.max(jnp.abs(self.jt), axis=1))
        g_rows = jnp.max(jnp.abs(self.jt), axis=0) if k else jnp.zeros((0,), self.dtype)
        fb = jnp.maximum(jnp.abs(self.a), jnp.abs(self.b)).ravel()
        return jnp.concatenate([stat, g_rows, fb])

    def gram_diagonal_max(self, weight):
        """`max diag((W Jac)^T (W Jac))`, the largest squared column norm of the
        row-scaled Jacobian (estimated from probes for the columns of `x` where `K`
        is not formed); it is also the largest entry of that Gram matrix."""
        n, k = self.n, self.k
        w2 = weight**2
        if self.dense:
            x_cols = self.x_cols + jnp.diag(self.proximal)[:n]
            x_norms = jnp.sum(w2[None, :] * x_cols**2, axis=1)
        else:
            signs = jax.random.rademacher(
                jax.random.key(1), (_PROBES, self.size), self.dtype
            )
            back = jax.vmap(lambda v: self.rmv(weight * v))(signs)
            x_norms = jnp.mean(jnp.square(back[:, :n]), axis=0)
        lam_norms = jnp.sum(w2[None, :] * self.lam_cols**2, axis=1)
        w_stat = w2[:n]
        w_fb = w2[n + k :].reshape(self.p, n)
        mu_norms = w_stat[None, :] * self.c**2 + w_fb * self.a**2
        return jnp.maximum(
            jnp.maximum(jnp.max(x_norms), jnp.max(lam_norms, initial=0.0)),
            jnp.max(mu_norms),
        )

    def least_eigenvalue(self):
        """The least eigenvalue of `s K` (before the proximal term), estimated."""
        n, sign = self.n, self.sign
        if self.dense:
            a = sign * 0.5 * (self.hess + self.hess.T)
            a = jnp.where(jnp.isfinite(a), a, 0.0)
            bound = jnp.max(jnp.sum(jnp.abs(a), axis=1))
            return least_eigenvalue_mv(lambda v: a @ v, n, self.dtype, bound)
        matvec = lambda v: sign * self.hessian_matvec(v)
        # The spectral radius by a few power steps, doubled for the margin.
        v = jnp.ones((n,), self.dtype) / jnp.sqrt(n)

        def power(_, c):
            v, _ = c
            w = matvec(v)
            w = jnp.where(jnp.isfinite(w), w, 0.0)
            norm = jnp.linalg.norm(w)
            return jnp.where(norm > 0, w / jnp.where(norm > 0, norm, 1.0), v), norm

        _, radius = lax.fori_loop(0, 16, power, (v, jnp.zeros((), self.dtype)))
        return least_eigenvalue_mv(matvec, n, self.dtype, 2 * radius)

    # -- the Newton solve -------------------------------------------------------------

    def prepare(self):
        """Split the bound rows into eliminated and active-ish ones, and set up the
        reduced solve (formed and factored, or MINRES's preconditioner)."""
        n, k, dtype = self.n, self.k, self.dtype
        a, b, c = self.a, self.b, self.c
        big = jnp.abs(b) > jnp.abs(a)  # (p, n)
        size_b = jnp.where(big, jnp.abs(b), -1.0)
        chosen = jnp.argmax(size_b, axis=0)  # (n,)
        act = jnp.any(big, axis=0)
        onehot = (jnp.arange(self.p)[:, None] == chosen[None, :]) & act[None, :]
        self.onehot = onehot
        self.act = act
        eliminated = jnp.invert(onehot)
        safe_a = jnp.where(a != 0, a, 1.0)
        # Eliminated rows: dmu = (q - B dx) / A, adding -C B / A to the diagonal.
        self.delta = jnp.sum(jnp.where(eliminated, -c * b / safe_a, 0.0), axis=0)
        b_act = jnp.sum(jnp.where(onehot, b, 0.0), axis=0)
        a_act = jnp.sum(jnp.where(onehot, a, 0.0), axis=0)
        c_act = jnp.sum(jnp.where(onehot, c, 0.0), axis=0)
        self.b_act = jnp.where(act, b_act, 1.0)
        self.a_act, self.c_act = a_act, c_act
        # dx_i = p_i - e_i u_i on the active-ish set; u_i = C dmu_i.
        self.e = jnp.where(act, a_act * c_act / self.b_act, 0.0)
        self.s_diag = jnp.where(act, -self.e, 1.0)
        self.diag_all = self.proximal[:n] + self.delta
        self.check_rtol = 1e-6
        if self.dense:
            matrix = jax.vmap(self.reduced_mv)(jnp.eye(n + k, dtype=dtype)).T
            self.factors = jsp.linalg.lu_factor(jnp.where(self.finite, matrix, 0.0))
        else:
            operator = lx.FunctionLinearOperator(
                self.symmetric_mv,
                jax.ShapeDtypeStruct((2 * n + k,), dtype),
                tags=lx.symmetric_tag,
            )
            rtol = max(1e-12, 1000 * float(jnp.finfo(dtype).eps))
            self.krylov = MINRES(rtol=rtol, atol=0.0, max_steps=max(1000, 2 * n + k))
            # A Newton step is taken as solved to within what MINRES promises.
            self.check_rtol = max(1e-6, 2 * rtol)
            self.krylov_state = self.krylov.init(operator, {})

    def reduced_mv(self, y):
        """The reduced matrix of the module docstring times `y = (w, dlambda)`."""
        n = self.n
        w, dlam = y[:n], y[n:]
        dx = self.s_diag * w
        out = self.lin(self.tangent(x=dx, lam=dlam))
        stat = out[:n] + self.diag_all * dx + jnp.where(self.act, w, 0.0)
        return jnp.concatenate([stat, out[n : n + self.k]])

    def solve(self, rhs):
        """`Jac^{-1} rhs` (the proximal term included): exact up to round-off where
        the reduced matrix is formed, to MINRES's tolerance (or NaN where it fails)
        where it is not."""
        n, k, p = self.n, self.k, self.p
        f, h = rhs[:n], rhs[n : n + k]
        q = rhs[n + k :].reshape(p, n)
        a, b, c = self.a, self.b, self.c
        eliminated = jnp.invert(self.onehot)
        safe_a = jnp.where(a != 0, a, 1.0)
        f = f - jnp.sum(jnp.where(eliminated, c * q / safe_a, 0.0), axis=0)
        q_act = jnp.sum(jnp.where(self.onehot, q, 0.0), axis=0)
        if not self.dense:
            return self._solve_symmetric(f, h, q, q_act, eliminated, safe_a)
        fixed = jnp.where(self.act, q_act / self.b_act, 0.0)
        # The fixed part of dx moves to the right-hand side.
        out = self.lin(self.tangent(x=fixed))
        f = f - (out[:n] + self.diag_all * fixed)
        h = h - out[n : n + k]
        y = jsp.linalg.lu_solve(self.factors, jnp.concatenate([f, h]))
        w, dlam = y[:n], y[n:]
        dx = self.s_diag * w + fixed
        dmu_act = self.c_act * w  # C^2 = 1 on the active-ish set
        dmu = jnp.where(eliminated, (q - b * dx[None, :]) / safe_a, dmu_act[None, :])
        return jnp.concatenate([dx, dlam, dmu.ravel()])

    def symmetric_mv(self, v):
        """The symmetric form of the reduced system, `2n + k` unknowns
        `(dx, dlambda, u)`, `u_i = C dmu_i` on the active-ish set (identity rows
        elsewhere):

            [[K + D, J^T, M_A              ],
             [J,     0,   0                ],
             [M_A,   0,   M_A E + (1 - M_A)]]

        (`E = diag(A C / B)`); its last rows are `dx_i + E_i u_i = q_i / B_i`."""
        n, k = self.n, self.k
        dx, dlam, u = v[:n], v[n : n + k], v[n + k :]
        out = self.lin(self.tangent(x=dx, lam=dlam))
        stat = out[:n] + self.diag_all * dx + jnp.where(self.act, u, 0.0)
        last = jnp.where(self.act, dx + self.e * u, u)
        return jnp.concatenate([stat, out[n : n + k], last])

    def _solve_symmetric(self, f, h, q, q_act, eliminated, safe_a):
        """The Newton solve by MINRES on `symmetric_mv` (matrix-free)."""
        n, k = self.n, self.k
        fixed = jnp.where(self.act, q_act / self.b_act, 0.0)
        rhs = jnp.concatenate([f, h, fixed])
        value, result, _ = self.krylov.compute(self.krylov_state, rhs, {})
        v = jnp.where(result == lx.RESULTS.successful, value, jnp.nan)
        dx, dlam, u = v[:n], v[n : n + k], v[n + k :]
        dmu_act = self.c_act * u
        dmu = jnp.where(
            eliminated, (q - self.b * dx[None, :]) / safe_a, dmu_act[None, :]
        )
        return jnp.concatenate([dx, dlam, dmu.ravel()])


def bound_step(solver, residual, z, args):
    """One step of `solver` (a `SemismoothNewton`) on a residual with bound rows:
    the same iteration as its dense step (proximal term, natural monotonicity test,
    Levenberg-Marquardt fallback with an Armijo search on the weighted merit), with
    the Newton system solved by `BoundNewtonSystem`. Returns `(z, done, moved,
    finite)`."""
    dtype = z.dtype
    eps = jnp.finfo(dtype).eps
    rtol, atol = tolerances(solver, dtype)
    n = residual.n
    system = BoundNewtonSystem(residual, z, args)
    r = system.r
    stationarity = jnp.linalg.norm(r[:n])
    x_size = jnp.max(jnp.abs(z[:n]))
    curvature = system.least_eigenvalue()
    rho = jnp.minimum(stationarity, 1.0) * jnp.maximum(
        1 / jnp.maximum(x_size, 1.0) - 2 * curvature, 0.0
    )
    rho = jnp.where(jnp.isfinite(rho), rho, 0.0)
    system.set_proximal(rho)
    proximal = system.proximal
    res = lambda z_: residual(z_, args) + proximal * (z_ - z)
    finite = system.finite
    row_size = jnp.where(finite, system.row_sizes(), 0.0)
    weight = 1 / jnp.where(row_size > 0, row_size, 1.0)
    psi = 0.5 * jnp.dot(weight * r, weight * r)
    grad_psi = system.rmv(weight**2 * r)

    system.prepare()

    def lm_direction():
        nu = levenberg_marquardt_damping(psi, system.gram_diagonal_max(weight), eps)
        nu = jnp.where(finite & jnp.isfinite(nu), nu, 1.0)
        apply = lambda v: system.rmv(weight**2 * system.mv(v))
        steps = system.size if system.dense else min(system.size, 500)
        dz = conjugate_gradient_mv(apply, nu, -grad_psi, steps)
        return jnp.where(jnp.all(jnp.isfinite(dz)), dz, 0.0)

    z_new, converged, moved = globalized_step(
        z,
        r,
        res,
        finite,
        weight,
        psi,
        grad_psi,
        system.solve,
        system.mv,
        system.check_rtol,
        lm_direction,
        rtol,
        atol,
        solver.max_backtracks,
    )
    return z_new, converged, moved, finite
