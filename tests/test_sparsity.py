"""Sparsity patterns proven from the traced program (`constrained_jax._sparsity`):
sound against autodiff's Jacobians at random points, for many primitives; exact for
the scenes; the run-time pattern check left out only where proven, with answers bit
for bit those of the checked program; a pattern the program does not prove keeps
its check and its refusal."""

import collections
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax import _structure
from constrained_jax._sparsity import dependency_pattern, nonzero_pattern
from constrained_jax.scenes import chain, pendulum, two_cylinders


def _custom(x):
    @jax.custom_jvp
    def f(x):
        return x * 2.0

    f.defjvp(lambda p, t: (f(p[0]), 2.0 * t[0]))
    return f(x)


FUNCTIONS = {
    "elementwise": lambda x: jnp.sin(x) * x**2 + jnp.exp(x) / (1 + x * x),
    "slices and stack": lambda x: jnp.stack([x[0] * x[1], x[2], x[3] ** 2, x[1]]),
    "concatenate, pad, reverse": lambda x: jnp.concatenate(
        [jnp.pad(x[:2], (1, 1)), x[::-1][:2] * 3.0]
    ),
    "interior pad": lambda x: jax.lax.pad(x[:3], 0.0, [(1, -1, 1)]),
    "diff": lambda x: x[1:] - x[:-1],
    "broadcast, transpose, reduce": lambda x: jnp.sum(
        jnp.outer(x[:2], x[2:]).T, axis=0
    ),
    "dot": lambda x: jnp.array([[1.0, 0.0, 0.0, 2.0], [0.0, 1.0, 0.0, 0.0]]) @ x,
    "where": lambda x: jnp.where(x[0] > 0, x[1], x[2]) * jnp.ones(2),
    "reshape, max": lambda x: jnp.max(x.reshape(2, 2), axis=1) + jnp.min(x),
    "nested jit": lambda x: jax.jit(lambda y: y[1:] * y[:-1])(x),
    "checkpoint": lambda x: jax.checkpoint(lambda y: jnp.cos(y) * y[0])(x),
    "custom jvp": lambda x: _custom(x)[::2],
    "scan": lambda x: jax.lax.scan(lambda c, y: (c + y, c * y), 0.0, x)[1],
    "cond": lambda x: jax.lax.cond(x[0] > 0, lambda y: y * 2, lambda y: -y, x),
    "gather": lambda x: x[jnp.array([3, 0])],
    "cumsum": lambda x: jnp.cumsum(x),
    "norm": lambda x: jnp.linalg.norm(x[:3]) * jnp.ones(1),
}


@pytest.mark.parametrize("name", list(FUNCTIONS))
def test_dependency_pattern_is_sound(name):
    """Every nonzero of `jax.jacfwd` at random points lies inside the pattern."""
    fn = FUNCTIONS[name]
    x0 = jnp.array([0.3, -1.2, 0.7, 2.1])
    pattern = dependency_pattern(lambda x: jnp.atleast_1d(fn(x)), (x0,), 0)
    assert pattern is not None
    rng = np.random.default_rng(0)
    for _ in range(4):
        x = jnp.asarray(rng.normal(size=4))
        jac = np.asarray(jax.jacfwd(lambda x: jnp.atleast_1d(fn(x)))(x))
        assert jac.shape == pattern.shape
        assert not np.any((jac != 0) & ~pattern), name


def test_dependency_pattern_is_exact_where_the_data_flow_is():
    pattern = dependency_pattern(FUNCTIONS["diff"], (jnp.zeros(4),), 0)
    band = np.eye(3, 4, 0, bool) | np.eye(3, 4, 1, bool)
    np.testing.assert_array_equal(pattern, band)
    pattern = dependency_pattern(FUNCTIONS["slices and stack"], (jnp.zeros(4),), 0)
    np.testing.assert_array_equal(
        pattern, [[1, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 1, 0, 0]]
    )
    # Opaque operations depend on every input.
    assert dependency_pattern(FUNCTIONS["cumsum"], (jnp.zeros(4),), 0).all()


def test_nonzero_pattern_counts_only_exact_zeros():
    def g(x):
        zero = jnp.zeros_like(x[0])
        return jnp.stack(
            [
                jnp.stack([x[0], zero, -zero, zero + zero]),
                # 0 * x is NaN for an infinite x: possibly nonzero.
                jnp.stack([0.0 * x[1], zero / x[1], jnp.cos(zero), x[2]]),
            ]
        )

    pattern = nonzero_pattern(g, (jnp.ones(3),))
    np.testing.assert_array_equal(pattern, [[1, 0, 0, 0], [1, 1, 1, 1]])


