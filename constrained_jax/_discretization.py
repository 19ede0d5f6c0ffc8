"""Discretizations of a functional `F[y] = int L(y, y', x) dx` (the direct method).

A discretization turns the function `y(x)` into its values `y_i` at nodes
`xL = x_0 < x_1 < ... < x_{N-1} = xR` and every integral into a quadrature rule on
them, so that the functional and its constraints become functions of finitely many
unknowns (the values at the interior nodes; the end values are fixed).

- [`constrained_jax.Chebyshev`][]: one polynomial of degree `N - 1` through the values
  at the Chebyshev-Gauss-Lobatto nodes, integrals by Gauss-Legendre quadrature at
  interior points. The error falls exponentially with `N` for analytic solutions.
- [`constrained_jax.PiecewiseLinear`][]: a uniform mesh of linear elements with the
  midpoint rule on each element. Second order; its KKT matrix is bordered block
  tridiagonal and is solved in time and memory linear in `N`
  ([`constrained_jax.BorderedBlockTridiagonal`][]).

Neither evaluates the integrand at the two ends of the interval, so integrands that
are singular there (a vertical tangent, `1/sqrt(y)` with `y(xL) = 0`) do not make the
discrete functional infinite.
"""

import abc
import functools as ft
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Float

from ._misc import default_float_dtype
from ._solver.block_tridiagonal import (
    BorderedBlockTridiagonal,
    CONSTANT_INDICES_MAX,
)
from ._solver.equilibrated_lu import EquilibratedDenseLU


Interval = tuple[Float[Array, ""], Float[Array, ""]]


class AbstractDiscretization(eqx.Module):
    """How a function `y(x)` on `[xL, xR]` is represented and integrated.

    The unknowns are the values at the `num_nodes - 2` interior nodes. Subclasses
    implement

    - `reference_nodes()`: the nodes on `[-1, 1]` (NumPy, static);
    - `integrate(integrand, values, interval)`: `int integrand(y, y', x) dx` for the
        function with nodal values `values` (shape `(num_nodes, n)`);
    - `node_weights(interval)`: weights `w_i` such that `sum_i w_i f(x_i)` is the
        matching quadrature of `f`;
    - `pointwise_constraint(G, values, interval)`: the discrete holonomic
        constraint, scaled so that its discrete multipliers approximate the
        multiplier *function* `lambda(x_i)` (not `w_i lambda(x_i)`);
    - `interpolate(interval, values, x, derivative, interior)`: the represented
        function (or its derivative) anywhere in the interval, from its values at
        all the nodes or at the interior ones;
    - `make_linear_solver(num_components, num_holonomic, num_integral)`: a Lineax
        solver suited to the structure of the KKT matrix;
    - `order`: the convergence order in `1/N`, or `None` for exponential convergence;
    - `error_estimate(values, interval)`: an a-posteriori estimate of the error of
        the represented function, `max_x |y_h(x) - y(x)|`, from the computed values
        alone (no second solve);
    - `default_rtol`: the relative tolerance on that estimate that
        [`constrained_jax.solve_functional`][] uses when none is given.
    """

    num_nodes: eqx.AbstractVar[int]

    @abc.abstractmethod
    def reference_nodes(self) -> np.ndarray:
        """The nodes mapped to `[-1, 1]`, ascending, both ends included."""

    @abc.abstractmethod
    def integrate(
        self,
        integrand,
        values: Float[Array, "N n"],
        interval: Interval,
        singular: tuple[bool, bool] = (False, False),
    ):
        """`int_{xL}^{xR} integrand(y(x), y'(x), x) dx` for the represented `y`.

        `singular = (left, right)` flags an end where the integrand may have an
        integrable singularity like `1/sqrt(x - xL)` (for instance `1/sqrt(y)` on a
        curve leaving `y = 0` with a finite slope): the quadrature then clusters its
        points there (the substitution `x - xL ~ v^2` makes such an integrand
        smooth in `v`), so that the discrete functional cannot gain by it."""

    @abc.abstractmethod
    def node_weights(self, interval: Interval) -> Float[Array, " N"]:
        """Quadrature weights at the nodes."""

    @abc.abstractmethod
    def pointwise_constraint(
        self, constraint, values: Float[Array, "N n"], interval: Interval
    ) -> Float[Array, "N-2 m"]:
        """The discrete form of `G(y(x), x) = 0` on the whole interval, one row of
        `m` equations per interior node, scaled so that the multiplier of row `i`
        approximates the multiplier function `lambda(x_i)`: the discrete term
        `sum_i mu_i . row_i` approximates `int lambda(x) . G(y(x), x) dx`."""

    @abc.abstractmethod
    def interpolate(
        self,
        interval: Interval,
        values: Float[Array, "M ..."],
        x: Float[Array, ""],
        derivative: int = 0,
        interior: bool = False,
    ) -> Float[Array, "..."]:
        """The represented function (or its `derivative`-th derivative) at `x`.

        `values` are given at all `num_nodes` nodes, or, if `interior`, at the
        `num_nodes - 2` interior ones (pointwise multipliers live there); the
        function is then extrapolated to the ends.
        """

    @abc.abstractmethod
    def make_linear_solver(
        self, num_components: int, num_holonomic: int, num_integral: int
    ) -> lx.AbstractLinearSolver:
        """The default Lineax solver for the KKT matrix of this discretization."""

    @property
    @abc.abstractmethod
    def order(self) -> int | None:
        """Algebraic convergence order, or `None` for exponential convergence."""

    @abc.abstractmethod
    def error_estimate(
        self, values: Float[Array, "N n"], interval: Interval
    ) -> Float[Array, ""]:
        """An estimate of `max_x |y_h(x) - y(x)|` over the interval and the
        components, for the function with nodal `values` (a diagnostic: not
        differentiated)."""

    @property
    @abc.abstractmethod
    def default_rtol(self) -> float:
        """The relative tolerance on `error_estimate` (relative to `max |y|`) used by
        [`constrained_jax.solve_functional`][] when the caller gives none."""

    def roundoff_rtol(self, dtype) -> float:
        """The level, relative to `max |y|`, that `error_estimate` may report for a
        solution resolved to round-off in `dtype` (its round-off plateau).
        [`constrained_jax.solve_functional`][] never sets its default tolerance
        below it, so that more nodes never turn a resolved solution into a refusal.
        By default `0`: an estimate whose round-off stays below `default_rtol`."""
        del dtype
        return 0.0

    def start_parameter(self, interval: Interval) -> Float[Array, " N"]:
        """`s` in `[0, 1]` at the nodes: the variable in which the default start of
        [`constrained_jax.solve_functional`][] is a straight line,
        `y = yL + s (yR - yL)`. By default the position, `(x - xL) / (xR - xL)`."""
        x = self.nodes(interval)
        return (x - x[0]) / (x[-1] - x[0])

    def nodes(self, interval: Interval) -> Float[Array, " N"]:
        """The nodes on `[xL, xR]`: sorted, and inside it also after rounding (the
        last node of `xL + (xR - xL) * 1` is `xR + 1 ULP` for some ends, e.g.
        `(-1.95, 1.38)`: clipped to `xR`)."""
        xl, xr = interval
        t = jnp.asarray(self.reference_nodes(), xl.dtype)
        return jnp.clip(xl + (xr - xl) * (t + 1) / 2, xl, xr)

    def tabulate(
        self, singular_ends: tuple[tuple[bool, bool], ...] = ((False, False),)
    ) -> "AbstractDiscretization":
        """A copy that holds, as JAX arrays, the tables (interpolation and
        differentiation matrices) its methods would otherwise build at every call;
        `singular_ends` lists the `singular` flags `integrate` will be called with.

        [`constrained_jax.solve_functional`][] calls it once at the start of the
        compiled solve: the tables are then computed once per solve, at run time, and
        reach every evaluation of the functional as arguments, never as constants
        baked into the program. By default there is nothing to tabulate."""
        del singular_ends
        return self


