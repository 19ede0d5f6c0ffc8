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
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Float

from ._banded import BorderedBlockTridiagonal, EquilibratedDenseLU


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
    - `linear_solver(...)`: a Lineax solver suited to the structure of the KKT matrix;
    - `order`: the convergence order in `1/N`, or `None` for exponential convergence.
    """

    num_nodes: eqx.AbstractVar[int]

    @abc.abstractmethod
    def reference_nodes(self) -> np.ndarray:
        """The nodes mapped to `[-1, 1]`, ascending, both ends included."""

    @abc.abstractmethod
    def integrate(self, integrand, values: Float[Array, "N n"], interval: Interval):
        """`int_{xL}^{xR} integrand(y(x), y'(x), x) dx` for the represented `y`."""

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
    def linear_solver(
        self, num_components: int, num_holonomic: int, num_integral: int
    ) -> lx.AbstractLinearSolver:
        """The default Lineax solver for the KKT matrix of this discretization."""

    @property
    @abc.abstractmethod
    def order(self) -> int | None:
        """Algebraic convergence order, or `None` for exponential convergence."""

    def nodes(self, interval: Interval) -> Float[Array, " N"]:
        """The nodes on `[xL, xR]`."""
        xl, xr = interval
        t = jnp.asarray(self.reference_nodes(), xl.dtype)
        return xl + (xr - xl) * (t + 1) / 2


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


def barycentric_weights(nodes: np.ndarray) -> np.ndarray:
    """`w_j = 1 / prod_{k != j} (x_j - x_k)`, rescaled to max 1 (float64, NumPy)."""
    diff = nodes[:, None] - nodes[None, :]
    np.fill_diagonal(diff, 1.0)
    # Products of many factors under- or overflow: work with logs and signs.
    log_w = -np.sum(np.log(np.abs(diff)), axis=1)
    sign = np.prod(np.sign(diff), axis=1)
    return sign * np.exp(log_w - log_w.max())


def differentiation_matrix(nodes: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """`D_ij = l_j'(x_i)` for the Lagrange basis through `nodes` (NumPy)."""
    diff = nodes[:, None] - nodes[None, :]
    np.fill_diagonal(diff, 1.0)
    d = (weights[None, :] / weights[:, None]) / diff
    np.fill_diagonal(d, 0.0)
    np.fill_diagonal(d, -d.sum(axis=1))
    return d


def interpolation_matrix(
    nodes: np.ndarray, weights: np.ndarray, points: np.ndarray
) -> np.ndarray:
    """`P_qj = l_j(t_q)`: values at `points` of the Lagrange basis (barycentric)."""
    diff = points[:, None] - nodes[None, :]
    exact = diff == 0
    diff = np.where(exact, 1.0, diff)
    terms = weights[None, :] / diff
    p = terms / terms.sum(axis=1, keepdims=True)
    rows = exact.any(axis=1)
    p[rows] = exact[rows].astype(float)
    return p


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

    def _matrices(self):
        """Gauss points, weights, and the value / derivative matrices (reference)."""
        t = self.reference_nodes()
        bw = self._reference_weights()
        tq, wq = np.polynomial.legendre.leggauss(self._num_quadrature())
        d = differentiation_matrix(t, bw)
        p = interpolation_matrix(t, bw, tq)
        return tq, wq, p, p @ d

    def integrate(self, integrand, values, interval):
        xl, xr = interval
        dtype = values.dtype
        tq, wq, p, pd = self._matrices()
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
        cc = p.T @ wq
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
        t_int = self.reference_nodes()[1:-1]
        p_int = interpolation_matrix(t_int, barycentric_weights(t_int), tq)
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

    def linear_solver(self, num_components, num_holonomic, num_integral):
        return EquilibratedDenseLU()


Chebyshev.__init__.__doc__ = """**Arguments:**

- `num_nodes`: the number of nodes `N >= 3`, both ends included (the polynomial has
    degree `N - 1`; there are `N - 2` unknown values per function).
- `num_quadrature`: Gauss-Legendre points for the integrals; default `ceil(3N/2)`.
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

    def integrate(self, integrand, values, interval):
        xl, xr = interval
        dtype = values.dtype
        h = (xr - xl) / (self.num_nodes - 1)
        mid = xl + h * (jnp.arange(self.num_nodes - 1, dtype=dtype) + 0.5)
        ym = (values[1:] + values[:-1]) / 2
        ypm = (values[1:] - values[:-1]) / h
        return h * jnp.sum(jax.vmap(integrand)(ym, ypm, mid))

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

    def linear_solver(self, num_components, num_holonomic, num_integral):
        return BorderedBlockTridiagonal(
            self.num_nodes - 2, num_components, num_holonomic, num_integral
        )


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
