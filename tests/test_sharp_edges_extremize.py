"""Catalog of sharp edges of `extremize` (issue 11): each case is right or refused, and
a refusal names its cause. What each case now returns:

- infeasible constraint (F = x0 + x1, G = x.x + 1; also far starts, a 1e3-scaled
  copy, two parallel constraints, x.x = 1 with x0 = 3): `infeasible_constraints`,
  `kind == unknown` (never `maximum`/`minimum` on failure).
- vanishing constraint gradient where it holds (G = g**2, g**3, from starts off the
  surface; also with a second, regular constraint): `redundant_constraints`.
- F (or G, or a derivative) NaN/inf at a finite x0: `nonfinite_objective`.
- dense LU failures: `singular_kkt` (message about the KKT matrix, no "Krylov"); a NaN
  Hessian: `nonfinite_objective`; DenseLU on a NaN matrix: lineax `nonfinite_input`;
  MINRES out of iterations: `linear_solve_failed` (message names the Krylov solver).
- `jax.grad` / `jax.jacfwd` / `jax.jit` / `jax.vmap` of a failed solve under
  throw=False: NaN derivative, never an error from the backward pass; successful
  rows keep their (closed-form) derivative; `fit` over such a loss stops with
  `nonfinite` and keeps the last finite parameters (also when failing at the start);
  the same for `solve_functional`.
- multipliers0 NaN/inf: `invalid_input`; a start at a saddle: `successful`, kind
  `saddle`; a start where the Hessian is singular, an unbounded (linear) F, F with no
  stationary point on a satisfied constraint: `singular_kkt`, kind `unknown`;
  max_steps=1: `nonlinear_max_steps_reached`, never success.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optax
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import catenary as cat

from .helpers import finite_difference_grad


R = cjax.RESULTS


def _linear(x, a):
    return x[0] + x[1]


def _sum_squares(x, a):
    return jnp.sum(x**2)


def _solve(objective, x0, constraints=None, args=None, **kwargs):
    return cjax.extremize(
        objective,
        jnp.asarray(x0, float),
        args,
        constraints=constraints,
        throw=False,
        **kwargs,
    )


# ---------------------------------------------------------------------------------
# 1. Infeasible constraints
# ---------------------------------------------------------------------------------


def _unit_sphere_plus_one(x, a):
    return x @ x + 1.0


@pytest.mark.parametrize("x0", [[0.3, 0.7], [10.0, -3.0]])
def test_infeasible_constraint(x0):
    sol = _solve(_linear, x0, _unit_sphere_plus_one)
    assert sol.result == R.infeasible_constraints
    assert sol.kind == cjax.EXTREMUM.unknown
    with pytest.raises(eqx.EquinoxRuntimeError, match="could not be satisfied"):
        cjax.extremize(
            _linear, jnp.array(x0), constraints=_unit_sphere_plus_one, throw=True
        )


@pytest.mark.parametrize(
    "constraints, x0",
    [
        # Scaled by 1e3 (the line search fails instead of the KKT matrix).
        (lambda x, a: x @ x + 1e6, [300.0, 700.0]),
        # Two parallel constraints with different values: J J^T singular.
        (lambda x, a: jnp.stack([x[0] + x[1], x[0] + x[1] - 1.0]), [0.3, 0.7, 0.1]),
        # A circle and a line that misses it.
        (lambda x, a: jnp.stack([x @ x - 1.0, x[0] - 3.0]), [0.3, 0.7, 0.2]),
    ],
)
def test_infeasible_constraint_variants(constraints, x0):
    sol = _solve(_linear, x0, constraints)
    assert sol.result == R.infeasible_constraints
    assert sol.kind == cjax.EXTREMUM.unknown


# ---------------------------------------------------------------------------------
# 2. Vanishing constraint gradient where the constraint holds
# ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "objective, constraints, x0",
    [
        (_sum_squares, lambda x, a: (x[0] + x[1] - 1.0) ** 2, [0.3, 0.1]),
        (_linear, lambda x, a: (x @ x - 1.0) ** 2, [0.3, 0.1]),
        (_linear, lambda x, a: (x @ x - 1.0) ** 2, [3.0, -2.0]),
        (_sum_squares, lambda x, a: (x[0] + x[1] - 1.0) ** 3, [0.3, 0.1]),
        (
            _sum_squares,
            lambda x, a: jnp.stack([(x[0] + x[1] - 1.0) ** 2, x[2] - x[0]]),
            [0.3, 0.1, 0.2],
        ),
    ],
)
def test_vanishing_gradient_from_off_the_surface(objective, constraints, x0):
    sol = _solve(objective, x0, constraints)
    assert sol.result == R.redundant_constraints
    assert sol.kind == cjax.EXTREMUM.unknown


# ---------------------------------------------------------------------------------
# 3. F, G or a derivative undefined at a finite start
# ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "objective, constraints",
    [
        # F NaN, its gradient finite.
        (lambda x, a: jnp.log(x[0]) + x[1], None),
        # F and its gradient NaN.
        (lambda x, a: jnp.sum(jnp.sqrt(x)), lambda x, a: x[0] + x[1] - 1.0),
        # G NaN.
        (_sum_squares, lambda x, a: jnp.sqrt(x[0]) - 1.0),
        # F and its gradient finite, the Hessian infinite (|x|^1.5 at 0).
        (lambda x, a: jnp.abs(x[0] + 1.0) ** 1.5 + x[0] + x[1] ** 2, None),
    ],
)
def test_nonfinite_objective_at_start(objective, constraints):
    sol = _solve(objective, [-1.0, 0.5], constraints)
    assert sol.result == R.nonfinite_objective
    assert sol.kind == cjax.EXTREMUM.unknown
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf at the starting"):
        cjax.extremize(objective, jnp.array([-1.0, 0.5]), constraints=constraints)


# ---------------------------------------------------------------------------------
# 4. Linear-solver failures name their cause
# ---------------------------------------------------------------------------------


def _diagonal(x, a):
    return x[0] - x[1]


def test_dense_lu_singular_says_kkt_not_krylov():
    with pytest.raises(eqx.EquinoxRuntimeError) as info:
        cjax.extremize(_linear, jnp.array([0.3, 0.1]), constraints=_diagonal)
    assert "KKT matrix" in str(info.value)
    assert "Krylov" not in str(info.value)


def test_dense_lu_nonfinite_matrix():
    op = lx.MatrixLinearOperator(jnp.array([[1.0, jnp.nan], [0.0, 1.0]]))
    sol = lx.linear_solve(op, jnp.ones(2), cjax.DenseLU(), throw=False)
    assert sol.result == lx.RESULTS.nonfinite_input
    op = lx.MatrixLinearOperator(jnp.array([[1.0, 1.0], [1.0, 1.0]]))
    sol = lx.linear_solve(op, jnp.ones(2), cjax.DenseLU(), throw=False)
    assert sol.result == lx.RESULTS.singular
    assert jnp.all(sol.value == 0.0)


def test_krylov_failure_says_krylov():
    n = 20
    d = jnp.linspace(1.0, 1e4, n)
    solver = cjax.Newton(linear_solver=cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=3))
    with pytest.raises(eqx.EquinoxRuntimeError, match="Krylov"):
        cjax.extremize(
            lambda x, d: 0.5 * jnp.sum(d * x**2),
            jnp.ones(n),
            d,
            constraints=lambda x, d: jnp.sum(x) - 1.0,
            solver=solver,
        )


# ---------------------------------------------------------------------------------
# 5. Derivatives of failed solves: NaN, never an error
# ---------------------------------------------------------------------------------


def _line(x, p):
    return x[0] + 2.0 * x[1]


def _circle(x, p):
    return x @ x - p


def _on_circle(p, max_steps=256):
    """Extremize x0 + 2 x1 on x.x = p: x = -sqrt(p / 5) (1, 2), value -sqrt(5 p);
    infeasible for p < 0."""
    return cjax.extremize(
        _line,
        jnp.array([-0.5, -0.8]),
        p,
        constraints=_circle,
        max_steps=max_steps,
        throw=False,
    )


_value = lambda p: _on_circle(p).value
_grad = jax.jit(jax.grad(_value))


def test_grad_of_successful_solve_is_unchanged():
    p = jnp.array(1.3)
    assert _on_circle(p).result == R.successful
    g = _grad(p)
    np.testing.assert_allclose(g, -np.sqrt(5.0) / (2 * np.sqrt(1.3)), rtol=1e-10)
    fd = finite_difference_grad(lambda q: _value(q), np.array(1.3))
    np.testing.assert_allclose(g, fd, rtol=1e-7)
    np.testing.assert_allclose(jax.jacfwd(_value)(p), g, rtol=1e-12)


def test_grad_of_failed_solve_is_nan():
    p = jnp.array(-1.0)
    assert _on_circle(p).result == R.infeasible_constraints
    assert jnp.isnan(_grad(p))
    assert jnp.isnan(jax.grad(_value)(p))
    assert jnp.isnan(jax.jacfwd(_value)(p))
    # Also through the multipliers and x.
    assert jnp.all(jnp.isnan(jax.jacrev(lambda q: _on_circle(q).x)(p)))


def test_grad_of_max_steps_is_nan():
    """The KKT matrix is fine there: only the status says the solve failed."""
    value = lambda p: _on_circle(p, max_steps=1).value
    assert _on_circle(jnp.array(1.0), max_steps=1).result != R.successful
    assert jnp.isnan(jax.grad(value)(jnp.array(1.0)))


def test_grad_of_singular_kkt_does_not_raise():
    def value(p):
        return cjax.extremize(
            lambda x, p: p * (x[0] + x[1]),
            jnp.array([0.3, 0.1]),
            p,
            constraints=_diagonal,
            throw=False,
        ).value

    assert jnp.isnan(jax.grad(value)(jnp.array(1.0)))


def test_vmapped_grad_with_a_failing_row():
    ps = jnp.array([1.0, -1.0, 4.0])
    grads = jax.vmap(_grad)(ps)
    assert jnp.isnan(grads[1])
    expected = -np.sqrt(5.0) / (2 * np.sqrt(np.array([1.0, 4.0])))
    np.testing.assert_allclose(grads[jnp.array([0, 2])], expected, rtol=1e-10)


def _fit_loss(p, args):
    return -_on_circle(p).value  # sqrt(5 p), decreasing as p goes to 0 and below


@pytest.mark.parametrize("p0", [1.0, -1.0])
def test_fit_stops_at_a_failed_inner_solve(p0):
    """sgd(0.3) from p = 1 goes 1 -> 0.665 -> 0.253 -> -0.41 (infeasible)."""
    res = cjax.fit(
        _fit_loss, jnp.array(p0), optimizer=optax.sgd(0.3), steps=20, throw=False
    )
    assert res.result == R.nonfinite
    if p0 > 0:
        p1 = 1.0 - 0.3 * np.sqrt(5.0) / 2
        p2 = p1 - 0.3 * np.sqrt(5.0) / (2 * np.sqrt(p1))
        assert int(res.steps) == 2
        np.testing.assert_allclose(res.params, p2, rtol=1e-10)
        assert jnp.isfinite(res.losses[2])
    else:
        assert int(res.steps) == 0
        assert res.params == p0


def test_grad_of_failed_functional_is_nan():
    rope = cjax.Functional(
        cat.potential_energy,
        (0.0, 1.0),
        (0.0, 0.0),
        (cjax.IntegralConstraint(cat.arc_length, cat.rope_length),),
    )

    def energy(length, max_steps):
        return cjax.solve_functional(
            rope,
            {"rho_g": 1.0, "length": length},
            discretization=cjax.PiecewiseLinear(11),
            y0=lambda x: -0.3 * 4 * x * (1 - x),
            max_steps=max_steps,
            throw=False,
        ).value

    assert jnp.isfinite(jax.grad(energy)(jnp.array(1.5), 256))
    assert jnp.isnan(jax.grad(energy)(jnp.array(1.5), 1))
    # No rope shorter than the chord: the backward pass must not raise either.
    assert jnp.isnan(jax.grad(energy)(jnp.array(0.9), 256))


# ---------------------------------------------------------------------------------
# 6. Variants
# ---------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [jnp.nan, jnp.inf])
def test_nonfinite_multipliers0(bad):
    sol = _solve(_sum_squares, [0.3, 0.1], _diagonal, multipliers0=jnp.array([bad]))
    assert sol.result == R.invalid_input
    assert sol.kind == cjax.EXTREMUM.unknown


def test_start_at_a_saddle():
    sol = _solve(lambda x, a: x[0] ** 2 - x[1] ** 2, [0.0, 0.0])
    assert sol.result == R.successful
    assert sol.kind == cjax.EXTREMUM.saddle
    assert jnp.all(sol.x == 0.0)


@pytest.mark.parametrize(
    "objective, constraints, x0",
    [
        # The Hessian is singular at the start (an inflection in x0).
        (lambda x, a: x[0] ** 3 - 3 * x[0] + x[1] ** 2, None, [0.0, 0.0]),
        # Unbounded: F linear, no stationary point anywhere.
        (lambda x, a: x[0], None, [0.3, 0.1]),
        # The constraint holds at the start; F has no stationary point on it.
        (_linear, lambda x, a: x[1], [1.0, 0.0]),
    ],
)
def test_no_stationary_point_reachable(objective, constraints, x0):
    sol = _solve(objective, x0, constraints)
    assert sol.result == R.singular_kkt
    assert sol.kind == cjax.EXTREMUM.unknown


def test_one_step_is_not_success():
    """A quadratic on a plane: one Newton step lands on the answer, but convergence
    is only known at the next step."""
    sol = _solve(_sum_squares, [0.3, 0.1], lambda x, a: x[0] + x[1] - 1.0, max_steps=1)
    assert sol.result == R.nonlinear_max_steps_reached
    assert sol.kind == cjax.EXTREMUM.unknown
    sol = _solve(_sum_squares, [0.3, 0.1], lambda x, a: x[0] + x[1] - 1.0)
    assert sol.result == R.successful
    np.testing.assert_allclose(sol.x, [0.5, 0.5], rtol=1e-14)
    assert sol.kind == cjax.EXTREMUM.minimum


def test_statuses_per_row_under_vmap():
    sols = jax.vmap(_on_circle)(jnp.array([1.0, -1.0, jnp.nan]))
    assert list(sols.result == R.successful) == [True, False, False]
    assert list(sols.result == R.infeasible_constraints) == [False, True, False]
    assert list(sols.result == R.invalid_input) == [False, False, True]
    assert list(sols.kind == cjax.EXTREMUM.minimum) == [True, False, False]
    assert list(sols.kind == cjax.EXTREMUM.unknown) == [False, True, True]