_END_POINTS = 8  # Gauss points on an end element flagged singular (PiecewiseLinear).


def _cluster(tq, wq, singular):
    """Gauss-Legendre points and weights on `[-1, 1]` moved by the substitution
    `s = v^2` (`s = (t + 1)/2`) towards each flagged end (`s = v^2 / (v^2 + (1 -
    v)^2)` for both): an integrand like `1/sqrt(s)` becomes smooth in `v`, and a
    smooth one stays smooth. The points stay inside the interval."""
    left, right = singular
    if not (left or right):
        return tq, wq
    v = (tq + 1) / 2
    if left and right:
        den = v**2 + (1 - v) ** 2
        s, ds = v**2 / den, 2 * v * (1 - v) / den**2
    elif left:
        s, ds = v**2, 2 * v
    else:
        s, ds = 1 - (1 - v) ** 2, 2 * (1 - v)
    return 2 * s - 1, wq * ds


def _check_num_nodes(cls_name: str, num_nodes, minimum: int):
    if (
        not isinstance(num_nodes, int)
        or isinstance(num_nodes, bool)
        or num_nodes < minimum
    ):
        raise ValueError(
            f"`{cls_name}(num_nodes)` needs an int num_nodes >= {minimum} (the two "
            "ends plus at least one interior node carrying an unknown), got "
            f"{num_nodes!r}."
        )


@ft.lru_cache(maxsize=64)
def _gauss_legendre(num: int, singular: tuple[bool, bool]):
    """Gauss-Legendre points and weights on `[-1, 1]` (NumPy, read-only, cached:
    NumPy finds them by an eigenvalue problem of size `num`), clustered towards the
    flagged ends (`_cluster`)."""
    tq, wq = _cluster(*np.polynomial.legendre.leggauss(num), singular)
    tq.flags.writeable = False
    wq.flags.writeable = False
    return tq, wq


def barycentric_weights(nodes: np.ndarray) -> np.ndarray:
    """`w_j = 1 / prod_{k != j} (x_j - x_k)`, rescaled to max 1 (float64, NumPy)."""
    diff = nodes[:, None] - nodes[None, :]
    np.fill_diagonal(diff, 1.0)
    # Products of many factors under- or overflow: work with logs and signs.
    log_w = -np.sum(np.log(np.abs(diff)), axis=1)
    sign = np.prod(np.sign(diff), axis=1)
    return sign * np.exp(log_w - log_w.max())


# The matrices below are built with jnp operations from the nodes (vectors), inside
# the traced program: an `(M, N)` matrix is then computed at run time, not embedded
# in the program as a constant (`jnp.asarray` of a NumPy matrix under `jit` is one).
# They are built in the default float dtype (float64 with `jax_enable_x64`) and
# cast to the dtype of the values where used.


def _vector(array: np.ndarray) -> Float[Array, " N"]:
    return jnp.asarray(array, default_float_dtype())


# Up to this many nodes the tables are NumPy constants, as small as the program around
# them (building small tables in the program makes a solve slower); above, they are
# built in the program (large tables as constants would be gigabytes of program at
# their many call sites).
CONSTANT_TABLES_MAX = 128


