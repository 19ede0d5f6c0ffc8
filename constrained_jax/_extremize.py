"""Constrained extremization of functions with Lagrange multipliers.

Extremize `F(x)` subject to `G_j(x) = 0` by freely extremizing
`F*(x, lambda) = F(x) + sum_j lambda_j G_j(x)` over `x` and `lambda`: the `n + k`
equations `grad F + sum_j lambda_j grad G_j = 0`, `G_j = 0`. With inequalities
`H_i(x) <= 0` the KKT conditions gain multipliers `mu` and complementarity rows
(`constrained_jax._inequalities`). Both are one `KKTProblem` solved by one
`kkt_solve` (`constrained_jax._kkt`), in one jitted core: a prologue (argument
checks, the flat problem, defaults, the start), the solve, and an epilogue (the
second-order classification, the statuses).
"""

import warnings
from typing import Any, Literal

import equinox as eqx
import jax
import jax.flatten_util as jfu
import jax.numpy as jnp
import jax.tree_util as jtu
from jaxtyping import Array, ArrayLike, Bool, Float, PyTree

from ._compat import NamedEnumerationMeta
from ._custom_types import Args, ConstraintFn, ObjectiveFn, Scalar, X
from ._implicit import nan_tangent_where
from ._inequalities import (
    check_concrete_bounds,
    check_inequalities,
    flat_bound,
    flat_inequalities,
)
from ._kkt import (
    check_kkt_solver,
    constraint_jacobian,
    gram_factors,
    kkt_solve,
    KKTProblem,
    KKTSolution,
    lagrangian_problem,
    least_squares_multipliers,
    reduced_hessian_extremes,
    tangent_projector,
)
from ._misc import (
    all_finite,
    as_traced_args,
    check_max_steps,
    check_signature,
    check_unknowns,
    full_precision,
    inexact_asarray,
    lists_as_arrays,
    warn_near_mapping_limit,
)
from ._results import raise_if_failed, RESULTS
from ._solver.dense_lu import dense_factor, dense_solve, DenseLU
from ._solver.equilibrated_lu import EquilibratedDenseLU
from ._solver.fallback import Fallback
from ._solver.globalization import conjugate_gradient_mv
from ._solver.kkt_solver import AbstractKKTSolver
from ._solver.minres import MINRES
from ._solver.newton import Newton
from ._solver.semismooth_newton import conjugate_gradient, SemismoothNewton


# The default linear solver is chosen by what fits (`default_solver`): dense LU while
# the KKT matrix takes at most `DENSE_BYTES`, where forming it (n + k Hessian-vector
# products) and factoring it (2 (n + k)^3 / 3 flops, under a gigaflop) at every
# Newton step stay cheap; above, preconditioned MINRES, with dense LU as its fallback
# while the matrix takes at most `FALLBACK_BYTES`.
DENSE_BYTES = 2**23  # 8 MiB: n + k = 1024 in float64, 1448 in float32
FALLBACK_BYTES = 2**27  # 128 MiB: n + k = 4096 in float64, 5792 in float32
# An explicitly dense solver above this size is warned about (the KKT matrix alone
# takes `8 (n + k)^2` bytes, 134 MB at 4,096, and XLA's scratch several times that).
DENSE_WARN = 4096


def default_solver(
    n: int,
    k: int,
    dtype,
    dense_bytes: int = DENSE_BYTES,
    fallback_bytes: int = FALLBACK_BYTES,
) -> Newton:
    """The solver [`constrained_jax.extremize`][] uses when none is given and there
    are no inequalities (with them, `SemismoothNewton()`).

    `Newton(rtol=1e-10, atol=1e-10)` with the linear solver chosen at trace time by
    the memory the KKT matrix of `n + k` rows takes, `(n + k)^2` entries of `dtype`:

    - at most 8 MiB (`n + k <= 1024` in float64, `1448` in float32):
        [`constrained_jax.DenseLU`][], which forms the KKT matrix and factors it
        (unrolled elimination for tiny systems, LAPACK's LU above) at every Newton
        step; in float32 [`constrained_jax.EquilibratedDenseLU`][] (rows and
        columns scaled first, so that its pivot test, about `1e-5 m` of the largest
        entry, does not take a badly scaled matrix for a singular one). Its cost,
        at most `n + k` Hessian-vector products and `2 (n + k)^3 / 3` flops
        (under a gigaflop) per step, does not depend on the conditioning of the
        problem; above this size it grows to seconds per step.
    - larger: matrix-free [`constrained_jax.MINRES`][] with its diagonal
        (row-norm, Jacobi-type) preconditioner, whose cost per iteration is one
        Hessian-vector product and whose memory is a few vectors. It stops on the
        true residual, `||K dz + r|| <= max(1e-12, 1000 eps) ||r||`, within
        `max(1000, n + k)` iterations. While the matrix takes at most 128 MiB
        (`n + k <= 4096` in float64) a Newton step whose MINRES solve does not
        converge is solved by `DenseLU` instead; above, it is reported as
        `RESULTS.linear_solve_failed`, never a wrong answer (in float32 the
        fallback is `EquilibratedDenseLU`).

    (`dense_bytes`, `fallback_bytes`: the two memory bounds, 8 MiB and 128 MiB.)
    """
    size = n + k
    itemsize = jnp.dtype(dtype).itemsize
    # In float32 the dense solve equilibrates first: DenseLU's pivot test, `10 m eps
    # max|K|`, is then about 1e-5 m of the largest entry, and a badly scaled KKT
    # matrix (Hessian entries `1/x_i` next to constraint rows of ones) would pass for
    # singular.
    single = jnp.dtype(dtype).itemsize <= 4
    if size**2 * itemsize <= dense_bytes:
        return Newton(linear_solver=EquilibratedDenseLU()) if single else Newton()
    rtol = max(1e-12, 1000 * float(jnp.finfo(dtype).eps))
    krylov = MINRES(rtol=rtol, atol=0.0, max_steps=max(1000, size))
    if size**2 * itemsize <= fallback_bytes:
        dense = EquilibratedDenseLU() if single else DenseLU(unroll_max=0)
        return Newton(linear_solver=Fallback(krylov, dense))
    return Newton(linear_solver=krylov)


