"""Bounds in `extremize` at scale: bounds alone (`lower`, `upper`, with or without
equality constraints) never form the Jacobian of all `n + k + 2n` unknowns, so that
bound-constrained problems of thousands of unknowns solve like equality-constrained
ones. Closed forms at n = 10 (the reduced system formed and factored) and n = 2000
(MINRES on its symmetric form; the backward pass matrix-free too):

- a separable quadratic on a box with infinite entries, started outside the box:
    `x = clip(c, lower, upper)`, `mu = d (lower - c)_+`, `d (c - upper)_+`;
- the projection onto the probability simplex (`sum x = 1`, `x >= 0`):
    `x = (c - tau)_+`, `lambda = tau`, `mu = (tau - c)_+`;
- maximum entropy with upper bounds (`sum p = 1`, `p <= u`): `p = min(u, t)`,
    `lambda = 1 + log t`, `mu = log(u / t)` where the bound holds (`<= 0`:
    maximizing).
"""

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax

from .helpers import run_python


SIZES = [10, 2000]


def quadratic(x, a):
    d, c = a
    return 0.5 * jnp.sum(d * (x - c) ** 2)


def simplex_sum(x, a):
    del a
    return jnp.sum(x) - 1.0


def box_problem(n: int, seed: int = 0, dtype=np.float64):
    rng = np.random.default_rng(seed)
    d = (1.0 + rng.uniform(size=n)).astype(dtype)
    c = (2.0 * rng.normal(size=n)).astype(dtype)
    lo = np.full(n, -1.0, dtype)
    up = np.full(n, 1.0, dtype)
    lo[::4] = -np.inf  # no lower bound on every fourth entry
    up[1::5] = np.inf  # no upper bound on every fifth entry from the second
    return d, c, lo, up


def simplex_projection(c: np.ndarray):
    """`(x, tau)`: the Euclidean projection of `c` onto the simplex, by sorting."""
    v = np.sort(c)[::-1]
    cumulative = np.cumsum(v) - 1.0
    index = np.arange(1, c.size + 1)
    rho = np.nonzero(v - cumulative / index > 0)[0][-1]
    tau = cumulative[rho] / (rho + 1)
    return np.maximum(c - tau, 0.0), tau


def water_level(u: np.ndarray) -> float:
    """`t` with `sum min(u, t) = 1` (`sum u > 1`), by sorting."""
    v = np.sort(u)
    below = np.concatenate([[0.0], np.cumsum(v)])
    for j in range(v.size):
        t = (1.0 - below[j]) / (v.size - j)
        if t <= v[j]:
            return t
    raise AssertionError("sum(u) <= 1")


def entropy(p, a):
    del a
    return -jnp.sum(p * jnp.log(p))


def entropy_problem(n: int):
    # Every third state is capped at half of the uniform value: the cap holds there.
    u = np.full(n, 4.0 / n)
    u[::3] = 0.5 / n
    return u, water_level(u)


@pytest.mark.parametrize("n", SIZES)
def test_box_quadratic_is_the_clip(n):
    d, c, lo, up = box_problem(n)
    x0 = jnp.full((n,), 3.0)  # outside the box wherever there is an upper bound
    sol = cjax.extremize(quadratic, x0, (d, c), lower=lo, upper=up, sense="minimize")
    assert sol.result == cjax.RESULTS.successful
    assert sol.kind == cjax.EXTREMUM.minimum
    np.testing.assert_allclose(sol.x, np.clip(c, lo, up), rtol=0, atol=1e-12)
    with np.errstate(invalid="ignore"):
        mu_lo = np.where(np.isfinite(lo), np.maximum(d * (lo - c), 0.0), 0.0)
        mu_up = np.where(np.isfinite(up), np.maximum(d * (c - up), 0.0), 0.0)
    mu = np.asarray(sol.inequality_multipliers)
    assert mu.shape == (2 * n,)
    np.testing.assert_allclose(mu[:n], mu_lo, rtol=0, atol=1e-10)
    np.testing.assert_allclose(mu[n:], mu_up, rtol=0, atol=1e-10)
    active = np.asarray(sol.active)
    np.testing.assert_array_equal(active[:n], mu_lo > 0)
    np.testing.assert_array_equal(active[n:], mu_up > 0)


