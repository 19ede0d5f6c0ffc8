"""The default solver's fast path for a structurally diagonal mass matrix (the
range-space method with reciprocals, `constrained_jax._solver.diagonal`), against
`FullKKTLU` on the same systems, with zero masses, singular systems and derivatives."""

import functools
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax._solver.diagonal import stack_by_select
from constrained_jax._solver.sparse import SparseMatrix
from constrained_jax.scenes import two_cylinders as cyl

from .helpers import assert_one_constraint_cases, finite_difference_grad, solve_with


AUTO = cjax.Automatic()


def _problem(rng, n, k, jac_pattern=None, masses=None):
    """`(mass, jac, rhs, bias)`: `M` diagonal (a `SparseMatrix`), `A` with the
    boolean pattern `jac_pattern` (a `SparseMatrix`; dense random if `None`)."""
    masses = rng.uniform(0.5, 2.0, size=n) if masses is None else np.asarray(masses)
    mass = SparseMatrix.from_dense(jnp.diag(jnp.asarray(masses)), np.eye(n, dtype=bool))
    jac = rng.normal(size=(k, n))
    if jac_pattern is not None:
        jac = SparseMatrix.from_dense(
            jnp.asarray(jac * jac_pattern), np.asarray(jac_pattern)
        )
    else:
        jac = jnp.asarray(jac)
    return mass, jac, jnp.asarray(rng.normal(size=n)), jnp.asarray(rng.normal(size=k))


# The reference, jitted: eagerly each of its operations compiles a program of its own.
_reference = jax.jit(solve_with(cjax.FullKKTLU()))


def _assert_agree(out, ref, tol=1e-12):
    x, lam, singular = out
    x_ref, lam_ref, singular_ref = ref
    assert not singular and not singular_ref
    scale = 1 + float(jnp.max(jnp.abs(jnp.concatenate([x_ref, lam_ref]))))
    np.testing.assert_allclose(x, x_ref, atol=tol * scale)
    np.testing.assert_allclose(lam, lam_ref, atol=tol * scale)


def test_fast_path_is_chosen():
    mass, jac, rhs, bias = _problem(np.random.default_rng(0), 3, 2)
    kkt = cjax.SaddlePointSystem(mass, jac, rhs, bias)
    assert AUTO._diagonal_fast_path(kkt)
    # A structurally zero mass that A couples: always the general method.
    pattern = np.diag([True, True, False])
    sparse = SparseMatrix.from_dense(jnp.eye(3), pattern)
    assert not AUTO._diagonal_fast_path(cjax.SaddlePointSystem(sparse, jac, rhs, bias))
    # Too large.
    assert not cjax.Automatic(unroll_max=4)._diagonal_fast_path(kkt)


@pytest.mark.parametrize(
    "n, k, pattern",
    [
        (3, 1, None),
        (4, 2, None),
        (5, 0, None),
        (4, 2, [[1, 0, 1, 0], [0, 1, 0, 0]]),
        (3, 2, [[1, 0, 0], [0, 1, 1]]),
        (5, 1, [[0, 1, 0, 0, 1]]),
    ],
)
def test_matches_full_lu(n, k, pattern):
    rng = np.random.default_rng(10 * n + k)
    pattern = None if pattern is None else np.asarray(pattern, bool)
    problem = _problem(rng, n, k, pattern)
    _assert_agree(jax.jit(solve_with(AUTO))(*problem), _reference(*problem))


def test_constant_rows_under_vmap():
    """`A` and the masses unbatched (constant rows, parameters), `f` batched."""
    rng = np.random.default_rng(1)
    mass, jac, _, bias = _problem(rng, 4, 2, np.array([[1, 1, 0, 0], [0, 0, 1, 1]]))
    rhs = jnp.asarray(rng.normal(size=(7, 4)))
    out = jax.jit(jax.vmap(solve_with(AUTO), in_axes=(None, None, 0, None)))(
        mass, jac, rhs, bias
    )
    for i in range(7):
        ref = _reference(mass, jac, rhs[i], bias)
        _assert_agree(jax.tree.map(lambda v, i=i: v[i], out), ref)


