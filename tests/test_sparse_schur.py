"""`SparseSchur`, the structured saddle-point solve: agreement with a dense solve of the
KKT matrix on chains, trees and rigid bodies, vmap, gradients, and refusals."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cj
from constrained_jax._solver import sparse as sparse_module
from constrained_jax._solver.sparse import SparseMatrix
from constrained_jax._solver.sparse_schur import _band_order, _gather_sum, _plan, _take
from constrained_jax.scenes import chain

from .helpers import solve_with


# The references and the problems are jitted: eagerly each of their operations would
# compile a program of its own (for every size).
@jax.jit
def dense_solve(mass, jac, rhs, bias):
    n, k = mass.shape[0], jac.shape[0]
    kkt = jnp.block([[mass, -jac.T], [jac, jnp.zeros((k, k))]])
    z = jnp.linalg.solve(kkt, jnp.concatenate([rhs, -bias]))
    return z[:n], z[n:]


def sparse(matrix, pattern=None):
    if pattern is None:
        pattern = np.asarray(matrix) != 0
    return SparseMatrix.from_dense(matrix, pattern)


METHODS = pytest.mark.parametrize("method", ["levels", "scan"])


def assert_agrees(
    mass, jac, rhs, bias, mass_pattern=None, jac_pattern=None, method="auto"
):
    x, lam, singular = jax.jit(solve_with(cj.SparseSchur(method=method)))(
        sparse(mass, mass_pattern), sparse(jac, jac_pattern), rhs, bias
    )
    x_ref, lam_ref = dense_solve(mass, jac, rhs, bias)
    assert not singular
    assert jnp.max(jnp.abs(x - x_ref)) <= 1e-12 * jnp.max(jnp.abs(x_ref))
    assert jnp.max(jnp.abs(lam - lam_ref)) <= 1e-12 * jnp.max(jnp.abs(lam_ref))


def tree_problem(parent, key, dim=2):
    """Particles `j` joined by rods to `parent[j]` (-1: the fixed pivot), random
    positive masses, random positions, forces and biases."""
    return _tree_problem(tuple(int(j) for j in parent), key, dim)


@functools.partial(jax.jit, static_argnums=(0, 2))
def _tree_problem(parent, key, dim):
    num = len(parent)
    k1, k2, k3, k4 = jax.random.split(key, 4)
    points = jax.random.normal(k1, (num, dim))
    parent = np.asarray(parent)

    def rods(q):
        p = q.reshape(num, dim)
        anchor = jnp.concatenate([jnp.zeros((1, dim)), p])[parent + 1]
        return 0.5 * jnp.sum((p - anchor) ** 2, axis=1)

    q = points.reshape(-1)
    masses = jnp.repeat(jax.random.uniform(k2, (num,), minval=0.5, maxval=2.0), dim)
    return (
        jnp.diag(masses),
        jax.jacfwd(rods)(q),
        jax.random.normal(k3, q.shape),
        jax.random.normal(k4, (num,)),
    )


@functools.partial(jax.jit, static_argnums=0)
def chain_problem(num_links, key):
    args = chain.default_args(m=1.3)
    q, _ = chain.state(num_links, 0.4, args)
    k1, k2, k3 = jax.random.split(key, 3)
    q = q + 0.05 * jax.random.normal(k1, q.shape)
    mass = jax.hessian(chain.lagrangian, argnums=1)(q, jnp.zeros_like(q), 0.0, args)
    jac = jax.jacfwd(chain.rods)(q, 0.0, args)
    return (
        mass,
        jac,
        jax.random.normal(k2, q.shape),
        jax.random.normal(k3, (num_links,)),
    )


@METHODS
@pytest.mark.parametrize("num_links", [1, 2, 5, 12, 64])
def test_chain_scene(num_links, method, getkey):
    """The chain scene's own M (from the Lagrangian) and A at a perturbed state."""
    assert_agrees(*chain_problem(num_links, getkey()), method=method)


def test_chain_is_cyclic_reduction(getkey):
    """The Schur complement of the 64-link chain is eliminated in log2 levels."""
    mass, jac, *_ = chain_problem(64, getkey())
    m, a = sparse(mass), sparse(jac)
    plan = _plan((m.rows, m.cols, m.shape), (a.rows, a.cols, a.shape))
    assert len(plan.levels) <= math.ceil(math.log2(64)) + 1