def _tables_in_numpy(size: int) -> bool:
    """Whether the tables through `size` nodes are built by NumPy in float64 at trace
    time and rounded: small tables (`size <= CONSTANT_TABLES_MAX`), and every table
    of a float32 run (built in float32 arithmetic the differentiation matrix loses
    about `N^2 eps`, enough to stall Newton on the sphere geodesic). Otherwise JAX
    builds them inside the program: no size-`N^2` constants."""
    return size <= CONSTANT_TABLES_MAX or default_float_dtype() != np.float64


def _as_table(x) -> Array:
    return jnp.asarray(x, default_float_dtype())


def _matmul(a, b) -> Array:
    """A product of tables at full precision (never TF32 or bfloat16 passes)."""
    if isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
        return a @ b
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def _table_key(singular) -> str:
    """The key of the tables for the quadrature clustered as in `singular`."""
    return "quadrature_" + "".join("1" if flag else "0" for flag in singular) + "_"


def _differentiation_matrix(xp, nodes, weights):
    nodes, weights = xp.asarray(nodes), xp.asarray(weights)
    diagonal = xp.eye(nodes.shape[0], dtype=bool)
    diff = xp.where(diagonal, 1.0, nodes[:, None] - nodes[None, :])
    d = xp.where(diagonal, 0.0, (weights[None, :] / weights[:, None]) / diff)
    return xp.where(diagonal, -xp.sum(d, axis=1, keepdims=True), d)


def _interpolation_matrix(xp, nodes, weights, points):
    nodes, weights, points = xp.asarray(nodes), xp.asarray(weights), xp.asarray(points)
    diff = points[:, None] - nodes[None, :]
    exact = diff == 0
    terms = weights[None, :] / xp.where(exact, 1.0, diff)
    p = terms / xp.sum(terms, axis=1, keepdims=True)
    hit = xp.any(exact, axis=1, keepdims=True)
    return xp.where(hit, exact.astype(p.dtype), p)


def _table_inputs(*arrays):
    """`(module, arrays)`: NumPy float64 arrays for a float32 run, JAX arrays of the
    default float dtype otherwise (see `_tables_in_numpy`)."""
    if _tables_in_numpy(len(arrays[0])):
        return np, [np.asarray(a, np.float64) for a in arrays]
    return jnp, [_vector(a) for a in arrays]


def differentiation_matrix(nodes: np.ndarray, weights: np.ndarray) -> Array:
    """`D_ij = l_j'(x_i)` for the Lagrange basis through `nodes`."""
    xp, arrays = _table_inputs(nodes, weights)
    return _as_table(_differentiation_matrix(xp, *arrays))


def interpolation_matrix(
    nodes: np.ndarray, weights: np.ndarray, points: np.ndarray
) -> Array:
    """`P_qj = l_j(t_q)`: values at `points` of the Lagrange basis (barycentric)."""
    xp, arrays = _table_inputs(nodes, weights, points)
    return _as_table(_interpolation_matrix(xp, *arrays))


def _value_and_derivative_tables(nodes, weights, points):
    """`(P, P D)` at full precision (see `_tables_in_numpy`)."""
    xp, (n, w, pts) = _table_inputs(nodes, weights, points)
    p = _interpolation_matrix(xp, n, w, pts)
    pd = _matmul(p, _differentiation_matrix(xp, n, w))
    return _as_table(p), _as_table(pd)


def _barycentric(nodes, weights, values, x):
    """The polynomial through `(nodes, values)` at `x` (second barycentric formula)."""
    diff = x - nodes
    exact = diff == 0
    safe = jnp.where(exact, 1.0, diff)
    terms = jnp.where(exact, 0.0, weights / safe)
    interp = jnp.tensordot(terms, values, axes=1) / jnp.sum(terms)
    hit = jnp.tensordot(exact.astype(values.dtype), values, axes=1)
    return jnp.where(jnp.any(exact), hit, interp)