@pytest.mark.parametrize("n", SIZES)
def test_simplex_projection(n):
    rng = np.random.default_rng(1)
    c = (2.0 + 4.0 * rng.normal(size=n)) / n
    x_exact, tau = simplex_projection(c)
    assert 0 < np.sum(x_exact == 0) < n  # some bounds hold, some do not
    sol = cjax.extremize(
        quadratic,
        jnp.full((n,), 1.0 / n),
        (np.ones(n), c),
        constraints=simplex_sum,
        lower=0.0,
        sense="minimize",
    )
    assert sol.result == cjax.RESULTS.successful
    assert sol.kind == cjax.EXTREMUM.minimum
    np.testing.assert_allclose(sol.x, x_exact, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.multipliers, [tau], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(
        sol.inequality_multipliers, np.maximum(tau - c, 0.0), rtol=0, atol=1e-10
    )


@pytest.mark.parametrize("n", SIZES)
def test_max_entropy_with_upper_bounds(n):
    u, t = entropy_problem(n)
    p0 = jnp.full((n,), 0.5 / n)
    sol = cjax.extremize(
        entropy, p0, constraints=simplex_sum, upper=u, sense="maximize"
    )
    assert sol.result == cjax.RESULTS.successful
    p_exact = np.minimum(u, t)
    np.testing.assert_allclose(sol.x, p_exact, rtol=1e-10)
    np.testing.assert_allclose(sol.multipliers, [1 + np.log(t)], rtol=1e-10)
    capped = u < t
    mu = np.asarray(sol.inequality_multipliers)
    np.testing.assert_allclose(mu[capped], np.log(u[capped] / t), rtol=1e-9)
    assert np.all(mu[~capped] == 0)
    assert np.all(mu <= 0)
    np.testing.assert_array_equal(sol.active, capped)


def _tenth_of_n(x, args):
    return jnp.sum(x) - 0.1 * x.shape[0]


@pytest.mark.parametrize("n", SIZES)
def test_derivatives_against_finite_differences(n):
    """The envelope theorem for the bounds (`dF/d upper = -mu`, `dF/d lower = +mu`)
    and directional derivatives of `x` with respect to `args`, `lower` and `upper`
    against central differences, on the box quadratic with a sum constraint."""
    d, c, lo, up = box_problem(n, seed=2)
    lo = np.where(np.isfinite(lo), lo, -2.0)

    # One constraint function for every call: a new one per call would be a new
    # program (compiled again) each time.
    def solve(c_, lo_, up_):
        return cjax.extremize(
            quadratic,
            jnp.zeros(n),
            (d, c_),
            constraints=_tenth_of_n,
            lower=lo_,
            upper=up_,
            sense="minimize",
        )

    sol = solve(c, lo, up)
    mu = np.asarray(sol.inequality_multipliers)
    assert 0 < np.sum(sol.active) < n
    grad_lo, grad_up = jax.grad(lambda a, b: solve(c, a, b).value, argnums=(0, 1))(
        jnp.asarray(lo), jnp.asarray(up)
    )
    np.testing.assert_allclose(grad_lo, mu[:n], rtol=0, atol=1e-9)
    np.testing.assert_allclose(grad_up, -mu[n:], rtol=0, atol=1e-9)

    # One direction per input, all three in one forward-mode program (`jacfwd` over
    # the three step lengths), each against its own central difference.
    rng = np.random.default_rng(3)
    h = 1e-6
    inputs = [np.asarray(c), lo, up]
    directions = rng.normal(size=(3, n))

    def x_of(s):
        moved = zip(inputs, s, directions, strict=True)
        return solve(*(x + s_i * v for x, s_i, v in moved)).x

    tangents = jax.jacfwd(x_of)(jnp.zeros(3))
    for which in range(3):
        step = h * np.eye(3)[which]
        central = (x_of(step) - x_of(-step)) / (2 * h)
        np.testing.assert_allclose(tangents[:, which], central, rtol=0, atol=1e-7)


def test_float32_and_vmap():
    n = 2000
    d, c, lo, up = box_problem(n, dtype=np.float32)
    sol = cjax.extremize(
        quadratic,
        jnp.zeros(n, jnp.float32),
        (d, c),
        lower=lo,
        upper=up,
        sense="minimize",
    )
    assert sol.result == cjax.RESULTS.successful
    assert sol.x.dtype == jnp.float32
    np.testing.assert_allclose(sol.x, np.clip(c, lo, up), rtol=0, atol=1e-5)

    # A batch with the reduced system formed (n = 10) and with MINRES (n = 600).
    for n in (10, 600):
        d, _, lo, up = box_problem(n)
        cs = np.random.default_rng(4).normal(size=(3, n)) * 2

        def one(c_, d=d, lo=lo, up=up, n=n):
            out = cjax.extremize(
                quadratic, jnp.zeros(n), (d, c_), lower=lo, upper=up,
                sense="minimize", throw=False,
            )  # fmt: skip
            return out.x, out.result == cjax.RESULTS.successful

        xs, ok = jax.vmap(one)(jnp.asarray(cs))
        assert np.all(ok)
        np.testing.assert_allclose(xs, np.clip(cs, lo, up), rtol=0, atol=1e-12)


@pytest.mark.parametrize("n", SIZES)
def test_careless_bounds(n):
    d, c, lo, up = box_problem(n)
    crossed = up.copy()
    crossed[2] = -3.0  # below lower[2] = -1
    with pytest.raises(ValueError, match="lower > upper"):
        cjax.extremize(
            quadratic, jnp.zeros(n), (d, c), lower=lo, upper=crossed, sense="minimize"
        )

    @jax.jit
    def traced(lo_, up_):
        return cjax.extremize(
            quadratic, jnp.zeros(n), (d, c), lower=lo_, upper=up_, sense="minimize",
            throw=False,
        )  # fmt: skip

    assert traced(lo, crossed).result == cjax.RESULTS.infeasible_inequalities
    with_nan = lo.copy()
    with_nan[1] = np.nan
    assert traced(with_nan, up).result == cjax.RESULTS.invalid_input


@pytest.mark.slow
def test_ten_thousand_unknowns_in_seconds():
    """n = 10,000 with a constraint and bounds (the simplex projection) in a fresh
    process under a time limit, so that a solve that went dense again fails instead
    of stalling the suite."""
    code = textwrap.dedent(
        """
        import jax, jax.numpy as jnp, numpy as np
        jax.config.update("jax_enable_x64", True)
        import constrained_jax as cjax
        n = 10_000
        c = (2.0 + 4.0 * np.random.default_rng(1).normal(size=n)) / n
        v = np.sort(c)[::-1]
        cumulative = np.cumsum(v) - 1.0
        rho = np.nonzero(v - cumulative / np.arange(1, n + 1) > 0)[0][-1]
        tau = cumulative[rho] / (rho + 1)
        sol = cjax.extremize(
            lambda x, c: 0.5 * jnp.sum((x - c) ** 2), jnp.full((n,), 1.0 / n), c,
            constraints=lambda x, c: jnp.sum(x) - 1.0, lower=0.0, sense="minimize",
        )
        error = np.max(np.abs(np.asarray(sol.x) - np.maximum(c - tau, 0.0)))
        print("ERROR", error, float(sol.multipliers[0] - tau))
        """
    )
    out = run_python(code, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    line = next(s for s in out.stdout.splitlines() if s.startswith("ERROR"))
    error, lam_error = map(float, line.split()[1:])
    # The default tolerances, `rtol = atol = 1e-10`.
    assert error < 1e-10
    assert abs(lam_error) < 1e-10
