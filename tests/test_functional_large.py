"""A 100,001-node mesh: linear time and memory (bordered block-tridiagonal KKT)."""

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import catenary as cat


CASE = (0.0, 0.0, 1.0, 0.5, 2.0, 2.5)


def _solver(num_nodes):
    xl, yl, xr, yr, _, _ = CASE

    def solve(args):
        return cjax.solve_functional(
            cat.functional(xl, yl, xr, yr),
            args,
            discretization=cjax.PiecewiseLinear(num_nodes),
            y0=cat.initial_guess(xl, yl, xr, yr, args["length"]),
            throw=False,
        )

    return solve


def _args():
    return {"rho_g": jnp.asarray(CASE[5]), "length": jnp.asarray(CASE[4])}


@pytest.mark.slow
def test_memory_is_linear_in_nodes():
    """XLA's buffer assignment for 10,001 and 40,001 nodes: a dense KKT matrix would
    grow 16x; the bordered block-tridiagonal solve grows ~4x."""
    sizes = {}
    for n in (10_001, 40_001):
        compiled = jax.jit(_solver(n)).lower(_args()).compile()
        stats = compiled.memory_analysis()
        if stats is None:
            pytest.skip("this backend reports no memory analysis")
        sizes[n] = stats.temp_size_in_bytes + stats.argument_size_in_bytes
    ratio = sizes[40_001] / sizes[10_001]
    assert ratio < 5.0, sizes
    # Bytes per node: a few hundred doubles at most (no n x n anything).
    assert sizes[40_001] / 40_001 < 8 * 400, sizes


@pytest.mark.slow
def test_hundred_thousand_nodes():
    xl, yl, xr, yr, length, rho_g = CASE
    solve = jax.jit(_solver(100_001))
    start = time.perf_counter()
    sol = jax.block_until_ready(solve(_args()))
    elapsed = time.perf_counter() - start
    assert sol.result == cjax.RESULTS.successful
    ref = cat.closed_form(xl, yl, xr, yr, length, rho_g)
    h = (xr - xl) / 100_000
    err = np.max(np.abs(np.asarray(sol.y) - ref["y"](np.asarray(sol.x))))
    # Second order: 0.1 h^2 bounds the discretization error of this case (h^2
    # coefficient ~0.03 from the 101..401-node slope test), plus round-off that
    # accumulates over the N-term sums and the N-step elimination, ~N eps: at
    # 100,000 nodes round-off (2e-11), not h^2 (1e-11), dominates.
    eps = np.finfo(np.float64).eps
    assert err < 0.1 * h**2 + 10 * 100_001 * eps, err
    np.testing.assert_allclose(
        sol.multipliers.integral[0], ref["multiplier"], rtol=1e-8
    )
    # A loose guard against an O(N^2) regression, on a CPU (on a GPU the sequential
    # block elimination is a round of small kernels per node, far slower).
    if jax.default_backend() == "cpu":
        assert elapsed < 30.0, elapsed