def _solver_or_default(
    solver, n: int, k: int, m: int, dtype, bounds: bool = False
) -> AbstractKKTSolver:
    """`solver`, or the default; a warning where the size makes a dense solve slow.

    With bounds only (`bounds`), the Newton steps reduce to `n + k` unknowns, and the
    default `SemismoothNewton` takes the linear solver `default_solver` picks for the
    `n + k + m` unknowns of the backward pass."""
    if m and bounds:
        if solver is not None:
            size = n + k + m
            if isinstance(solver.linear_solver, DenseLU) and size > DENSE_WARN:
                warnings.warn(
                    f"`extremize` with bounds and a solver whose `linear_solver` is "
                    f"dense: derivatives (the backward pass) form the {size} x {size} "
                    "matrix of the KKT conditions (n + k + m, bounds add n rows each). "
                    "Pass `solver=None`, which picks a matrix-free one at this size, "
                    "or `linear_solver=cjax.MINRES(rtol=1e-12, atol=0.0)`.",
                    stacklevel=2,
                )
            return solver
        linear_solver = default_solver(n, k + m, dtype).linear_solver
        return SemismoothNewton(linear_solver=linear_solver)
    if m:
        if n + k + m > DENSE_WARN:
            size = n + k + m
            warnings.warn(
                f"`extremize` with inequalities forms the dense {size} x {size} "
                f"Jacobian of the KKT system (n + k + m = {size}; bounds add n rows "
                "each) and factors it at every step, in O((n + k + m)^3) time: expect "
                "it to be slow. Bounds alone (`lower`, `upper` without "
                "`inequalities`) are solved without it.",
                stacklevel=2,
            )
        return SemismoothNewton() if solver is None else solver
    if solver is None:
        return default_solver(n, k, dtype)
    linear_solver = solver.linear_solver
    if isinstance(linear_solver, DenseLU) and n + k > DENSE_WARN:
        size = n + k
        warnings.warn(
            f"`extremize` with a dense linear solver on a KKT system of n + k = "
            f"{size} unknowns forms the {size} x {size} KKT matrix "
            f"({8 * size**2 / 1e9:.2g} GB in float64) and factors it in O((n + k)^3) "
            "time. Pass `solver=None` (the default picks a matrix-free solver at "
            "this size) or `solver=cjax.Newton(linear_solver=cjax.MINRES(rtol=1e-12, "
            "atol=0.0))`.",
            stacklevel=2,
        )
    return solver


class EXTREMUM(eqx.Enumeration, metaclass=NamedEnumerationMeta):
    """What kind of stationary point an [`constrained_jax.Extremum`][] is.

    Judged by the eigenvalues of the Hessian of `F* = F + lambda . G` restricted to the
    tangent space `ker J` of the constraints (the second-order conditions).
    """

    minimum = "a strict local minimum: the reduced Hessian is positive definite"
    maximum = "a strict local maximum: the reduced Hessian is negative definite"
    saddle = "a saddle: the reduced Hessian has eigenvalues of both signs"
    degenerate = (
        "degenerate: the reduced Hessian is singular (an eigenvalue is zero to within "
        "sqrt(eps) of its scale), so the second-order test is inconclusive"
    )
    isolated = (
        "isolated: as many independent constraints as unknowns, so the feasible set is "
        "a single point near x and there is no tangent space to test"
    )
    unknown = (
        "unknown: the solve did not succeed (`result` is not successful), so `x` is "
        "not a stationary point and has no kind"
    )


class Extremum(eqx.Module):
    """The solution of [`constrained_jax.extremize`][].

    **Attributes:**

    - `x`: the stationary point, with the structure of `x0`.
    - `multipliers`: the Lagrange multipliers `lambda`, shape `(k,)`, in the convention
        `grad F + sum_j lambda_j grad G_j = 0`.
    - `value`: `F(x)`. By the envelope theorem its derivative with respect to a
        parameter `p` is `dF/dp + lambda . dG/dp`.
    - `inequality_multipliers`: the multipliers `mu` of the inequalities `H_i <= 0`,
        shape `(m,)`, in the convention `grad F + lambda . grad G + mu . grad H = 0`,
        `mu_i H_i = 0`: `mu >= 0` for `sense="minimize"`, `mu <= 0` for
        `sense="maximize"`. The rows are the user's `H`, then one per entry of
        `lower` (`H = lower - x`), then one per entry of `upper` (`H = x - upper`).
        Shape `(0,)` without inequalities.
    - `active`: boolean, shape `(m,)`: where `H_i = 0` at the solution (the
        binding inequalities; see `extremize` for the tolerance). Shape `(0,)`
        without inequalities.
    - `kind`: an [`constrained_jax.EXTREMUM`][] member; `EXTREMUM.unknown` whenever
        `result` is not successful (the point where a failed solve stopped is not a
        stationary point, so it is neither a minimum nor a maximum).
    - `result`: a [`constrained_jax.RESULTS`][] member; `RESULTS.successful` if the
        solve converged. The failures that name their cause:
        `invalid_input` (NaN or inf in `x0`, `multipliers0` or `args`),
        `nonfinite_objective` (`F`, `G` or their derivatives NaN or inf at `x0`
        or where the solver stopped), `singular_kkt` (the Hessian of `F*` is
        singular on the tangent space: no isolated stationary point there),
        `redundant_constraints` (dependent constraints, or a constraint gradient that
        vanishes where the constraint holds, e.g. `G = g(x)**2`),
        `infeasible_constraints` (the iterates approach a stationary point of `|G|^2`
        with `G != 0`), `line_search_failed`, `linear_solve_failed` (an iterative
        linear solver did not converge), `nonlinear_max_steps_reached`; with
        inequalities also `infeasible_inequalities` (the solve stopped where some
        `H_i > 0`, at a local minimum of the violation), `kkt_conditions_violated`
        (the iteration stopped but the KKT conditions do not hold to tolerance),
        `unbounded_objective` (the iterates ran off while `F` kept improving) and,
        whenever `sense` is given, `not_an_optimum` (a KKT point whose second-order
        test contradicts `sense`).
    - `stats`: `num_steps`, `max_steps`, the extreme eigenvalues of the reduced
        Hessian (`reduced_hessian_eigenvalues`, `[min, max]`) and the final KKT
        residual (`kkt_residual`, root mean square).

    !!! note

        `kind` is judged from the smallest and largest eigenvalue `mu` of the reduced
        Hessian `Z^T H Z` (`Z` an orthonormal basis of `ker J`): from the formed
        matrix when `n <= 64`, by Lanczos otherwise (exactly, to round-off, when
        `n - k <= 64`, as extreme Ritz values beyond).
        An eigenvalue counts as zero when `|mu| <= sqrt(eps) max(1, |mu_min|,
        |mu_max|)`, an absolute floor for tiny Hessians and relative otherwise. It is
        meaningful only when `result` is successful, and is `EXTREMUM.unknown`
        otherwise (`stats["reduced_hessian_eigenvalues"]` still holds the eigenvalues
        at the point where the solve stopped).

    !!! note

        Which constraint failure is reported is decided at the point where Newton
        stopped, `x`, from the constraint values `G`, the Jacobian `J` and the
        Gauss-Newton correction `dx = -J^T (J J^T + mu I)^-1 G` that the linearised
        constraints predict (`mu = 1000 k eps max|J J^T|`, a regularisation far
        below any meaningful singular value). When the KKT matrix is singular because
        `J` lost rank (`J J^T` singular, or a singular KKT matrix with a nondegenerate
        reduced Hessian, which leaves only `J` to blame), the constraints are
        `redundant_constraints` when `|dx| <= L / 10` (the constraint surface is
        within reach: `G = 0` holds there but its gradient vanishes or is dependent)
        and `infeasible_constraints` otherwise, or when the linearised constraints
        are inconsistent (the part of `G` along the null space of `J^T` is not
        zero). `L = max(|x|, |x0|, |x - x0|)` is the length scale of the problem.
        A line search that fails where `|dx| > L` is reported as
        `infeasible_constraints` too. These tests are heuristics, and a near-miss
        (constraints that almost hold) can be reported as redundant rather than
        infeasible; either way the solve is not successful.
    """

    x: X
    multipliers: Float[Array, " k"]
    value: Scalar
    kind: EXTREMUM
    result: RESULTS
    stats: dict[str, Any]
    # Defaults (empty) so that an `Extremum` built without inequalities, as before
    # they existed, still constructs.
    inequality_multipliers: Float[Array, " m"] = eqx.field(
        default_factory=lambda: jnp.zeros((0,))
    )
    active: Bool[Array, " m"] = eqx.field(default_factory=lambda: jnp.zeros((0,), bool))


