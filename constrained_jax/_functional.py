"""Constrained variational problems: extremize `F[y] = int L(y, y', x) dx`.

The functional is extremized over functions `y(x)` (one or `n` of them) on
`[xL, xR]` with fixed end values, subject to

- integral constraints `int N_j(y, y', x) dx = C_j`, each with a constant multiplier
  `lambda_j` (the extended Lagrangian is `L* = L + sum_j lambda_j N_j`), and
- holonomic constraints `G_j(y, x) = 0` on the whole interval, each with a multiplier
  function `lambda_j(x)`.

The Euler-Lagrange equations, in the library's sign convention, are

    d/dx (dL*/dy') - dL*/dy = sum_j lambda_j(x) dG_j/dy,    G_j = 0,
    int N_j dx = C_j.

The direct method ([`constrained_jax.solve_functional`][]) discretizes `y` and the
integrals ([`constrained_jax.Chebyshev`][], [`constrained_jax.PiecewiseLinear`][]) and
solves the resulting finite constrained extremization with the KKT machinery of
[`constrained_jax.extremize`][] (the same residual, Newton iteration and
implicit-function derivatives).
"""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._custom_types import Args, Scalar
from ._discretization import AbstractDiscretization, Chebyshev
from ._implicit import nan_tangent_where
from ._kkt import (
    check_kkt_solver,
    gram_factors,
    kkt_solve,
    lagrangian_problem,
    least_squares_multipliers,
)
from ._misc import (
    all_finite,
    as_traced_args,
    check_max_steps,
    check_signature,
    default_float_dtype,
    full_precision,
    warn_near_mapping_limit,
)
from ._results import raise_if_failed, RESULTS
from ._solver.kkt_solver import AbstractKKTSolver
from ._solver.newton import Newton


LagrangianFn = Callable[[Any, Any, Scalar, Args], Scalar]
"""`L(y, y', x, args) -> scalar`."""


def _float_dtype(*values):
    dtype = jnp.result_type(*values)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = default_float_dtype()
    return dtype


class IntegralConstraint(eqx.Module):
    """The integral constraint `int_{xL}^{xR} N(y, y', x, args) dx = C`.

    **Arguments:**

    - `integrand`: `N(y, y', x, args) -> scalar`, with `y`, `y'` shaped like the
        boundary values of the [`constrained_jax.Functional`][].
    - `value`: the constant `C`: a number, an array (closed over, it is
        differentiable), or a callable `C(args)` reading it from the parameters.
    """

    integrand: Callable
    value: ArrayLike | Callable

    def __check_init__(self):
        check_signature(
            self.integrand,
            "The integrand of `cjax.IntegralConstraint`",
            "N(y, yp, x, args)",
        )
        if callable(self.value):
            check_signature(
                self.value, "The `value` of `cjax.IntegralConstraint`", "C(args)"
            )

    def target(self, args, dtype) -> Scalar:
        value = self.value(args) if callable(self.value) else self.value
        value = jnp.asarray(value)
        if value.shape != ():
            raise ValueError(
                f"`IntegralConstraint(..., value)` must be a scalar, got shape "
                f"{value.shape}."
            )
        return value.astype(dtype)


class Functional(eqx.Module):
    """The functional `F[y] = int_{xL}^{xR} L(y, y', x, args) dx` and its constraints.

    **Arguments:**

    - `lagrangian`: `L(y, y', x, args) -> scalar`. `y` and `y'` are scalars when the
        boundary values are scalars (one function), arrays of shape `(n,)` otherwise.
    - `interval`: `(xL, xR)` with `xL < xR`.
    - `boundary`: `(y(xL), y(xR))`, both scalars or both of shape `(n,)`.
    - `integral_constraints`: a tuple of [`constrained_jax.IntegralConstraint`][].
    - `holonomic`: `G(y, x, args) -> (m,)` (a scalar means one constraint), imposed at
        every `x`; or `None`. The end values must satisfy it.

    Arrays in `interval`, `boundary` and the constraint values may be traced: the
    solution is differentiable with respect to them.
    """

    lagrangian: Callable
    interval: tuple[Scalar, Scalar]
    boundary: tuple[Float[Array, "..."], Float[Array, "..."]]
    integral_constraints: tuple[IntegralConstraint, ...]
    holonomic: Callable | None

    def __init__(
        self,
        lagrangian: LagrangianFn,
        interval: tuple[ArrayLike, ArrayLike],
        boundary: tuple[ArrayLike, ArrayLike],
        integral_constraints: tuple[IntegralConstraint, ...] = (),
        holonomic: Callable | None = None,
    ):
        check_signature(lagrangian, "The Lagrangian", "L(y, yp, x, args)")
        if holonomic is not None:
            check_signature(holonomic, "`holonomic`", "G(y, x, args)")
        if isinstance(integral_constraints, IntegralConstraint):
            integral_constraints = (integral_constraints,)
        integral_constraints = tuple(integral_constraints)
        for c in integral_constraints:
            if not isinstance(c, IntegralConstraint):
                raise ValueError(
                    "`integral_constraints` must be a tuple of "
                    f"`cjax.IntegralConstraint(N, C)`, got {type(c).__name__}."
                )
        if not (isinstance(interval, (tuple, list)) and len(interval) == 2):
            raise ValueError("`interval` must be a pair (xL, xR).")
        if not (isinstance(boundary, (tuple, list)) and len(boundary) == 2):
            raise ValueError("`boundary` must be a pair (y(xL), y(xR)).")
        yl, yr = (jnp.asarray(b) for b in boundary)
        if yl.shape != yr.shape or yl.ndim > 1:
            raise ValueError(
                "The boundary values (y(xL), y(xR)) must both be scalars (one "
                "function) or both have shape (n,) (n functions); got shapes "
                f"{yl.shape} and {yr.shape}."
            )
        if yl.shape == (0,):
            raise ValueError("The boundary values are empty: there is no function.")
        dtype = _float_dtype(yl, yr)
        xl, xr = (jnp.asarray(x) for x in interval)
        if xl.shape != () or xr.shape != ():
            raise ValueError("`interval` must hold two scalars (xL, xR).")
        try:
            ordered = bool(xl < xr)
        except jax.errors.ConcretizationTypeError:
            ordered = True  # traced: cannot be checked here
        if not ordered:
            raise ValueError(f"`interval` must have xL < xR, got ({xl}, {xr}).")
        self.lagrangian = lagrangian
        self.interval = (xl.astype(dtype), xr.astype(dtype))
        self.boundary = (yl.astype(dtype), yr.astype(dtype))
        self.integral_constraints = integral_constraints
        self.holonomic = holonomic

    @property
    def num_components(self) -> int:
        """`n`, the number of functions."""
        return 1 if self.boundary[0].ndim == 0 else self.boundary[0].shape[0]

    def extended_lagrangian(self, multipliers: Float[Array, " k"]) -> LagrangianFn:
        """`L* = L + sum_j lambda_j N_j`, for the given constant multipliers.

        Its Euler-Lagrange equations (see [`constrained_jax.euler_lagrange`][]) are
        those of the constrained problem; when `L` and the `N_j` do not depend on `x`
        its first integral ([`constrained_jax.first_integral`][]) is conserved.
        """
        multipliers = jnp.asarray(multipliers)
        if multipliers.shape != (len(self.integral_constraints),):
            raise ValueError(
                "`multipliers` must have one entry per integral constraint, shape "
                f"({len(self.integral_constraints)},), got {multipliers.shape}."
            )

        def lagrangian_star(y, yp, x, args):
            out = self.lagrangian(y, yp, x, args)
            for lam, c in zip(multipliers, self.integral_constraints, strict=True):
                out = out + lam * c.integrand(y, yp, x, args)
            return out

        return lagrangian_star


