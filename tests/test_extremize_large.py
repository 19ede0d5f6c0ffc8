"""A large problem solved matrix-free: the maximum-entropy distribution.

Maximise the entropy S = -sum_i p_i log p_i over n states with energies E_i subject
to three constraints: sum p = 1, sum p E = m1, sum p E^2 = m2. Stationarity gives
-log p_i - 1 + lambda_1 + lambda_2 E_i + lambda_3 E_i^2 = 0, i.e. the Gibbs-like
distribution p_i = exp(-b E_i - g E_i^2) / Z with b = -lambda_2, g = -lambda_3, and
(b, g) minimise the convex dual log Z(b, g) + b m1 + g m2. The reference solves that
2 x 2 dual by Newton's method in NumPy: an independent route to the same answer.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax


M1, M2 = 0.35, 0.2


def entropy(p, args):
    return -jnp.sum(p * jnp.log(p))


def moments(p, args):
    energies, m1, m2 = args
    return jnp.stack(
        [jnp.sum(p) - 1.0, jnp.dot(p, energies) - m1, jnp.dot(p, energies**2) - m2]
    )


def dual_reference(energies, m1, m2):
    """Damped Newton on the convex dual; returns (b, g, p, log Z)."""
    e = np.asarray(energies, dtype=np.float64)
    feats = np.stack([e, e**2])
    target = np.array([m1, m2])

    def dual(v):
        w = -v @ feats
        log_z = w.max() + np.log(np.exp(w - w.max()).sum())
        return log_z + v @ target, np.exp(w - log_z)

    v = np.zeros(2)
    for _ in range(200):
        value, p = dual(v)
        mean = feats @ p
        grad = target - mean
        cov = (feats * p) @ feats.T - np.outer(mean, mean)
        step = -np.linalg.solve(cov, grad)
        t = 1.0
        while dual(v + t * step)[0] > value + 1e-4 * t * grad @ step and t > 1e-12:
            t /= 2
        v = v + t * step
        if np.max(np.abs(t * step)) < 1e-14 * max(1.0, np.max(np.abs(v))):
            break
    value, p = dual(v)
    log_z = value - v @ target
    return v[0], v[1], p, log_z


def _check(sol, energies):
    b, g, p, log_z = dual_reference(energies, M1, M2)
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, p, rtol=1e-9)
    lam = np.asarray(sol.multipliers)
    np.testing.assert_allclose(lam[1:], [-b, -g], rtol=1e-9)
    # lambda_1 = 1 - log Z from the stationarity condition.
    np.testing.assert_allclose(lam[0], 1 - log_z, rtol=1e-9)
    # Entropy at the maximum: S = log Z + b m1 + g m2.
    np.testing.assert_allclose(sol.value, log_z + b * M1 + g * M2, rtol=1e-11)
    assert sol.kind == cjax.EXTREMUM.maximum


def test_maximum_entropy_dense():
    n = 300
    energies = jnp.linspace(0.0, 1.0, n)
    sol = cjax.extremize(
        entropy, jnp.full(n, 1.0 / n), (energies, M1, M2), constraints=moments
    )
    _check(sol, energies)


def test_dense_and_matrix_free_agree_with_gradients():
    """Same problem, both linear solvers, including implicit-function gradients (the
    matrix-free backward pass solves with MINRES too)."""
    n = 200
    energies = jnp.linspace(0.0, 1.0, n)
    krylov = cjax.Newton(linear_solver=cjax.MINRES(rtol=1e-12, atol=0.0))

    def value(m1, solver):
        return cjax.extremize(
            entropy,
            jnp.full(n, 1.0 / n),
            (energies, m1, M2),
            constraints=moments,
            solver=solver,
        ).value

    m1 = jnp.asarray(M1)
    dense_grad = jax.grad(value)(m1, cjax.Newton())
    krylov_grad = jax.grad(value)(m1, krylov)
    # Envelope theorem: dS/dm1 = lambda_2 dG_2/dm1 = -lambda_2 = b.
    b, _, _, _ = dual_reference(energies, M1, M2)
    np.testing.assert_allclose(dense_grad, b, rtol=1e-9)
    np.testing.assert_allclose(krylov_grad, b, rtol=1e-8)


@pytest.mark.slow
def test_maximum_entropy_100k_unknowns_matrix_free():
    """n = 100,000: a dense KKT matrix would need 80 GB; MINRES needs vectors only."""
    n = 100_000
    energies = jnp.linspace(0.0, 1.0, n)
    solver = cjax.Newton(linear_solver=cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=500))
    sol = cjax.extremize(
        entropy,
        jnp.full(n, 1.0 / n),
        (energies, M1, M2),
        constraints=moments,
        solver=solver,
    )
    _check(sol, energies)