def test_stack_by_select_is_stack():
    """The batched path's `where` chain gives `jnp.stack`'s values bit for bit (NaN,
    infinities and the sign of zero included), alone and under `jax.vmap`."""
    values = [jnp.asarray(v) for v in (-0.0, 1.5, jnp.nan, -jnp.inf, 3.0)]
    np.testing.assert_array_equal(stack_by_select(values), jnp.stack(values))
    assert jnp.signbit(stack_by_select(values)[0])
    batch = jnp.asarray(np.random.default_rng(4).normal(size=(6, 3)))
    stacked = jax.jit(jax.vmap(lambda r: stack_by_select([r[2], r[0], r[1]])))(batch)
    np.testing.assert_array_equal(stacked, batch[:, [2, 0, 1]])
    assert stack_by_select([jnp.asarray(2.0)]).shape == (1,)


def test_batched_fast_path_is_the_single_one():
    """Under `jax.vmap` the fast path assembles its outputs with `stack_by_select`
    (written in place; the time is in `benchmarks/eom_threads.py`): the same numbers
    as one state at a time."""
    rng = np.random.default_rng(5)
    pattern = np.array([[1, 0, 0], [0, 1, 1]], bool)
    mass, jac, _, _ = _problem(rng, 3, 2, pattern)
    rhs = jnp.asarray(rng.normal(size=(64, 3)))
    bias = jnp.asarray(rng.normal(size=(64, 2)))
    batched = jax.jit(jax.vmap(solve_with(AUTO), in_axes=(None, None, 0, 0)))
    x, lam, singular = batched(mass, jac, rhs, bias)
    one = jax.jit(solve_with(AUTO))
    for i in range(0, 64, 9):
        x_i, lam_i, singular_i = one(mass, jac, rhs[i], bias[i])
        np.testing.assert_allclose(x[i], x_i, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(lam[i], lam_i, rtol=1e-14, atol=1e-14)
        assert bool(singular[i]) == bool(singular_i)


@pytest.mark.parametrize("sparse_jac", [False, True])
def test_everything_batched(sparse_jac):
    """`M`, `A`, `f` and the bias all batched (their batch axis crosses into the
    batch's `lax.cond` last): each state as alone, with the fast path and, in a
    batch where one state has a coupled zero mass, with the general method."""
    rng = np.random.default_rng(6)
    pattern = np.array([[1, 0, 1], [0, 1, 1]], bool)
    num = 5
    masses = rng.uniform(0.5, 2.0, size=(num, 3))
    jacs = rng.normal(size=(num, 2, 3)) * pattern
    rhs = jnp.asarray(rng.normal(size=(num, 3)))
    bias = jnp.asarray(rng.normal(size=(num, 2)))
    eye = np.eye(3, dtype=bool)

    def make(m, a):
        mass = SparseMatrix(jnp.asarray(m), (0, 1, 2), (0, 1, 2), (3, 3))
        if not sparse_jac:
            return mass, jnp.asarray(a)
        rows, cols = np.nonzero(pattern)
        jac = SparseMatrix(
            jnp.asarray(a[..., rows, cols]),
            tuple(int(r) for r in rows),
            tuple(int(c) for c in cols),
            (2, 3),
        )
        return mass, jac

    solve = jax.jit(jax.vmap(solve_with(AUTO)))
    for zero in (False, True):
        m = masses.copy()
        if zero:
            m[3, 2] = 0.0  # coupled by both rows: the general method, whole batch
        mass, jac = make(m, jacs)
        out = solve(mass, jac, rhs, bias)
        for i in range(num):
            dense_mass = SparseMatrix.from_dense(jnp.diag(jnp.asarray(m[i])), eye)
            ref = _reference(dense_mass, jnp.asarray(jacs[i]), rhs[i], bias[i])
            _assert_agree(jax.tree.map(lambda v, i=i: v[i], out), ref)


def test_free_gauge():
    """A zero mass that nothing couples to: zero acceleration without a force on it,
    singular with one."""
    rng = np.random.default_rng(2)
    pattern = np.array([[1, 1, 0]], bool)
    mass, jac, rhs, bias = _problem(rng, 3, 1, pattern, masses=[1.0, 2.0, 0.0])
    rhs = rhs.at[2].set(0.0)
    x, lam, singular = jax.jit(solve_with(AUTO))(mass, jac, rhs, bias)
    assert not singular and x[2] == 0
    _assert_agree((x, lam, singular), _reference(mass, jac, rhs, bias))
    _, _, singular = jax.jit(solve_with(AUTO))(mass, jac, rhs.at[2].set(1.0), bias)
    assert singular


def test_coupled_zero_mass_single_and_batched():
    """A zero mass that `A` couples (the cylinder with `I = 0`): solved by the general
    method, alone and in a batch where only some states need it."""
    rng = np.random.default_rng(3)
    pattern = np.array([[1, 0, 0], [0, 1, 1]], bool)
    mass, jac, rhs, bias = _problem(rng, 3, 2, pattern, masses=[1.0, 2.0, 0.0])
    _assert_agree(
        jax.jit(solve_with(AUTO))(mass, jac, rhs, bias),
        _reference(mass, jac, rhs, bias),
    )
    values = jnp.stack([mass.values, jnp.array([1.0, 2.0, 0.5]), mass.values])
    masses = SparseMatrix(values, mass.rows, mass.cols, mass.shape)
    out = jax.jit(jax.vmap(solve_with(AUTO), in_axes=(0, None, None, None)))(
        masses, jac, rhs, bias
    )
    for i in range(3):
        m_i = SparseMatrix(values[i], mass.rows, mass.cols, mass.shape)
        ref = _reference(m_i, jac, rhs, bias)
        _assert_agree(jax.tree.map(lambda v, i=i: v[i], out), ref)


def test_cylinders_with_zero_inertia():
    """The scene with `alpha = 0`, against its closed form."""
    system, args = cyl.system(), cyl.default_args(alpha=0.0)
    theta = jnp.asarray([0.3, 0.5])
    q, qd = jax.vmap(lambda th: cyl.state(th, 0.7 * th, args))(theta)
    qdd, lam, singular = jax.jit(
        jax.vmap(lambda q_, qd_: system.solve_accelerations(q_, qd_, 0.0, args))
    )(q, qd)
    assert not jnp.any(singular)
    np.testing.assert_allclose(
        qdd[:, 1], cyl.angular_acceleration(theta, args), rtol=1e-12
    )
    np.testing.assert_allclose(lam[:, 1], 0.0, atol=1e-12)


def test_singular_cases():
    rng = np.random.default_rng(4)
    mass, jac, rhs, bias = _problem(rng, 3, 2)
    redundant = jnp.stack([jac[0], 2 * jac[0]])
    for problem in (
        (mass, redundant, rhs, bias),
        (mass, jac, rhs.at[0].set(jnp.nan), bias),
        (SparseMatrix(mass.values.at[1].set(jnp.nan), *_static(mass)), jac, rhs, bias),
    ):
        x, lam, singular = jax.jit(solve_with(AUTO))(*problem)
        assert singular
        assert jnp.all(x == 0) and jnp.all(lam == 0)
    # In a batch, only the singular state is flagged.
    rhs_b = jnp.stack([rhs, rhs.at[0].set(jnp.nan)])
    _, _, singular = jax.vmap(solve_with(AUTO), in_axes=(None, None, 0, None))(
        mass, jac, rhs_b, bias
    )
    assert not singular[0] and singular[1]


def test_one_constraint_singular_cases():
    """One constraint: `s = A D^-1 A^T` is singular exactly where it is 0, overflows
    to inf or is NaN (`assert_one_constraint_cases`); else the range-space formulas,
    in NumPy."""
    masses = np.array([1.0, 2.0, 3.0])
    mass = SparseMatrix.from_dense(jnp.diag(masses), np.eye(3, dtype=bool))
    rhs, bias = np.array([1.0, -2.0, 0.5]), np.array([0.3])
    kkt = cjax.SaddlePointSystem(mass, jnp.ones((1, 3)), rhs, bias)
    assert AUTO._diagonal_fast_path(kkt)

    def reference(jac):
        a = jac[0]
        lam = (-bias[0] - np.sum(a * rhs / masses)) / np.sum(a * a / masses)
        return (rhs + a * lam) / masses, [lam]

    assert_one_constraint_cases(
        AUTO, mass, jnp.asarray(rhs), jnp.asarray(bias), reference, rtol=1e-14
    )


def _static(mass):
    return mass.rows, mass.cols, mass.shape


def _loss(solver, pattern):
    def loss(theta):
        masses, jac = theta[:3], theta[3:9].reshape(2, 3)
        mass = SparseMatrix(masses, (0, 1, 2), (0, 1, 2), (3, 3))
        jac = SparseMatrix.from_dense(jnp.where(pattern, jac, 0.0), pattern)
        x, lam, _ = solve_with(solver)(mass, jac, theta[9:12], theta[12:14])
        return jnp.sum(jnp.sin(x)) + jnp.sum(lam**2)

    return loss


@functools.cache
def _derivative_programs():
    """The jitted programs of `test_derivatives`, built once: both cases (with and
    without a zero mass) differ only in the traced `theta`, so they share them."""
    pattern = np.array([[1, 0, 0], [0, 1, 1]], bool)
    loss, loss_lu = _loss(AUTO, pattern), _loss(cjax.FullKKTLU(), pattern)
    return types.SimpleNamespace(
        loss=jax.jit(loss),
        grad=jax.jit(jax.grad(loss)),
        grad_lu=jax.jit(jax.grad(loss_lu)),
        jvp=jax.jit(lambda t, v: jax.jvp(loss, (t,), (v,))),
        vmap_grad=jax.jit(jax.vmap(jax.grad(loss))),
        hessian=jax.jit(jax.jacfwd(jax.grad(loss))),
        hessian_lu=jax.jit(jax.hessian(loss_lu)),
    )


@pytest.mark.parametrize("zero_mass", [False, True])
def test_derivatives(zero_mass):
    """jvp, grad and vmap(grad) against finite differences and `FullKKTLU`; with a
    coupled zero mass the derivatives go through the general method."""
    rng = np.random.default_rng(5)
    theta = jnp.asarray(rng.normal(size=14)).at[:3].set(jnp.array([1.0, 2.0, 0.7]))
    if zero_mass:
        theta = theta.at[2].set(0.0)
    programs = _derivative_programs()
    grad = programs.grad(theta)
    grad_lu = programs.grad_lu
    np.testing.assert_allclose(grad, grad_lu(theta), rtol=1e-9, atol=1e-10)
    free = np.ones(14, bool)
    free[2] = not zero_mass  # finite differences would step into negative mass
    fd = finite_difference_grad(programs.loss, theta)
    np.testing.assert_allclose(grad[free], fd[free], rtol=1e-6, atol=1e-7)
    tangent = jnp.asarray(rng.normal(size=14))
    _, dout = programs.jvp(theta, tangent)
    np.testing.assert_allclose(dout, grad @ tangent, rtol=1e-10)
    thetas = jnp.stack([theta, theta.at[0].set(1.5)])
    grads = programs.vmap_grad(thetas)
    np.testing.assert_allclose(
        grads, jnp.stack([grad_lu(t) for t in thetas]), rtol=1e-9, atol=1e-10
    )
    hessian = programs.hessian(theta)
    np.testing.assert_allclose(
        hessian, programs.hessian_lu(theta), rtol=1e-7, atol=1e-8
    )


def _nan_x_problems():
    """Solvable and singular systems, through the fast path and the general method
    (a coupled zero mass): `[(name, problem, singular)]`."""
    rng = np.random.default_rng(6)
    mass, jac, rhs, bias = _problem(rng, 3, 2)
    redundant = jnp.stack([jac[0], 2 * jac[0]])
    coupled = np.array([[1, 0, 0], [0, 1, 1]], bool)
    zero = _problem(rng, 3, 2, coupled, masses=[1.0, 2.0, 0.0])
    # The coupled zero mass with a redundant pair of rows.
    zero_redundant = SparseMatrix.from_dense(
        jnp.asarray([[0.0, 1.0, 1.0], [0.0, 2.0, 2.0]]), np.array([[0, 1, 1]] * 2, bool)
    )
    return [
        ("fast", (mass, jac, rhs, bias), False),
        ("fast, redundant", (mass, redundant, rhs, bias), True),
        ("fast, NaN", (mass, jac, rhs.at[0].set(jnp.nan), bias), True),
        ("general", zero, False),
        ("general, redundant", (zero[0], zero_redundant, zero[2], zero[3]), True),
    ]


def _assert_nan_x(out, ref, singular):
    """`out` is `ref` (zeros where singular) with `x` NaN where singular."""
    x, lam, flag = (np.asarray(v) for v in out)
    x_ref, lam_ref, flag_ref = (np.asarray(v) for v in ref)
    assert bool(flag) == bool(flag_ref) == singular
    np.testing.assert_array_equal(lam, lam_ref)
    if singular:
        assert np.all(np.isnan(x)) and np.all(lam == 0)
    else:
        np.testing.assert_array_equal(x, x_ref)  # bit for bit


@pytest.mark.parametrize(
    "solver", [AUTO, cjax.RangeSpaceLDL(), cjax.FullKKTLU()], ids=type
)
def test_nan_x_only_where_singular(solver):
    """The solve with `fill=nan` (what `simulate`'s vector field calls) is the
    solve with `x` NaN instead of zero where singular: alone and in a batch that
    mixes both, through the fast path (set inside its branch) and the general
    method."""
    nan_x = jax.jit(solve_with(solver, fill=jnp.nan))
    plain = jax.jit(solve_with(solver))
    batched_nan_x = jax.jit(jax.vmap(nan_x, in_axes=(None, None, 0, None)))
    batched = jax.jit(jax.vmap(plain, in_axes=(None, None, 0, None)))
    for _, problem, singular in _nan_x_problems():
        _assert_nan_x(nan_x(*problem), plain(*problem), singular)
        mass, jac, rhs, bias = problem
        rhs_b = jnp.stack([rhs, rhs.at[0].set(jnp.nan), 2 * rhs])
        out = batched_nan_x(mass, jac, rhs_b, bias)
        ref = batched(mass, jac, rhs_b, bias)
        for i, singular_i in enumerate((singular, True, singular)):
            pick = lambda t, i=i: jax.tree.map(lambda v: v[i], t)
            _assert_nan_x(pick(out), pick(ref), singular_i)


def test_nan_x_derivatives():
    """The derivatives of the NaN-filled solve are those of `solve` (no NaN enters
    the tangents or cotangents, also at a singular system, where they are zero):
    through the library's solve, and the solver's own `solve` differentiated
    directly."""
    from constrained_jax._solver.saddle_point import SaddlePointSystem

    pattern = np.array([[1, 0, 0], [0, 1, 1]], bool)

    def loss(theta, fill):
        masses, jac = theta[:3], theta[3:9].reshape(2, 3)
        mass = SparseMatrix(masses, (0, 1, 2), (0, 1, 2), (3, 3))
        jac = SparseMatrix.from_dense(jnp.where(pattern, jac, 0.0), pattern)
        rhs, bias = theta[9:12], theta[12:14]
        if fill == "system":
            x, lam, s = solve_with(AUTO, fill=jnp.nan)(mass, jac, rhs, bias)
        elif fill == "solver":
            x, lam, s = AUTO.solve(SaddlePointSystem(mass, jac, rhs, bias), jnp.nan)
        else:
            x, lam, s = solve_with(AUTO)(mass, jac, rhs, bias)
        x = jnp.where(s, 0.0, x)
        return jnp.sum(jnp.sin(x)) + jnp.sum(lam**2)

    rng = np.random.default_rng(7)
    theta = jnp.asarray(rng.normal(size=14)).at[:3].set(jnp.array([1.0, 2.0, 0.7]))
    # Singular: the two rows of A along the same direction, with a NaN force.
    singular = theta.at[3:9].set(jnp.array([1.0, 0.0, 0.0, 2.0, 0.0, 0.0]))
    singular = singular.at[9].set(jnp.nan)
    grads = {
        fill: jax.jit(jax.vmap(jax.grad(functools.partial(loss, fill=fill))))
        for fill in ("plain", "system", "solver")
    }
    thetas = jnp.stack([theta, theta.at[2].set(0.0), singular])
    ref = grads["plain"](thetas)
    assert np.all(np.isfinite(ref[:2])) and np.all(ref[2] == 0)
    for fill in ("system", "solver"):
        np.testing.assert_allclose(grads[fill](thetas), ref, rtol=1e-13, atol=1e-14)