def test_exact_reading_skips_the_random_states():
    """Where every rule is exact (the scenes), the structure comes from the program
    alone; a product with an exact zero or an opaque operation only bounds it."""
    x = jnp.ones(3)
    assert dependency_pattern(lambda x: x[1:] * x[:-1], (x,), 0, exact=True) is not None
    assert dependency_pattern(lambda x: jnp.cumsum(x), (x,), 0, exact=True) is None
    masked = lambda x: jnp.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]) @ x
    assert dependency_pattern(masked, (x,), 0, exact=True) is None
    assert dependency_pattern(masked, (x,), 0).all()  # the bound: dense


@pytest.mark.parametrize(
    "scene, system, n",
    [
        ("two_cylinders", two_cylinders.system(), 3),
        ("two_cylinders contact", two_cylinders.contact_system(), 3),
        ("pendulum", pendulum.system(), 2),
        ("chain", chain.system(), 6),
    ],
)
def test_scene_patterns_are_proven(scene, system, n):
    module = {"two": two_cylinders, "pen": pendulum, "cha": chain}[scene[:3]]
    args = module.default_args()
    structure = system.structure(jnp.ones(n), jnp.asarray(0.0), args)
    assert structure.detected
    assert structure.mass_proven and structure.jac_proven


def test_switched_coupling_is_not_proven_and_keeps_its_check():
    """`lax.cond(c > 5, qd0 qd1 / 2, 0)`: opaque to the reading, so the random
    states decide, and random parameters never switch it on; the reading's bound has
    the entry, so the pattern is not proven and the check refuses the solve."""

    def lagrangian(q, qd, t, args):
        coupling = jax.lax.cond(
            args["c"] > 5.0, lambda: 0.5 * qd[0] * qd[1], lambda: 0.0 * qd[0]
        )
        return 0.5 * jnp.dot(qd, qd) + coupling - 9.81 * q[1]

    system = cjax.LagrangianSystem(
        lagrangian, cjax.Holonomic(lambda q, t, args: jnp.dot(q, q) - 1.0)
    )
    q, qd, t = jnp.array([0.6, -0.8]), jnp.array([0.8, 0.6]), jnp.asarray(0.0)
    on = {"c": jnp.asarray(10.0)}
    structure = system.structure(q, t, on)
    assert not structure.mass[0, 1] and not structure.mass_proven
    assert structure.jac_proven  # dense: nothing to check
    _, _, singular = jax.jit(system.solve_accelerations)(q, qd, t, on)
    assert singular


def _unproven(monkeypatch):
    """Structure detection as before the proofs: every sparse pattern checked."""
    detect = _structure.detect

    def without_proofs(*a, **k):
        return dataclasses.replace(detect(*a, **k), mass_proven=False, jac_proven=False)

    monkeypatch.setattr("constrained_jax._system.detect", without_proofs)