def _flat_constraints(constraints, unravel):
    def flat(x, args):
        out = constraints(unravel(x), args)
        return jnp.atleast_1d(out)

    return flat


def _check_structure(objective, constraints, x_flat, args, multipliers0):
    f_struct = jax.eval_shape(objective, x_flat, args)
    if not (isinstance(f_struct, jax.ShapeDtypeStruct) and f_struct.shape == ()):
        shape = getattr(f_struct, "shape", type(f_struct).__name__)
        raise ValueError(
            f"The objective F(x, args) must return a scalar, but it returned {shape}. "
            "Extremize a scalar function, for example the sum or the norm of a vector."
        )
    if not jnp.issubdtype(f_struct.dtype, jnp.floating):
        raise ValueError(
            f"The objective F(x, args) must return a floating-point scalar, got dtype "
            f"{f_struct.dtype}."
        )
    n = x_flat.size
    if constraints is None:
        k = 0
    else:
        g_struct = jax.eval_shape(constraints, x_flat, args)
        if not isinstance(g_struct, jax.ShapeDtypeStruct) or g_struct.ndim != 1:
            shape = getattr(g_struct, "shape", type(g_struct).__name__)
            raise ValueError(
                "The constraints G(x, args) must return an array of shape (k,) (or a "
                f"scalar for a single constraint), but returned {shape}. Stack the "
                "constraints into one vector, e.g. `jnp.stack([g1, g2])`."
            )
        k = g_struct.shape[0]
        if k == 0:
            raise ValueError(
                "The constraints returned an empty array: pass `constraints=None` for "
                "an unconstrained extremization."
            )
        if k > n:
            raise ValueError(
                f"There are more constraints (k = {k}) than unknowns (n = {n}): at "
                "most n of them can be independent, so the multipliers are not "
                "determined. Remove the redundant constraints."
            )
    if multipliers0 is not None and jnp.shape(multipliers0) != (k,):
        raise ValueError(
            f"`multipliers0` must have shape (k,) = ({k},), one per constraint, got "
            f"{jnp.shape(multipliers0)}."
        )
    return n, k


def _value_and_jacobian(constraints, x, args):
    """`G(x)` and `J = dG/dx` (one forward pass, one reverse pass per constraint)."""
    g, vjp = jax.vjp(lambda x_: constraints(x_, args), x)
    (jac,) = jax.vmap(vjp)(jnp.eye(g.shape[0], dtype=g.dtype))
    return g, jac


def _constraint_distance(g, jac):
    """`(distance, inconsistent)` of the linearised constraints `G + J dx = 0`.

    `distance = |dx|` for the Gauss-Newton correction `dx = -J^T (J J^T + mu I)^-1 G`
    (`mu = 1000 k eps max|J J^T|`, far below any meaningful singular value): the
    distance to the constraint surface that the linearisation predicts.
    `inconsistent`: more than half of `G` lies along directions in which `J` has no
    rank (to that `mu`), so that no step of any size satisfies the linearised
    constraints (e.g. two parallel constraints with different values, or `J = 0`
    with `G != 0`).
    """
    k = g.shape[0]
    dtype = g.dtype
    gram = jac @ jac.T
    mu = 1000 * k * jnp.finfo(dtype).eps * jnp.max(jnp.abs(gram))
    mu = mu + jnp.finfo(dtype).tiny
    factors = dense_factor(gram + mu * jnp.eye(k, dtype=dtype), unroll_max=12)
    y = dense_solve(factors, g, unroll_max=12)
    distance = jnp.linalg.norm(jac.T @ y)
    left = jnp.linalg.norm(g - gram @ y)
    # NaN (from J = 0, G != 0: y overflows) counts as inconsistent.
    inconsistent = jnp.invert(left <= 0.5 * jnp.linalg.norm(g))
    distance = jnp.where(jnp.isfinite(distance), distance, jnp.inf)
    return distance, inconsistent