class Chebyshev(AbstractDiscretization):
    """Spectral discretization: one polynomial through Chebyshev-Gauss-Lobatto nodes.

    `y` is the polynomial of degree `N - 1` through its values at
    `x_j = (xL + xR)/2 - (xR - xL)/2 cos(pi j / (N - 1))`. Integrals use
    Gauss-Legendre quadrature with `num_quadrature` points (by default `3N/2`,
    rounded up, which integrates a Lagrangian quadratic in `(y, y')` exactly and
    leaves a margin for nonpolynomial ones), so the integrand is never evaluated at
    the ends. Pointwise constraints use the Clenshaw-Curtis weights at the nodes.

    For an analytic solution the error falls like `rho^-N` for some `rho > 1` that
    depends on the distance of the nearest complex singularity of `y` from the
    interval. A solution with a singular derivative at an end (a vertical tangent)
    converges only algebraically: use [`constrained_jax.PiecewiseLinear`][] there.

    The KKT matrix is dense: the default linear solver is
    [`constrained_jax.EquilibratedDenseLU`][]. Use up to a few hundred nodes.

    **Reference:** L. N. Trefethen, *Spectral Methods in MATLAB*, SIAM (2000),
    chapter 6; J.-P. Berrut and L. N. Trefethen, *Barycentric Lagrange
    interpolation*, SIAM Review 46 (2004) 501-517.
    """

    num_nodes: int = eqx.field(static=True)
    num_quadrature: int | None = eqx.field(static=True, default=None)
    tables: dict[str, Array] | None = eqx.field(default=None, repr=False)

    def __check_init__(self):
        _check_num_nodes("Chebyshev", self.num_nodes, 3)
        if self.num_quadrature is not None and (
            not isinstance(self.num_quadrature, int) or self.num_quadrature < 2
        ):
            raise ValueError("`num_quadrature` must be an int >= 2 or None.")

    @property
    def order(self) -> None:
        return None

    def _num_quadrature(self) -> int:
        if self.num_quadrature is None:
            return math.ceil(3 * self.num_nodes / 2)
        return self.num_quadrature

    def reference_nodes(self) -> np.ndarray:
        j = np.arange(self.num_nodes)
        t = -np.cos(np.pi * j / (self.num_nodes - 1))
        t[0], t[-1] = -1.0, 1.0
        if self.num_nodes % 2 == 1:
            t[self.num_nodes // 2] = 0.0
        return t

    def _reference_weights(self) -> np.ndarray:
        w = (-1.0) ** np.arange(self.num_nodes)
        w[0] *= 0.5
        w[-1] *= 0.5
        return w

    def _matrices(self, singular=(False, False)):
        """Gauss points, weights (NumPy), and the value / derivative matrices at
        them (JAX arrays: from `tables` when tabulated, else built here)."""
        singular = tuple(bool(flag) for flag in singular)
        tq, wq = _gauss_legendre(self._num_quadrature(), singular)
        key = _table_key(singular)
        if self.tables is not None and key + "p" in self.tables:
            return tq, wq, self.tables[key + "p"], self.tables[key + "pd"]
        t = self.reference_nodes()
        bw = self._reference_weights()
        p, pd = _value_and_derivative_tables(t, bw, tq)
        return tq, wq, p, pd

    def _interior_matrix(self):
        """Values at the (unclustered) Gauss points of the Lagrange basis of the
        interior nodes, for the weak form of pointwise constraints."""
        if self.tables is not None and "interior" in self.tables:
            return self.tables["interior"]
        tq, _ = _gauss_legendre(self._num_quadrature(), (False, False))
        t_int = self.reference_nodes()[1:-1]
        return interpolation_matrix(t_int, barycentric_weights(t_int), tq)

    def tabulate(self, singular_ends=((False, False),)) -> "Chebyshev":
        """A copy holding the matrices at the Gauss points, clustered as in each of
        `singular_ends`, and that of the interior nodes (see
        `AbstractDiscretization.tabulate`)."""
        base = eqx.tree_at(lambda d: d.tables, self, None, is_leaf=lambda x: x is None)
        tables = {"interior": base._interior_matrix()}
        flag_sets = {tuple(bool(f) for f in flags) for flags in singular_ends}
        for flags in sorted(flag_sets | {(False, False)}):
            _, _, p, pd = base._matrices(flags)
            key = _table_key(flags)
            tables[key + "p"], tables[key + "pd"] = p, pd
        return eqx.tree_at(
            lambda d: d.tables, self, tables, is_leaf=lambda x: x is None
        )

    def integrate(self, integrand, values, interval, singular=(False, False)):
        xl, xr = interval
        dtype = values.dtype
        tq, wq, p, pd = self._matrices(singular)
        half = (xr - xl) / 2
        xq = xl + half * (jnp.asarray(tq, dtype) + 1)
        yq = jnp.asarray(p, dtype) @ values
        ypq = (jnp.asarray(pd, dtype) @ values) / half
        fq = jax.vmap(integrand)(yq, ypq, xq)
        return half * jnp.dot(jnp.asarray(wq, dtype), fq)

    def node_weights(self, interval):
        xl, xr = interval
        _, wq, p, _ = self._matrices()
        # Interpolatory (Clenshaw-Curtis) weights: integrals of the Lagrange basis.
        cc = _matmul(p.T, _vector(wq))
        return (xr - xl) / 2 * jnp.asarray(cc, xl.dtype)

    def pointwise_constraint(self, constraint, values, interval):
        """Weak form: `int l_i(x) G(y(x), x) dx = 0` for the Lagrange basis `l_i` of
        the interior nodes (degree `N - 3`), by the same Gauss quadrature as the
        functional. Then `sum_i mu_i row_i = int lambda G dx` exactly for the
        polynomial `lambda` with values `mu_i` at the interior nodes. (Collocating
        `G = 0` at the nodes with Clenshaw-Curtis weights instead would halve the
        exponential rate: lumping the mass matrix of `lambda` is exact only up to
        degree `N - 1`.)"""
        xl, xr = interval
        dtype = values.dtype
        tq, wq, p, _ = self._matrices()
        p_int = self._interior_matrix()
        half = (xr - xl) / 2
        xq = xl + half * (jnp.asarray(tq, dtype) + 1)
        yq = jnp.asarray(p, dtype) @ values
        gq = jax.vmap(constraint)(yq, xq)  # (M, m)
        weighted = jnp.asarray(wq, dtype)[:, None] * gq
        return half * (jnp.asarray(p_int.T, dtype) @ weighted)

    def interpolate(self, interval, values, x, derivative=0, interior=False):
        xl, xr = interval
        dtype = values.dtype
        t_ref = self.reference_nodes()
        if interior:
            t_ref = t_ref[1:-1]
        bw = barycentric_weights(t_ref)
        t = 2 * (x - xl) / (xr - xl) - 1
        if derivative:
            d = jnp.asarray(differentiation_matrix(t_ref, bw), dtype) * (2 / (xr - xl))
            for _ in range(derivative):
                values = jnp.tensordot(d, values, axes=1)
        return _barycentric(
            jnp.asarray(t_ref, dtype), jnp.asarray(bw, dtype), values, t
        )

    def make_linear_solver(self, num_components, num_holonomic, num_integral):
        # LAPACK's LU at every size: on a functional's KKT matrix the unrolled
        # elimination of small sizes compiles markedly slower, and solves no faster
        # one at a time (only a `jax.vmap` batch of the smallest sizes gains a little).
        return EquilibratedDenseLU(unroll_max=0)

    def _coefficient_matrix(self) -> Array:
        """`C` with `c = C @ values`: the Chebyshev coefficients of the interpolant
        through the Chebyshev-Gauss-Lobatto nodes (a discrete cosine transform)."""
        n = self.num_nodes - 1
        # The nodes are ascending, t_j = cos(pi (n - j) / n).
        if _tables_in_numpy(n + 1):
            j = np.arange(n + 1)
            c = np.cos(np.pi * j[:, None] * (n - j)[None, :] / n)
            w = np.ones(n + 1)
            w[0] = w[-1] = 0.5
            c = (2.0 / n) * c * w[None, :]
            c[0] /= 2
            c[-1] /= 2
            return _as_table(c)
        # (Built with jnp, like the matrices above: no (N, N) constant.)
        j = jnp.arange(n + 1, dtype=default_float_dtype())
        c = jnp.cos(jnp.pi * j[:, None] * (n - j)[None, :] / n)
        w = jnp.ones(n + 1, j.dtype).at[0].set(0.5).at[-1].set(0.5)
        c = (2.0 / n) * c * w[None, :]
        return c.at[0].divide(2).at[-1].divide(2)

    def error_estimate(self, values, interval):
        """From the decay of the Chebyshev coefficients `c_k` of the interpolant
        (the test Chebfun uses to decide that a function is resolved).

        With the envelope `E_k = max_{j >= k} |c_j|` (maximum over the components),
        the tail is modelled as `E_k ~ k^-p`, `p` from `E` at `k = (N - 2)/2` and at
        `N - 2` (two indices, so that a solution with only even or only odd
        coefficients is not taken for a converged one). The error of the interpolant
        is at most twice the sum of the coefficients not represented, estimated as

            2 E_{N-2} max(1, (N - 2) / (p - 1)),

        which covers both algebraic decay (`p` small: a singular solution) and
        exponential decay (`p` large, the factor tends to 1). A tail that does not
        decay (`p <= 3/2`: a plateau above round-off, a slowly decaying series, or
        a tail that grows towards `N`, the trace of a layer narrower than the grid at
        an end) is not extrapolated beyond `N`: it is itself the part of the
        interpolant the grid does not resolve, and counts as what it holds, twice
        the sum of its coefficients `2 sum_{k >= (N-2)/2} max|c_k|` (a flat plateau
        `E`: `N E`). The estimate never exceeds `max |c_k|`, the size of the
        function. A tail already at round-off (`E_{N-2} <= N^2 eps max |c_k|`, the
        conditioning of spectral differentiation) gives that round-off level: it
        grows like `N^2`, and the default tolerance is floored there
        (`roundoff_rtol`).
        """
        n = self.num_nodes
        dtype = values.dtype
        coeffs = jnp.asarray(self._coefficient_matrix(), dtype) @ values
        mags = jnp.max(jnp.abs(coeffs), axis=1)
        envelope = jax.lax.cummax(mags, axis=0, reverse=True)
        scale = envelope[0]
        last = envelope[n - 2]
        mid_index = max((n - 2) // 2, 1)
        mid = envelope[mid_index]
        eps = jnp.finfo(dtype).eps
        noise = n**2 * eps * scale
        ratio = math.log((n - 2) / mid_index) if n - 2 > mid_index else 1.0
        safe_last = jnp.where(last > 0, last, 1.0)
        p = jnp.log(jnp.where(last > 0, mid / safe_last, 1.0)) / ratio
        decaying = 2 * last * jnp.maximum(1.0, (n - 2) / jnp.maximum(p - 1, 0.5))
        held = 2 * jnp.sum(mags[mid_index:])
        tail = jnp.minimum(jnp.where(p > 1.5, decaying, held), scale)
        return jnp.where(last <= noise, noise, tail)

    @property
    def default_rtol(self) -> float:
        """`10^(-(N - 4)/8)`: the error of a solution whose coefficients fall by at
        least a factor of 10 every 8 nodes (a Bernstein ellipse `rho >= 1.33`),
        floored at `1e-10`. It asks nothing of 4 nodes, `3e-4` of 32, `1e-10` from
        84 on: a tail that has not started to fall is refused, a convergence study at
        few nodes is not."""
        return max(10.0 ** (-(self.num_nodes - 4) / 8), 1e-10)

    def roundoff_rtol(self, dtype) -> float:
        """`2 N^2 eps`: the round-off level `N^2 eps max |c_k|` of `error_estimate`,
        relative to `max |y|` (`|c_k| <= 2 max |y|` for the Chebyshev coefficients of
        the interpolant through the values). It passes `1e-10` in float64 from about
        `N = 480` on."""
        return 2.0 * self.num_nodes**2 * float(jnp.finfo(dtype).eps)


Chebyshev.__init__.__doc__ = """**Arguments:**

- `num_nodes`: the number of nodes `N >= 3`, both ends included (the polynomial has
    degree `N - 1`; there are `N - 2` unknown values per function).
- `num_quadrature`: Gauss-Legendre points for the integrals; default `ceil(3N/2)`.
- `tables`: leave it `None`; [`constrained_jax.solve_functional`][] fills it (by
    `tabulate`) with the interpolation matrices, computed once per solve at run time.
"""


class PiecewiseLinear(AbstractDiscretization):
    """Low-order mesh: `y` linear between `N` equally spaced nodes.

    On element `[x_i, x_{i+1}]` (width `h`) the integrand is evaluated once, at the
    midpoint, with `y = (y_i + y_{i+1})/2` and `y' = (y_{i+1} - y_i)/h`:

        F_h = h sum_i L((y_i + y_{i+1})/2, (y_{i+1} - y_i)/h, x_i + h/2).

    Its stationarity conditions are the standard second-order difference scheme for
    the Euler-Lagrange equation, so nodal values and multipliers converge like
    `h^2`. Integrands of arc length (`sqrt(1 + y'^2)`) are exact for the polygon, so
    the discrete constraint says what it means even where the true curve has a
    vertical tangent.

    Each node couples only to its neighbours: the default linear solver,
    [`constrained_jax.BorderedBlockTridiagonal`][], costs time and memory linear in
    `N` (100,000 nodes are routine).
    """

    num_nodes: int = eqx.field(static=True)

    def __check_init__(self):
        _check_num_nodes("PiecewiseLinear", self.num_nodes, 3)

    @property
    def order(self) -> int:
        return 2

    def reference_nodes(self) -> np.ndarray:
        return np.linspace(-1.0, 1.0, self.num_nodes)

    def nodes(self, interval):
        if self.num_nodes <= CONSTANT_INDICES_MAX:  # as constants (see there)
            return super().nodes(interval)
        # `np.linspace`'s arithmetic, from iota: no (N,) constant in the program.
        xl, xr = interval
        i = jnp.arange(self.num_nodes, dtype=default_float_dtype())
        t = (i * (2.0 / (self.num_nodes - 1)) + -1.0).at[-1].set(1.0)
        return jnp.clip(xl + (xr - xl) * (t.astype(xl.dtype) + 1) / 2, xl, xr)

    def integrate(self, integrand, values, interval, singular=(False, False)):
        xl, xr = interval
        dtype = values.dtype
        h = (xr - xl) / (self.num_nodes - 1)
        mid = xl + h * (jnp.arange(self.num_nodes - 1, dtype=dtype) + 0.5)
        ym = (values[1:] + values[:-1]) / 2
        ypm = (values[1:] - values[:-1]) / h
        fm = jax.vmap(integrand)(ym, ypm, mid)
        if not any(singular):
            return h * jnp.sum(fm)
        # At a flagged end, the end element by Gauss-Legendre in v, x - x_end ~ v^2.
        tq, wq = np.polynomial.legendre.leggauss(_END_POINTS)
        out = h * jnp.sum(fm[1:-1])
        for end, flagged in ((0, singular[0]), (-1, singular[1])):
            if not flagged:
                out = out + h * fm[end]
                continue
            sq, ws = _cluster(tq, wq, (end == 0, end == -1))
            sq = jnp.asarray((sq + 1) / 2, dtype)
            a, b = (values[0], values[1]) if end == 0 else (values[-2], values[-1])
            x0 = xl if end == 0 else xr - h
            yq = a[None] + sq[:, None] * (b - a)[None]
            yp = jnp.broadcast_to((b - a) / h, yq.shape)
            fq = jax.vmap(integrand)(yq, yp, x0 + h * sq)
            out = out + h / 2 * jnp.dot(jnp.asarray(ws, dtype), fq)
        return out

    def node_weights(self, interval):
        xl, xr = interval
        h = (xr - xl) / (self.num_nodes - 1)
        w = jnp.full((self.num_nodes,), 1.0, xl.dtype)
        w = w.at[0].set(0.5).at[-1].set(0.5)
        return h * w

    def pointwise_constraint(self, constraint, values, interval):
        """Collocation at the interior nodes, weighted by the trapezoid weight `h`:
        `h G(y_i, x_i) = 0`."""
        nodes = self.nodes(interval)
        weights = self.node_weights(interval)
        g = jax.vmap(constraint)(values[1:-1], nodes[1:-1])
        return weights[1:-1, None] * g

    def interpolate(self, interval, values, x, derivative=0, interior=False):
        nodes = self.nodes(interval)
        if interior:
            nodes = nodes[1:-1]
        for _ in range(derivative):
            values = _nodal_derivative(nodes, values)
        # Linear interpolation, extrapolated linearly beyond the end nodes.
        m = nodes.shape[0]
        i = jnp.clip(jnp.searchsorted(nodes, x, side="right") - 1, 0, m - 2)
        x0, x1 = nodes[i], nodes[i + 1]
        s = (x - x0) / (x1 - x0)
        return values[i] + s * (values[i + 1] - values[i])

    def make_linear_solver(self, num_components, num_holonomic, num_integral):
        return BorderedBlockTridiagonal(
            self.num_nodes - 2, num_components, num_holonomic, num_integral
        )

    def error_estimate(self, values, interval):
        """The largest difference between the solution and its restriction to the
        coarser mesh of every other node, `max_i |y_{i-1} - 2 y_i + y_{i+1}| / 2`
        (maximum over the components).

        For a smooth solution this is `h^2 |y''| / 2`, four times the error of linear
        interpolation on this mesh (`h^2 |y''| / 8`) and of the order of the nodal
        error: a safe margin. Where the discrete solution does not converge (a kink
        or a jump at a singular end, which the midpoint rule never samples) it is the
        size of the kink, not an `h^2` term.
        """
        d2 = values[2:] - 2 * values[1:-1] + values[:-2]
        return jnp.max(jnp.abs(d2)) / 2

    @property
    def default_rtol(self) -> float:
        """`(10 / (N - 1))^2`, floored at `1e-10`: the error a second-order method
        makes on a solution with `|y''| <= 50 max|y| / (xR - xL)^2`, by the estimate
        above. It asks nothing of 11 nodes, `1e-2` of 101, `1e-6` of 10,001."""
        return max((10.0 / (self.num_nodes - 1)) ** 2, 1e-10)


PiecewiseLinear.__init__.__doc__ = """**Arguments:**

- `num_nodes`: the number of mesh nodes `N >= 3`, both ends included.
"""


def _nodal_derivative(nodes, values):
    """Second-order finite-difference derivative at (possibly nonuniform) nodes."""
    if nodes.shape[0] < 3:
        return jnp.broadcast_to(
            (values[1] - values[0]) / (nodes[1] - nodes[0]), values.shape
        )
    h0 = nodes[1:-1] - nodes[:-2]
    h1 = nodes[2:] - nodes[1:-1]
    shape = (-1,) + (1,) * (values.ndim - 1)
    h0, h1 = h0.reshape(shape), h1.reshape(shape)
    vm, v0, vp = values[:-2], values[1:-1], values[2:]
    inner = (h0**2 * (vp - v0) + h1**2 * (v0 - vm)) / (h0 * h1 * (h0 + h1))
    # One-sided second-order formulas at the ends.
    a, b = nodes[1] - nodes[0], nodes[2] - nodes[0]
    first = (
        -(a + b) / (a * b) * values[0]
        + b / (a * (b - a)) * values[1]
        - a / (b * (b - a)) * values[2]
    )
    a, b = nodes[-1] - nodes[-2], nodes[-1] - nodes[-3]
    last = (
        (a + b) / (a * b) * values[-1]
        - b / (a * (b - a)) * values[-2]
        + a / (b * (b - a)) * values[-3]
    )
    return jnp.concatenate([first[None], inner, last[None]], axis=0)


def _bell_polynomials(order: int, inner: list) -> list[list]:
    """`B[n][k]`, the partial Bell polynomials of the derivatives `inner[j]` (the
    `(j + 1)`-th derivative of the inner function), for `n, k <= order`: Faa di
    Bruno's formula `(f o g)^(n) = sum_k f^(k)(g) B[n][k]`."""
    bell = [[None] * (order + 1) for _ in range(order + 1)]
    bell[0][0] = 1.0
    for n in range(1, order + 1):
        bell[n][0] = 0.0
        for k in range(1, n + 1):
            total = 0.0
            for i in range(1, n - k + 2):
                if bell[n - i][k - 1] is not None:
                    total = (
                        total
                        + math.comb(n - 1, i - 1) * inner[i - 1] * (bell[n - i][k - 1])
                    )
            bell[n][k] = total
    return bell


class Graded(AbstractDiscretization):
    """A discretization on a graded grid: nodes clustered at a singular end.

    Wraps another discretization (the *base*) by a change of variables. The base
    represents `Y(u) = y(x(u))` on `[xL, xR]` in a new variable `u`, with

        x(u) = xL + (xR - xL) phi(s),    s = (u - xL) / (xR - xL),

    where `phi(s) = s^p` (`left = p`), `1 - (1 - s)^q` (`right = q`), or
    `s^p / (s^p + (1 - s)^p)` (both ends, `left = right = p`). Every integral is
    transformed exactly, `int L(y, y', x) dx = int L(Y, Y_u / x_u, x(u)) x_u du`,
    and integrated by the base's own quadrature in `u`; the nodes `x(u_i)` crowd
    towards a graded end like `h^p`.

    Use it when the solution is singular at an end, e.g. a vertical tangent
    `y ~ (x - xL)^(1/m)` or `y ~ (x - xL)^(r/m)`: with `p = m` the function
    `Y(u) ~ s^r` is smooth (analytic) in `u`, and the base converges at its usual
    rate: spectrally for [`constrained_jax.Chebyshev`][], like `h^2` for
    [`constrained_jax.PiecewiseLinear`][]. The brachistochrone (a cycloid,
    `y ~ x^(2/3)` at its start, where the integrand `1/sqrt(-y)` is singular)
    wants `Graded(Chebyshev(N), left=3)`. Without grading, the quadrature never
    samples the singular end, the discrete curve exploits it, and the discrete
    minimum lies *below* the true one; the a-posteriori error estimate of
    [`constrained_jax.solve_functional`][] then refuses the solution.

    The error estimate, the default tolerance, the convergence order and the linear
    solver are the base's (the error of `Y(u)` in the max norm is that of `y(x)`).

    **Reference:** C. Schwab, *p- and hp-Finite Element Methods*, Oxford (1998),
    section 3.3 (graded meshes); the same substitution makes Gauss quadrature
    exact-rate for endpoint singularities (P. J. Davis and P. Rabinowitz, *Methods
    of Numerical Integration*, 2nd ed. (1984), section 2.12.6).
    """

    discretization: AbstractDiscretization
    left: int = eqx.field(static=True, default=1)
    right: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if not isinstance(self.discretization, AbstractDiscretization) or isinstance(
            self.discretization, Graded
        ):
            raise ValueError(
                "`Graded(discretization, ...)` wraps a discretization such as "
                "`cjax.Chebyshev(32)` or `cjax.PiecewiseLinear(1001)` (not another "
                f"`Graded`), got {self.discretization!r}."
            )
        for name, power in (("left", self.left), ("right", self.right)):
            if not isinstance(power, int) or isinstance(power, bool) or power < 1:
                raise ValueError(
                    f"`Graded(..., {name}=p)` needs an int power p >= 1 (1: no "
                    f"grading at that end), got {power!r}."
                )
        if self.left > 1 and self.right > 1 and self.left != self.right:
            raise ValueError(
                "`Graded` grades both ends only with the same power: "
                f"left={self.left}, right={self.right}. Use left == right."
            )
        if self.left == 1 and self.right == 1:
            raise ValueError(
                "`Graded(discretization)` with left = right = 1 grades nothing: pass "
                "`left=p` and/or `right=p` with p > 1 (p = 3 for a cycloid's cusp), "
                "or use the discretization itself."
            )

    @property
    def num_nodes(self) -> int:
        return self.discretization.num_nodes

    @property
    def order(self) -> int | None:
        return self.discretization.order

    @property
    def default_rtol(self) -> float:
        return self.discretization.default_rtol

    def roundoff_rtol(self, dtype) -> float:
        return self.discretization.roundoff_rtol(dtype)

    def start_parameter(self, interval):
        """The graded variable `s` (`x = xL + (xR - xL) phi(s)`): a default start
        straight in it leaves a graded end like `y ~ (x - xL)^(1/p)`, steeply, as
        the singular solutions a grading is for do (a vertical tangent). The
        straight line in `x` creeps along `y = yL` there, where an integrand
        singular at the end value (the brachistochrone's `1/sqrt(-y)`) makes the
        KKT matrix numerically singular."""
        return self.discretization.start_parameter(interval)

    # The map s -> phi(s) on [0, 1], its derivative, and its inverse.
    def _phi(self, s):
        p, q = self.left, self.right
        if q == 1:
            return s**p
        if p == 1:
            return 1 - (1 - s) ** q
        a, b = s**p, (1 - s) ** p
        return a / (a + b)

    def _phi_prime(self, s):
        p, q = self.left, self.right
        if q == 1:
            return p * s ** (p - 1)
        if p == 1:
            return q * (1 - s) ** (q - 1)
        a, b = s**p, (1 - s) ** p
        return p * s ** (p - 1) * (1 - s) ** (p - 1) / (a + b) ** 2

    def _phi_inverse(self, r):
        p, q = self.left, self.right
        if q == 1:
            return r ** (1.0 / p)
        if p == 1:
            return 1 - (1 - r) ** (1.0 / q)
        a, b = r ** (1.0 / p), (1 - r) ** (1.0 / p)
        return a / (a + b)

    def reference_nodes(self) -> np.ndarray:
        s = (self.discretization.reference_nodes() + 1) / 2
        t = 2 * self._phi(s) - 1
        t[0], t[-1] = -1.0, 1.0
        return t

    def _x_of_u(self, u, interval):
        xl, xr = interval
        s = (u - xl) / (xr - xl)
        return xl + (xr - xl) * self._phi(s), self._phi_prime(s)

    def integrate(self, integrand, values, interval, singular=(False, False)):
        def transformed(y, yu, u):
            x, xu = self._x_of_u(u, interval)
            return integrand(y, yu / xu, x) * xu

        # A graded end is one where the integrand is expected to be singular:
        # cluster the quadrature there too, so that a discrete curve leaving the
        # end with a finite slope in u (a 1/sqrt singularity) is integrated right.
        flags = (singular[0] or self.left > 1, singular[1] or self.right > 1)
        return self.discretization.integrate(transformed, values, interval, flags)

    def node_weights(self, interval):
        u = self.discretization.nodes(interval)
        _, xu = self._x_of_u(u, interval)
        return self.discretization.node_weights(interval) * xu

    def pointwise_constraint(self, constraint, values, interval):
        def transformed(y, u):
            x, xu = self._x_of_u(u, interval)
            return constraint(y, x) * xu

        return self.discretization.pointwise_constraint(transformed, values, interval)

    def interpolate(self, interval, values, x, derivative=0, interior=False):
        xl, xr = interval
        width = xr - xl

        def u_of_x(x_):
            r = (x_ - xl) / width
            # (Not jnp.clip: its derivative at the ends is 1/2, a tie of min/max.)
            r = jnp.where(r < 0, 0.0, jnp.where(r > 1, 1.0, r))
            return xl + width * self._phi_inverse(r)

        u = u_of_x(x)
        base = lambda k: self.discretization.interpolate(
            interval, values, u, derivative=k, interior=interior
        )
        if derivative == 0:
            return base(0)
        # Faa di Bruno: d^n/dx^n Y(u(x)) = sum_k Y^(k)(u) B_{n,k}(u', u'', ...).
        inner, fn = [], u_of_x
        for _ in range(derivative):
            fn = jax.grad(fn)
            inner.append(fn(x))
        bell = _bell_polynomials(derivative, inner)
        out = 0.0
        for k in range(1, derivative + 1):
            out = out + base(k) * bell[derivative][k]
        return out

    def make_linear_solver(self, num_components, num_holonomic, num_integral):
        return self.discretization.make_linear_solver(
            num_components, num_holonomic, num_integral
        )

    def tabulate(self, singular_ends=((False, False),)) -> "Graded":
        # The base integrates with the graded ends flagged (see `integrate`).
        flags = tuple(
            (left or self.left > 1, right or self.right > 1)
            for left, right in singular_ends
        )
        return eqx.tree_at(
            lambda d: d.discretization, self, self.discretization.tabulate(flags)
        )

    def error_estimate(self, values, interval):
        return self.discretization.error_estimate(values, interval)


Graded.__init__.__doc__ = """**Arguments:**

- `discretization`: the base, [`constrained_jax.Chebyshev`][] or
    [`constrained_jax.PiecewiseLinear`][], which represents `y` in the graded
    variable.
- `left`: the power `p >= 1` of the grading at `xL` (1: none). For a solution that
    behaves like `(x - xL)^(r/m)` (a vertical tangent), `p = m` makes it smooth:
    3 for a cycloid's cusp, 2 for a quarter circle `sqrt(x - xL)`.
- `right`: the same at `xR`; when both ends are graded, `left == right`.
"""
