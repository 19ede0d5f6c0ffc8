"""Bad input to `extremize`: a trace-time ValueError for structure, a RESULTS member
for values (raised when throw=True). Never a silent NaN."""

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import cylinder_volume as cyl


ARGS = {"b": jnp.array(2.0), "l": jnp.array(3.0)}
X0 = jnp.array([0.2, 1.0])


def _solve(**kwargs):
    kwargs.setdefault("constraints", cyl.constraint)
    objective = kwargs.pop("objective", cyl.volume)
    x0 = kwargs.pop("x0", X0)
    args = kwargs.pop("args", ARGS)
    return cjax.extremize(objective, x0, args, **kwargs)


def test_non_scalar_objective():
    with pytest.raises(ValueError, match="must return a scalar"):
        _solve(objective=lambda x, args: x**2)


def test_integer_objective():
    with pytest.raises(ValueError, match="floating-point"):
        _solve(objective=lambda x, args: jnp.sum(x > 0), constraints=None)


def test_constraints_of_wrong_shape():
    with pytest.raises(ValueError, match=r"shape \(k,\)"):
        _solve(constraints=lambda x, args: jnp.ones((2, 1)) * x[0])


def test_more_constraints_than_unknowns():
    with pytest.raises(ValueError, match="more constraints"):
        _solve(constraints=lambda x, args: jnp.stack([x[0], x[1], x[0] + x[1] - 1]))


def test_empty_constraints():
    with pytest.raises(ValueError, match="constraints=None"):
        _solve(constraints=lambda x, args: jnp.zeros((0,)))


def test_multipliers0_of_wrong_shape():
    with pytest.raises(ValueError, match="multipliers0"):
        _solve(multipliers0=jnp.zeros(2))


def test_solver_given_as_string():
    with pytest.raises(ValueError, match="solver"):
        _solve(solver="newton")


@pytest.mark.parametrize("max_steps", [0, -3, 2.5, None])
def test_bad_max_steps(max_steps):
    with pytest.raises(ValueError, match="max_steps"):
        _solve(max_steps=max_steps)


def test_bad_tolerances():
    with pytest.raises(ValueError, match="non-negative"):
        cjax.Newton(rtol=-1.0)
    with pytest.raises(ValueError, match="positive"):
        cjax.Newton(rtol=0.0, atol=0.0)


@pytest.mark.parametrize("bad", [jnp.nan, jnp.inf, -jnp.inf])
def test_nonfinite_x0(bad):
    x0 = X0.at[1].set(bad)
    sol = _solve(x0=x0, throw=False)
    assert sol.result == cjax.RESULTS.invalid_input
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf"):
        _solve(x0=x0)


@pytest.mark.parametrize("bad", [jnp.nan, jnp.inf])
def test_nonfinite_args(bad):
    args = {"b": jnp.array(bad), "l": jnp.array(3.0)}
    sol = _solve(args=args, throw=False)
    assert sol.result == cjax.RESULTS.invalid_input
    with pytest.raises(eqx.EquinoxRuntimeError, match="NaN or inf"):
        _solve(args=args)


def test_nonfinite_in_one_batch_element_is_reported_there():
    ls = jnp.array([3.0, jnp.nan, 1.0])
    sols = jax.vmap(lambda l: _solve(args={"b": jnp.array(2.0), "l": l}, throw=False))(
        ls
    )
    ok = sols.result == cjax.RESULTS.successful
    assert ok[0] and ok[2] and not ok[1]
    assert (sols.result == cjax.RESULTS.invalid_input)[1]
    assert jnp.all(jnp.isfinite(sols.x[jnp.array([0, 2])]))


def test_redundant_constraints():
    """Two copies of one constraint: the Jacobian has rank 1 < k = 2."""
    redundant = lambda x, args: jnp.stack(
        [cyl.constraint(x, args)[0], 2.0 * cyl.constraint(x, args)[0]]
    )
    sol = _solve(constraints=redundant, throw=False)
    assert sol.result == cjax.RESULTS.redundant_constraints
    with pytest.raises(eqx.EquinoxRuntimeError, match="rank-deficient"):
        _solve(constraints=redundant)


def test_vanishing_constraint_gradient():
    """G = (x + y - 1)^2 holds on the line but its gradient vanishes there."""
    sol = cjax.extremize(
        lambda x, a: jnp.sum(x**2),
        jnp.array([0.5, 0.5]),
        constraints=lambda x, a: (x[0] + x[1] - 1.0) ** 2,
        throw=False,
    )
    assert sol.result == cjax.RESULTS.redundant_constraints


def test_singular_kkt_matrix():
    """F = x + y on x - y = 0: F is linear along the constraint, so there is no
    stationary point and the KKT matrix [[0, J^T], [J, 0]] is singular."""
    sol = cjax.extremize(
        lambda x, a: x[0] + x[1],
        jnp.array([0.3, 0.1]),
        constraints=lambda x, a: x[0] - x[1],
        throw=False,
    )
    assert sol.result == cjax.RESULTS.singular_kkt
    assert jnp.all(jnp.isfinite(sol.x))
    with pytest.raises(eqx.EquinoxRuntimeError, match="KKT matrix"):
        cjax.extremize(
            lambda x, a: x[0] + x[1],
            jnp.array([0.3, 0.1]),
            constraints=lambda x, a: x[0] - x[1],
        )


def test_max_steps_reached():
    sol = _solve(x0=jnp.array([5.0, 3.0]), max_steps=2, throw=False)
    assert sol.result == cjax.RESULTS.nonlinear_max_steps_reached
    with pytest.raises(eqx.EquinoxRuntimeError, match="maximum number of steps"):
        _solve(x0=jnp.array([5.0, 3.0]), max_steps=2)


def test_no_stationary_point_is_reported():
    """exp(x) has no stationary point; Newton marches off and must say so."""
    sol = cjax.extremize(
        lambda x, a: jnp.sum(jnp.exp(x)), jnp.array([0.0]), max_steps=50, throw=False
    )
    assert sol.result != cjax.RESULTS.successful


def test_krylov_failure_is_reported():
    """MINRES with too few iterations for the KKT system says so."""
    n = 50
    d = jnp.linspace(1.0, 1e4, n)
    solver = cjax.Newton(linear_solver=cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=3))
    sol = cjax.extremize(
        lambda x, d: 0.5 * jnp.sum(d * x**2),
        jnp.ones(n),
        d,
        constraints=lambda x, d: jnp.sum(x) - 1.0,
        solver=solver,
        throw=False,
    )
    assert sol.result == cjax.RESULTS.linear_solve_failed
