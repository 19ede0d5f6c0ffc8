"""The saddle-point solvers of mechanics, `RangeSpaceLDL` and `FullKKTLU`, against
NumPy's dense solve of the same KKT matrix."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax

from .helpers import assert_one_constraint_cases, finite_difference_grad, solve_with


def _kkt_reference(mass, jac, rhs, bias):
    n, k = mass.shape[0], jac.shape[0]
    matrix = np.block([[mass, -jac.T], [jac, np.zeros((k, k))]])
    sol = np.linalg.solve(matrix, np.concatenate([rhs, -bias]))
    return sol[:n], sol[n:]


def _random_problem(rng, n, k, rank_m):
    """`M` positive semidefinite of rank `rank_m` (singular when `rank_m < n`), `A` of
    full row rank, and `M` positive definite on `ker A` when `rank_m + k >= n`."""
    basis = rng.normal(size=(n, rank_m))
    mass = basis @ basis.T
    jac = rng.normal(size=(k, n))
    return mass, jac, rng.normal(size=n), rng.normal(size=k)


SOLVERS = [cjax.RangeSpaceLDL(), cjax.FullKKTLU(), cjax.RangeSpaceLDL(unroll_max=0)]


@pytest.mark.parametrize("solver", SOLVERS, ids=["range-space", "full-lu", "lapack"])
@pytest.mark.parametrize(
    "n, k, rank_m", [(2, 1, 2), (3, 2, 3), (3, 2, 1), (5, 3, 2), (6, 0, 6), (4, 4, 0)]
)
def test_matches_dense_solve(solver, n, k, rank_m):
    rng = np.random.default_rng(100 * n + 10 * k + rank_m)
    mass, jac, rhs, bias = _random_problem(rng, n, k, rank_m)
    x, lam, singular = jax.jit(solve_with(solver))(
        *map(jnp.asarray, (mass, jac, rhs, bias))
    )
    x_ref, lam_ref = _kkt_reference(mass, jac, rhs, bias)
    assert not singular
    scale = 1 + np.max(np.abs(np.concatenate([x_ref, lam_ref])))
    np.testing.assert_allclose(x, x_ref, atol=1e-11 * scale)
    np.testing.assert_allclose(lam, lam_ref, atol=1e-11 * scale)


def test_badly_scaled_units():
    """Masses of 1e6 next to a constraint row of 1e-3: the augmentation weight follows
    the units, so the answer keeps its relative accuracy."""
    rng = np.random.default_rng(0)
    mass, jac, rhs, bias = _random_problem(rng, 4, 2, 3)
    mass, jac = 1e6 * mass, 1e-3 * jac
    x, lam, singular = solve_with(cjax.RangeSpaceLDL())(
        *map(jnp.asarray, (mass, jac, rhs, bias))
    )
    x_ref, lam_ref = _kkt_reference(mass, jac, rhs, bias)
    assert not singular
    np.testing.assert_allclose(x, x_ref, rtol=1e-9, atol=1e-12 * np.max(np.abs(x_ref)))
    np.testing.assert_allclose(lam, lam_ref, rtol=1e-9)


@pytest.mark.parametrize(
    "solver",
    [*SOLVERS, cjax.Automatic()],
    ids=["range-space", "full-lu", "lapack", "automatic"],
)
@pytest.mark.parametrize("mass", [1e-300, 1e-30, 1e30, 1e300])
def test_extreme_masses_keep_the_mass_independent_answer(solver, mass):
    """The Cartesian pendulum under gravity: its accelerations do not depend on the
    mass `m` and its multiplier is proportional to it, down to `m = 1e-300` next to
    a Jacobian of order 1 (FullKKTLU once took such a mass for zero and returned the
    massless answer as a success) and up to `1e300`."""
    from constrained_jax.scenes import pendulum

    base = pendulum.system()
    system = cjax.LagrangianSystem(
        base.lagrangian, base.constraints, base.forces, saddle_point_solver=solver
    )
    args = pendulum.default_args()
    q, qd = pendulum.state(0.7, 0.3, args)
    solve = jax.jit(system.solve_accelerations)
    qdd_ref, lam_ref, _ = solve(q, qd, 0.0, dict(args, m=jnp.asarray(1.0)))
    qdd, lam, singular = solve(q, qd, 0.0, dict(args, m=jnp.asarray(mass)))
    assert not singular
    np.testing.assert_allclose(qdd, qdd_ref, rtol=1e-12)
    np.testing.assert_allclose(lam / mass, lam_ref, rtol=1e-12)


@pytest.mark.parametrize("solver", SOLVERS[:2], ids=["range-space", "full-lu"])
def test_singular_systems_are_flagged(solver):
    rng = np.random.default_rng(1)
    # M singular on ker A: rank(M) + k < n.
    mass, jac, rhs, bias = _random_problem(rng, 4, 1, 2)
    x, lam, singular = jax.jit(solve_with(solver))(
        *map(jnp.asarray, (mass, jac, rhs, bias))
    )
    assert singular and np.all(x == 0) and np.all(lam == 0)
    # Redundant rows: the second row repeats the first.
    mass, jac, rhs, bias = _random_problem(rng, 4, 2, 4)
    jac[1] = 2 * jac[0]
    _, _, singular = jax.jit(solve_with(solver))(
        *map(jnp.asarray, (mass, jac, rhs, bias))
    )
    assert singular


def test_one_constraint_singular_cases():
    """`RangeSpaceLDL` with one constraint and a coupled `M`: its `1 x 1` Schur
    complement needs no pivot test (`schur_solve_unrolled`); the cases of
    `assert_one_constraint_cases`, against NumPy's dense solve."""
    mass = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 3.0]])
    rhs, bias = np.array([1.0, -2.0, 0.5]), np.array([0.3])
    assert_one_constraint_cases(
        cjax.RangeSpaceLDL(),
        jnp.asarray(mass),
        jnp.asarray(rhs),
        jnp.asarray(bias),
        lambda jac: _kkt_reference(mass, jac, rhs, bias),
        rtol=1e-12,
    )