@full_precision
def extremize(
    objective: ObjectiveFn,
    x0: X,
    args: Args = None,
    *,
    constraints: ConstraintFn | None = None,
    inequalities: ConstraintFn | None = None,
    lower: PyTree[ArrayLike] | None = None,
    upper: PyTree[ArrayLike] | None = None,
    sense: Literal["minimize", "maximize"] | None = None,
    solver: AbstractKKTSolver | None = None,
    multipliers0: Float[Array, " k"] | None = None,
    max_steps: int = 256,
    throw: bool = True,
) -> Extremum:
    """Find a stationary point of `F(x)` subject to `G(x) = 0` (Lagrange multipliers).

    Solves the `n + k` equations

        grad F(x) + sum_j lambda_j grad G_j(x) = 0,    G_j(x) = 0,

    i.e. freely extremizes `F* = F + lambda . G` over `x` and `lambda`. Gradients,
    Hessians and constraint Jacobians come from autodiff.

    **Arguments:**

    - `objective`: `F(x, args) -> scalar`.
    - `x0`: the starting point: an array of shape `(n,)` or any pytree of arrays
        (a list of numbers is the array it spells). Every leaf is an unknown and must
        be real floating-point: an integer, boolean, complex or text leaf is refused,
        named by its path (fixed values belong in `args`).
    - `args`: parameters, passed last to `F` and `G`. Python numbers in it are turned
        into arrays, so changing them never recompiles; anything that must stay static
        (text, a shape) belongs in the closure of `F`; text in `args` is refused.
    - `constraints`: `G(x, args) -> (k,)` (a scalar means one constraint), or `None`.
    - `inequalities`: `H(x, args) -> (m,)` (a scalar means one inequality), the
        constraints `H_i(x) <= 0`, or `None`.
    - `lower`, `upper`: bounds `lower <= x <= upper`, or `None`: a scalar (for every
        entry of `x`), an array that broadcasts to `x0`, or a pytree with the
        structure of `x0` whose leaves broadcast to its leaves. An infinite entry
        (`-inf` in `lower`, `inf` in `upper`) means no bound. They are folded into
        `H` (see `inequality_multipliers` below) and are differentiable like `args`.
    - `sense`: `"minimize"` or `"maximize"`; required with inequalities or bounds
        (it fixes the sign of `mu`, see below). Without them it is optional: the
        equality-constrained solve is unchanged, and a successful point whose `kind`
        contradicts `sense` is reported as `RESULTS.not_an_optimum`.
    - `solver`: an [`constrained_jax.AbstractKKTSolver`][], or `None` (default):
        `Newton(rtol=1e-10, atol=1e-10)` with the linear solver chosen by the
        memory the KKT matrix of `n + k` rows takes: [`constrained_jax.DenseLU`][]
        while it takes at most 8 MiB (`n + k <= 1024` in float64), preconditioned
        matrix-free [`constrained_jax.MINRES`][] above, falling back on `DenseLU`
        where MINRES does not converge and the matrix takes at most 128 MiB
        (`constrained_jax._extremize.default_solver`). An explicitly dense solver
        above 4,096 unknowns is warned about. With inequalities the default is
        [`constrained_jax.SemismoothNewton`][]`()`, and a solver given is replaced
        by its `complementarity_solver()` (a `Newton` by the `SemismoothNewton` of
        its tolerances and linear solver).
    - `multipliers0`: a starting guess for `lambda`; by default the least-squares
        multipliers at `x0`, `-(J J^T)^{-1} J grad F`.
    - `max_steps`: the most Newton steps.
    - `throw`: raise on failure if `True`; otherwise report it in `result`.

    **Returns:**

    An [`constrained_jax.Extremum`][].

    Differentiable with respect to `args` (and to arrays `F`, `G` close over) by the
    implicit function theorem on the KKT system: the backward pass costs one more
    linear solve with the KKT matrix, however many Newton steps were taken. The
    derivative of a failed solve (`result` not successful, or that linear solve
    failing) is NaN, never an error, also with `throw=False` inside `jax.grad`: an
    outer loop such as [`constrained_jax.fit`][] then stops with `RESULTS.nonfinite`.
    Composes with `jax.jit` and `jax.vmap`.

    !!! note

        Which stationary point is found depends on `x0`: Newton's method on the KKT
        system converges to nearby minima, maxima and saddles alike. Check `kind`.

    **Inequalities.** With `inequalities`, `lower` or `upper` the KKT conditions are

        grad F + sum_j lambda_j grad G_j + sum_i mu_i grad H_i = 0,    G = 0,
        H <= 0,    s mu >= 0,    mu_i H_i = 0,

    with `s = +1` for `sense="minimize"` and `s = -1` for `"maximize"`: the *same*
    stationarity formula in both senses, so `mu >= 0` when minimizing and `mu <= 0`
    when maximizing. The envelope theorem then reads `dF*/dp = dF/dp + lambda .
    dG/dp + mu . dH/dp` in both senses; for an upper bound `H = x - b`,
    `dF*/db = -mu`, for a lower bound `H = b - x`, `dF*/db = +mu`.

    The rows of `H` (and of `sol.inequality_multipliers`, `sol.active`) are the
    user's `H` (`m_H` rows), then `n` rows `lower - x` if `lower` is given, then
    `n` rows `x - upper` if `upper` is given (`n` the size of the flattened `x`, in
    the order of `jax.flatten_util.ravel_pytree(x0)`). An infinite bound keeps its
    row, with `H = -1` (never active) and `mu = 0`, so that the shapes do not depend
    on the values (bounds may be traced, batched and differentiated).

    The complementarity conditions are written with the Fischer-Burmeister function
    `phi(s mu_i, -H_i) = 0`, `phi(a, b) = a + b - sqrt(a^2 + b^2)`, and the square
    system in `(x, lambda, mu)` is solved by a semismooth Newton method (with
    `inequalities`, a dense Jacobian by forward-mode autodiff, LU-factored; with
    bounds alone, whose rows are diagonal, a reduced system of `n + k` unknowns,
    LU-factored up to `n + k = 512` in float64 and solved by MINRES above, so that
    bounds cost about what equality constraints do), damped by the natural monotonicity
    test of [`constrained_jax.Newton`][], with a Levenberg-Marquardt step and an Armijo
    line search on `|r|^2 / 2` where the Newton step fails, each step regularised by
    a proximal term (see [`constrained_jax.SemismoothNewton`][]), from any start,
    feasible or not (with `mu0 = 0`). `solver` is `None`,
    a `SemismoothNewton` or a [`constrained_jax.Newton`][]: its `rtol`, `atol` give
    the stopping test (as for equalities), its `linear_solver` the backward pass.
    After the iteration the KKT conditions are checked, relative to
    `max(1, |mu|)` for `mu`, `max(1, |x|) |grad H_i|` for `H_i`, `max(1, |grad F|)` for
    stationarity and `max(1, |x|)` for `G`, to `tol = sqrt(max(rtol, atol, 100 eps))`
    (`sol.stats["kkt_tolerance"]`, `1e-5` by default; the violation found is
    `sol.stats["kkt_violation"]`): a point that fails them is never successful
    (`RESULTS.infeasible_inequalities` where some `H_i > 0`,
    `RESULTS.kkt_conditions_violated` otherwise). `sol.active` marks the inequalities
    whose `H_i` is the zero of the complementary pair (`|H_i|` within `max(rtol, atol)`
    relative, or smaller than `|mu_i|` in those units); `mu` is exactly zero on the
    others.

    `kind` is judged on the tangent space of `G` and of the *strictly* active
    inequalities (active with `|mu_i|` above `max(rtol, atol)` relative). Weakly
    active ones (`H_i = 0`, `mu_i = 0`) make that space larger than the critical
    cone, so an indefinite answer is then reported as `EXTREMUM.degenerate`
    (inconclusive). When the active constraints leave no tangent space, `kind` is
    `EXTREMUM.isolated` (a vertex: first-order conditions with the sign of `mu`
    suffice). A successful point whose `kind` contradicts `sense` (a maximum or a
    saddle when minimizing, a minimum or a saddle when maximizing) is
    `RESULTS.not_an_optimum`, and so is one where the Hessian of `F*` has curvature
    of the wrong sign for `sense` on the subspace that keeps every active
    constraint (strictly or weakly) at zero, which lies in the critical cone with
    each direction's negative (the second-order necessary condition fails).
    Newton finds a nearby KKT point, not the best one: minimizing `-x^2` on
    `[-1, 1]` descends to the nearer bound `x = +-1`, except from the KKT point
    `x = 0` itself (reported `not_an_optimum`). A failed solve whose iterates ran
    off (`|x - x0| > 1000 max(1, |x0|)`) while `F` kept improving is
    `RESULTS.unbounded_objective`; one stopped by `max_steps` is
    `RESULTS.nonlinear_max_steps_reached` unless the iterate is stuck at a local
    minimum of the violation (checked by a few Levenberg-Marquardt steps on it),
    which is `RESULTS.infeasible_inequalities`.

    Derivatives with respect to `args`, `lower`, `upper` (and arrays `F`, `G`, `H`
    close over) come from the implicit function theorem on the KKT system with the
    strictly active inequalities as equalities and the others held at `mu_i = 0`:
    exact where strict complementarity holds. At a weakly active inequality the
    derivative is one-sided: that of the problem without it (correct for
    perturbations that make it inactive, wrong for those that make it bind). Where
    the strictly active constraints are dependent (a degenerate vertex, with
    multipliers that are not unique) that reduced system is singular and the
    derivatives are NaN.
    """
    check_signature(objective, "The objective", "F(x, args)")
    if constraints is not None:
        check_signature(constraints, "`constraints`", "G(x, args)")
    if inequalities is not None:
        check_signature(inequalities, "`inequalities`", "H(x, args)")
    max_steps = check_max_steps(max_steps)
    args = as_traced_args(args)
    x0 = lists_as_arrays(x0)
    check_unknowns(x0, "x0")
    x0 = jtu.tree_map(inexact_asarray, x0)
    with_inequalities = not (inequalities is None and lower is None and upper is None)
    if sense not in (None, "minimize", "maximize"):
        raise ValueError(
            f'`sense` must be "minimize", "maximize" or None, got {sense!r}.'
        )
    if with_inequalities and sense is None:
        raise ValueError(
            "With inequalities (`inequalities`, `lower` or `upper`) the problem is an "
            'optimization: pass `sense="minimize"` or `sense="maximize"`. It decides '
            "the sign of the inequality multipliers (mu >= 0 to minimize, mu <= 0 to "
            "maximize), so it has no default."
        )
    if inequalities is not None and not callable(inequalities):
        raise ValueError(
            "`inequalities` must be a callable H(x, args) -> (m,) or None."
        )
    lower = None if lower is None else jtu.tree_map(jnp.asarray, lists_as_arrays(lower))
    upper = None if upper is None else jtu.tree_map(jnp.asarray, lists_as_arrays(upper))
    check_concrete_bounds(lower, upper)
    sol = _extremize(
        objective,
        x0,
        args,
        constraints,
        inequalities,
        lower,
        upper,
        sense,
        solver,
        multipliers0,
        max_steps,
    )
    return raise_if_failed(sol, throw)


