"""Choices by size, made at trace time: the linear solver of `extremize` by the size of
the KKT system, and discretization tables built at run time (not program constants).

Small sizes only: the switch is tested by passing a small threshold explicitly, the
constants by reading the lowered program.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax import _extremize
from constrained_jax._discretization import Chebyshev, Graded, PiecewiseLinear
from constrained_jax._solver.fallback import Fallback
from constrained_jax.scenes import catenary


D = jnp.array([1.0, 2.0, 4.0, 5.0, 8.0, 10.0])


def weighted_energy(x, args):
    return 0.5 * args * jnp.sum(D * x**2)


def total(x, args):
    return jnp.sum(x) - 1.0


def _closed_form():
    """min 1/2 sum d_i x_i^2 subject to sum x = 1: x_i = (1/d_i) / sum_j 1/d_j,
    lambda = -1 / sum_j 1/d_j (grad F + lambda grad G = 0)."""
    inv = 1.0 / np.asarray(D)
    return inv / inv.sum(), -1.0 / inv.sum()


def test_default_solver_is_chosen_by_memory():
    """Dense while the KKT matrix takes at most 8 MiB, preconditioned MINRES above,
    with a dense fallback while it takes at most 128 MiB (issue 41: the old switch at
    n + k = 256 turned well-posed problems into Krylov failures)."""
    dense = _extremize.default_solver(1000, 2, jnp.float64)
    assert isinstance(dense.linear_solver, cjax.DenseLU)
    # The boundary is inclusive: (n + k)^2 * 8 bytes = 8 MiB at n + k = 1024.
    boundary = _extremize.default_solver(1023, 1, jnp.float64)
    assert isinstance(boundary.linear_solver, cjax.DenseLU)
    # float32 entries take half the memory; the dense solve equilibrates first.
    assert isinstance(
        _extremize.default_solver(1400, 3, jnp.float32).linear_solver,
        cjax.EquilibratedDenseLU,
    )
    single = _extremize.default_solver(1448, 1, jnp.float32).linear_solver
    assert isinstance(single.second, cjax.EquilibratedDenseLU)
    fallback = _extremize.default_solver(1024, 1, jnp.float64).linear_solver
    assert isinstance(fallback, Fallback)
    assert isinstance(fallback.first, cjax.MINRES)
    assert isinstance(fallback.second, cjax.DenseLU)
    assert fallback.first.rtol == 1e-12
    assert fallback.first.max_steps >= 1025
    assert fallback.first.probes > 0
    krylov = _extremize.default_solver(5000, 2, jnp.float64).linear_solver
    assert isinstance(krylov, cjax.MINRES)
    assert krylov.max_steps >= 5002
    # The bounds can be passed.
    small = _extremize.default_solver(6, 1, jnp.float64, dense_bytes=4)
    assert isinstance(small.linear_solver, Fallback)
    bare = _extremize.default_solver(6, 1, jnp.float64, dense_bytes=4, fallback_bytes=4)
    assert isinstance(bare.linear_solver, cjax.MINRES)
    # float32 cannot reach a relative residual of 1e-12: the tolerance follows eps.
    loose = _extremize.default_solver(3000, 3, jnp.float32).linear_solver.first
    assert loose.rtol == pytest.approx(1000 * np.finfo(np.float32).eps)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_both_default_solvers_agree_with_the_closed_form(sign):
    """The matrix-free choice (forced at a small size) gives the dense answer and the
    same kind: a minimum, or a maximum for the negated objective."""
    x_ref, lam_ref = _closed_form()
    x0 = jnp.full(D.shape, 0.3)
    args = jnp.asarray(sign)
    dense = cjax.extremize(weighted_energy, x0, args, constraints=total)
    krylov_solver = _extremize.default_solver(
        6, 1, jnp.float64, dense_bytes=4, fallback_bytes=4
    )
    krylov = cjax.extremize(
        weighted_energy, x0, args, constraints=total, solver=krylov_solver
    )
    kind = cjax.EXTREMUM.minimum if sign > 0 else cjax.EXTREMUM.maximum
    for sol in (dense, krylov):
        assert sol.result == cjax.RESULTS.successful
        assert sol.kind == kind
        np.testing.assert_allclose(sol.x, x_ref, rtol=1e-12)
        np.testing.assert_allclose(sol.multipliers, [sign * lam_ref], rtol=1e-12)
    # Derivatives by the implicit function theorem, through either linear solver:
    # d value / d args = F(x) / args at the optimum (F is linear in args).
    grads = [
        jax.grad(
            lambda a, s=s: (
                cjax.extremize(
                    weighted_energy, x0, a, constraints=total, solver=s
                ).value
            )
        )(args)
        for s in (None, krylov_solver)
    ]
    expected = 0.5 * np.sum(np.asarray(D) * x_ref**2)
    np.testing.assert_allclose(grads, [expected, expected], rtol=1e-10)


def test_explicitly_dense_solver_above_the_size_warns(monkeypatch):
    monkeypatch.setattr(_extremize, "DENSE_WARN", 4)
    # A fresh objective, so that no earlier compilation is reused.
    objective = lambda x, args: weighted_energy(x, args) + 0.0
    with pytest.warns(UserWarning, match="MINRES"):
        cjax.extremize(
            objective,
            jnp.full(D.shape, 0.3),
            jnp.asarray(1.0),
            constraints=total,
            solver=cjax.Newton(),
        )


def test_minres_default_refuses_rather_than_answers_wrong():
    """At x = 0 the Hessian of sum x^3 / 3 - x_0 vanishes and its gradient does not:
    no Newton step exists. Dense LU says the KKT matrix is singular; MINRES cannot
    meet its residual test and says so; with the dense fallback of the default the
    dense solve says the matrix is singular. None returns a point as successful."""
    objective = lambda x, args: jnp.sum(x**3) / 3 - args * x[0]
    x0, args = jnp.zeros(6), jnp.asarray(1.0)
    dense = cjax.extremize(objective, x0, args, throw=False)
    assert dense.result == cjax.RESULTS.singular_kkt
    solver = _extremize.default_solver(
        6, 0, jnp.float64, dense_bytes=4, fallback_bytes=4
    )
    krylov = cjax.extremize(objective, x0, args, solver=solver, throw=False)
    assert krylov.result == cjax.RESULTS.linear_solve_failed
    assert krylov.kind == cjax.EXTREMUM.unknown
    solver = _extremize.default_solver(6, 0, jnp.float64, dense_bytes=4)
    fallback = cjax.extremize(objective, x0, args, solver=solver, throw=False)
    assert fallback.result == cjax.RESULTS.singular_kkt
    assert fallback.kind == cjax.EXTREMUM.unknown


# ---------------------------------------------------------------------------------
# Discretization tables
# ---------------------------------------------------------------------------------


@pytest.fixture(params=["numpy constants", "built in the program"])
def table_path(request, monkeypatch):
    """Both ways of building tables and node arrays: NumPy constants (small sizes,
    the default here) and JAX in the program (the size thresholds lowered to 8)."""
    if request.param == "built in the program":
        from constrained_jax import _discretization

        monkeypatch.setattr(_discretization, "CONSTANT_TABLES_MAX", 8)
        monkeypatch.setattr(_discretization, "CONSTANT_INDICES_MAX", 8)
    return request.param


def test_chebyshev_matrices_are_exact_on_polynomials(table_path):
    """The interpolation and differentiation matrices reproduce a polynomial of
    degree N - 1 and its derivative at the Gauss points."""
    disc = Chebyshev(9)
    t = disc.reference_nodes()
    coeffs = np.arange(1.0, 10.0) / 7
    poly = np.polynomial.Polynomial(coeffs)
    for singular in [(False, False), (True, False), (True, True)]:
        tq, _, p, pd = disc._matrices(singular)
        np.testing.assert_allclose(p @ poly(t), poly(tq), rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(
            pd @ poly(t), poly.deriv()(tq), rtol=1e-12, atol=1e-12
        )


def test_tabulated_discretizations_give_the_same_numbers():
    interval = (jnp.asarray(0.0), jnp.asarray(2.0))
    integrand = lambda y, yp, x: jnp.sum(y**2 * jnp.sqrt(1 + yp**2)) + x
    constraint = lambda y, x: y[:1] - x
    for disc in (Chebyshev(11), Graded(Chebyshev(11), left=3)):
        values = jnp.sin(disc.nodes(interval))[:, None] + 0.5
        tab = disc.tabulate()
        for fn in (
            lambda d, v=values: d.integrate(integrand, v, interval),
            lambda d: d.node_weights(interval),
            lambda d, v=values: d.pointwise_constraint(constraint, v, interval),
        ):
            np.testing.assert_allclose(fn(tab), fn(disc), rtol=1e-15, atol=1e-15)


def test_piecewise_linear_nodes_are_numpy_linspace(table_path):
    disc = PiecewiseLinear(1001)
    xl, xr = jnp.asarray(-0.3), jnp.asarray(2.0)
    expected = -0.3 + 2.3 * (np.linspace(-1.0, 1.0, 1001) + 1) / 2
    np.testing.assert_array_equal(disc.nodes((xl, xr)), expected)


_CONSTANT = re.compile(r"stablehlo\.constant dense<.*?> : tensor<([0-9x]*)x?[fi]64>")


def _largest_constant(text: str) -> int:
    sizes = [
        int(np.prod([int(d) for d in shape.split("x") if d]))
        for shape in _CONSTANT.findall(text)
    ]
    return max(sizes, default=0)


@pytest.mark.parametrize(
    "disc, bound",
    [(Chebyshev(24), 64), (PiecewiseLinear(401), 64)],
    ids=["chebyshev", "piecewise_linear"],
)
def test_no_table_is_a_program_constant(disc, bound, monkeypatch):
    """`solve_functional` on the catenary, with the size thresholds below which tables
    and indices stay NumPy constants lowered to 8 (they are 128 nodes and 10,000
    blocks): no matrix, node, probe or index array sized by N is embedded in the
    program (the largest 64-bit constant is a vector of Gauss points, 36 for
    Chebyshev(24))."""
    from constrained_jax import _discretization
    from constrained_jax._solver import block_tridiagonal

    monkeypatch.setattr(_discretization, "CONSTANT_TABLES_MAX", 8)
    monkeypatch.setattr(_discretization, "CONSTANT_INDICES_MAX", 8)
    monkeypatch.setattr(block_tridiagonal, "CONSTANT_INDICES_MAX", 8)
    fn = lambda length: catenary.solve(length=length, discretization=disc)
    text = jax.jit(fn).lower(jnp.asarray(1.5)).as_text()
    assert _largest_constant(text) <= bound
