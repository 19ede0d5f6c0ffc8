"""The linear solvers behind every KKT solve: unrolled dense LU and MINRES."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax._solver.dense_lu import lu_factor_unrolled, lu_solve_unrolled
from constrained_jax._solver.minres import minres


def _kkt_matrix(rng, n, k):
    h = rng.normal(size=(n, n))
    h = h + h.T
    j = rng.normal(size=(k, n))
    return np.block([[h, j.T], [j, np.zeros((k, k))]])


@pytest.mark.parametrize("m", [1, 2, 3, 5, 8, 12])
def test_unrolled_lu_matches_numpy(m):
    rng = np.random.default_rng(m)
    a = rng.normal(size=(m, m)) + m * np.eye(m) * rng.choice([-1, 1])
    b = rng.normal(size=m)
    lu, perm, singular = lu_factor_unrolled(jnp.asarray(a))
    assert not singular
    x = lu_solve_unrolled(lu, perm, jnp.asarray(b))
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10, atol=1e-12)


def test_unrolled_lu_pivots_on_zero_diagonal():
    """A KKT matrix has a zero block: elimination without pivoting would divide by 0."""
    rng = np.random.default_rng(0)
    a = _kkt_matrix(rng, 3, 2)
    a = np.roll(a, 3, axis=0)  # put the zero block first
    b = rng.normal(size=5)
    lu, perm, singular = lu_factor_unrolled(jnp.asarray(a))
    assert not singular
    np.testing.assert_allclose(
        lu_solve_unrolled(lu, perm, jnp.asarray(b)), np.linalg.solve(a, b), rtol=1e-10
    )


def test_unrolled_lu_detects_singular():
    a = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]])
    assert lu_factor_unrolled(jnp.asarray(a))[2]
    assert lu_factor_unrolled(jnp.zeros((2, 2)))[2]


def test_unrolled_lu_vmaps():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(64, 4, 4)) + 4 * np.eye(4)
    b = rng.normal(size=(64, 4))
    solve = jax.vmap(lambda a, b: lu_solve_unrolled(*lu_factor_unrolled(a)[:2], b))
    np.testing.assert_allclose(solve(a, b), np.linalg.solve(a, b[..., None])[..., 0])


@pytest.mark.parametrize("size", [4, 20])
def test_dense_lu_in_lineax_with_derivatives(size):
    """DenseLU (unrolled for 4, LAPACK for 20) as a Lineax solver: the solution and its
    derivatives with respect to the matrix and vector (which use the transpose)."""
    rng = np.random.default_rng(size)
    a = jnp.asarray(rng.normal(size=(size, size)) + size * np.eye(size))
    b = jnp.asarray(rng.normal(size=size))
    solver = cjax.DenseLU(unroll_max=12)

    def ours(a, b):
        op = lx.MatrixLinearOperator(a)
        return jnp.sum(jnp.sin(lx.linear_solve(op, b, solver).value))

    def ref(a, b):
        return jnp.sum(jnp.sin(jnp.linalg.solve(a, b)))

    np.testing.assert_allclose(ours(a, b), ref(a, b), rtol=1e-12)
    for argnum in (0, 1):
        np.testing.assert_allclose(
            jax.grad(ours, argnum)(a, b), jax.grad(ref, argnum)(a, b), rtol=1e-9
        )


def test_dense_lu_reports_singular():
    op = lx.MatrixLinearOperator(jnp.array([[1.0, 1.0], [1.0, 1.0]]))
    sol = lx.linear_solve(op, jnp.ones(2), cjax.DenseLU(), throw=False)
    assert sol.result == lx.RESULTS.singular
    assert jnp.all(jnp.isfinite(sol.value))


def test_minres_on_indefinite_kkt_matrix():
    rng = np.random.default_rng(2)
    a = _kkt_matrix(rng, 40, 3)
    b = rng.normal(size=43)
    x, _, converged = minres(
        lambda v: jnp.asarray(a) @ v,
        jnp.asarray(b),
        rtol=1e-12,
        atol=0.0,
        max_steps=500,
    )
    assert converged
    np.testing.assert_allclose(a @ np.asarray(x), b, atol=1e-9)


def test_minres_in_lineax_requires_symmetry():
    op = lx.MatrixLinearOperator(jnp.eye(3))
    with pytest.raises(ValueError, match="symmetric"):
        lx.linear_solve(op, jnp.ones(3), cjax.MINRES(rtol=1e-10, atol=0.0))
    op = lx.MatrixLinearOperator(2 * jnp.eye(3), lx.symmetric_tag)
    sol = lx.linear_solve(op, jnp.ones(3), cjax.MINRES(rtol=1e-10, atol=0.0))
    np.testing.assert_allclose(sol.value, 0.5)


def test_minres_reports_max_steps():
    rng = np.random.default_rng(3)
    a = _kkt_matrix(rng, 40, 3)
    op = lx.MatrixLinearOperator(jnp.asarray(a), lx.symmetric_tag)
    sol = lx.linear_solve(
        op,
        jnp.asarray(rng.normal(size=43)),
        cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=5),
        throw=False,
    )
    assert sol.result == lx.RESULTS.max_steps_reached