def euler_lagrange(lagrangian: LagrangianFn) -> Callable:
    """The Euler-Lagrange expression of `L`, by autodiff.

    Returns `el(y, y', y'', x, args)`, the value of

        d/dx (dL/dy') - dL/dy
          = d2L/dy'dy y' + d2L/dy'2 y'' + d2L/dy'dx - dL/dy,

    shaped like `y`. It vanishes along an extremal of `int L dx` (use the extended
    Lagrangian `L*` of a problem with integral constraints,
    [`constrained_jax.Functional.extended_lagrangian`][]); with holonomic
    constraints it equals `sum_j lambda_j(x) dG_j/dy`.
    """

    def el(y, yp, ypp, x, args):
        dl_dy = jax.grad(lagrangian, argnums=0)
        dl_dyp = jax.grad(lagrangian, argnums=1)
        _, ddx = jax.jvp(
            lambda y_, yp_, x_: dl_dyp(y_, yp_, x_, args),
            (y, yp, x),
            (yp, ypp, jnp.ones_like(x)),
        )
        return ddx - dl_dy(y, yp, x, args)

    return el


def first_integral(lagrangian: LagrangianFn) -> Callable:
    """`H(y, y', x, args) = y' . dL/dy' - L` (the "Hamiltonian" of a functional).

    If `L` does not depend on `x`, `dH/dx = -dL/dx = 0` along every extremal, so `H`
    is constant along the solution (use the extended Lagrangian `L*` when there are
    integral constraints).
    """

    def hamiltonian(y, yp, x, args):
        dl_dyp = jax.grad(lagrangian, argnums=1)(y, yp, x, args)
        return jnp.sum(yp * dl_dyp) - lagrangian(y, yp, x, args)

    return hamiltonian


@eqx.filter_jit
def _evaluate(
    discretization, interval, values, x, order: int, interior: bool, inside: bool
):
    """The interpolant through nodal `values` (or a derivative) at the points `x`;
    with `inside`, NaN at points outside the interval (beyond round-off: `16 eps` of
    the size of its ends), where the interpolant extrapolates and is not the
    solution."""
    fn = lambda x_: discretization.interpolate(
        interval, values, x_, derivative=order, interior=interior
    )
    flat = x.reshape(-1)
    out = jax.vmap(fn)(flat)
    if inside:
        xl, xr = (jnp.asarray(v, x.dtype) for v in interval)
        lo, hi = jnp.minimum(xl, xr), jnp.maximum(xl, xr)
        slack = (
            16
            * jnp.finfo(x.dtype).eps
            * jnp.maximum(jnp.maximum(jnp.abs(lo), jnp.abs(hi)), hi - lo)
        )
        outside = (flat < lo - slack) | (flat > hi + slack)
        out = jnp.where(outside.reshape((-1,) + (1,) * (out.ndim - 1)), jnp.nan, out)
    return out.reshape(x.shape + values.shape[1:])


class MultiplierFunction(eqx.Module):
    """A holonomic multiplier function `x -> lambda(x)`, shape `(m,)` (or scalar).

    Interpolates the multipliers at the interior nodes with the discretization's own
    interpolant (extrapolated to the ends). `values` holds them at `nodes`. NaN at
    points outside the interval.
    """

    nodes: Float[Array, " M"]
    values: Float[Array, "M ..."]
    interval: tuple[Scalar, Scalar]
    discretization: AbstractDiscretization

    def __call__(self, x: ArrayLike) -> Float[Array, "..."]:
        x = jnp.asarray(x, self.values.dtype)
        return _evaluate(
            self.discretization, self.interval, self.values, x, 0, True, True
        )


class FunctionalMultipliers(eqx.Module):
    """The multipliers of a [`constrained_jax.FunctionalSolution`][].

    **Attributes:**

    - `integral`: the constants `lambda_j` of the integral constraints, shape `(k,)`.
    - `holonomic`: a [`constrained_jax.MultiplierFunction`][] `x -> lambda(x)`, or
        `None` without holonomic constraints. Convention:
        `d/dx(dL*/dy') - dL*/dy = sum_j lambda_j(x) dG_j/dy`.
    """

    integral: Float[Array, " k"]
    holonomic: MultiplierFunction | None


class FunctionalSolution(eqx.Module):
    """The solution of [`constrained_jax.solve_functional`][].

    **Attributes:**

    - `x`: the nodes, shape `(N,)`, ends included.
    - `y`: the values at the nodes, shape `(N,)` (one function) or `(N, n)`.
    - `multipliers`: a [`constrained_jax.FunctionalMultipliers`][].
    - `value`: `F[y] = int L dx` (without the constraint terms).
    - `result`: a [`constrained_jax.RESULTS`][] member.
    - `stats`: `num_steps`, `max_steps`, `kkt_residual` (root mean square of the
        discrete KKT residual), `error_estimate` (the discretization's a-posteriori
        estimate of `max_x |y_h(x) - y(x)|`, see its `error_estimate`; not
        differentiated) and `error_tolerance` (`atol + rtol * max |y|`, which it
        must not exceed for `result` to be `successful`).

    Call it, `sol(x)`, for the interpolant at any `x` in `[xL, xR]` (scalar or
    array); `sol.derivative(x, order)` for its derivatives. Both are NaN at points
    outside `[xL, xR]` (beyond round-off), where the interpolant would extrapolate:
    not the solution of the problem. (As a starting guess `y0` of another solve it
    is evaluated as the interpolant everywhere, extrapolating.)
    """

    x: Float[Array, " N"]
    y: Float[Array, " N ..."]
    multipliers: FunctionalMultipliers
    value: Scalar
    result: RESULTS
    stats: dict[str, Any]
    interval: tuple[Scalar, Scalar]
    discretization: AbstractDiscretization

    def derivative(self, x: ArrayLike, order: int = 1) -> Float[Array, "..."]:
        """The `order`-th derivative of the interpolant at `x`."""
        if not isinstance(order, int) or order < 0:
            raise ValueError(f"`order` must be a non-negative int, got {order!r}.")
        x = jnp.asarray(x, self.y.dtype)
        return _evaluate(
            self.discretization, self.interval, self.y, x, order, False, True
        )

    def _extrapolated(self, x):
        """The interpolant at `x`, extrapolating outside `[xL, xR]` (a start)."""
        x = jnp.asarray(x, self.y.dtype)
        return _evaluate(self.discretization, self.interval, self.y, x, 0, False, False)

    def __call__(self, x: ArrayLike) -> Float[Array, "..."]:
        return self.derivative(x, order=0)


# ---------------------------------------------------------------------------------
# The direct method
# ---------------------------------------------------------------------------------


def _check_scalar(struct, what: str, fix: str):
    if not (isinstance(struct, jax.ShapeDtypeStruct) and struct.shape == ()):
        shape = getattr(struct, "shape", type(struct).__name__)
        raise ValueError(f"{what} must return a scalar, but it returned {shape}. {fix}")
    if not jnp.issubdtype(struct.dtype, jnp.floating):
        raise ValueError(f"{what} must return a floating-point scalar.")