def test_chain_is_thomas(getkey):
    """The chain's Schur complement is tridiagonal in the natural order: the
    sequential elimination is the Thomas algorithm, the default choice."""
    mass, jac, *_ = chain_problem(64, getkey())
    m, a = sparse(mass), sparse(jac)
    plan = _plan((m.rows, m.cols, m.shape), (a.rows, a.cols, a.shape))
    assert plan.band_width == 1
    assert np.array_equal(plan.band_order, np.arange(64))


def test_band_order_star():
    """A star numbered hub first (bandwidth 8 in the natural order): reverse
    Cuthill-McKee starts from a leaf, so the hub comes second to last."""
    order, width = _band_order(9, [(0, j) for j in range(1, 9)])
    assert sorted(order) == list(range(9))
    assert width == 7 and order[7] == 0


def test_unknown_method(getkey):
    mass, jac, rhs, bias = chain_problem(3, getkey())
    with pytest.raises(ValueError, match="method"):
        solve_with(cj.SparseSchur(method="qr"))(sparse(mass), sparse(jac), rhs, bias)


@METHODS
@pytest.mark.parametrize("seed", range(4))
def test_random_trees(seed, method):
    rng = np.random.default_rng(seed)
    num = int(rng.integers(2, 13))
    parent = [-1] + [int(rng.integers(-1, j)) for j in range(1, num)]
    assert_agrees(
        *tree_problem(parent, jax.random.key(seed), dim=int(rng.integers(2, 4))),
        method=method,
    )


@METHODS
def test_star_tree(method, getkey):
    """A hub with many branches (the hub is eliminated last, no fill blow-up)."""
    parent = [-1] + [0] * 6 + [1, 2, 3]
    assert_agrees(*tree_problem(parent, getkey()), method=method)


@METHODS
@pytest.mark.parametrize("seed", range(3))
def test_rigid_bodies(seed, method):
    """Block-diagonal M with 3x3 blocks (and one point mass), coordinates shuffled, rows
    coupling neighbouring bodies and a branch."""
    rng = np.random.default_rng(seed)
    sizes = [3, 3, 1, 3, 3]
    n = sum(sizes)
    blocks = []
    for s in sizes:
        b = rng.normal(size=(s, s))
        blocks.append(b @ b.T + s * np.eye(s))
    mass = np.zeros((n, n))
    starts = np.cumsum([0] + sizes)
    for s0, b in zip(starts, blocks, strict=False):
        mass[s0 : s0 + len(b), s0 : s0 + len(b)] = b
    pairs = [(0, 1), (1, 2), (2, 3), (1, 4), (0, 0), (3, 4)]
    jac = np.zeros((len(pairs), n))
    for r, (i, j) in enumerate(pairs):
        for body in {i, j}:
            jac[r, starts[body] : starts[body + 1]] = rng.normal(size=sizes[body])
    perm = rng.permutation(n)
    mass, jac = mass[np.ix_(perm, perm)], jac[:, perm]
    assert_agrees(
        jnp.asarray(mass),
        jnp.asarray(jac),
        jnp.asarray(rng.normal(size=n)),
        jnp.asarray(rng.normal(size=len(pairs))),
        method=method,
    )


def test_no_constraints(getkey):
    mass, jac, rhs, _ = chain_problem(3, getkey())
    x, lam, singular = jax.jit(solve_with(cj.SparseSchur()))(
        sparse(mass), sparse(jnp.zeros((0, 6))), rhs, jnp.zeros((0,))
    )
    assert not singular and lam.shape == (0,)
    assert jnp.allclose(x, rhs / mass[0, 0], rtol=1e-14)