def _check_callables(objective, constraints, x0):
    if not callable(objective):
        raise ValueError("`objective` must be a callable F(x, args) -> scalar.")
    if constraints is not None and not callable(constraints):
        raise ValueError("`constraints` must be a callable G(x, args) -> (k,) or None.")
    leaves = jtu.tree_leaves(x0)
    if not leaves:
        raise ValueError("`x0` has no arrays in it: pass the starting point.")
    for leaf in leaves:
        if not jnp.issubdtype(jnp.result_type(leaf), jnp.number):
            raise ValueError(
                f"`x0` must hold numbers, got dtype {jnp.result_type(leaf)}."
            )


@eqx.filter_jit
def _extremize(
    objective,
    x0,
    args,
    constraints,
    inequalities,
    lower,
    upper,
    sense,
    solver,
    multipliers0,
    max_steps,
):
    warn_near_mapping_limit()  # (at trace time: before a compilation)
    # Prologue: argument checks, the flat problem, defaults, the start.
    with_inequalities = not (inequalities is None and lower is None and upper is None)
    if with_inequalities and not isinstance(solver, (AbstractKKTSolver, type(None))):
        raise ValueError(
            "With inequalities `extremize` runs a semismooth Newton method on a dense "
            "Jacobian: pass `solver=None`, `cjax.SemismoothNewton(rtol=..., atol=..., "
            "linear_solver=...)` or a `cjax.Newton` (whose tolerances and linear "
            f"solver it takes), got {type(solver).__name__}."
        )
    check_kkt_solver(Newton() if solver is None else solver, max_steps)
    _check_callables(objective, constraints, x0)
    x_flat, unravel = jfu.ravel_pytree(x0)
    dtype = x_flat.dtype
    objective_flat = lambda x, a: objective(unravel(x), a)
    constraints_flat = (
        None if constraints is None else _flat_constraints(constraints, unravel)
    )
    n, k = _check_structure(
        objective_flat, constraints_flat, x_flat, args, multipliers0
    )
    m, m_user, inequalities_flat = 0, 0, None
    if with_inequalities:
        m_user = check_inequalities(inequalities, x_flat, unravel, args)
        lower = flat_bound(lower, x0, "lower", dtype)
        upper = flat_bound(upper, x0, "upper", dtype)
        m = m_user + (0 if lower is None else n) + (0 if upper is None else n)
        inequalities_flat = flat_inequalities(
            inequalities, unravel, m_user, lower, upper
        )
    # Bounds alone: the Jacobian of H is diagonal, and never formed.
    bounds = bool(m) and not m_user
    solver = _solver_or_default(solver, n, k, m, dtype, bounds)
    # The bounds travel with `args` so that they are differentiated like it.
    aug = (args, lower, upper)
    problem = lagrangian_problem(
        _undefined_is_nan(lambda x, a: objective_flat(x, a[0])),
        None if constraints_flat is None else lambda x, a: constraints_flat(x, a[0]),
        inequalities_flat,
        x_flat,
        aug,
        sign=1.0 if sense == "minimize" else -1.0,
        bounds=bounds,
    )
    start_ok = all_finite((x_flat, args, multipliers0)) & _bounds_ok(lower, upper)
    x_safe = jnp.where(start_ok, x_flat, 0.0)
    f0, lam0, g0, jac0 = _start(
        objective_flat, constraints_flat, x_safe, args, multipliers0, m
    )
    # F(x0) itself (Newton uses only its derivatives, whose finiteness the first
    # step checks): NaN there means x0 is outside the domain of F.
    start_defined = jnp.isfinite(f0)

    z0 = jnp.concatenate([x_flat, lam0, jnp.zeros((m,), dtype)])
    sol = kkt_solve(problem, solver, z0, aug, max_steps, start_ok & start_defined)

    # Epilogue: the statuses, the second-order classification, the outputs.
    result = RESULTS.where(
        start_ok & jnp.invert(start_defined), RESULTS.nonfinite_objective, sol.result
    )
    if m:
        stuck = _violation_stationary(
            problem, constraints_flat, jax.lax.stop_gradient(sol.z)[:n], args, aug
        )
        result = _complementarity_statuses(result, sol, stuck)
    xs = jax.lax.stop_gradient(sol.z)[:n]
    kind, extremes, jac, factors, wrong_curvature = _second_order(
        problem, sol, constraints_flat, args, aug, dtype
    )
    if k and not m:
        result = _constraint_statuses(
            result, kind, sol.residual[n:], jac, factors, g0, jac0, xs, x_flat
        )
    value = objective_flat(xs, args)
    if m:
        result = _unbounded_status(result, value, f0, xs, x_flat, sense)
    result = RESULTS.where(
        (result == RESULTS.successful) & jnp.invert(jnp.isfinite(value)),
        RESULTS.nonfinite_objective,
        result,
    )
    result = _check_sense(result, kind, sense, jnp.array(False))
    result = RESULTS.where(
        (result == RESULTS.successful) & wrong_curvature,
        RESULTS.not_an_optimum,
        result,
    )
    failed = result != RESULTS.successful
    kind = EXTREMUM.where(failed, EXTREMUM.unknown, kind)
    # The derivative of a failed solve is NaN (also for failures decided above, after
    # the implicit function theorem).
    x, lam, mu = problem.split(nan_tangent_where(sol.z, failed))
    # Inactive: mu_i = 0 exactly (the iteration leaves round-off there; its
    # derivative is zero by the rewrite anyway).
    mu = mu * sol.active.astype(dtype)
    return Extremum(
        x=unravel(x),
        multipliers=lam,
        value=objective_flat(x, args),
        kind=kind,
        result=result,
        stats={**sol.stats, "reduced_hessian_eigenvalues": extremes},
        inequality_multipliers=mu,
        active=sol.active,
    )