class _Problem(eqx.Module):
    """The discretized functional: unknowns are the interior values (node-major)."""

    functional: Functional
    discretization: AbstractDiscretization

    @property
    def shape(self):
        return self.functional.boundary[0].shape

    def full_values(self, x_flat):
        yl, yr = self.functional.boundary
        n = self.functional.num_components
        inner = x_flat.reshape(self.discretization.num_nodes - 2, n)
        return jnp.concatenate([yl.reshape(1, n), inner, yr.reshape(1, n)], axis=0)

    def integral(self, integrand, x_flat, args):
        shape = self.shape
        fn = lambda y, yp, x: integrand(y.reshape(shape), yp.reshape(shape), x, args)
        return self.discretization.integrate(
            fn, self.full_values(x_flat), self.functional.interval
        )

    def holonomic_rows(self, x_flat, args):
        """The discrete holonomic constraints, shape `(N - 2, m)`."""
        shape = self.shape
        holonomic = self.functional.holonomic
        constraint = lambda y, x: jnp.atleast_1d(holonomic(y.reshape(shape), x, args))
        return self.discretization.pointwise_constraint(
            constraint, self.full_values(x_flat), self.functional.interval
        )


def _objective(x_flat, args):
    problem, user_args = args
    return problem.integral(problem.functional.lagrangian, x_flat, user_args)


def _integral_constraints(x_flat, args):
    problem, user_args = args
    dtype = x_flat.dtype
    return jnp.stack(
        [
            problem.integral(c.integrand, x_flat, user_args)
            - c.target(user_args, dtype)
            for c in problem.functional.integral_constraints
        ]
    )


def _constraints(x_flat, args):
    """`(discrete G rows for the interior nodes (node-major), int N_j - C_j)`."""
    problem, user_args = args
    parts = []
    if problem.functional.holonomic is not None:
        parts.append(problem.holonomic_rows(x_flat, user_args).reshape(-1))
    if problem.functional.integral_constraints:
        parts.append(_integral_constraints(x_flat, args))
    return jnp.concatenate(parts)


# ---------------------------------------------------------------------------------
# The default start, continuation, boundary consistency
# ---------------------------------------------------------------------------------


_START_MODES = 4
"""Smooth modes `sin(j pi s)` per function, beyond one per integral constraint, in
which the default start corrects the straight line."""

_START_ITERATIONS = 40
"""Gauss-Newton iterations of the search for a feasible default start."""

_CONTINUATION_STAGES = 24
"""The most Newton solves of the continuation in the constraint values."""


def _stop_gradient(tree):
    return jtu.tree_map(
        lambda x: jax.lax.stop_gradient(x) if eqx.is_inexact_array(x) else x, tree
    )


def _line(problem, straight_in=None):
    """The straight line between the end values at the nodes, shape `(N, n)`; with
    `straight_in`, a discretization, straight in its `start_parameter` instead of
    in `x`."""
    interval = problem.functional.interval
    if straight_in is None:
        nodes = problem.discretization.nodes(interval)
        s = (nodes - nodes[0]) / (nodes[-1] - nodes[0])
    else:
        s = straight_in.start_parameter(interval)
    yl, yr = problem.functional.boundary
    n = problem.functional.num_components
    return yl.reshape(1, n) + s[:, None] * (yr - yl).reshape(1, n)


class _Modes(eqx.Module):
    """A base curve (the straight line, or the user's start) corrected in smooth
    modes: `base + sum_j u_j sin(j pi s) / j^2` in every function, and the integral
    residuals `int N - C + offset` as functions of the amplitudes `u` (shape
    `(J n,)`, mode-major). The modes vanish at the ends: the end values stay."""

    full_args: Any
    offset: Array
    line: Array
    basis: Array

    def __init__(self, full_args, offset, base=None):
        problem, _ = full_args
        functional = problem.functional
        k = len(functional.integral_constraints)
        self.full_args = full_args
        self.offset = offset
        self.line = _line(problem) if base is None else base
        nodes = problem.discretization.nodes(functional.interval)
        dtype = self.line.dtype
        s = (nodes - nodes[0]) / (nodes[-1] - nodes[0])
        j = jnp.arange(1, k + _START_MODES + 1, dtype=dtype)
        self.basis = jnp.sin(jnp.pi * s[:, None] * j[None, :]) / j**2  # (N, J)

    @property
    def size(self) -> int:
        return self.basis.shape[1] * self.line.shape[1]

    def values(self, u):
        return self.line + self.basis @ u.reshape(self.basis.shape[1], -1)

    def residual(self, u):
        x_flat = self.values(u)[1:-1].reshape(-1)
        return _integral_constraints(x_flat, self.full_args) + self.offset

    def objective(self, u):
        return _objective(self.values(u)[1:-1].reshape(-1), self.full_args)

    def scales(self):
        """`(scale of each residual, amplitude a)`: `|C| + |int N[line]|` (1 where
        both vanish), and a tenth of the size of the problem."""
        problem, user_args = self.full_args
        functional = problem.functional
        dtype = self.line.dtype
        targets = jnp.stack(
            [c.target(user_args, dtype) for c in functional.integral_constraints]
        )
        r_line = self.residual(jnp.zeros((self.size,), dtype))
        scale = jnp.abs(targets - self.offset) + jnp.abs(r_line + targets - self.offset)
        scale = jnp.where(scale > 0, scale, 1.0)
        (xl, xr), (yl, yr) = functional.interval, functional.boundary
        size = jnp.maximum(xr - xl, jnp.max(jnp.abs(jnp.stack([yl, yr]))))
        return scale, 0.1 * size


def _degenerate_at_line(full_args):
    """Whether an integral constraint holds at the straight line, to rounding, with
    a gradient that vanishes there (a length equal to the distance between the
    ends): the line is then the only feasible function and has no multiplier.

    Judged in the smooth modes of `_Modes`: `|int N_j[line] - C_j| <= 100 eps s_j`
    and `|d(int N_j)/du| a <= sqrt(eps) s_j`, with `s_j` and `a` from `_Modes.scales`.
    """
    problem, _ = full_args
    k = len(problem.functional.integral_constraints)
    modes = _Modes(full_args, jnp.zeros((k,), problem.functional.boundary[0].dtype))
    dtype = modes.line.dtype
    eps = jnp.finfo(dtype).eps
    zero = jnp.zeros((modes.size,), dtype)
    scale, amplitude = modes.scales()
    r_line = modes.residual(zero)
    jac = jax.jacfwd(modes.residual)(zero)
    flat = jnp.max(jnp.abs(jac), axis=1) * amplitude <= jnp.sqrt(eps) * scale
    met = jnp.abs(r_line) <= 100 * eps * scale
    return jnp.any(flat & met)