@METHODS
def test_vmap(method, getkey):
    problems = [chain_problem(5, getkey()) for _ in range(3)]
    mass, jac, rhs, bias = (jnp.stack(p) for p in zip(*problems, strict=True))
    pattern_m, pattern_a = np.asarray(mass[0]) != 0, np.asarray(jac[0]) != 0

    def solve(m, a, f, b):
        return solve_with(cj.SparseSchur(method=method))(
            sparse(m, pattern_m), sparse(a, pattern_a), f, b
        )

    x, lam, singular = jax.jit(jax.vmap(solve))(mass, jac, rhs, bias)
    assert not jnp.any(singular)
    for i in range(3):
        x_ref, lam_ref = dense_solve(mass[i], jac[i], rhs[i], bias[i])
        assert jnp.allclose(x[i], x_ref, rtol=1e-12, atol=1e-12)
        assert jnp.allclose(lam[i], lam_ref, rtol=1e-12, atol=1e-12)


@METHODS
def test_gradients(method, getkey):
    """Reverse and forward mode through the solve agree with the dense solve's."""
    mass, jac, rhs, bias = chain_problem(6, getkey())
    pattern_m, pattern_a = np.asarray(mass) != 0, np.asarray(jac) != 0
    weights = jax.random.normal(getkey(), (18,))
    mask = jnp.asarray(pattern_a, float)  # A's gradient off its pattern is not defined

    def loss(solve, scale, jac, rhs, bias):
        x, lam = solve(scale * mass, jac, rhs, bias)
        return jnp.dot(weights, jnp.concatenate([x, lam]))

    def structured(m, a, f, b):
        x, lam, _ = solve_with(cj.SparseSchur(method=method))(
            sparse(m, pattern_m), sparse(a, pattern_a), f, b
        )
        return x, lam

    primals = (jnp.asarray(1.7), jac, rhs, bias)
    grads = jax.jit(jax.grad(lambda *p: loss(structured, *p), argnums=(0, 1, 2, 3)))(
        *primals
    )
    expected = jax.jit(
        jax.grad(lambda *p: loss(dense_solve, *p), argnums=(0, 1, 2, 3))
    )(*primals)
    for g, e in zip(grads, expected, strict=True):
        g = g * mask if g.shape == jac.shape else g
        e = e * mask if e.shape == jac.shape else e
        assert jnp.allclose(g, e, rtol=1e-10, atol=1e-10)
    tangents = tuple(jax.random.normal(getkey(), jnp.shape(p)) for p in primals)
    tangents = (tangents[0], tangents[1] * mask, *tangents[2:])
    along = lambda solve: jax.jit(
        lambda p, t: jax.jvp(lambda *p_: loss(solve, *p_), p, t)[1]
    )
    dot = along(structured)(primals, tangents)
    dot_ref = along(dense_solve)(primals, tangents)
    assert jnp.allclose(dot, dot_ref, rtol=1e-10)


def _assert_singular(mass, jac, rhs, bias, method="auto", mass_pattern=None):
    x, lam, singular = jax.jit(solve_with(cj.SparseSchur(method=method)))(
        sparse(mass, mass_pattern), sparse(jac), rhs, bias
    )
    assert singular
    assert jnp.all(x == 0) and jnp.all(lam == 0)


@METHODS
def test_redundant_constraint(method, getkey):
    """The same rod twice: A rank-deficient, multipliers not unique."""
    mass, jac, rhs, bias = chain_problem(4, getkey())
    jac = jnp.concatenate([jac, jac[2:3]])
    _assert_singular(mass, jac, rhs, jnp.concatenate([bias, bias[2:3]]), method=method)


@METHODS
def test_zero_mass_refused(method, getkey):
    """A mass set to zero at run time (the pattern is the nonzero one)."""
    mass, jac, rhs, bias = chain_problem(4, getkey())
    pattern = np.asarray(mass) != 0
    mass = mass.at[3, 3].set(0.0)
    _assert_singular(mass, jac, rhs, bias, method=method, mass_pattern=pattern)


@METHODS
def test_nonfinite_refused(method, getkey):
    """A NaN in A at run time: singular, zeros returned."""
    mass, jac, rhs, bias = chain_problem(4, getkey())
    pattern = np.asarray(jac) != 0
    jac = jac.at[1, 2].set(jnp.nan)
    x, lam, singular = jax.jit(solve_with(cj.SparseSchur(method=method)))(
        sparse(mass), sparse(jac, pattern), rhs, bias
    )
    assert singular and jnp.all(x == 0) and jnp.all(lam == 0)


