"""Bad input to the functional solvers: trace-time ValueErrors and RESULTS statuses."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import catenary as cat


def _rope(length_fn=cat.rope_length):
    return cjax.Functional(
        cat.potential_energy,
        (0.0, 1.0),
        (0.0, 0.0),
        (cjax.IntegralConstraint(cat.arc_length, length_fn),),
    )


_GUESS = lambda x: -0.3 * 4 * x * (1 - x)
_SMALL = cjax.PiecewiseLinear(11)


def test_length_not_exceeding_chord():
    with pytest.raises(ValueError, match="must exceed the chord"):
        cat.solve(0.0, 0.0, 1.0, 0.0, length=1.0)
    with pytest.raises(ValueError, match="must exceed the chord"):
        cat.closed_form(0.0, 0.0, 3.0, 4.0, 4.9)
    # Through the general solver no rope exists: a failure status, never a silent
    # answer, and throw=True raises. The start `y0` cannot be moved onto the
    # length, so the status names the constraints (issue 41; it was Newton's own).
    sol = cjax.solve_functional(
        _rope(),
        {"rho_g": 1.0, "length": 0.9},
        discretization=_SMALL,
        y0=_GUESS,
        throw=False,
    )
    assert sol.result == cjax.RESULTS.infeasible_constraints
    with pytest.raises(Exception, match="length shorter than the distance"):
        cjax.solve_functional(
            _rope(), {"rho_g": 1.0, "length": 0.9}, discretization=_SMALL, y0=_GUESS
        )


def test_non_convergence_status():
    sol = cjax.solve_functional(
        _rope(),
        {"rho_g": 1.0, "length": 1.5},
        discretization=_SMALL,
        y0=_GUESS,
        max_steps=1,
        throw=False,
    )
    assert sol.result == cjax.RESULTS.nonlinear_max_steps_reached


def test_nonfinite_args_status():
    sol = cjax.solve_functional(
        _rope(),
        {"rho_g": jnp.nan, "length": 1.5},
        discretization=_SMALL,
        y0=_GUESS,
        throw=False,
    )
    assert sol.result == cjax.RESULTS.invalid_input


def test_non_scalar_lagrangian():
    fun = cjax.Functional(
        lambda y, yp, x, a: jnp.stack([y, yp]), (0.0, 1.0), (0.0, 1.0)
    )
    with pytest.raises(ValueError, match="must return a scalar"):
        cjax.solve_functional(fun, discretization=_SMALL)


def test_non_scalar_integrand():
    fun = cjax.Functional(
        cat.potential_energy,
        (0.0, 1.0),
        (0.0, 0.0),
        (cjax.IntegralConstraint(lambda y, yp, x, a: jnp.stack([y, y]), 1.0),),
    )
    with pytest.raises(ValueError, match="must return a scalar"):
        cjax.solve_functional(fun, {"rho_g": 1.0}, discretization=_SMALL)


@pytest.mark.parametrize(
    "boundary",
    [(0.0, jnp.zeros(2)), (jnp.zeros((2, 2)), jnp.zeros((2, 2))), (jnp.zeros(0),) * 2],
)
def test_boundary_shapes(boundary):
    with pytest.raises(ValueError, match="boundary"):
        cjax.Functional(cat.potential_energy, (0.0, 1.0), boundary)


def test_interval_order():
    with pytest.raises(ValueError, match="xL < xR"):
        cjax.Functional(cat.potential_energy, (1.0, 0.0), (0.0, 0.0))


@pytest.mark.parametrize("cls", [cjax.Chebyshev, cjax.PiecewiseLinear])
@pytest.mark.parametrize("num_nodes", [2, 0, 3.5])
def test_too_few_nodes(cls, num_nodes):
    with pytest.raises(ValueError, match="num_nodes"):
        cls(num_nodes)


def test_strategies_are_objects():
    with pytest.raises(ValueError, match="discretization"):
        cjax.solve_functional(
            _rope(), {"rho_g": 1.0, "length": 1.5}, discretization="x"
        )
    with pytest.raises(ValueError, match="solver"):
        cjax.solve_functional(
            _rope(), {"rho_g": 1.0, "length": 1.5}, discretization=_SMALL, solver="x"
        )


def test_y0_shape():
    with pytest.raises(ValueError, match="y0"):
        cjax.solve_functional(
            _rope(), {"rho_g": 1.0, "length": 1.5}, discretization=_SMALL, y0=np.ones(7)
        )


def test_too_many_holonomic_constraints():
    fun = cjax.Functional(
        lambda y, yp, x, a: jnp.sum(yp**2),
        (0.0, 1.0),
        (jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0])),
        holonomic=lambda y, x, a: jnp.stack([y[0] - 1.0, y[1]]),
    )
    with pytest.raises(ValueError, match="m < n"):
        cjax.solve_functional(fun, discretization=_SMALL)


def test_shooting_rejects_holonomic():
    fun = cjax.Functional(
        lambda y, yp, x, a: jnp.sum(yp**2),
        (0.0, 1.0),
        (jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0])),
        holonomic=lambda y, x, a: jnp.sum(y**2) - 1.0,
    )
    with pytest.raises(ValueError, match="holonomic"):
        cjax.solve_shooting(fun, slope0=jnp.zeros(2))


def test_jit_of_errors_is_trace_time():
    """Structure errors surface at trace time, also under jit."""
    fun = cjax.Functional(
        lambda y, yp, x, a: jnp.stack([y, yp]), (0.0, 1.0), (0.0, 1.0)
    )
    with pytest.raises(ValueError, match="must return a scalar"):
        jax.jit(lambda: cjax.solve_functional(fun, discretization=_SMALL))()


@pytest.mark.parametrize("discretization", [_SMALL, cjax.Chebyshev(12)])
def test_solution_is_nan_outside_its_interval(discretization):
    """`sol(x)` outside [xL, xR] extrapolated without a word (the rope at x = 2 was
    3.76 above its ends, with a spectral interpolant): NaN there; the ends and the
    inside as before (the nodal values at the nodes). As the start `y0` of another
    solve (a continuation in the length, on other nodes) it works as before."""
    args = {"rho_g": 1.0, "length": 1.5}
    sol = cjax.solve_functional(_rope(), args, discretization=discretization, y0=_GUESS)
    assert sol.result == cjax.RESULTS.successful
    xs = jnp.array([-1.0, -1e-9, 1.0 + 1e-9, 2.0])
    assert np.all(np.isnan(sol(xs))) and np.all(np.isnan(sol.derivative(xs)))
    np.testing.assert_allclose(sol(sol.x), sol.y, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(sol(jnp.array([0.0, 1.0])), 0.0, atol=1e-14)
    assert np.all(np.isfinite(sol.derivative(jnp.linspace(0.0, 1.0, 7))))
    args = {"rho_g": 1.0, "length": 1.55}
    moved = cjax.solve_functional(
        _rope(), args, discretization=cjax.Chebyshev(24), y0=sol
    )
    assert moved.result == cjax.RESULTS.successful
    ref = cat.closed_form(0.0, 0.0, 1.0, 0.0, 1.55)
    np.testing.assert_allclose(
        moved.multipliers.integral[0], ref["multiplier"], rtol=1e-9
    )


def test_shooting_from_a_far_start_is_refused_not_crept():
    """A trial slope whose solution does not reach xR used to hand Newton the state
    where the integration stopped (x < xR) as the residual at xR, and a NaN iterate
    ran each later integration to 100,000 rejected steps, which a `jax.vmap` batch
    waited for. Now such trials give NaN and integrate nothing. Checked here: the far
    row is refused and the batch's other row is right (the time is not asserted)."""
    fun = cat.functional(0.0, 0.0, 1.0, 0.0)
    args = {"rho_g": jnp.asarray(1.0), "length": jnp.asarray(1.5)}
    ref = cat.closed_form(0.0, 0.0, 1.0, 0.0, 1.5, 1.0)
    solve = jax.jit(
        jax.vmap(
            lambda s, m: cjax.solve_shooting(
                fun, args, slope0=s, multipliers0=m, throw=False
            )
        )
    )
    sol = solve(jnp.array([-1.5, -2.3]), jnp.array([[-1.0], [0.8]]))
    assert sol.result._value[0] != cjax.RESULTS.successful._value
    assert sol.result._value[1] == cjax.RESULTS.successful._value
    np.testing.assert_allclose(sol.multipliers.integral[1, 0], ref["multiplier"])
    one = jax.tree.map(lambda v: v[1], sol)
    xs = np.linspace(0.0, 1.0, 11)
    np.testing.assert_allclose(one(xs), ref["y"](xs), atol=1e-9)


def test_shooting_ode_max_steps_bounds_each_trial():
    """`ode_max_steps` caps each trial's integration: a start that converges with the
    default (see the test above) is refused when no trial may reach `xR`, never
    answered from a state short of it; a bad value is refused at once."""
    fun = cat.functional(0.0, 0.0, 1.0, 0.0)
    args = {"rho_g": jnp.asarray(1.0), "length": jnp.asarray(1.5)}
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="`ode_max_steps` must be a positive int"):
            cjax.solve_shooting(fun, args, slope0=-2.3, ode_max_steps=bad)
    sol = cjax.solve_shooting(
        fun, args, slope0=-2.3, multipliers0=jnp.array([0.8]), ode_max_steps=4,
        throw=False,
    )  # fmt: skip
    assert sol.result == cjax.RESULTS.nonfinite  # as documented for such trials
    with pytest.raises(eqx.EquinoxRuntimeError, match="Nonfinite"):
        cjax.solve_shooting(
            fun, args, slope0=-2.3, multipliers0=jnp.array([0.8]), ode_max_steps=4
        )
