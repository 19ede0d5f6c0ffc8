"""Sharp edges of `extremize` with inequalities (issue 41): convex problems solve from
any start, feasible or not; textbook nonconvex problems reach their published optima;
a KKT point that is no optimum, an objective with no optimum and a step budget that
ran out are each refused by name. Every answer is checked against a closed form (or
a published optimum, with SciPy's SLSQP as a check of the transcription).

- a linear objective over the unit disc (maximize and minimize, from the centre, from
  a nearby point, from far outside; batched, in float64 and float32): `(1, 2) /
  sqrt(5)` and its multiplier;
- an LP over a polygon and an LP over a box, from inside and from far outside: the
  vertex and its multipliers;
- a QP from a far infeasible start: the projection onto the disc;
- maximizing a convex function over a box: a corner;
- a separable quadratic with box bounds (and with `sum x = c`): the clipped closed
  form (a clipped shift, its scalar root found here by bisection);
- Hock-Schittkowski problems 21, 35, 44 (bilinear), 71 and 76 from their standard
  starts: the published optimum;
- a KKT point with a weakly active bound and negative curvature along the subspace
  of the active constraints: `not_an_optimum`;
- maximizing a convex function with no maximum, minimizing a linear function that is
  unbounded below: `unbounded_objective`;
- a feasible problem stopped by `max_steps`: `nonlinear_max_steps_reached`, not
  `infeasible_inequalities`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize as scipy_minimize

import constrained_jax as cjax


R = cjax.RESULTS


def _disc(x, args):
    return x @ x - 1.0


def _linear(x, args):
    return x[0] + 2 * x[1]


@eqx.filter_jit
def _disc_linear(x0, sense):
    return cjax.extremize(_linear, x0, inequalities=_disc, sense=sense, throw=False)


@pytest.mark.parametrize("sense", ["maximize", "minimize"])
@pytest.mark.parametrize(
    "x0", [[0.0, 0.0], [0.1, -0.2], [-0.5, 0.3], [3.0, 3.0], [-40.0, 25.0]]
)
def test_linear_objective_over_the_disc(sense, x0):
    """Extremize `x + 2 y` on `x^2 + y^2 <= 1`: `x = s' (1, 2) / sqrt(5)` (`s' = +1`
    to maximize), and stationarity `(1, 2) + 2 mu x = 0` gives `mu = -s' sqrt(5) /
    2`. At the centre the objective is flat (Hessian zero, the constraint inactive):
    the semismooth Newton matrix is singular there."""
    sol = _disc_linear(jnp.asarray(x0), sense)
    assert sol.result == R.successful
    side = 1.0 if sense == "maximize" else -1.0
    np.testing.assert_allclose(
        sol.x, side * np.array([1.0, 2.0]) / np.sqrt(5), atol=1e-12
    )
    np.testing.assert_allclose(
        sol.inequality_multipliers, [-side * np.sqrt(5) / 2], rtol=1e-10
    )
    assert sol.kind == (cjax.EXTREMUM.maximum if side > 0 else cjax.EXTREMUM.minimum)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_linear_objective_over_the_disc_batched(dtype):
    """The same under `jax.vmap` (the centre, where the Newton matrix is singular,
    in one batch with feasible and far infeasible starts), in float64 and float32."""
    starts = jnp.array([[0.0, 0.0], [0.1, -0.2], [3.0, 3.0], [-40.0, 25.0]], dtype)
    sol = jax.vmap(lambda x0: _disc_linear(x0, "maximize"))(starts)
    assert jnp.all(sol.result == R.successful)
    assert sol.x.dtype == dtype
    tol = 1e-12 if dtype == jnp.float64 else 1e-6
    np.testing.assert_allclose(
        sol.x, np.tile([1.0, 2.0], (4, 1)) / np.sqrt(5), atol=tol
    )


def _polygon(x, args):
    return jnp.stack([x[0] + 2 * x[1] - 4.0, 3 * x[0] + x[1] - 6.0])


@pytest.mark.parametrize("x0", [[0.0, 0.0], [1.0, 1.0], [10.0, -7.0]])
def test_lp_over_a_polygon(x0):
    """Maximize `x + y` on `x + 2y <= 4, 3x + y <= 6, x, y >= 0`: the vertex
    `(8/5, 6/5)` where both rows bind, with `(1, 1) + mu_1 (1, 2) + mu_2 (3, 1) = 0`,
    `mu = (-2/5, -1/5)`; the lower bounds inactive."""
    sol = cjax.extremize(
        lambda x, a: x[0] + x[1],
        jnp.asarray(x0),
        inequalities=_polygon,
        lower=0.0,
        sense="maximize",
        throw=False,
    )
    assert sol.result == R.successful
    np.testing.assert_allclose(sol.x, [1.6, 1.2], rtol=1e-12)
    np.testing.assert_allclose(
        sol.inequality_multipliers, [-0.4, -0.2, 0.0, 0.0], atol=1e-12
    )
    np.testing.assert_array_equal(sol.active, [True, True, False, False])


@pytest.mark.parametrize("x0", [[0.0, 0.0, 0.0], [5.0, 5.0, -5.0], [-30.0, 0.5, 9.0]])
def test_lp_over_a_box(x0):
    """Maximize `c . x` on `-1 <= x <= 2`: `x_i = 2` where `c_i > 0`, `-1` where
    `c_i < 0`, with the multiplier `-|c_i|` on the bound that binds."""
    c = jnp.array([1.0, -2.0, 0.5])
    sol = cjax.extremize(
        lambda x, a: c @ x,
        jnp.asarray(x0),
        lower=-1.0,
        upper=2.0,
        sense="maximize",
        throw=False,
    )
    assert sol.result == R.successful
    np.testing.assert_allclose(sol.x, [2.0, -1.0, 2.0], rtol=1e-12)
    np.testing.assert_allclose(
        sol.inequality_multipliers, [0.0, -2.0, 0.0, -1.0, 0.0, -0.5], atol=1e-12
    )
    assert sol.kind == cjax.EXTREMUM.isolated


@pytest.mark.parametrize("x0", [[100.0, -50.0], [-1e3, 1e3]])
def test_qp_from_a_far_infeasible_start(x0):
    """Minimize `|x - c|^2` on the unit disc, `c = (2, 1)`: `x = c / |c|`,
    `mu = |c| - 1`."""
    c = jnp.array([2.0, 1.0])
    sol = cjax.extremize(
        lambda x, a: jnp.sum((x - c) ** 2),
        jnp.asarray(x0),
        inequalities=_disc,
        sense="minimize",
        throw=False,
    )
    assert sol.result == R.successful
    np.testing.assert_allclose(sol.x, c / jnp.sqrt(5.0), rtol=1e-12)
    np.testing.assert_allclose(sol.inequality_multipliers, [np.sqrt(5) - 1], rtol=1e-10)


def test_maximizing_a_convex_function_over_a_box_finds_a_corner():
    """`max |x|^2` on `[-1, 1]^2` is attained at the four corners (value 2); from an
    interior start the ascent ends at one of them, with `mu = -2 x` on the bound
    that binds."""
    sol = cjax.extremize(
        lambda x, a: x @ x,
        jnp.array([0.3, -0.2]),
        lower=-1.0,
        upper=1.0,
        sense="maximize",
        throw=False,
    )
    assert sol.result == R.successful
    np.testing.assert_allclose(jnp.abs(sol.x), [1.0, 1.0], rtol=1e-12)
    np.testing.assert_allclose(sol.value, 2.0, rtol=1e-12)
    mu = np.asarray(sol.inequality_multipliers)
    np.testing.assert_allclose(mu[:2] + mu[2:], -2 * np.abs(sol.x), rtol=1e-10)


# ---------------------------------------------------------------------------------
# Separable quadratics with bounds: clipped closed forms
# ---------------------------------------------------------------------------------


W = np.array([1.0, 2.0, 0.5, 4.0, 1.5, 3.0])
T = np.array([-2.0, 0.3, 1.7, 0.9, -0.4, 5.0])
LO = np.array([-1.0, 0.0, -3.0, 1.0, -0.5, 0.0])
UP = np.array([1.0, 2.0, 1.0, 3.0, 0.5, 4.0])


def _separable(x, args):
    return 0.5 * jnp.sum(jnp.asarray(W) * (x - jnp.asarray(T)) ** 2)


def test_separable_quadratic_box_is_clipped():
    """`min sum w_i (x_i - t_i)^2 / 2` on `lo <= x <= up`: `x = clip(t, lo, up)`,
    and the bound that binds carries `w_i |x_i - t_i|`."""
    sol = cjax.extremize(
        _separable,
        jnp.zeros(6),
        lower=jnp.asarray(LO),
        upper=jnp.asarray(UP),
        sense="minimize",
        throw=False,
    )
    assert sol.result == R.successful
    x = np.clip(T, LO, UP)
    np.testing.assert_allclose(sol.x, x, rtol=1e-12, atol=1e-14)
    mu = np.asarray(sol.inequality_multipliers)
    np.testing.assert_allclose(mu[:6], np.maximum(W * (LO - T), 0.0), atol=1e-12)
    np.testing.assert_allclose(mu[6:], np.maximum(W * (T - UP), 0.0), atol=1e-12)


def _clipped_shift(total):
    """`x(nu) = clip(t - nu / w, lo, up)` with `sum x(nu) = total`: the KKT point of
    the separable quadratic with `sum x = total` (`nu` the equality multiplier),
    `sum x(nu)` decreasing in `nu`, found by bisection."""
    x_of = lambda nu: np.clip(T - nu / W, LO, UP)
    lo, hi = -1e3, 1e3
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if x_of(mid).sum() > total else (lo, mid)
    nu = 0.5 * (lo + hi)
    return x_of(nu), nu


@pytest.mark.parametrize("total", [3.0, 6.5])
def test_separable_quadratic_box_with_a_sum_is_a_clipped_shift(total):
    x_ref, nu = _clipped_shift(total)
    sol = cjax.extremize(
        _separable,
        jnp.asarray(LO),
        constraints=lambda x, a: jnp.sum(x) - total,
        lower=jnp.asarray(LO),
        upper=jnp.asarray(UP),
        sense="minimize",
        throw=False,
    )
    assert sol.result == R.successful
    np.testing.assert_allclose(sol.x, x_ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sol.multipliers, [nu], rtol=1e-8)


# ---------------------------------------------------------------------------------
# Hock-Schittkowski problems: published optima
# ---------------------------------------------------------------------------------

_A44 = np.array(
    [
        [1, 2, 0, 0],
        [4, 1, 0, 0],
        [3, 4, 0, 0],
        [0, 0, 2, 1],
        [0, 0, 1, 2],
        [0, 0, 1, 1],
    ],
    float,
)
_B44 = np.array([8, 12, 12, 8, 8, 5], float)

# name: (F, H (<= 0), G or None, lower, upper, x0, published f*, x* or None).
# W. Hock and K. Schittkowski, Test Examples for Nonlinear Programming Codes,
# Lecture Notes in Economics and Mathematical Systems 187, Springer (1981).
HS = {
    "hs21": (
        lambda x, a: 0.01 * x[0] ** 2 + x[1] ** 2 - 100.0,
        lambda x, a: -(10 * x[0] - x[1] - 10.0),
        None,
        [2.0, -50.0],
        [50.0, 50.0],
        [-1.0, -1.0],
        -99.96,
        [2.0, 0.0],
    ),
    "hs35": (
        lambda x, a: (
            9
            - 8 * x[0]
            - 6 * x[1]
            - 4 * x[2]
            + 2 * x[0] ** 2
            + 2 * x[1] ** 2
            + x[2] ** 2
            + 2 * x[0] * x[1]
            + 2 * x[0] * x[2]
        ),
        lambda x, a: x[0] + x[1] + 2 * x[2] - 3.0,
        None,
        0.0,
        None,
        [0.5, 0.5, 0.5],
        1 / 9,
        [4 / 3, 7 / 9, 4 / 9],
    ),
    "hs44": (
        lambda x, a: (
            x[0] - x[1] - x[2] - x[0] * x[2] + x[0] * x[3] + x[1] * x[2] - x[1] * x[3]
        ),
        lambda x, a: jnp.asarray(_A44) @ x - jnp.asarray(_B44),
        None,
        0.0,
        None,
        [0.0, 0.0, 0.0, 0.0],
        -15.0,
        [0.0, 3.0, 0.0, 4.0],
    ),
    "hs71": (
        lambda x, a: x[0] * x[3] * (x[0] + x[1] + x[2]) + x[2],
        lambda x, a: 25.0 - x[0] * x[1] * x[2] * x[3],
        lambda x, a: x @ x - 40.0,
        1.0,
        5.0,
        [1.0, 5.0, 5.0, 1.0],
        17.0140173,
        [1.0, 4.7429994, 3.8211503, 1.3794082],
    ),
    "hs76": (
        lambda x, a: (
            x[0] ** 2
            + 0.5 * x[1] ** 2
            + x[2] ** 2
            + 0.5 * x[3] ** 2
            - x[0] * x[2]
            + x[2] * x[3]
            - x[0]
            - 3 * x[1]
            + x[2]
            - x[3]
        ),
        lambda x, a: jnp.stack(
            [
                x[0] + 2 * x[1] + x[2] + x[3] - 5.0,
                3 * x[0] + x[1] + 2 * x[2] - x[3] - 4.0,
                1.5 - x[1] - 4 * x[2],
            ]
        ),
        None,
        0.0,
        None,
        [0.5, 0.5, 0.5, 0.5],
        -4.681818181,
        [3 / 11, 23 / 11, 0.0, 6 / 11],
    ),
}


@pytest.mark.parametrize("name", sorted(HS))
def test_hock_schittkowski(name):
    f, h, g, lo, up, x0, f_star, x_star = HS[name]
    n = len(x0)
    sol = cjax.extremize(
        f,
        jnp.asarray(x0),
        constraints=g,
        inequalities=h,
        lower=None if lo is None else jnp.asarray(lo),
        upper=None if up is None else jnp.asarray(up),
        sense="minimize",
        throw=False,
    )
    assert sol.result == R.successful
    np.testing.assert_allclose(sol.value, f_star, rtol=1e-8)
    np.testing.assert_allclose(sol.x, x_star, rtol=1e-6, atol=1e-7)
    # The transcription, checked by SLSQP from the same start.
    cons = [{"type": "ineq", "fun": lambda x: -np.atleast_1d(h(jnp.asarray(x), None))}]
    if g is not None:
        cons.append(
            {"type": "eq", "fun": lambda x: np.atleast_1d(g(jnp.asarray(x), None))}
        )
    lo_ = np.broadcast_to(-np.inf if lo is None else np.asarray(lo), (n,))
    up_ = np.broadcast_to(np.inf if up is None else np.asarray(up), (n,))
    ref = scipy_minimize(
        lambda x: float(f(jnp.asarray(x), None)),
        np.asarray(x0),
        method="SLSQP",
        bounds=list(zip(lo_, up_, strict=True)),
        constraints=cons,
        options={"ftol": 1e-12, "maxiter": 500},
    )
    np.testing.assert_allclose(ref.fun, f_star, rtol=1e-6)


# ---------------------------------------------------------------------------------
# Refusals by name
# ---------------------------------------------------------------------------------


@pytest.mark.parametrize("x0", [[0.1, 0.1, 0.0], [0.0, 0.3, 0.0], [0.0, 0.0, 0.0]])
def test_kkt_point_with_negative_curvature_is_not_an_optimum(x0):
    """`min x y - z^2` with `x >= 0`: the KKT points are `x = 0, y >= 0, z = 0`
    (`mu = y`), and along `z`, which keeps the bound at zero, the curvature is -2:
    none is a local minimum (the problem is unbounded below). Where the bound is
    weakly active (`y = 0`) `kind` alone is inconclusive."""
    sol = cjax.extremize(
        lambda x, a: x[0] * x[1] - x[2] ** 2,
        jnp.asarray(x0),
        lower=jnp.array([0.0, -jnp.inf, -jnp.inf]),
        sense="minimize",
        throw=False,
    )
    assert sol.result in (R.not_an_optimum, R.unbounded_objective)
    assert sol.kind == cjax.EXTREMUM.unknown


@pytest.mark.parametrize(
    "objective, sense, bounds",
    [
        (lambda x, a: x @ x, "maximize", {"lower": -1.0}),
        (lambda x, a: x @ x, "maximize", {"upper": jnp.array([5.0, jnp.inf])}),
        (lambda x, a: x[0] + x[1], "minimize", {"upper": 1.0}),
    ],
)
def test_an_objective_with_no_optimum_is_unbounded(objective, sense, bounds):
    sol = cjax.extremize(
        objective, jnp.array([0.3, 0.2]), sense=sense, throw=False, **bounds
    )
    assert sol.result == R.unbounded_objective
    assert sol.kind == cjax.EXTREMUM.unknown
    with pytest.raises(eqx.EquinoxRuntimeError, match="no optimum"):
        cjax.extremize(objective, jnp.array([0.3, 0.2]), sense=sense, **bounds)


def test_a_feasible_problem_out_of_steps_is_not_infeasible():
    """The disc is not empty: a run stopped by `max_steps` outside it says that the
    budget ran out; with the budget it solves."""
    sol = cjax.extremize(
        _linear,
        jnp.array([3.0, 3.0]),
        inequalities=_disc,
        sense="minimize",
        max_steps=3,
        throw=False,
    )
    assert sol.result == R.nonlinear_max_steps_reached
    assert _disc(sol.x, None) > 0  # stopped outside the disc