@METHODS
def test_negative_mass_refused(method, getkey):
    """An indefinite M: the pivot-free elimination is not trusted (singular), even
    where the KKT matrix is nonsingular."""
    mass, jac, rhs, bias = chain_problem(4, getkey())
    mass = mass.at[5, 5].set(-0.7)
    _assert_singular(mass, jac, rhs, bias, method=method)
    assert abs(jnp.linalg.det(jnp.block([[mass, -jac.T], [jac, jnp.zeros((4, 4))]])))


def test_structurally_zero_diagonal_is_dense(getkey):
    """A mass matrix with a structurally zero diagonal entry is solved densely."""
    mass, jac, rhs, bias = chain_problem(3, getkey())
    mass = mass.at[0, 0].set(0.0)
    x, lam, singular = jax.jit(solve_with(cj.SparseSchur()))(
        sparse(mass), sparse(jac), rhs, bias
    )
    x_ref, lam_ref, singular_ref = jax.jit(solve_with(cj.FullKKTLU(unroll_max=0)))(
        mass, jac, rhs, bias
    )
    assert singular == singular_ref
    assert jnp.allclose(x, x_ref, rtol=1e-12) and jnp.allclose(lam, lam_ref, rtol=1e-12)


def test_static_indices_as_slices_or_gathers():
    """`_take` reads evenly spaced static indices as slices (the identity, a range, a
    stride, a single position, 2-D index arrays) and anything else as a gather, with
    NumPy's answer in every case, also under `jax.vmap`; `_gather_sum` pads only when
    an index reads the padding slot."""
    values = np.arange(10.0) ** 2 + 1
    cases = [
        np.arange(10),
        np.arange(2, 7),
        np.arange(1, 10, 3),
        np.array([4]),
        np.array(7),
        np.arange(6).reshape(2, 3),
        np.array([3, 1, 4, 1, 5]),
        np.array([[0, 2], [5, 9]]),
        np.zeros((0,), int),
    ]
    for index in cases:
        np.testing.assert_array_equal(_take(jnp.asarray(values), index), values[index])
    batch = np.stack([values, -values])
    for index in cases[:3] + cases[6:7]:
        out = jax.vmap(lambda v, index=index: _take(v, index))(jnp.asarray(batch))
        np.testing.assert_array_equal(out, batch[:, index])
    padded = np.append(values, 0.0)
    for index in (np.array([[0, 1], [2, 10]]), np.array([[0, 1], [2, 3]])):
        np.testing.assert_array_equal(
            _gather_sum(jnp.asarray(values), index), padded[index].sum(axis=1)
        )


@pytest.mark.parametrize(
    "shape, density", [((3, 3), 0.5), ((2, 5), 0.6), ((40, 30), 0.1)]
)
@pytest.mark.parametrize("transpose", [False, True])
def test_matvec_matches_the_dense_product(shape, density, transpose):
    """`matvec` on the nonzeros equals the dense product, both ways, also under
    `jax.vmap`; up to `_UNROLL` nonzeros its program has no gather or scatter (which
    keep XLA:CPU from compiling a small loop into one function), above it is one
    scatter-add."""
    rng = np.random.default_rng(0)
    pattern = rng.random(shape) < density
    pattern[0, 0] = True
    dense = np.where(pattern, rng.normal(size=shape), 0.0)
    matrix = SparseMatrix.from_dense(jnp.asarray(dense), pattern)
    vector = jnp.asarray(rng.normal(size=shape[0] if transpose else shape[1]))
    expected = (dense.T if transpose else dense) @ np.asarray(vector)
    out = matrix.matvec(vector, transpose=transpose)
    np.testing.assert_allclose(out, expected, rtol=1e-13, atol=1e-13)
    batched = jax.vmap(lambda v: matrix.matvec(v, transpose=transpose))(
        jnp.stack([vector, 2 * vector])
    )
    np.testing.assert_allclose(batched[1], 2 * expected, rtol=1e-13, atol=1e-13)
    jaxpr = str(jax.make_jaxpr(lambda m, v: m.matvec(v, transpose))(matrix, vector))
    small = int(pattern.sum()) <= sparse_module._UNROLL
    assert ("gather" in jaxpr or "scatter" in jaxpr) is not small