def test_indefinite_mass_matrix_needs_full_kkt_lu():
    """`M = [[-2, 1], [1, 1]]` (indefinite) with the row `A = (1, 0)`: `M` is positive
    definite on `ker A = span(0, 1)`, so the KKT matrix is nonsingular. With
    `rho = tr|M| / tr(A A^T) = 3` the augmented `M + rho A^T A = [[1, 1], [1, 1]]` is
    singular: the range-space method breaks down and says so (never a wrong answer),
    and `FullKKTLU` solves the system."""
    mass = np.array([[-2.0, 1.0], [1.0, 1.0]])
    jac = np.array([[1.0, 0.0]])
    rhs, bias = np.array([1.0, 2.0]), np.array([0.5])
    x_ref, lam_ref = _kkt_reference(mass, jac, rhs, bias)
    args = tuple(map(jnp.asarray, (mass, jac, rhs, bias)))
    x, lam, singular = jax.jit(solve_with(cjax.FullKKTLU()))(*args)
    assert not singular
    np.testing.assert_allclose(x, x_ref, atol=1e-13)
    np.testing.assert_allclose(lam, lam_ref, atol=1e-13)
    x, lam, singular = jax.jit(solve_with(cjax.RangeSpaceLDL()))(*args)
    assert singular and np.all(x == 0) and np.all(lam == 0)


def test_vmap_and_grad():
    rng = np.random.default_rng(2)
    problems = [_random_problem(rng, 3, 2, 2) for _ in range(5)]
    stacked = [jnp.asarray(np.stack(p)) for p in zip(*problems, strict=True)]
    solver = cjax.RangeSpaceLDL()
    xs, lams, singular = jax.jit(jax.vmap(solve_with(solver)))(*stacked)
    assert not np.any(singular)
    for i, p in enumerate(problems):
        x_ref, lam_ref = _kkt_reference(*p)
        np.testing.assert_allclose(xs[i], x_ref, atol=1e-11)
        np.testing.assert_allclose(lams[i], lam_ref, atol=1e-11)

    mass, jac, rhs, bias = map(jnp.asarray, problems[0])

    def loss(scale):
        x, lam, _ = solve_with(solver)(mass * scale[0], jac * scale[1], rhs, bias)
        return jnp.sum(x**2) + jnp.sum(jnp.sin(lam))

    point = jnp.array([1.3, 0.7])
    np.testing.assert_allclose(
        jax.jit(jax.grad(loss))(point),
        finite_difference_grad(jax.jit(loss), point),
        rtol=1e-6,
    )


def test_system_uses_its_solver():
    """The two cylinders at alpha = 0 (singular M): both solvers give the lecture's
    normal force, and `FullKKTLU` can be chosen per system."""
    cyl = cjax.scenes.two_cylinders
    args = cyl.default_args(alpha=0.0)
    q, qd = cyl.state(0.4, 0.0, args)
    for solver in (cjax.RangeSpaceLDL(), cjax.FullKKTLU()):
        system = cjax.LagrangianSystem(
            cyl.system().lagrangian,
            cyl.system().constraints,
            saddle_point_solver=solver,
        )
        _, lam = jax.jit(system.accelerations)(q, qd, 0.0, args)
        np.testing.assert_allclose(lam[0], cyl.normal_force(0.4, 0.4, args), rtol=1e-12)
    with pytest.raises(ValueError, match="saddle_point_solver"):
        cjax.LagrangianSystem(
            cyl.system().lagrangian, saddle_point_solver=cjax.DenseLU()
        )


