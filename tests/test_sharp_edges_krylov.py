"""Sharp edges of the linear solve inside `extremize`'s Newton (issue 41, section 2).

- A linear solve never turns NaN into a number: MINRES given a NaN (or inf)
  right-hand side or matrix returns NaN and `nonfinite_input`, never zeros.
- Newton's damping treats every linear solver alike: a trial point where the residual
  is not finite is rejected, for MINRES exactly as for dense LU.
- F or its gradient NaN at an iterate is `nonfinite_objective`, whatever the linear
  solver, never `linear_solve_failed`.
- The default linear solver is chosen by memory; the Krylov solve is preconditioned
  and falls back on dense LU where it fails and the matrix fits.
- The reproducer: the maximum-entropy distribution over n states with a
  normalisation and a mean-energy constraint (strictly concave, well posed), whose
  closed form x_i = exp(-beta E_i) / Z has beta from a scalar root found here
  independently by SciPy's `brentq`. It failed with the defaults at n = 1000 and with
  `Newton(linear_solver=MINRES(...))` at n = 100 (the iterate left the domain of
  `x log x` and the NaN was taken for a Krylov failure).
"""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
from scipy.optimize import brentq

import constrained_jax as cjax
from constrained_jax._solver.fallback import Fallback
from constrained_jax._solver.minres import minres


R = cjax.RESULTS
E_MEAN = 0.3


# ---------------------------------------------------------------------------------
# The maximum-entropy distribution
# ---------------------------------------------------------------------------------


def entropy(x, args):
    return -jnp.sum(x * jnp.log(x))


def normalisation_and_mean(x, args):
    energies, mean = args
    return jnp.stack([jnp.sum(x) - 1.0, jnp.dot(x, energies) - mean])


def closed_form(n: int, mean: float = E_MEAN):
    """x_i = exp(-beta E_i) / Z with E_i = i / n and beta the root of
    <E>_beta = mean (monotone in beta), by `brentq`."""
    e = np.arange(n) / n

    def mean_minus_target(beta):
        w = -beta * (e - mean)
        w = np.exp(w - w.max())
        return np.dot(e - mean, w) / w.sum()

    beta = brentq(mean_minus_target, -200.0, 200.0, xtol=1e-15, rtol=1e-15)
    w = -beta * (e - mean)
    w = np.exp(w - w.max())
    return w / w.sum()


def _args(n, dtype=jnp.float64):
    return (jnp.arange(n, dtype=dtype) / n, jnp.asarray(E_MEAN, dtype))


def _maximise(n, solver, x0=None, dtype=jnp.float64):
    x0 = jnp.full((n,), 1.0 / n, dtype) if x0 is None else x0
    return cjax.extremize(
        entropy,
        x0,
        _args(n, dtype),
        constraints=normalisation_and_mean,
        sense="maximize",
        solver=solver,
        throw=False,
    )


def _check(sol, n, rtol=1e-9):
    assert sol.result == R.successful, sol.result
    assert sol.kind == cjax.EXTREMUM.maximum
    np.testing.assert_allclose(np.asarray(sol.x, np.float64), closed_form(n), rtol=rtol)


def _krylov(probes=16):
    return cjax.Newton(linear_solver=cjax.MINRES(rtol=1e-12, atol=0.0, probes=probes))


@pytest.mark.parametrize(
    "solver",
    [cjax.Newton(), _krylov(), _krylov(probes=0)],
    ids=["dense", "minres", "minres-unpreconditioned"],
)
def test_maximum_entropy_n100_any_linear_solver(solver):
    """From the uniform start the full Newton step leaves the domain (some x_i < 0);
    the damping backs off for every linear solver alike."""
    _check(_maximise(100, solver), 100)


def test_maximum_entropy_n1000_defaults():
    """The defaults at n + k = 1002: a dense solve (formerly unpreconditioned MINRES,
    which failed)."""
    _check(_maximise(1000, None), 1000)


@pytest.mark.parametrize("solver", [None, _krylov()], ids=["default", "minres"])
def test_maximum_entropy_from_a_careless_start(solver):
    """A start far from the answer, not normalised, with entries near zero."""
    n = 100
    x0 = jnp.where(jnp.arange(n) % 3 == 0, 1e-9, 0.5)
    _check(_maximise(n, solver, x0), n)