def _undefined_is_nan(objective):
    """`F`, with its derivatives NaN wherever `F` itself is NaN or inf.

    Newton sees only the derivatives of `F`, which may be finite where `F` is not
    (`-log(1.5 - x)` has the gradient `1 / (1.5 - x)` at `x = 2`): so a step out of
    the domain of `F` would be taken, and the solve would end where `F` is undefined.
    Multiplying `F` by a constant (to autodiff) that is NaN there makes the KKT
    residual NaN at such a point, and the line search backs off from it as from any
    other undefined point. Where `F` is finite the derivatives are unchanged."""

    def checked(x, args):
        f = objective(x, args)
        return f * jax.lax.stop_gradient(jnp.where(jnp.isfinite(f), 1.0, jnp.nan))

    return checked


def _bounds_ok(lower, upper) -> Bool[Array, ""]:
    """No NaN in the bounds, and no `lower = inf` or `upper = -inf`."""
    ok = jnp.array(True)
    if lower is not None:
        ok = ok & jnp.all(jnp.invert(jnp.isnan(lower)) & (lower < jnp.inf))
    if upper is not None:
        ok = ok & jnp.all(jnp.invert(jnp.isnan(upper)) & (upper > -jnp.inf))
    return ok


def _start(objective, constraints, x, args, multipliers0, m: int):
    """`(F(x), lambda0, G(x), J(x))` at the start `x` (`G`, `J` are `None` without
    constraints): `lambda0` is `multipliers0`, by default the least-squares
    multipliers `-(J J^T)^{-1} J grad F`. With inequalities a non-finite default
    (dependent constraints at `x`) is replaced by zero: the semismooth iteration
    starts from anywhere."""
    if constraints is None:
        return objective(x, args), jnp.zeros((0,), x.dtype), None, None
    g, jac = _value_and_jacobian(constraints, x, args)
    if multipliers0 is not None:
        return objective(x, args), jnp.asarray(multipliers0, x.dtype), g, jac
    f, grad = jax.value_and_grad(objective)(x, args)
    lam = least_squares_multipliers(grad, jac, gram_factors(jac))
    if m:
        lam = jnp.where(jnp.all(jnp.isfinite(lam)), lam, 0.0)
    return f, lam, g, jac


def _violation_stationary(
    problem, constraints, x, args, aug, num_steps: int = 20
) -> Bool[Array, ""]:
    """Whether the violation `v = (|max(H, 0)|^2 + |G|^2) / 2` stays positive and
    stationary when minimized from `x`: `num_steps` Levenberg-Marquardt steps on
    `q = (max(H, 0), G)` (the feasibility restoration of SQP methods), after which
    `v > 0` and its gradient `A_+^T H_+ + J^T G` is below `0.01 (sum_i H_i+
    |grad H_i| + sum_j |G_j| |grad G_j|)`, the size its terms would have if they did
    not cancel. An iteration that stopped where `H > 0` is then stuck at a local
    minimum of the violation (the mark of an empty feasible set); otherwise a point
    with less violation is within reach, and it ran out of steps."""

    def parts(x_):
        h = jnp.maximum(problem.inequalities(x_, aug), 0.0)
        if constraints is None:
            return h
        return jnp.concatenate([h, constraints(x_, args)])

    if problem.bounds:
        return _bound_violation_stationary(problem, parts, x, aug, num_steps)

    def measure(x_):
        values = parts(x_)
        rows = jax.jacrev(parts)(x_)
        gradient = rows.T @ values
        size = jnp.sum(jnp.abs(values) * jnp.linalg.norm(rows, axis=1))
        return values, rows, gradient, size

    def restore(_, x_):
        values, rows, gradient, _ = measure(x_)
        gram = rows.T @ rows
        shift = 1e-8 * jnp.maximum(jnp.max(jnp.abs(jnp.diag(gram))), 1.0)
        dx = conjugate_gradient(gram, shift, -gradient)
        x_new = x_ + dx
        better = jnp.sum(parts(x_new) ** 2) < jnp.sum(values**2)
        return jnp.where(better & jnp.all(jnp.isfinite(x_new)), x_new, x_)

    x = jax.lax.fori_loop(0, num_steps, restore, x)
    values, _, gradient, size = measure(x)
    return (jnp.linalg.norm(gradient) <= 0.01 * size) & jnp.any(values != 0)