def _dependent_integral_constraints(x_flat, full_args):
    """Whether the gradients of the integral constraints at `x_flat` are linearly
    dependent while the constraints hold (to `sqrt(eps)` of their scale): the
    smallest eigenvalue of their Gram matrix, normalised to a unit diagonal, is
    below `sqrt(eps)` (a zero gradient counts as dependent)."""
    problem, user_args = full_args
    functional = problem.functional
    dtype = x_flat.dtype
    eps = jnp.finfo(dtype).eps
    r = _integral_constraints(x_flat, full_args)
    targets = jnp.stack(
        [c.target(user_args, dtype) for c in functional.integral_constraints]
    )
    met = jnp.all(
        jnp.abs(r) <= jnp.sqrt(eps) * (jnp.abs(targets) + jnp.abs(r + targets) + 1)
    )
    jac = jax.jacrev(_integral_constraints)(x_flat, full_args)
    gram = jac @ jac.T
    d = jnp.sqrt(jnp.diagonal(gram))
    zero = jnp.any(d <= eps * jnp.max(d))
    safe = jnp.where(d > 0, d, 1.0)
    smallest = jnp.linalg.eigvalsh(gram / (safe[:, None] * safe[None, :]))[0]
    return met & jnp.all(jnp.isfinite(gram)) & (zero | (smallest <= jnp.sqrt(eps)))


def _feasible_start(full_args, offset, base=None):
    """The default start: the straight line, corrected to satisfy the integral
    constraints `int N_j dx = C_j - offset_j`. With a `base` curve (the user's start,
    shape `(N, n)`, its end values the boundary values), that curve corrected the
    same way, searched first from the curve itself (`u = 0`) and kept if that
    search becomes feasible: the user's curve moved onto the constraints.

    The correction lives in the span of the smooth modes `sin(j pi s)` (`s` in
    `[0, 1]` along the interval, `j = 1..J`, `J = k + _START_MODES`) of every
    function, weighted by `1 / j^2` so that the search prefers the lowest modes. The
    line itself is no start when an integral constraint is even in the correction (a
    length): its gradient vanishes there and the KKT matrix is singular. So the
    search starts at a finite amplitude `+a` and `-a` of the first mode of every
    function (`a` a tenth of the size of the problem) and runs damped Gauss-Newton
    (minimum-norm steps) on the integral residuals. Of the starts that become
    feasible the one with the lower objective is kept: the default start looks for
    the minimizing extremal. Where the first mode alone cannot satisfy the
    constraints (`int y^2 = 1` with `int y sin(pi x) = 0`), the search starts again
    from `+-a (1, 1/2, ..., 1/J)` in the modes.

    Returns `(values, feasible)`: the nodal values `(N, n)` and whether the search
    satisfied the integral constraints (to `sqrt(eps)` of their scale).
    """
    modes = _Modes(full_args, offset, base)
    dtype = modes.line.dtype
    n = modes.line.shape[1]
    num_modes = modes.basis.shape[1]
    eps = jnp.finfo(dtype).eps
    residual, objective = modes.residual, modes.objective
    scale, amplitude = modes.scales()
    norm = lambda r: jnp.max(jnp.abs(r) / scale)
    done_tol = 100 * eps
    feasible_tol = jnp.sqrt(eps)

    def search(u0):

        def cond(carry):
            _, r, it, stuck = carry
            return (norm(r) > done_tol) & (it < _START_ITERATIONS) & jnp.invert(stuck)

        def body(carry):
            u, r, it, _ = carry
            jac = jax.jacfwd(residual)(u)
            du = -jnp.linalg.pinv(jac) @ r
            du = jnp.where(jnp.all(jnp.isfinite(du)), du, 0.0)
            r_norm = norm(r)
            sufficient = lambda alpha, r_new: norm(r_new) <= (1 - alpha / 4) * r_norm

            def ls_cond(c):
                alpha, r_new, tries = c
                return jnp.invert(sufficient(alpha, r_new)) & (tries < 30)

            def ls_body(c):
                alpha, _, tries = c
                alpha = alpha / 2
                return alpha, residual(u + alpha * du), tries + 1

            one = jnp.ones((), dtype)
            alpha, r_new, _ = jax.lax.while_loop(
                ls_cond, ls_body, (one, residual(u + du), jnp.array(0))
            )
            ok = sufficient(alpha, r_new)
            u = jnp.where(ok, u + alpha * du, u)
            r = jnp.where(ok, r_new, r)
            return u, r, it + 1, jnp.invert(ok)

        u, r, _, _ = jax.lax.while_loop(
            cond, body, (u0, residual(u0), jnp.array(0), jnp.array(False))
        )
        return u, norm(r) <= feasible_tol, objective(u), norm(r)

    first = jnp.zeros((num_modes, n), dtype).at[0].set(1.0)
    generic = jnp.broadcast_to(
        1 / jnp.arange(1, num_modes + 1, dtype=dtype)[:, None], (num_modes, n)
    )
    starts = amplitude * jnp.stack([first, -first, generic, -generic]).reshape(4, -1)

    def from_modes():
        u, feasible, value, infeasibility = jax.vmap(search)(starts)
        value = jnp.where(feasible & jnp.isfinite(value), value, jnp.inf)
        infeasibility = jnp.where(jnp.isnan(infeasibility), jnp.inf, infeasibility)
        best = jnp.where(
            jnp.any(feasible[:2]),
            jnp.argmin(value[:2]),
            jnp.where(
                jnp.any(feasible[2:]),
                2 + jnp.argmin(value[2:]),
                jnp.argmin(infeasibility),
            ),
        )
        return u[best], feasible[best]

    if base is None:
        u, feasible = from_modes()
    else:
        # The base itself first; the finite amplitudes only where that fails (a
        # separate search: batched with them, it would cost as much as all of them).
        u0, feasible0, _, _ = search(jnp.zeros_like(starts[0]))
        u, feasible = jax.lax.cond(feasible0, lambda: (u0, feasible0), from_modes)
    return modes.values(u), feasible


def _start_multipliers(x_flat, full_args, num_holonomic_rows):
    """Zero holonomic multipliers and the least-squares integral multipliers
    `-(J J^T)^{-1} J grad F` at `x_flat`."""
    problem, _ = full_args
    dtype = x_flat.dtype
    lam_hol = jnp.zeros((num_holonomic_rows,), dtype)
    if problem.functional.integral_constraints:
        grad0 = jax.grad(_objective)(x_flat, full_args)
        jac = jax.jacrev(_integral_constraints)(x_flat, full_args)
        lam_int = least_squares_multipliers(grad0, jac, gram_factors(jac))
        lam_int = jnp.where(jnp.all(jnp.isfinite(lam_int)), lam_int, 0.0)
    else:
        lam_int = jnp.zeros((0,), dtype)
    return jnp.concatenate([lam_hol, lam_int])