def test_proofs_leave_the_answers_bit_for_bit(monkeypatch):
    """The proof removes a check that could not fire: the accelerations, the
    multipliers and the `singular` flag are the same bits, and the program smaller."""
    args = two_cylinders.default_args()
    theta = jnp.linspace(-1.0, 1.0, 7)
    q, qd = jax.vmap(lambda th: two_cylinders.state(th, 2.0 * th, args))(theta)
    # Off the manifold too, and a vanishing inertia (the general path).
    q = q.at[:, 0].add(0.01 * theta)
    args_zero = {**args, "I": jnp.asarray(0.0)}

    def solve(system):
        return jax.jit(
            jax.vmap(
                lambda q_, qd_, a: system.solve_accelerations(q_, qd_, 0.0, a),
                in_axes=(0, 0, None),
            )
        )

    system = two_cylinders.system()
    proven = [solve(system)(q, qd, a) for a in (args, args_zero)]
    size_proven = len(solve(system).lower(q, qd, args).as_text())
    _unproven(monkeypatch)
    fresh = two_cylinders.system()  # a new system: not in the jit cache above
    checked = [solve(fresh)(q, qd, a) for a in (args, args_zero)]
    size_checked = len(solve(fresh).lower(q, qd, args).as_text())
    for a, b in zip(proven, checked, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
    assert size_proven < size_checked


@pytest.mark.parametrize("scene", ["two_cylinders", "pendulum", "chain"])
def test_read_structure_equals_the_sampled_one(scene, monkeypatch):
    """The structure read from the program against the one found at random states
    (and proven by the bound) for the same system: the same patterns and rows."""
    module = {"two_cylinders": two_cylinders, "pendulum": pendulum, "chain": chain}
    module = module[scene]
    system, args = module.system(), module.default_args()
    n = {"two_cylinders": 3, "pendulum": 2, "chain": 6}[scene]
    q, t = jnp.ones(n), jnp.asarray(0.0)
    monkeypatch.setattr(_structure, "_CACHE", collections.OrderedDict())
    read = system.structure(q, t, args)
    monkeypatch.setattr(_structure, "_CACHE", collections.OrderedDict())
    monkeypatch.setattr(_structure, "_read_structure", lambda *a, **k: None)
    sampled = system.structure(q, t, args)
    assert sampled.mass_proven and sampled.jac_proven
    np.testing.assert_array_equal(read.mass, sampled.mass)
    np.testing.assert_array_equal(read.jac, sampled.jac)
    np.testing.assert_array_equal(read.constant_rows, sampled.constant_rows)


def _systems():
    """Lagrangians and constraints written the ways users write them: each read
    exactly, bounded, or opaque to the reading."""
    rod = cjax.Holonomic(lambda q, t, a: jnp.stack([q[0] ** 2 + q[1] ** 2 - 1.0]))
    kinetic = lambda qd: 0.5 * jnp.sum(jnp.array([1.0, 2.0, 3.0]) * qd**2)
    potential = lambda q: 9.81 * q[1] + 0.5 * q[2] ** 2

    def lagrangian(kind):
        def fn(q, qd, t, a):
            if kind == "diag constant matrix":
                t_ = 0.5 * qd @ jnp.diag(jnp.array([1.0, 2.0, 3.0])) @ qd
            elif kind == "gather":
                t_ = kinetic(qd[jnp.array([0, 1, 2])])
            elif kind == "norm":
                t_ = 0.5 * jnp.linalg.norm(qd[:2]) ** 2 + 1.5 * qd[2] ** 2
            elif kind == "coupled by q":
                t_ = kinetic(qd) + 0.3 * jnp.cos(q[2]) * qd[0] * qd[2]
            elif kind == "cond":
                t_ = kinetic(qd) + jax.lax.cond(
                    a["c"] > 0, lambda: 0.2 * qd[1] * qd[2], lambda: 0.0 * qd[1]
                )
            else:
                t_ = kinetic(qd)
            return t_ - potential(q)

        return fn

    pfaffian = cjax.Pfaffian(
        lambda q, t, a: jnp.zeros((1, 3)).at[0, 1].set(1.0).at[0, 2].set(-q[0])
    )
    out = {
        kind: cjax.LagrangianSystem(lagrangian(kind), rod)
        for kind in ("plain", "diag constant matrix", "gather", "norm", "coupled by q")
    }
    out["cond"] = cjax.LagrangianSystem(lagrangian("cond"), rod)
    out["scatter Pfaffian"] = cjax.LagrangianSystem(lagrangian("plain"), pfaffian)
    out["eye Pfaffian"] = cjax.LagrangianSystem(
        lagrangian("plain"),
        cjax.Pfaffian(lambda q, t, a: jnp.eye(3)[:1] * (1 + q[2] ** 2)),
    )
    return out


@pytest.mark.parametrize("kind", list(_systems()))
def test_structured_solve_agrees_with_dense_however_written(kind):
    """Read (plain, norm, coupled by q), sampled and proven by the bound (the
    Pfaffians) or sampled and checked (a constant matrix, a gather, a `lax.cond`
    switch the random draws see), the structured solve equals the dense LU at
    random states and parameters."""
    system = _systems()[kind]
    dense = cjax.LagrangianSystem(
        system.lagrangian,
        system.constraints,
        saddle_point_solver=cjax.FullKKTLU(),
    )
    rng = np.random.default_rng(3)
    for c in (1.0, -1.0):
        args = {"c": jnp.asarray(c)}
        for _ in range(2):
            q = jnp.asarray(rng.normal(size=3))
            qd = jnp.asarray(rng.normal(size=3))
            qdd, lam, singular = jax.jit(system.solve_accelerations)(q, qd, 0.0, args)
            ref, ref_lam, ref_singular = dense.solve_accelerations(q, qd, 0.0, args)
            assert not ref_singular and not singular
            np.testing.assert_allclose(qdd, ref, rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(lam, ref_lam, rtol=1e-10, atol=1e-10)