def test_maximum_entropy_float32_minres():
    """float32 throughout, with a float64 tolerance passed carelessly: MINRES raises
    `rtol=1e-12` to 100 eps = 1.2e-5, as Newton does its own."""
    n = 100
    sol = _maximise(n, _krylov(), dtype=jnp.float32)
    assert sol.x.dtype == jnp.float32
    _check(sol, n, rtol=1e-4)


def test_maximum_entropy_float32_default():
    """float32 with the defaults: the dense solve equilibrates first (DenseLU's pivot
    test, `10 m eps max|K|`, would take the badly scaled KKT matrix, entries `1/x_i`
    next to constraint rows of ones, for singular)."""
    n = 100
    sol = _maximise(n, None, dtype=jnp.float32)
    _check(sol, n, rtol=1e-4)


# ---------------------------------------------------------------------------------
# MINRES never turns NaN into a number
# ---------------------------------------------------------------------------------


def _kkt(n=8, k=2, seed=0):
    rng = np.random.default_rng(seed)
    h = np.diag(rng.uniform(1.0, 3.0, n))
    j = rng.normal(size=(k, n))
    return np.block([[h, j.T], [j, np.zeros((k, k))]])


@pytest.mark.parametrize("bad", [jnp.nan, jnp.inf])
@pytest.mark.parametrize("probes", [16, 0])
def test_minres_nonfinite_rhs_is_nan(bad, probes):
    a = _kkt()
    b = jnp.ones(a.shape[0]).at[3].set(bad)
    op = lx.MatrixLinearOperator(jnp.asarray(a), lx.symmetric_tag)
    solver = cjax.MINRES(rtol=1e-12, atol=0.0, probes=probes)
    sol = lx.linear_solve(op, b, solver, throw=False)
    assert sol.result == lx.RESULTS.nonfinite_input
    assert jnp.all(jnp.isnan(sol.value))


@pytest.mark.parametrize("probes", [16, 0])
def test_minres_nonfinite_matrix_is_nan(probes):
    a = _kkt()
    a[2, 5] = a[5, 2] = np.nan
    op = lx.MatrixLinearOperator(jnp.asarray(a), lx.symmetric_tag)
    solver = cjax.MINRES(rtol=1e-12, atol=0.0, probes=probes)
    sol = lx.linear_solve(op, jnp.ones(a.shape[0]), solver, throw=False)
    assert sol.result == lx.RESULTS.nonfinite_input
    assert jnp.all(jnp.isnan(sol.value))


def test_minres_function_nan_rhs_is_nan_not_converged():
    a = jnp.asarray(_kkt())
    b = jnp.full(a.shape[0], jnp.nan)
    x, _, converged = minres(lambda v: a @ v, b, rtol=1e-12, atol=0.0, max_steps=50)
    assert not converged
    assert jnp.all(jnp.isnan(x))


def test_minres_zero_rhs_is_zero():
    """The one right-hand side whose answer is zero."""
    a = _kkt()
    op = lx.MatrixLinearOperator(jnp.asarray(a), lx.symmetric_tag)
    sol = lx.linear_solve(op, jnp.zeros(a.shape[0]), cjax.MINRES(rtol=1e-12, atol=0.0))
    assert jnp.all(sol.value == 0.0)


# ---------------------------------------------------------------------------------
# The preconditioner and the dense fallback
# ---------------------------------------------------------------------------------


def _ill_conditioned_kkt(n=200):
    """A KKT matrix whose Hessian diagonal spans ten orders of magnitude (and
    dominates its rows: the diagonal preconditioner is then Jacobi on the Hessian)."""
    rng = np.random.default_rng(1)
    d = np.logspace(0, 10, n)
    rng.shuffle(d)
    j = np.stack([np.ones(n), np.arange(n) / n])
    return np.block([[np.diag(d), j.T], [j, np.zeros((2, 2))]])


def test_preconditioner_makes_ill_conditioned_kkt_converge():
    a = _ill_conditioned_kkt()
    b = np.random.default_rng(2).normal(size=a.shape[0])
    op = lx.MatrixLinearOperator(jnp.asarray(a), lx.symmetric_tag)
    plain = cjax.MINRES(rtol=1e-10, atol=0.0, max_steps=100, probes=0)
    sol = lx.linear_solve(op, jnp.asarray(b), plain, throw=False)
    assert sol.result == lx.RESULTS.max_steps_reached
    preconditioned = cjax.MINRES(rtol=1e-10, atol=0.0, max_steps=100)
    sol = lx.linear_solve(op, jnp.asarray(b), preconditioned)
    x = np.asarray(sol.value)
    assert np.linalg.norm(a @ x - b) <= 1e-10 * np.linalg.norm(b)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-6, atol=1e-12)