class _Continuation(eqx.Module):
    """The start on the integral constraints, Newton from it, and if that fails,
    continuation in the integral constraint values (a `strategy` of `kkt_solve`).

    The start (`start`) is the default start, or the user's curve `base` moved onto
    the constraints (see `_feasible_start`), with the least-squares multipliers. The
    continuation solves the problem with the targets
    `C_j(t) = N_j[line] + t (C_j - N_j[line])`, between the values at the straight
    line (`t = 0`) and the requested ones (`t = 1`): first at some `t` from the start
    for those targets, then with `t` growing by a factor `q` from each solution to
    the next (`q = 2`, square rooted after a failure), until `t = 1`. For a rope that
    sags deeply this follows the branch from a shallow sag, where Newton's method
    converges from the start, down to the requested length.

    The start at `t = 1` and the continuation's fresh starts are one call in the
    compiled program (each copy of the start's search and multipliers costs about a
    second of compilation): the first pass of the loop builds the start and solves
    from it. What the solve needs to know about the start is returned in `stats`
    under `_start_*` keys (popped by `_solve_functional`).
    """

    r_line: Array
    num_holonomic_rows: int = eqx.field(static=True)
    # The line is a degenerate start (a length equal to the chord).
    degenerate: Array
    # `args` and the functional's arrays are finite.
    inputs_finite: Array
    # The user's curve with the boundary values at its ends (finite), or None.
    base: Array | None
    base_finite: Array
    # The user's curve as given (used as it is where it cannot be moved), or None.
    user_guess: Array | None
    # The curve the sag of the start is measured from, and the interval's width.
    reference: Array
    width: Array

    def start(self, args, t, first):
        """The start for the targets `C_j(t)`: `(z, found, values, finite)`, the
        unknowns and multipliers, whether it satisfies the integral constraints,
        the nodal values `(N, n)` and whether they are finite. At the first pass a
        start that is not usable is zeros (no step is taken)."""
        args = _stop_gradient(args)
        values, found = _feasible_start(args, -(1 - t) * self.r_line, self.base)
        # A start that is not finite stays as it is: `RESULTS.invalid_input`.
        found = found & self.base_finite
        if self.user_guess is not None:
            values = jnp.where(found | jnp.invert(first), values, self.user_guess)
        x = values[1:-1].reshape(-1)
        finite = jnp.all(jnp.isfinite(x))
        x = jnp.where(first & jnp.invert(finite & self.inputs_finite), 0.0, x)
        lam = _start_multipliers(x, args, self.num_holonomic_rows)
        return jnp.concatenate([x, lam]), found, values, finite

    def __call__(self, solve, residual, z0, args, start_ok):
        r_line, num_holonomic_rows = self.r_line, self.num_holonomic_rows
        dtype = z0.dtype
        pad = jnp.zeros((z0.shape[0] - r_line.shape[0],), dtype)
        num_unknowns = z0.shape[0] - r_line.shape[0] - num_holonomic_rows
        shape = self.reference.shape

        # One Newton solve in the program (it dominates the compilation): the first
        # pass of the loop is the direct solve from the start at `t = 1`, the later
        # ones the continuation's trials.
        def cond(carry):
            stage, q, finished = carry[3], carry[2], carry[4]
            return jnp.invert(finished) & (stage <= _CONTINUATION_STAGES) & (q > 1.01)

        def body(carry):
            t_done, t_try, q, stage, _, z_done, steps, direct, facts = carry
            first = stage == 0
            have = t_done > 0
            t = jnp.where(first, 1.0, t_try).astype(dtype)
            z_start, found, values, finite = jax.lax.cond(
                first | jnp.invert(have),
                lambda: self.start(args, t, first),
                lambda: (
                    z_done,
                    jnp.array(True),
                    jnp.zeros(shape, dtype),
                    jnp.array(True),
                ),
            )
            # What the first pass learns about the start, kept for the later ones.
            usable = start_ok & finite
            continue_ok = found & jnp.invert(self.degenerate & usable)
            # A deep start (moved onto the constraints by more than twice the
            # interval) goes to the continuation at once: Newton from it may
            # converge to a spurious discrete extremal.
            deep = jnp.max(jnp.abs(values - self.reference)) > 2 * self.width
            direct_ok = usable & jnp.invert(deep & continue_ok)
            skipped = jnp.invert(direct_ok) & usable
            new_facts = (usable, continue_ok, skipped, found, finite, z_start)
            facts = jax.tree.map(
                lambda new, old: jnp.where(first, new, old), new_facts, facts
            )
            usable, continue_ok, skipped = facts[:3]
            offset = -(1 - t) * r_line
            shifted = lambda z_, a: residual(z_, a) + jnp.concatenate([pad, offset])
            z_t, result_t, stats_t = solve(
                shifted, z_start, jnp.where(first, direct_ok, usable)
            )
            ok = result_t == RESULTS.successful
            steps = steps + stats_t["num_steps"]
            # The direct solve's outcome, kept as what is returned unless the
            # continuation solves the problem.
            direct = jax.tree.map(
                lambda new, old: jnp.where(first, new, old),
                (z_t, result_t, stats_t),
                direct,
            )
            need = (
                (skipped | (result_t != RESULTS.successful))
                & (result_t != RESULTS.nonlinear_max_steps_reached)
                & usable
                & continue_ok
            )
            # After a failure: from the last solution, a smaller factor; before the
            # first solution, a smaller t.
            q_new = jnp.where(ok | jnp.invert(have), q, jnp.sqrt(q))
            t_done_new = jnp.where(ok & jnp.invert(first), t, t_done)
            z_done_new = jnp.where(ok & jnp.invert(first), z_t, z_done)
            t_next = jnp.where(
                ok | have, jnp.minimum(1.0, t_done_new * q_new), t_try / 4
            )
            t_first = jnp.where(skipped, 1 / 16, 1 / 4).astype(dtype)
            finished = jnp.where(first, jnp.invert(need), ok & (t >= 1))
            return (
                t_done_new,
                jnp.where(first, t_first, t_next),
                jnp.where(first, q, q_new),
                stage + 1,
                finished,
                z_done_new,
                steps,
                direct,
                facts,
            )

        one = jnp.ones((), dtype)
        # The direct solve's outputs, zeros until the first pass writes them.
        shapes = jax.eval_shape(lambda: solve(residual, z0, start_ok))
        direct = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        steps = jnp.zeros((), shapes[2]["num_steps"].dtype)
        false = jnp.array(False)
        facts = (false, false, false, false, false, z0)
        init = (0 * one, one, 2 * one, jnp.array(0), false, z0, steps, direct, facts)
        t_done, _, _, stage, finished, z_c, steps, direct, facts = jax.lax.while_loop(
            cond, body, init
        )
        _, _, skipped, found, finite, z_start = facts
        z, result, stats = direct
        # Solved by the continuation: a trial at t = 1 after the first pass.
        solved = finished & (stage > 1) & (t_done >= 1)
        z = jnp.where(solved, z_c, z)
        result = RESULTS.where(
            skipped & jnp.invert(solved), RESULTS.line_search_failed, result
        )
        result = RESULTS.where(solved, RESULTS.successful, result)
        stats = {
            **stats,
            "num_steps": steps,
            "_start_found": found,
            "_start_finite": finite,
            "_start_x": z_start[:num_unknowns],
        }
        return z, result, stats


def _boundary_violation(functional, args):
    """`(|G| at both ends, tolerance)`, shape `(2, m)` each.

    The tolerance is `64 eps (1 + |x| |dG/dx| + sum_i |y_i| |dG/dy_i|)` per row: a
    few rounding errors of end values on the constraint surface.
    """
    holonomic = functional.holonomic
    dtype = functional.boundary[0].dtype
    eps = jnp.finfo(dtype).eps

    def one_end(y, x):
        g = lambda y_, x_: jnp.atleast_1d(holonomic(y_, x_, args)).astype(dtype)
        value = g(y, x)
        dg_dy, dg_dx = jax.jacfwd(g, argnums=(0, 1))(y, x)
        dg_dy = dg_dy.reshape(value.shape[0], -1)
        sensitivity = jnp.abs(dg_dy) @ jnp.abs(y).reshape(-1) + jnp.abs(dg_dx * x)
        return jnp.abs(value), 64 * eps * (1 + sensitivity)

    (xl, xr), (yl, yr) = functional.interval, functional.boundary
    left, tol_left = one_end(yl, xl)
    right, tol_right = one_end(yr, xr)
    return jnp.stack([left, right]), jnp.stack([tol_left, tol_right])


