"""[`constrained_jax.SemismoothNewton`][]: Newton's method on a KKT residual with
complementarity rows (inequality constraints), which is only semismooth."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy as jsp
import lineax as lx
from jaxtyping import Array, Bool

from .._results import RESULTS
from .bound_step import bound_step
from .dense_lu import DenseLU
from .globalization import (
    conjugate_gradient_mv,
    globalized_step,
    least_eigenvalue_mv,
    levenberg_marquardt_damping,
    tolerances,
)
from .kkt_solver import AbstractKKTSolver, KKTResidual


def conjugate_gradient(matrix, shift, rhs):
    """Solve `(matrix + shift I) d = rhs` (symmetric positive definite) by conjugate
    gradients from `d = 0`, at most `len(rhs)` steps, to a relative residual of
    `sqrt(eps)`.

    Used for the Levenberg-Marquardt direction instead of a second factorisation:
    two batched LAPACK factorisations in one loop body can deadlock XLA's CPU
    runtime under `jax.vmap` (every thread of its intra-op pool idle). Every
    conjugate-gradient iterate of an SPD system started at zero is a descent
    direction of its quadratic model, `rhs . d > 0`, so with `rhs = -grad Psi` the
    direction descends `Psi` however early the iteration stops.
    """
    return conjugate_gradient_mv(lambda v: matrix @ v, shift, rhs, rhs.shape[0])


def _least_eigenvalue(matrix):
    """An estimate of the least eigenvalue of the symmetric part of `matrix`, by
    power iteration on `L I - A` (`L = |A|_inf`, a bound on the spectral radius,
    so that `L I - A` is positive semidefinite), from a fixed start. Matrix-vector
    products only (no second LAPACK call in the step, see `conjugate_gradient`).
    The Rayleigh quotient bounds the least eigenvalue from above: an estimate that
    errs on the side of less regularisation, which the globalisation then guards."""
    a = 0.5 * (matrix + matrix.T)
    a = jnp.where(jnp.isfinite(a), a, 0.0)
    bound = jnp.max(jnp.sum(jnp.abs(a), axis=1))
    return least_eigenvalue_mv(lambda v: a @ v, a.shape[0], a.dtype, bound)


class _State(eqx.Module):
    done: Bool[Array, ""]
    result: RESULTS


class SemismoothNewton(AbstractKKTSolver):
    """Semismooth Newton on a KKT residual with complementarity rows, globalised by
    the natural monotonicity test and a Levenberg-Marquardt fallback.

    [`constrained_jax.extremize`][] writes the KKT conditions of inequality
    constraints `H(x) <= 0` as a square system through the Fischer-Burmeister
    function, which is not differentiable where `mu_i = H_i = 0`: Newton's method
    then takes an element of the (B-)subdifferential as its Jacobian (Qi and Sun
    1993). Each step forms that Jacobian `K` by forward-mode autodiff and
    LU-factors it (dense: for small and medium problems). The Newton step
    `dz = -K^-1 r` is damped by Deuflhard's natural monotonicity test, as in
    [`constrained_jax.Newton`][]: the simplified correction at the trial point must
    shrink, `|K^-1 r(z + a dz)| <= (1 - a/4) |dz|` in the scaled norm
    `rms(v / (atol + rtol |z|))`. That test is affine invariant, so it comes first: a
    line search on `|r|` alone can stall at a local minimum of the residual
    (Rosenbrock's function in a disk from (-1.2, 1)). Where `K` is singular
    (degenerate vertices, dependent active constraints) or the test fails, a
    Levenberg-Marquardt step with an Armijo line search on the merit
    `Psi = |W r|^2 / 2` is taken instead (`W` scales each row by the reciprocal of its
    row of `K`, so that complementarity is not drowned by large multipliers); `Psi`
    is continuously differentiable for this residual and the step descends it
    whenever `grad Psi != 0` (De Luca, Facchinei and Kanzow 1996).

    On the KKT residual of [`constrained_jax.extremize`][] (whose layout, `n`
    unknowns `x` and the sense `s`, the solve passes in a `KKTResidual`) every step
    is regularised by a proximal term centred at the iterate `x_k`: the residual is
    that of extremizing `F - s rho |x - x_k|^2 / 2`, the same at `x_k`, with
    Jacobian `K + s rho I` on the block of `x` (the proximal point method, one
    Newton step per centre). `rho = min(1, |grad F*|) max(0, 1 / max(1, |x|) -
    2 lambda_min(s Hess_x F*))`, the least eigenvalue estimated by power iteration:
    zero where the curvature already agrees with `s` by a margin (a plain Newton
    step), it vanishes with the residual, which keeps Newton's local convergence
    (Li, Fukushima, Qi and Yamashita 2004), and away from the solution it makes the
    curvature agree with `s`. So a flat objective (a linear one with
    no active constraint, where `K` is singular and `r` constant in `x`) and an
    iterate where the curvature has the wrong sign (multipliers of the wrong sign,
    a concave objective minimized) still move towards the optimum.

    Converged when a full Newton step is within tolerance (scaled norm below 1); the
    step is then taken. Tolerances below `100 eps` of the dtype are raised to it.
    A step that cannot be taken stops the iteration with `RESULTS.line_search_failed`
    (or `RESULTS.nonfinite_objective` where the residual or `K` is NaN or inf).

    Where every complementarity row is a bound (`extremize` with `lower`, `upper`
    and no `inequalities`: the `KKTResidual` says so), their Jacobian is diagonal,
    and the same iteration runs without forming the Jacobian of all `n + k + m`
    unknowns: each bound row is eliminated (an inactive bound: a diagonal term on
    the Hessian) or fixes its `dx_i` (an active one), exactly, leaving `n + k`
    unknowns, LU-factored while they take at most 2 MiB and solved by
    [`constrained_jax.MINRES`][] in a symmetric form of `2n + k` unknowns above;
    the proximal term's curvature estimate, the row weights and the
    Levenberg-Marquardt direction (conjugate gradients) then use
    Jacobian-vector products (`constrained_jax._solver.bound_step`).

    [`constrained_jax.Newton`][] hands inequality-constrained solves to the
    `SemismoothNewton` of its own `rtol`, `atol`, `linear_solver` and
    `max_backtracks` (see `complementarity_solver`), so either may be passed. On a
    KKT system without inequalities this is a dense Newton method with a
    Levenberg-Marquardt fallback.

    **References:** L. Qi and J. Sun, *A nonsmooth version of Newton's method*,
    Math. Programming 58 (1993) 353-367; T. De Luca, F. Facchinei and C. Kanzow, *A
    semismooth equation approach to the solution of nonlinear complementarity
    problems*, Math. Programming 75 (1996) 407-439; P. Deuflhard, *Newton Methods
    for Nonlinear Problems*, Springer (2004), section 3.3; D.-H. Li, M. Fukushima,
    L. Qi and N. Yamashita, *Regularized Newton methods for convex minimization
    problems with singular solutions*, Comput. Optim. Appl. 28 (2004) 131-147;
    R. T. Rockafellar, *Monotone operators and the proximal point algorithm*, SIAM
    J. Control Optim. 14 (1976) 877-898.
    """

    rtol: float = 1e-10
    atol: float = 1e-10
    linear_solver: lx.AbstractLinearSolver = DenseLU()
    max_backtracks: int = 40

    def __check_init__(self):
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if isinstance(value, (int, float)) and not value >= 0:
                raise ValueError(
                    f"`SemismoothNewton({name}=...)` must be non-negative."
                )
        if (
            isinstance(self.rtol, (int, float))
            and isinstance(self.atol, (int, float))
            and self.rtol == 0
            and self.atol == 0
        ):
            raise ValueError("`SemismoothNewton` needs a positive `rtol` or `atol`.")

    def init(self, residual, z, args):
        del residual, args
        return _State(done=jnp.array(False), result=RESULTS.successful)

    def step(self, residual, z, args, state):
        if isinstance(residual, KKTResidual) and residual.bounds:
            z_new, converged, moved, finite = bound_step(self, residual, z, args)
        else:
            z_new, converged, moved, finite = self._dense_step(residual, z, args)
        result = RESULTS.where(
            moved,
            RESULTS.successful,
            RESULTS.where(
                finite, RESULTS.line_search_failed, RESULTS.nonfinite_objective
            ),
        )
        done = converged | jnp.invert(moved)
        return z_new, _State(done=done, result=result)

    def _dense_step(self, residual, z, args):
        """The step with the Jacobian of the whole residual formed (by `jacfwd`) and
        LU-factored. Returns `(z, converged, moved, finite)`."""
        dtype = z.dtype
        eps = jnp.finfo(dtype).eps
        rtol, atol = tolerances(self, dtype)
        r = residual(z, args)
        # The proximal (regularised) residual, centred at this iterate: the KKT
        # residual of extremizing `F - s rho |x - x_k|^2 / 2` instead (the proximal
        # point method), equal to `r` at `z` and with Jacobian `K + rho D`. Where `F`
        # is flat (a linear objective with no active constraint) `K` is singular and
        # `r` constant in `x`, so that neither Newton nor a line search on `|r|` can
        # move; the proximal step is the step of the regularised Newton method
        # `(Hess F* + s rho I) dx = -r` that ascends (descends) `F`. `rho` (see the
        # class docstring) is zero where the curvature of `F*` in `x` agrees with
        # `s` by a margin, adds what is missing where it does not, and vanishes
        # with the residual, which keeps Newton's local convergence (Li, Fukushima,
        # Qi and Yamashita 2004).
        jac = jax.jacfwd(lambda z_: residual(z_, args))(z)
        if isinstance(residual, KKTResidual):
            signs = residual.proximal_signs(z)
            n = residual.n
            stationarity = jnp.linalg.norm(r[:n])
            x_size = jnp.max(jnp.abs(z[:n]))
            curvature = _least_eigenvalue(residual.sign * jac[:n, :n])
            rho = jnp.minimum(stationarity, 1.0) * jnp.maximum(
                1 / jnp.maximum(x_size, 1.0) - 2 * curvature, 0.0
            )
            rho = jnp.where(jnp.isfinite(rho), rho, 0.0)
            proximal = rho * signs
        else:
            proximal = jnp.zeros_like(z)
        res = lambda z_: residual(z_, args) + proximal * (z_ - z)
        jac = jac + jnp.diag(proximal)
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

        # The Newton direction, if the Jacobian is (numerically) invertible; the
        # same factorisation gives the simplified Newton corrections.
        factors = jsp.linalg.lu_factor(jnp.where(finite, jac, 0.0))
        newton_solve = lambda rhs: jsp.linalg.lu_solve(factors, rhs)

        def lm_direction():
            scaled_jac = weight[:, None] * jac
            jtj = scaled_jac.T @ scaled_jac
            nu = levenberg_marquardt_damping(psi, jnp.max(jnp.diag(jtj)), eps)
            dz = conjugate_gradient(
                jnp.where(finite, jtj, 0.0), jnp.where(finite, nu, 1.0), -grad_psi
            )
            return jnp.where(jnp.all(jnp.isfinite(dz)), dz, 0.0)

        z_new, converged, moved = globalized_step(
            z,
            r,
            res,
            finite,
            weight,
            psi,
            grad_psi,
            newton_solve,
            lambda v: jac @ v,
            1e-6,
            lm_direction,
            rtol,
            atol,
            self.max_backtracks,
        )
        return z_new, converged, moved, finite

    def terminate(self, residual, z, args, state):
        del residual, z, args
        return state.done, state.result

    def postprocess(self, residual, z, args, state):
        del residual, args, state
        return z, {}

    def complementarity_solver(self) -> "SemismoothNewton":
        """Itself: it solves complementarity rows."""
        return self


SemismoothNewton.__init__.__doc__ = """**Arguments:**

- `rtol`, `atol`: relative and absolute tolerance on the unknowns
    `z = (x, lambda, mu)`. They also set the tolerance to which
    [`constrained_jax.extremize`][] checks the KKT conditions after the iteration,
    `sqrt(max(rtol, atol, 100 eps))`.
- `linear_solver`: a Lineax solver for the tangent system of the implicit function
    theorem in the backward pass (symmetric: the strictly active inequalities as
    equalities). The Newton steps themselves LU-factor the dense Jacobian (or, with
    bounds alone, the reduced system of `n + k` unknowns, or solve its symmetric
    form by MINRES: see the class docstring).
    [`constrained_jax.DenseLU`][] (default) or [`constrained_jax.MINRES`][].
- `max_backtracks`: halvings of the step before a line search gives up.
"""