class _PlainDense(cjax.AbstractSaddlePointSolver):
    """A solver of the user's: a dense solve of the KKT matrix (`jnp.linalg.solve`),
    keeping the protocol's contract: a solution that is not finite is `singular`,
    with `x = fill` and `lambda = 0`."""

    def form(self, n, k):
        return cjax.KKTForm(sparse=False, unroll=False)

    def solve(self, system, fill):
        mass, jac = system.mass.todense(), system.jac.todense()
        n, k = system.n, system.k
        matrix = jnp.block([[mass, -jac.T], [jac, jnp.zeros((k, k), mass.dtype)]])
        sol = jnp.linalg.solve(matrix, jnp.concatenate([system.rhs, -system.bias]))
        singular = jnp.invert(jnp.all(jnp.isfinite(sol)))
        x = jnp.where(singular, fill, sol[:n])
        return x, jnp.where(singular, 0.0, sol[n:]), singular


class _ChoosesPlain(cjax.Automatic):
    """`Automatic` whose `choose` returns the user's solver."""

    def choose(self, system):
        return _PlainDense()


@pytest.mark.parametrize("unroll_max", [0, 6], ids=["chosen", "fast-path-fallback"])
def test_automatic_choosing_a_solver_of_the_users(unroll_max):
    """An `Automatic` subclass whose `choose` returns a solver of the user's: that
    solver gets the blocks in `Automatic`'s form (it densifies them itself), and its
    singular answers come back as the protocol says (zeros). `unroll_max=0`: the
    chosen solver solves every state; `6`: the diagonal fast path solves the
    pendulum and the user's solver is its fallback for a vanishing mass."""
    pend = cjax.scenes.pendulum
    base = pend.system()
    system = cjax.LagrangianSystem(
        base.lagrangian,
        base.constraints,
        saddle_point_solver=_ChoosesPlain(unroll_max=unroll_max),
    )
    solve = jax.jit(system.solve_accelerations)
    args = pend.default_args()
    q, qd = pend.state(0.4, 0.3, args)
    qdd, lam, singular = solve(q, qd, 0.0, args)
    ref_qdd, ref_lam, _ = base.solve_accelerations(q, qd, 0.0, args)
    assert not singular
    np.testing.assert_allclose(qdd, ref_qdd, rtol=1e-12)
    np.testing.assert_allclose(lam, ref_lam, rtol=1e-12)
    # A massless bob: the KKT matrix is singular, and the dense solve is not finite
    # (the fast path's fallback, or the chosen solver).
    massless = dict(args, m=jnp.asarray(0.0))
    for q_, args_ in ((q.at[0].set(jnp.nan), args), (q, massless)):
        qdd, lam, singular = solve(q_, qd, 0.0, args_)
        assert singular
        assert jnp.all(qdd == 0) and jnp.all(lam == 0)


def test_dot_is_the_negated_sum_bit_for_bit():
    """`dot` adds the products in order; it gives the values of
    `minus_sum(None, [-u_i v_i, ...])` bit for bit, signed zeros and non-finite
    entries included, and `None` (a structural zero) where every term is one."""
    from constrained_jax._solver.ldl import dot as _dot, minus_sum as _minus_sum

    rng = np.random.default_rng(7)
    special = [0.0, -0.0, 1e-300, -1e300, np.inf, np.nan]
    for _ in range(200):
        m = int(rng.integers(1, 5))
        pool = list(rng.normal(size=8) * 10.0 ** rng.integers(-5, 5, 8)) + special

        def entries(pool=pool, m=m):
            return [
                None if rng.random() < 0.2 else jnp.asarray(rng.choice(pool))
                for _ in range(m)
            ]

        u, v = entries(), entries()
        pairs = zip(u, v, strict=True)
        terms = [None if a is None or b is None else -a * b for a, b in pairs]
        old, new = _minus_sum(None, terms), _dot(u, v)
        if old is None:
            assert new is None
            continue
        np.testing.assert_array_equal(np.asarray(new), np.asarray(old))
        assert np.signbit(new) == np.signbit(old) or np.isnan(old)