def _check_boundary(functional, args) -> None:
    """Raise `ValueError` when concrete end values violate the holonomic constraint."""
    if not isinstance(functional, Functional) or functional.holonomic is None:
        return
    leaves = jtu.tree_leaves((functional, args))
    if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
        return  # traced: `result` reports it instead
    try:
        violation, tol = _boundary_violation(functional, args)
    except Exception:
        return  # bad structure: reported by the solve with its own message
    if violation.ndim != 2 or violation.shape[1] >= functional.num_components:
        return  # too many constraints (m >= n): reported by the solve
    violation, tol = np.asarray(violation), np.asarray(tol)
    if not np.all(np.isfinite(violation)):
        return  # non-finite values: `RESULTS.invalid_input`
    bad = violation > tol
    if np.any(bad):
        end, row = (int(i[0]) for i in np.nonzero(bad))
        which = ("y(xL)", "y(xR)")[end]
        raise ValueError(
            f"The end value {which} = {np.asarray(functional.boundary[end])} violates "
            f"the holonomic constraint: |G_{row}| = {violation[end, row]:.3g} at "
            f"x = {float(functional.interval[end])} (tolerance "
            f"{tol[end, row]:.3g}). No curve between the end values can satisfy "
            "G = 0 on the whole interval: put the end points on the constraint "
            "surface, or fix G."
        )


@full_precision
def solve_functional(
    functional: Functional,
    args: Args = None,
    *,
    discretization: AbstractDiscretization = Chebyshev(32),
    solver: AbstractKKTSolver | None = None,
    y0: Callable | ArrayLike | None = None,
    max_steps: int = 256,
    rtol: ArrayLike | None = None,
    atol: ArrayLike | None = None,
    throw: bool = True,
) -> FunctionalSolution:
    """Extremize a [`constrained_jax.Functional`][] by the direct method.

    The discretization turns `y` into its values at `N` nodes and every integral into
    a quadrature, giving the finite problem: extremize `F_h(Y)` over the interior
    values `Y` subject to `int_h N_j = C_j` and one discrete form `G_i = 0` of the
    holonomic constraints per interior node (see the discretization's
    `pointwise_constraint`). Its KKT system,

        grad F_h + sum_j lambda_j grad (int_h N_j) + sum_i mu_i grad G_i = 0,

    is solved by the KKT machinery of [`constrained_jax.extremize`][] (Newton on the
    KKT residual with an affine-covariant line search). The discrete multipliers
    approximate the continuous ones: `lambda_j` are the integral multipliers, and
    `mu_i -> lambda(x_i)`, the holonomic multiplier function at the nodes, in the
    convention `d/dx(dL*/dy') - dL*/dy = sum_j lambda_j(x) dG_j/dy`.

    **Arguments:**

    - `functional`: the [`constrained_jax.Functional`][].
    - `args`: parameters passed last to `L`, `N_j`, `G` and callable `C_j`; traced,
        so changing them never recompiles.
    - `discretization`: [`constrained_jax.Chebyshev`][] (spectral; default with 32
        nodes) or [`constrained_jax.PiecewiseLinear`][] (second order, linear cost).
    - `solver`: an [`constrained_jax.AbstractKKTSolver`][]. By default
        `Newton(rtol=1e-10, atol=1e-10, linear_solver=...)` with the linear solver that
        suits the discretization (`discretization.make_linear_solver(n, m, k)`:
        [`constrained_jax.EquilibratedDenseLU`][] for `Chebyshev`, the linear-cost
        [`constrained_jax.BorderedBlockTridiagonal`][] for `PiecewiseLinear`).
    - `y0`: the starting guess: a callable `y0(x)` (shaped like the boundary values),
        or the values at the nodes, shape `(N,)` or `(N, n)`. Newton's method finds
        the extremal nearest to it. By default the straight line between the end
        values (without integral constraints, straight in the discretization's
        `start_parameter`: in the graded variable on a [`constrained_jax.Graded`][]
        grid, so that it leaves a singular end steeply); with integral
        constraints, the line corrected in a few smooth modes
        `sin(j pi s)` until it satisfies them (of the candidates, the one with the
        lower `F`: the default start looks for the *minimizing* extremal; for a
        functional to be maximised, such as Dido's area, pass `y0`). From the
        default start, when Newton's method fails, or when the start sags more than
        twice the interval, the solve continues in the constraint values from those
        of the straight line to `C_j` (a sequence of Newton solves inside the same
        compiled program; `stats["num_steps"]` counts all their steps). A user `y0`
        with integral constraints (and no holonomic ones) is treated the same way:
        first moved onto the integral constraints in the same smooth modes (the
        nearest such curve is searched first, from `y0` itself), then Newton's
        method, then, if it fails or the move added a sag of more than twice the
        interval, the continuation, each of whose starts is `y0` moved onto the
        intermediate values. A [`constrained_jax.FunctionalSolution`][] as `y0` is
        mapped affinely onto this interval, plus the straight line from its end
        values to this functional's (a continuation in the ends: its shape, not its
        values at the same `x`, which beyond its ends would be extrapolated).
    - `max_steps`: the most Newton steps.
    - `rtol`, `atol`: the tolerance on the discretization error. The solution is
        `successful` only if the discretization's a-posteriori error estimate
        (`stats["error_estimate"]`, an estimate of `max_x |y_h(x) - y(x)|`) is at
        most `atol + rtol * max |y|`; otherwise `result` is
        `RESULTS.discretization_error` (more nodes, or a
        [`constrained_jax.Graded`][] grid at a singular end). By default
        `atol = 0` and `rtol = discretization.default_rtol`, a tolerance that falls
        with the number of nodes at the discretization's a-priori rate
        (`10^(-(N-4)/8)` for `Chebyshev(N)`, `(10/(N-1))^2` for
        `PiecewiseLinear(N)`, both floored at `1e-10`): it refuses a solution that
        the grid does not resolve at all (a singular end exploited by the
        quadrature, a boundary layer thinner than the mesh) without refusing a
        convergence study at few nodes. The default is never below what the
        precision can certify: `3000 eps`, and the round-off plateau of the
        estimate, `discretization.roundoff_rtol(dtype)` (`2 N^2 eps` for
        `Chebyshev(N)`, above `1e-10` from about 480 nodes in float64), so more
        nodes never turn a resolved solution into a refusal. Ask for the accuracy
        you need; a `rtol` below that plateau is refused however many nodes.
        Traced: changing them never recompiles.
    - `throw`: raise on failure if `True`; otherwise report it in `result`.

    **Returns:**

    A [`constrained_jax.FunctionalSolution`][]. Refusals: end values that violate
    the holonomic constraint raise `ValueError` (concrete values) or report
    `RESULTS.inconsistent_boundary` (traced); integral constraints that the start
    (the default, or `y0` moved onto them) cannot satisfy and Newton's method does
    not solve report `RESULTS.infeasible_constraints`; a constraint met only by the
    straight line where its gradient vanishes (a length equal to the chord), and
    dependent integral constraints (the same one given twice) where the solve
    fails, report `RESULTS.functional_redundant_constraints`.

    Differentiable with respect to `args` and to arrays in `functional` (implicit
    function theorem on the discrete KKT system; one more linear solve per backward
    pass). Composes with `jax.jit` and `jax.vmap`.
    """
    max_steps = check_max_steps(max_steps)
    args = as_traced_args(args)
    _check_boundary(functional, args)
    if (
        callable(y0)
        and isinstance(functional, Functional)
        and isinstance(discretization, AbstractDiscretization)
    ):
        # Evaluated here, outside the compiled solve: a callable would be a static
        # argument of it, so every new function (a fresh closure per call) would
        # compile the whole solve again. Values at the nodes are traced.
        nodes = discretization.nodes(functional.interval)
        start = y0
        if isinstance(y0, FunctionalSolution):
            # A solution, as a start, is mapped affinely onto this interval, plus
            # the straight line from its end values to this functional's: on
            # another interval or between other ends (a continuation) its values
            # at the same x would be extrapolated beyond its ends, where a
            # polynomial grows fast (from the rope on (0, 1) to (0, 1.05) the line
            # search failed; mapped, 4 Newton steps). On the same interval, with
            # the same ends, this is the solution itself, to round-off.
            (xl, xr), (sl, sr) = functional.interval, y0.interval
            (yl, yr), sol = functional.boundary, y0
            shift_l = yl - sol._extrapolated(sl)
            shift_r = yr - sol._extrapolated(sr)

            def start(x):
                u = (x - xl) / (xr - xl)
                old = sol._extrapolated(sl + u * (sr - sl))
                return old + (1 - u) * shift_l + u * shift_r

        y0 = jax.vmap(lambda x: jnp.asarray(start(x)))(nodes)
    dtype = (
        functional.boundary[0].dtype
        if isinstance(functional, Functional)
        else default_float_dtype()
    )
    tolerance = _error_tolerance(discretization, rtol, atol, dtype)
    sol = _solve_functional(
        functional, args, discretization, solver, y0, max_steps, tolerance
    )
    return raise_if_failed(sol, throw)