def test_minres_probes_must_be_non_negative():
    with pytest.raises(ValueError, match="probes"):
        cjax.MINRES(rtol=1e-10, atol=0.0, probes=-1)


def test_fallback_solves_where_krylov_fails():
    a = _ill_conditioned_kkt()
    b = np.random.default_rng(3).normal(size=a.shape[0])
    op = lx.MatrixLinearOperator(jnp.asarray(a), lx.symmetric_tag)
    weak = cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=2)
    sol = lx.linear_solve(op, jnp.asarray(b), Fallback(weak, cjax.DenseLU()))
    np.testing.assert_allclose(sol.value, np.linalg.solve(a, b), rtol=1e-8)


def test_fallback_keeps_nonfinite_input_and_reports_singular():
    a = _kkt()
    op = lx.MatrixLinearOperator(jnp.asarray(a), lx.symmetric_tag)
    solver = Fallback(cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=2), cjax.DenseLU())
    b = jnp.ones(a.shape[0]).at[0].set(jnp.nan)
    sol = lx.linear_solve(op, b, solver, throw=False)
    assert sol.result == lx.RESULTS.nonfinite_input
    assert jnp.all(jnp.isnan(sol.value))
    # Two equal constraint rows: singular, said by the dense solve.
    a[-1, :] = a[-2, :]
    a[:, -1] = a[:, -2]
    op = lx.MatrixLinearOperator(jnp.asarray(a), lx.symmetric_tag)
    sol = lx.linear_solve(op, jnp.ones(a.shape[0]), solver, throw=False)
    assert sol.result == lx.RESULTS.singular


def test_fallback_gradients_through_extremize():
    """The implicit-function derivative through the fallback solver (its transpose)
    matches the envelope theorem: d S / d mean = -lambda_2."""
    n = 30
    solver = cjax.Newton(
        linear_solver=Fallback(
            cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=1), cjax.DenseLU()
        )
    )

    def value(mean):
        sol = cjax.extremize(
            entropy,
            jnp.full((n,), 1.0 / n),
            (jnp.arange(n) / n, mean),
            constraints=normalisation_and_mean,
            solver=solver,
        )
        return sol.value, sol

    grad, sol = jax.grad(value, has_aux=True)(jnp.asarray(E_MEAN))
    np.testing.assert_allclose(sol.x, closed_form(n), rtol=1e-9)
    np.testing.assert_allclose(grad, -sol.multipliers[1], rtol=1e-8)


# ---------------------------------------------------------------------------------
# Undefined points: the same status for every linear solver
# ---------------------------------------------------------------------------------


_SOLVERS = [cjax.Newton(), _krylov()]
_IDS = ["dense", "minres"]


@pytest.mark.parametrize("solver", _SOLVERS, ids=_IDS)
def test_nan_gradient_at_start_is_nonfinite_objective(solver):
    """F(x0) is finite but its gradient is not (sqrt at 0): `nonfinite_objective`,
    not a Krylov failure."""
    sol = cjax.extremize(
        lambda x, a: jnp.sum(jnp.sqrt(x)),
        jnp.array([0.0, 1.0, 2.0]),
        constraints=lambda x, a: jnp.sum(x) - 3.0,
        solver=solver,
        throw=False,
    )
    assert sol.result == R.nonfinite_objective


@pytest.mark.parametrize("solver", _SOLVERS, ids=_IDS)
def test_newton_backs_off_at_the_edge_of_the_domain(solver):
    """min sum (x - 2)^2 - log(1.5 - x) subject to x_0 = x_1, convex on x < 1.5 with
    its minimum at x = 1 (the root of 2 x^2 - 7 x + 5 in the domain). From x = -3
    the full Newton step lands at 1.77, where F is NaN (its gradient is not): the
    damping backs off, for every linear solver alike, and the minimum is found (not
    the root x = 2.5 of the gradient outside the domain)."""

    def objective(x, a):
        return jnp.sum((x - 2.0) ** 2 - jnp.log(1.5 - x))

    sol = cjax.extremize(
        objective,
        jnp.array([-3.0, -3.0]),
        constraints=lambda x, a: x[0] - x[1],
        sense="minimize",
        solver=solver,
        throw=False,
    )
    assert sol.result == R.successful
    np.testing.assert_allclose(sol.x, [1.0, 1.0], rtol=1e-12)