def _bound_violation_stationary(problem, parts, x, aug, num_steps: int):
    """`_violation_stationary` for bounds (and `G`) without forming `dH/dx`: the
    rows of the bounds are `+-e_i`, so the Gauss-Newton matrix is diagonal plus
    `J^T J` and its products come from autodiff (conjugate gradients, which need
    at most about `k + 3` steps on it)."""
    n, m = problem.n, problem.m
    bound_rows = lambda x_: jnp.abs(problem.bound_derivatives(x_, aug)).ravel()

    def measure(x_):
        values, vjp = jax.vjp(parts, x_)
        (gradient,) = vjp(values)
        g_rows = jax.jacrev(lambda y: parts(y)[m:])(x_)  # (k, n)
        row_norms = jnp.concatenate([bound_rows(x_), jnp.linalg.norm(g_rows, axis=1)])
        size = jnp.sum(jnp.abs(values) * row_norms)
        return values, vjp, g_rows, gradient, size

    def restore(_, x_):
        values, vjp, g_rows, gradient, _ = measure(x_)
        _, jvp = jax.linearize(parts, x_)
        diag = jnp.sum(
            jnp.square(jvp(jnp.ones_like(x_))[:m].reshape(m // n, n)), axis=0
        )
        diag = diag + jnp.sum(jnp.square(g_rows), axis=0)
        shift = 1e-8 * jnp.maximum(jnp.max(diag), 1.0)
        apply = lambda v: vjp(jvp(v))[0]
        dx = conjugate_gradient_mv(apply, shift, -gradient, min(n, 64))
        x_new = x_ + dx
        better = jnp.sum(parts(x_new) ** 2) < jnp.sum(values**2)
        return jnp.where(better & jnp.all(jnp.isfinite(x_new)), x_new, x_)

    x = jax.lax.fori_loop(0, num_steps, restore, x)
    values, _, _, gradient, size = measure(x)
    return (jnp.linalg.norm(gradient) <= 0.01 * size) & jnp.any(values != 0)


def _complementarity_statuses(result: RESULTS, sol: KKTSolution, stuck) -> RESULTS:
    """A stop where `H > 0` that the iteration could not leave is infeasibility; a
    stop where the step budget ran out is `nonlinear_max_steps_reached` unless the
    iterate is `stuck` at a stationary point of the violation (the iterate of a
    feasible problem may still violate `H` when the budget runs out); a "converged"
    point where the KKT conditions fail is never a success."""
    tol = sol.stats["kkt_tolerance"]
    infeasible = sol.infeasibility > tol
    result = RESULTS.where(
        (result != RESULTS.successful)
        & (result != RESULTS.invalid_input)
        & (result != RESULTS.nonfinite_objective)
        & ((result != RESULTS.nonlinear_max_steps_reached) | stuck)
        & infeasible,
        RESULTS.infeasible_inequalities,
        result,
    )
    return RESULTS.where(
        (result == RESULTS.successful) & (sol.stats["kkt_violation"] > tol),
        RESULTS.where(
            infeasible,
            RESULTS.infeasible_inequalities,
            RESULTS.kkt_conditions_violated,
        ),
        result,
    )


def _unbounded_status(result, value, f0, x, x0, sense) -> RESULTS:
    """`RESULTS.unbounded_objective` for a failed solve whose iterates ran off
    (`|x - x0| > 1000 max(1, |x0|)`, or overflowed) while `F` improved in the
    direction of `sense`: the mark of an objective with no optimum on the feasible
    set (maximizing a convex function), not of an infeasible or badly started
    problem."""
    sign = 1.0 if sense == "minimize" else -1.0
    distance = jnp.linalg.norm(x - x0)
    ran_off = jnp.invert(distance <= 1000 * jnp.maximum(1.0, jnp.linalg.norm(x0)))
    improved = (sign * (value - f0) < 0) | (sign * value == -jnp.inf)
    return RESULTS.where(
        (result != RESULTS.successful)
        & (result != RESULTS.invalid_input)
        & jnp.isfinite(f0)
        & ran_off
        & improved,
        RESULTS.unbounded_objective,
        result,
    )


def _second_order(problem: KKTProblem, sol: KKTSolution, constraints, args, aug, dtype):
    """`(kind, extremes, J, factors of J J^T)`: the extreme eigenvalues of the Hessian
    of `F*` on the tangent space of `G` (and, with inequalities, of the strictly
    active `H`), and the `EXTREMUM` they make (see the notes of `Extremum`)."""
    n, k, m = problem.n, problem.k, problem.m
    zs = jax.lax.stop_gradient(sol.z)
    xs = zs[:n]
    jac = factors = None
    if m:
        jac_g = None if k == 0 else constraint_jacobian(constraints, xs, args)
        # Two subspaces (below), one batched eigendecomposition and one batched
        # reduced Hessian: one compiled body each.
        which = jnp.stack([sol.strict, sol.active])
        if problem.bounds:
            diag_h = problem.bound_derivatives(xs, aug)
            tangent = lambda w: _bound_tangent(diag_h, w, jac_g, n, dtype)
        else:
            jac_h = jax.jacrev(problem.inequalities)(xs, aug)
            tangent = lambda w: _tangent_basis(jac_h, w, jac_g, n, dtype)
        bases, frees = jax.vmap(tangent)(which)
        free = frees[0]
    elif k:
        jac = constraint_jacobian(constraints, xs, args)
        factors = gram_factors(jac)
        project = tangent_projector(jac, factors)
    else:
        project = lambda v: v

    def grad_star(x_):
        """grad_x F*(x, lambda, mu) at fixed multipliers: the first n equations."""
        return problem.equations(jnp.concatenate([x_, zs[n:]]), aug)[:n]

    hvp = lambda v: jax.jvp(grad_star, (xs,), (v,))[1]
    if m:

        def extremes_on(basis, mask):
            if problem.bounds:
                project = lambda v: _bound_project(basis, v)
            else:
                project = lambda v: basis @ (mask.astype(dtype) * (basis.T @ v))
            return reduced_hessian_extremes(hvp, project, n, k, dtype)

        both = jax.vmap(extremes_on)(bases, frees)
        extremes, (lo, hi) = both[0], both[1]
    else:
        extremes = reduced_hessian_extremes(hvp, project, n, k, dtype)
    kind = _classify(extremes, n, k, dtype)
    if m:
        kind = EXTREMUM.where(jnp.sum(free) == 0, EXTREMUM.isolated, kind)
        # Weakly active inequalities (H_i = 0 with mu_i = 0): the critical cone is
        # smaller than the subspace tested, so only a definite answer is conclusive.
        weakly = jnp.any(sol.active & jnp.invert(sol.strict))
        kind = EXTREMUM.where(
            weakly & (kind == EXTREMUM.saddle), EXTREMUM.degenerate, kind
        )
        # The critical cone contains the subspace on which every active H_i (and G)
        # is held at zero, each direction with its negative: curvature of the wrong
        # sign for `sense` there violates the second-order necessary condition, so
        # the point is no optimum, whatever `kind` (degenerate or not) says.
        free_active = frees[1]
        tol = jnp.sqrt(jnp.finfo(dtype).eps) * jnp.maximum(
            1.0, jnp.maximum(jnp.abs(lo), jnp.abs(hi))
        )
        wrong = (lo < -tol) if problem.sign > 0 else (hi > tol)
        wrong_curvature = wrong & (jnp.sum(free_active) > 0)
    else:
        wrong_curvature = jnp.array(False)
    return kind, extremes, jac, factors, wrong_curvature


def _tangent_basis(jac_h, which, jac_g, n: int, dtype):
    """`(vecs, free)`: the eigenvectors of the Gram matrix of the rows of `G`
    (`jac_g`, or `None`) and the rows `which` of `H` (normalised), and the mask of
    those spanning the common null space of the rows (an eigenvalue counts as zero
    below `1000 n eps` of the largest): the projection onto it is
    `vecs diag(free) vecs^T`."""
    rows = jac_h * which[:, None].astype(dtype)
    if jac_g is not None:
        rows = jnp.concatenate([jac_g, rows])
    norms = jnp.linalg.norm(rows, axis=1, keepdims=True)
    rows = rows / jnp.where(norms > 0, norms, 1.0)
    eigs, vecs = jnp.linalg.eigh(rows.T @ rows)
    eps = jnp.finfo(dtype).eps
    free = eigs <= 1000 * n * eps * jnp.maximum(jnp.max(eigs), 1.0)
    return vecs, free


def _bound_tangent(diag_h, which, jac_g, n: int, dtype):
    """`_tangent_basis` for bounds, whose rows are `+-e_i`: `(basis, free)` with
    `basis = (keep, rows, inverse)` describing the projection onto the vectors that
    vanish on the components held by a bound of `which` and lie in the null space of
    the rows of `G` there (`_bound_project`), and `free` a mask with as many entries
    set as that subspace has dimensions (the same eigenvalue threshold)."""
    held = jnp.any(which.reshape(diag_h.shape) & (diag_h != 0), axis=0)
    keep = jnp.invert(held).astype(dtype)
    eps = jnp.finfo(dtype).eps
    if jac_g is None:
        rows = jnp.zeros((0, n), dtype)
        inverse = jnp.zeros((0, 0), dtype)
        rank = 0
    else:
        rows = jac_g * keep[None, :]
        norms = jnp.linalg.norm(jac_g, axis=1, keepdims=True)
        rows = rows / jnp.where(norms > 0, norms, 1.0)
        eigs, vecs = jnp.linalg.eigh(rows @ rows.T)
        # The largest eigenvalue of the whole Gram matrix is at least 1 wherever a
        # bound holds (its rows are unit vectors).
        top = jnp.maximum(jnp.max(eigs), jnp.where(jnp.any(held), 1.0, 0.0))
        nonzero = eigs > 1000 * n * eps * jnp.maximum(top, 1.0)
        inv = jnp.where(nonzero, 1 / jnp.where(nonzero, eigs, 1.0), 0.0)
        inverse = (vecs * inv[None, :]) @ vecs.T
        rank = jnp.sum(nonzero)
    dimension = jnp.sum(jnp.invert(held)) - rank
    free = jnp.arange(n) < dimension
    return (keep, rows, inverse), free


def _bound_project(basis, v):
    """The orthogonal projection of `v` described by `_bound_tangent`."""
    keep, rows, inverse = basis
    v = keep * v
    return v - rows.T @ (inverse @ (rows @ v))


def _constraint_statuses(result, kind, g, jac, factors, g0, jac0, xs, x0):
    """A failure caused by the equality constraints, decided from `G`, `J` where the
    solve stopped and at the start (see the notes of `Extremum`)."""
    distance, inconsistent = _constraint_distance(g, jac)
    distance0, _ = _constraint_distance(g0, jac0)
    scale = jnp.maximum(
        jnp.maximum(jnp.linalg.norm(xs), jnp.linalg.norm(x0)),
        jnp.linalg.norm(xs - x0),
    )
    singular = result == RESULTS.singular_kkt
    nondegenerate = (
        (kind == EXTREMUM.minimum)
        | (kind == EXTREMUM.maximum)
        | (kind == EXTREMUM.saddle)
        | (kind == EXTREMUM.isolated)
    )
    jacobian_to_blame = factors[2] | (singular & nondegenerate)
    # The surface receded while Newton moved towards a rank-deficient J.
    receded = (distance > 0.1 * scale) & (distance > distance0)
    result = RESULTS.where(
        jacobian_to_blame & (singular | (result == RESULTS.successful)),
        RESULTS.where(
            inconsistent | receded,
            RESULTS.infeasible_constraints,
            RESULTS.redundant_constraints,
        ),
        result,
    )
    return RESULTS.where(
        (result == RESULTS.line_search_failed) & (inconsistent | (distance > scale)),
        RESULTS.infeasible_constraints,
        result,
    )


def _classify(extremes: Float[Array, "2"], n: int, k: int, dtype) -> EXTREMUM:
    if n == k:
        return EXTREMUM.isolated
    lo, hi = extremes[0], extremes[1]
    tol = jnp.sqrt(jnp.finfo(dtype).eps) * jnp.maximum(
        1.0, jnp.maximum(jnp.abs(lo), jnp.abs(hi))
    )
    return EXTREMUM.where(
        lo > tol,
        EXTREMUM.minimum,
        EXTREMUM.where(
            hi < -tol,
            EXTREMUM.maximum,
            EXTREMUM.where(
                (lo < -tol) & (hi > tol), EXTREMUM.saddle, EXTREMUM.degenerate
            ),
        ),
    )


def _check_sense(result, kind, sense, inconclusive):
    """`RESULTS.not_an_optimum` for a successful solve whose second-order test
    contradicts `sense` (a maximum or a saddle when minimizing, a minimum or a saddle
    when maximizing), unless the test is `inconclusive`."""
    if sense is None:
        return result
    wrong = EXTREMUM.maximum if sense == "minimize" else EXTREMUM.minimum
    contradicts = (kind == wrong) | (kind == EXTREMUM.saddle)
    return RESULTS.where(
        (result == RESULTS.successful) & contradicts & jnp.invert(inconclusive),
        RESULTS.not_an_optimum,
        result,
    )