def _error_tolerance(discretization, rtol, atol, dtype):
    """`(rtol, atol)` as float64 NumPy/JAX scalars; defaults from the discretization,
    floored by what the functional's `dtype` can certify."""
    if rtol is None:
        rtol = (
            discretization.default_rtol
            if isinstance(discretization, AbstractDiscretization)
            else 0.0
        )
        # A default tolerance below what the precision can certify would refuse a
        # resolved solution: in float32 the coefficient tail sits at round-off near
        # 1e-4, and the estimate's round-off plateau grows with the number of nodes
        # (`roundoff_rtol`), so that more nodes would turn a right answer into a
        # refusal.
        floor = 3000 * float(jnp.finfo(dtype).eps)
        if isinstance(discretization, AbstractDiscretization):
            floor = max(floor, discretization.roundoff_rtol(dtype))
        rtol = max(rtol, floor)
    if atol is None:
        atol = 0.0
    out = []
    for name, tol in (("rtol", rtol), ("atol", atol)):
        tol = jnp.asarray(tol)
        real = jnp.issubdtype(tol.dtype, jnp.floating) or jnp.issubdtype(
            tol.dtype, jnp.integer
        )
        if tol.shape != () or not real:
            raise ValueError(f"`{name}` must be a real scalar, got {tol!r}.")
        if not isinstance(tol, jax.core.Tracer) and not bool(tol >= 0):
            raise ValueError(f"`{name}` must be >= 0 (and not NaN), got {tol}.")
        out.append(tol)
    return tuple(out)


@eqx.filter_jit
def _solve_functional(
    functional, args, discretization, solver, y0, max_steps, tolerance
):
    warn_near_mapping_limit()  # (at trace time: before a compilation)
    if not isinstance(functional, Functional):
        raise ValueError(
            "`functional` must be a `cjax.Functional`, got "
            f"{type(functional).__name__}."
        )
    if not isinstance(discretization, AbstractDiscretization):
        raise ValueError(
            "`discretization` must be a discretization object such as "
            "`cjax.Chebyshev(32)` or `cjax.PiecewiseLinear(1001)`, got "
            f"{discretization!r}."
        )
    check_kkt_solver(Newton() if solver is None else solver, max_steps)

    # The discretization's matrices, computed once here at run time and passed to
    # every evaluation of the functional (not constants in the program).
    problem = _Problem(functional, discretization.tabulate())
    dtype = functional.boundary[0].dtype
    shape = functional.boundary[0].shape
    n = functional.num_components
    num_nodes = discretization.num_nodes
    nodes = discretization.nodes(functional.interval)
    yl, yr = functional.boundary
    zero = jnp.zeros(shape, dtype)

    # Structure checks (trace time).
    _check_scalar(
        jax.eval_shape(functional.lagrangian, zero, zero, nodes[0], args),
        "The Lagrangian L(y, y', x, args)",
        "Write L as a scalar density, e.g. sum the contributions of the components.",
    )
    for j, c in enumerate(functional.integral_constraints):
        _check_scalar(
            jax.eval_shape(c.integrand, zero, zero, nodes[0], args),
            f"The integrand N_{j}(y, y', x, args) of integral constraint {j}",
            "Write one IntegralConstraint per scalar constraint.",
        )
        c.target(args, dtype)
    m = 0
    if functional.holonomic is not None:
        g_struct = jax.eval_shape(functional.holonomic, zero, nodes[0], args)
        if not isinstance(g_struct, jax.ShapeDtypeStruct) or g_struct.ndim > 1:
            raise ValueError(
                "The holonomic constraints G(y, x, args) must return a scalar or an "
                "array of shape (m,): stack them with `jnp.stack([g1, g2])`."
            )
        m = 1 if g_struct.ndim == 0 else g_struct.shape[0]
        if m == 0:
            raise ValueError("`holonomic` returned no constraints: pass None instead.")
        if m >= n:
            raise ValueError(
                f"There are m = {m} holonomic constraints on n = {n} functions: at "
                "least one function must stay free (m < n). With m >= n the curve is "
                "fixed by the constraints alone."
            )
    k = len(functional.integral_constraints)
    num_unknowns = (num_nodes - 2) * n
    if k > num_unknowns - (num_nodes - 2) * m:
        raise ValueError(
            f"{k} integral constraints but only {num_unknowns - (num_nodes - 2) * m} "
            "free unknowns: use more nodes."
        )

    # The starting guess.
    full_args = (problem, args)
    default_start = y0 is None and k > 0
    # A user's curve is moved onto the integral constraints the same way as the
    # default start (not with holonomic constraints: the modes would leave them).
    user_start = y0 is not None and k > 0 and m == 0
    start_found = jnp.array(True)
    if y0 is None:
        # With integral constraints the start is built inside the solve (see
        # `_Continuation`).
        guess = _line(problem, straight_in=problem.discretization) if k == 0 else None
    elif callable(y0):
        guess = jax.vmap(lambda x: jnp.asarray(y0(x), dtype).reshape(n))(nodes)
    else:
        guess = jnp.asarray(y0, dtype)
        if guess.shape not in ((num_nodes, n), (num_nodes,) + shape):
            raise ValueError(
                "`y0` must be a callable y0(x) or the values at the "
                f"{num_nodes} nodes, shape {(num_nodes,) + shape}; got {guess.shape}."
            )
        guess = guess.reshape(num_nodes, n)
    if solver is None:
        solver = Newton(linear_solver=discretization.make_linear_solver(n, m, k))
    constraints = _constraints if m > 0 or k > 0 else None
    num_holonomic_rows = (num_nodes - 2) * m
    boundary_ok = jnp.array(True)
    if m > 0:
        violation, tol = _boundary_violation(functional, args)
        boundary_ok = jnp.all(violation <= tol)

    degenerate = jnp.array(False)
    check_line = m == 0 and k > 0
    if default_start or user_start:
        # The start is built inside the solve (see `_Continuation`); `x_safe` and
        # the multipliers here only give the shapes.
        line = _line(problem)
        base, user_guess, base_finite = None, None, jnp.array(True)
        if user_start:
            base = jnp.concatenate([line[:1], guess[1:-1], line[-1:]], axis=0)
            base_finite = jnp.all(jnp.isfinite(base))
            base = jnp.where(base_finite, base, line)
            user_guess = guess
        if check_line and default_start:
            degenerate = _degenerate_at_line(_stop_gradient(full_args))
        inputs_finite = all_finite((args, functional))
        continuation = _stop_gradient(
            _Continuation(
                r_line=_integral_constraints(line[1:-1].reshape(-1), full_args),
                num_holonomic_rows=num_holonomic_rows,
                degenerate=degenerate,
                inputs_finite=inputs_finite,
                base=base,
                base_finite=base_finite,
                user_guess=user_guess,
                reference=line if base is None else base,
                width=functional.interval[1] - functional.interval[0],
            )
        )
        x_safe = jnp.zeros((num_unknowns,), dtype)
        lam0 = jnp.zeros((num_holonomic_rows + k,), dtype)
        start_ok = inputs_finite
    else:
        continuation = None
        x0 = guess[1:-1].reshape(-1)
        start_ok = all_finite((x0, args, functional))
        x_safe = jnp.where(start_ok, x0, 0.0)
        lam0 = _start_multipliers(x_safe, _stop_gradient(full_args), num_holonomic_rows)
    kkt_problem = lagrangian_problem(_objective, constraints, None, x_safe, full_args)
    sol = kkt_solve(
        kkt_problem,
        solver,
        jnp.concatenate([x_safe, lam0]),
        full_args,
        max_steps,
        start_ok & boundary_ok,
        strategy=continuation,
    )
    z, result, stats = sol.z, sol.result, sol.stats
    if continuation is not None:
        stats = dict(stats)
        start_found = stats.pop("_start_found")
        start_ok = start_ok & stats.pop("_start_finite")
        x_safe = stats.pop("_start_x")
        degenerate = degenerate & start_ok
    # A start that is not usable is reported as that, not as an inconsistent end.
    boundary_ok = boundary_ok | jnp.invert(start_ok)
    if check_line and not default_start:
        # The degeneracy check costs about as much as the solve of a small problem, so
        # from a given start it runs only where it can matter: a degenerate problem has
        # the line as its only feasible function, so a successful solve that ends away
        # from it (by 1 % of the size of the problem: the constraint would then be off
        # by about 1e-4, far beyond Newton's tolerance) is not degenerate.
        values_z = problem.full_values(jax.lax.stop_gradient(z)[:num_unknowns])
        line = _line(problem)
        size = jnp.maximum(
            functional.interval[1] - functional.interval[0], jnp.max(jnp.abs(line))
        )
        away = jnp.max(jnp.abs(values_z.reshape(line.shape) - line)) > 0.01 * size
        maybe = start_ok & jnp.invert(away & (result == RESULTS.successful))
        degenerate = jax.lax.cond(
            maybe,
            lambda: _degenerate_at_line(_stop_gradient(full_args)),
            lambda: jnp.array(False),
        )
    # Statuses in the words of this function.
    # Singular before any step (the iterate is still the start): the start's fault.
    at_start = jnp.all(jax.lax.stop_gradient(z[:num_unknowns]) == x_safe)
    result = RESULTS.where(
        result == RESULTS.singular_kkt,
        RESULTS.where(
            at_start,
            RESULTS.functional_singular_start,
            RESULTS.functional_singular_kkt,
        ),
        result,
    )
    result = RESULTS.where(
        result == RESULTS.line_search_failed,
        RESULTS.functional_line_search_failed,
        result,
    )
    result = RESULTS.where(
        (result != RESULTS.successful) & jnp.invert(start_found) & start_ok,
        RESULTS.infeasible_constraints,
        result,
    )
    if k > 1:
        # Dependent integral constraints (the same one twice): their Jacobian has
        # lost rank wherever they hold, and the KKT matrix is singular with them
        # (a linear solver may report that as a singular matrix, a failed line
        # search or a Krylov failure, after which the iterate may have left the
        # constraints). Judged at the start and where the solve stopped, only
        # after a failure.
        points = jnp.stack([x_safe, jax.lax.stop_gradient(z[:num_unknowns])])
        dependent = jax.lax.cond(
            (result != RESULTS.successful) & start_ok & start_found,
            lambda: jnp.any(
                jax.vmap(_dependent_integral_constraints, in_axes=(0, None))(
                    points, _stop_gradient(full_args)
                )
            ),
            lambda: jnp.array(False),
        )
        degenerate = degenerate | dependent
    result = RESULTS.where(degenerate, RESULTS.functional_redundant_constraints, result)
    result = RESULTS.where(boundary_ok, result, RESULTS.inconsistent_boundary)
    # Failures decided after the solve have no derivative either (NaN, never raised).
    z = nan_tangent_where(z, result != RESULTS.successful)
    x_flat = z[:num_unknowns]
    mu = z[num_unknowns : num_unknowns + (num_nodes - 2) * m]
    lam = z[num_unknowns + (num_nodes - 2) * m :]
    values = problem.full_values(x_flat)
    value = _objective(x_flat, full_args)

    # The a-posteriori error estimate (a diagnostic: not differentiated).
    values_s = jax.lax.stop_gradient(values)
    estimate = discretization.error_estimate(values_s, functional.interval)
    rtol, atol = (jnp.asarray(t, dtype) for t in tolerance)
    bound = atol + rtol * jnp.max(jnp.abs(values_s))
    resolved = estimate <= bound
    result = RESULTS.where(
        (result == RESULTS.successful) & jnp.logical_not(resolved),
        RESULTS.discretization_error,
        result,
    )
    stats = {
        **stats,
        "error_estimate": estimate,
        "error_tolerance": bound,
    }
    if m > 0:
        g_shape = jax.eval_shape(functional.holonomic, zero, nodes[0], args).shape
        mu_values = mu.reshape((num_nodes - 2,) + g_shape)
        holonomic = MultiplierFunction(
            nodes[1:-1], mu_values, functional.interval, discretization
        )
    else:
        holonomic = None
    sol = FunctionalSolution(
        x=nodes,
        y=values.reshape((num_nodes,) + shape),
        multipliers=FunctionalMultipliers(integral=lam, holonomic=holonomic),
        value=value,
        result=result,
        stats=stats,
        interval=functional.interval,
        discretization=discretization,
    )
    return sol
