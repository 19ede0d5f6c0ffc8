"""Structure detection at trace time, the compressed one-pass equations of motion, the
sparsity-aware unrolled solve and the automatic choice of solver: always against the
dense path (`FullKKTLU`, dense `M` and `A` by `jacfwd`) and closed forms, and right or
refused when a detected pattern misses an entry."""

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax import Automatic, FullKKTLU, RangeSpaceLDL
from constrained_jax._solver.sparse import SparseMatrix
from constrained_jax._solver.sparse_schur import SparseSchur
from constrained_jax._stabilization import project_state
from constrained_jax._structure import colouring, detect
from constrained_jax.scenes import chain, pendulum, two_cylinders

from .helpers import solve_with


def _dense(system):
    return cjax.LagrangianSystem(
        system.lagrangian,
        system.constraints,
        system.forces,
        saddle_point_solver=cjax.FullKKTLU(),
    )


def _assert_same(system, q, qd, t, args, rtol=1e-12):
    """The structured default against the dense LU, and both not singular."""
    qdd, lam, singular = jax.jit(system.solve_accelerations)(q, qd, t, args)
    qdd_d, lam_d, singular_d = jax.jit(_dense(system).solve_accelerations)(
        q, qd, t, args
    )
    assert not singular and not singular_d
    scale = 1 + jnp.max(jnp.abs(qdd_d))
    np.testing.assert_allclose(qdd, qdd_d, rtol=0, atol=rtol * scale)
    np.testing.assert_allclose(
        lam, lam_d, rtol=0, atol=rtol * (1 + jnp.max(jnp.abs(lam_d)))
    )
    return qdd, lam


def test_chain_patterns_and_colouring():
    args = chain.default_args()
    system = chain.system()
    q, _ = chain.state(3, 0.4, args)
    structure = system.structure(q, jnp.asarray(0.0), args)
    assert structure.detected
    np.testing.assert_array_equal(structure.mass, np.eye(6, dtype=bool))
    # Rod j couples P_j and P_{j-1}: 2 nonzeros in the first row, 4 in the others.
    assert structure.jac.sum(axis=1).tolist() == [2, 4, 4]
    assert not structure.constant_rows.any()
    # A diagonal M needs one seed; the chain's A needs 4 (x and y of two points).
    assert colouring(structure.mass).max() + 1 == 1
    assert colouring(structure.jac).max() + 1 == 4


def test_colouring_columns_of_one_colour_are_disjoint():
    rng = np.random.default_rng(0)
    pattern = rng.uniform(size=(7, 9)) < 0.3
    colours = colouring(pattern)
    for c in range(colours.max() + 1):
        rows = pattern[:, colours == c].sum(axis=1)
        assert np.all(rows <= 1)


def test_cylinders_constant_rows_and_equations_match_closed_form():
    args = two_cylinders.default_args()
    system = two_cylinders.system()
    theta1, theta1d = jnp.asarray(0.4), jnp.asarray(0.7)
    q, qd = two_cylinders.state(theta1, theta1d, args)
    structure = system.structure(q, jnp.asarray(0.0), args)
    np.testing.assert_array_equal(structure.mass, np.eye(3, dtype=bool))
    assert structure.constant_rows.all()
    kkt = system.saddle_point_system(q, qd, jnp.asarray(0.0), args)
    mass, jac = kkt.mass, kkt.jac
    assert not mass.is_dense and not jac.is_dense
    assert kkt.mismatch is None  # proven by the traced program: nothing to check
    np.testing.assert_allclose(
        mass.todense(), jax.jacfwd(system.momentum, argnums=1)(q, qd, 0.0, args)
    )
    qdd, lam = _assert_same(system, q, qd, jnp.asarray(0.0), args)
    np.testing.assert_allclose(
        qdd[1], two_cylinders.angular_acceleration(theta1, args), rtol=1e-13
    )
    np.testing.assert_allclose(
        lam[1], two_cylinders.no_slip_multiplier(theta1, args), rtol=1e-13
    )


@pytest.mark.parametrize("num_links", [1, 2])
def test_chain_structured_equals_dense(num_links):
    args = chain.default_args()
    q, qd = chain.state(num_links, 0.6, args, thetadot0=1.3)
    # Off the manifold too: the equations hold at any state.
    q = q + 0.05 * jnp.sin(jnp.arange(q.shape[0], dtype=q.dtype))
    _assert_same(chain.system(), q, qd, jnp.asarray(0.0), args)


def test_pendulum_matches_tension():
    args = pendulum.default_args()
    theta, thetad = jnp.asarray(0.8), jnp.asarray(-1.1)
    q, qd = pendulum.state(theta, thetad, args)
    _, lam = _assert_same(pendulum.system(), q, qd, jnp.asarray(0.0), args)
    # G = r - l: lambda is minus the tension along the outward unit vector.
    np.testing.assert_allclose(
        -lam[0], pendulum.tension(theta, thetad, args), rtol=1e-12
    )


def _switched_system():
    """A coupling `c qd0 qd1` of two masses that is on only for `args["c"] > 5`,
    behind a `lax.cond`: opaque to the reading of the program
    (`constrained_jax._sparsity`), so the random states decide the pattern, and they
    never switch it on."""

    def lagrangian(q, qd, t, args):
        coupling = jax.lax.cond(
            args["c"] > 5.0, lambda: 0.5 * qd[0] * qd[1], lambda: 0.0 * qd[0]
        )
        return 0.5 * jnp.dot(qd, qd) + coupling - 9.81 * q[1] + 0.0 * t

    def rod(q, t, args):
        return jnp.dot(q, q) - 1.0

    return cjax.LagrangianSystem(lagrangian, cjax.Holonomic(rod))


def test_missed_entry_is_refused_never_wrong():
    system = _switched_system()
    q, qd = jnp.array([0.6, -0.8]), jnp.array([0.8, 0.6])
    t = jnp.asarray(0.0)
    # Random parameters are drawn in [0.5, 1.5]: the coupling is never seen.
    on = {"c": jnp.asarray(10.0)}
    structure = system.structure(q, t, on)
    assert not structure.mass[0, 1]
    qdd, lam, singular = jax.jit(system.solve_accelerations)(q, qd, t, on)
    assert singular
    np.testing.assert_array_equal(qdd, 0.0)
    with pytest.raises(Exception, match="sparsity pattern .* misses an entry"):
        # (Waited for: on a GPU the error surfaces when the result is used.)
        jax.block_until_ready(jax.jit(system.accelerations)(q, qd, t, on))
    # The remedy named in the message gives the right answer: with
    # M = [[1, 1/2], [1/2, 1]], A = 2 q^T, bias = 2 |qd|^2, f = (0, -g),
    # M qdd - A^T lambda = f and A qdd + bias = 0.
    qdd_d, lam_d, singular_d = _dense(system).solve_accelerations(q, qd, t, on)
    assert not singular_d
    mass = jnp.array([[1.0, 0.5], [0.5, 1.0]])
    np.testing.assert_allclose(
        mass @ qdd_d - 2 * q * lam_d[0], jnp.array([0.0, -9.81]), atol=1e-12
    )
    np.testing.assert_allclose(2 * q @ qdd_d + 2 * qd @ qd, 0.0, atol=1e-12)
    # With the coupling off the pattern is right and the solve goes through.
    off = {"c": jnp.asarray(1.0)}
    qdd_off, _, singular_off = system.solve_accelerations(q, qd, t, off)
    assert not singular_off
    np.testing.assert_allclose(
        qdd_off, _dense(system).solve_accelerations(q, qd, t, off)[0], atol=1e-13
    )


class _PlainSolve(cjax.AbstractSaddlePointSolver):
    """A user's solver that takes the detected patterns, with no special care for
    NaN: `jnp.linalg.solve` of the full KKT matrix, never `singular`."""

    def form(self, n, k):
        return cjax.KKTForm(sparse=True, unroll=False)

    def solve(self, system, fill):
        mass, jac = system.mass.todense(), system.jac.todense()
        n, k = system.n, system.k
        kkt = jnp.block([[mass, -jac.T], [jac, jnp.zeros((k, k), mass.dtype)]])
        sol = jnp.linalg.solve(kkt, jnp.concatenate([system.rhs, -system.bias]))
        return sol[:n], sol[n:], jnp.array(False)


@pytest.mark.parametrize(
    "solver",
    [cjax.RangeSpaceLDL(), cjax.SparseSchur(), _PlainSolve()],
    ids=["RangeSpaceLDL", "SparseSchur", "users-own"],
)
def test_missed_entry_is_refused_by_every_structured_solver(solver):
    """The refusal of a missed entry with each solver that takes the detected
    patterns, a solver of the user's (never `singular`) included: the library's one
    solve refuses the system (`singular`, zeros) whatever the solver returns."""
    base = _switched_system()
    system = cjax.LagrangianSystem(
        base.lagrangian, base.constraints, saddle_point_solver=solver
    )
    q, qd = jnp.array([0.6, -0.8]), jnp.array([0.8, 0.6])
    t = jnp.asarray(0.0)
    solve = jax.jit(system.solve_accelerations)
    qdd, lam, singular = solve(q, qd, t, {"c": jnp.asarray(10.0)})
    assert singular
    np.testing.assert_array_equal(qdd, 0.0)
    np.testing.assert_array_equal(lam, 0.0)
    # The same program with the coupling off: right.
    qdd, lam, singular = solve(q, qd, t, {"c": jnp.asarray(1.0)})
    assert not singular
    ref, ref_lam, _ = _dense(base).solve_accelerations(q, qd, t, {"c": 1.0})
    np.testing.assert_allclose(qdd, ref, atol=1e-12)
    np.testing.assert_allclose(lam, ref_lam, atol=1e-12)


def test_missed_entry_in_simulate_is_refused():
    """`simulate` (whose vector field refuses a missed entry by masking, not by a
    NaN right-hand side) stops with a failure instead of integrating the wrong
    equations; with the coupling off the same program runs."""
    system = _switched_system()
    q, qd = jnp.array([0.6, -0.8]), jnp.array([0.8, 0.6])

    @jax.jit
    def run(c):
        traj = cjax.simulate(system, (0.0, 0.5), q, qd, {"c": c}, throw=False)
        return traj.result, traj.q[-1]

    result, _ = run(jnp.asarray(10.0))
    assert result == cjax.RESULTS.singular_dynamics
    result, q1 = run(jnp.asarray(1.0))
    assert result == cjax.RESULTS.successful
    np.testing.assert_allclose(jnp.dot(q1, q1), 1.0, atol=1e-6)


def test_where_switch_read_from_the_program_is_right():
    """The same coupling by `jnp.where`: the program shows the data flow from
    `qd1` to `p0`, so the pattern has the entry (proven, no run-time check) and the
    solve is right with the coupling on and off."""

    def lagrangian(q, qd, t, args):
        coupling = jnp.where(args["c"] > 5.0, 0.5 * qd[0] * qd[1], 0.0)
        return 0.5 * jnp.dot(qd, qd) + coupling - 9.81 * q[1]

    system = cjax.LagrangianSystem(
        lagrangian, cjax.Holonomic(lambda q, t, args: jnp.dot(q, q) - 1.0)
    )
    q, qd, t = jnp.array([0.6, -0.8]), jnp.array([0.8, 0.6]), jnp.asarray(0.0)
    structure = system.structure(q, t, {"c": jnp.asarray(10.0)})
    assert structure.mass[0, 1] and structure.mass_proven
    for c in (10.0, 1.0):
        _assert_same(system, q, qd, t, {"c": jnp.asarray(c)})


def test_time_switch_seen_by_detection_is_right():
    """A coupling that switches on at `t > 0.5`: random times hit it, so the
    pattern has it and the solve is right before and after the switch."""

    def lagrangian(q, qd, t, args):
        coupling = jnp.where(t > 0.5, 0.3 * qd[0] * qd[1], 0.0)
        return 0.5 * jnp.dot(qd, qd) + coupling - 9.81 * q[1]

    system = cjax.LagrangianSystem(
        lagrangian, cjax.Holonomic(lambda q, t, args: jnp.dot(q, q) - 1.0)
    )
    q, qd = jnp.array([0.6, -0.8]), jnp.array([0.8, 0.6])
    for t in (0.0, 1.0):
        _assert_same(system, q, qd, jnp.asarray(t), None)


def test_detection_falls_back_to_dense():
    args = chain.default_args()
    q, qd = chain.state(2, 0.3, args, thetadot0=0.5)

    @jax.jit
    def closed_over(q, qd, m):
        # The Lagrangian closes over a traced value: detection gives up (dense).
        def lagrangian(q_, qd_, t, args_):
            return chain.lagrangian(q_, qd_, t, {**args_, "m": m})

        system = cjax.LagrangianSystem(lagrangian, cjax.Holonomic(chain.rods))
        structure = system.structure(q, jnp.asarray(0.0), args)
        assert not structure.detected and structure.mass.all()
        return system.solve_accelerations(q, qd, 0.0, args)

    qdd, lam, singular = closed_over(q, qd, args["m"])
    assert not singular
    np.testing.assert_allclose(
        qdd, _dense(chain.system()).solve_accelerations(q, qd, 0.0, args)[0]
    )

    # A traced integer parameter: dense as well.
    def lagrangian_int(q_, qd_, t, args_):
        scale = jnp.where(args_["flag"], 2.0, 1.0)
        return chain.lagrangian(q_, qd_, t, args_) * scale

    system = cjax.LagrangianSystem(lagrangian_int, cjax.Holonomic(chain.rods))

    @jax.jit
    def structure_of(args_):
        s = system.structure(q, jnp.asarray(0.0), args_)
        assert not s.detected
        return system.solve_accelerations(q, qd, 0.0, args_)[0]

    qdd = structure_of({**args, "flag": jnp.asarray(True)})
    np.testing.assert_allclose(
        qdd, _dense(chain.system()).solve_accelerations(q, qd, 0.0, args)[0]
    )


def test_prng_key_in_args_is_drawn_not_dense():
    """A typed PRNG key in `args` (a Lagrangian with a random parameter) used to make
    detection give up (dense: right, but the slow path). It is drawn like a float:
    the chain's patterns are found, concrete or traced, and the answer is the dense
    one's."""
    args = chain.default_args()
    q, qd = chain.state(2, 0.3, args, thetadot0=0.5)

    def lagrangian(q_, qd_, t, args_):
        g = args_["g"] * (1 + 0.01 * jax.random.normal(args_["key"]))
        return chain.lagrangian(q_, qd_, t, {**args_, "g": g})

    system = cjax.LagrangianSystem(lagrangian, cjax.Holonomic(chain.rods))
    keyed = {**args, "key": jax.random.key(3)}
    reference = chain.system().structure(q, jnp.asarray(0.0), args)
    assert reference.detected and not reference.mass.all()

    @jax.jit
    def solve(q_, qd_, args_):
        structure = system.structure(q_, jnp.asarray(0.0), args_)
        assert structure.detected
        assert np.array_equal(structure.mass, reference.mass)
        assert np.array_equal(structure.jac, reference.jac)
        return system.solve_accelerations(q_, qd_, 0.0, args_)

    assert system.structure(q, jnp.asarray(0.0), keyed).detected
    qdd, lam, singular = solve(q, qd, keyed)
    assert not singular
    qdd_ref, lam_ref, _ = _dense(system).solve_accelerations(q, qd, 0.0, keyed)
    np.testing.assert_allclose(qdd, qdd_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(lam, lam_ref, rtol=1e-12, atol=1e-12)


def test_assembly_follows_the_solver_scalar_or_array():
    """`LagrangianSystem` writes its assembly on scalars (fused under `jax.vmap`) only
    for a solver that is scalar code itself at that size; the 4-link chain's default
    (`SparseSchur`, `n + k = 12`) assembles on arrays, `RangeSpaceLDL(unroll_max=12)`
    on scalars. The two, and LAPACK's LU on dense matrices, agree to round-off, one
    state and a batch, with the pattern check on."""
    assert Automatic().form(3, 2).unroll and not Automatic().form(8, 4).unroll
    assert RangeSpaceLDL(unroll_max=12).form(8, 4).unroll
    assert not RangeSpaceLDL().form(10, 5).unroll
    assert not SparseSchur().form(2, 1).unroll
    assert (
        FullKKTLU().form(8, 4).unroll and not FullKKTLU(unroll_max=0).form(2, 1).unroll
    )
    args = chain.default_args()
    states = [chain.state(4, th, args, thetadot0=0.5 + th) for th in (0.1, 0.3, 0.7)]
    q = jnp.stack([s_[0] for s_ in states])
    qd = jnp.stack([s_[1] for s_ in states])
    base = chain.system()
    results = []
    for solver in (None, RangeSpaceLDL(unroll_max=12), FullKKTLU(unroll_max=0)):
        system = base if solver is None else cjax.LagrangianSystem(
            base.lagrangian, base.constraints, saddle_point_solver=solver
        )  # fmt: skip
        fn = lambda q_, qd_, system=system: system.accelerations(q_, qd_, 0.0, args)
        if solver is not None and not isinstance(solver, FullKKTLU):
            # The two assemblies of the sparse patterns: gathers of the compressed
            # products (arrays) or static slices of them (scalars).
            assembly = jax.make_jaxpr(
                lambda q_, qd_, s_=system: s_.saddle_point_system(
                    q_, qd_, jnp.asarray(0.0), args
                )
            )(q[0], qd[0])
            default = jax.make_jaxpr(
                lambda q_, qd_: base.saddle_point_system(
                    q_, qd_, jnp.asarray(0.0), args
                )
            )(q[0], qd[0])
            assert "gather" in str(default) and "gather" not in str(assembly)
        batch = jax.jit(jax.vmap(fn))(q, qd)
        one = jax.jit(fn)(q[1], qd[1])
        np.testing.assert_allclose(one[0], batch[0][1], rtol=1e-12, atol=1e-12)
        results.append(batch)
    for qdd, lam in results[1:]:
        np.testing.assert_allclose(qdd, results[0][0], rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(lam, results[0][1], rtol=1e-11, atol=1e-11)


def test_detection_is_cached():
    system = chain.system()
    args = chain.default_args()
    q = jnp.zeros(4)
    first = detect(system, q, 0.0, args, 4, 2)
    assert detect(system, q, 0.0, args, 4, 2) is first
    assert detect(system, jnp.zeros(6), 0.0, args, 6, 3) is not first


def test_structural_zero_pivot_gauge_and_force():
    """`q1` has no kinetic energy (a structurally zero diagonal entry of `M`): free
    gauge without a force on it, refused with one."""

    def lagrangian(q, qd, t, args):
        return 0.5 * qd[0] ** 2 + 0.5 * qd[2] ** 2 - args["f"] * q[1] - q[0]

    system = cjax.LagrangianSystem(
        lagrangian, cjax.Holonomic(lambda q, t, args: q[0] - q[2])
    )
    q, qd = jnp.array([0.1, 0.2, 0.1]), jnp.array([0.3, 0.4, 0.3])
    structure = system.structure(q, 0.0, {"f": 1.0})
    assert not structure.mass[1, 1]
    qdd, lam, singular = system.solve_accelerations(q, qd, 0.0, {"f": 0.0})
    assert not singular
    np.testing.assert_allclose(qdd, [-0.5, 0.0, -0.5], atol=1e-14)
    np.testing.assert_allclose(lam, [0.5], atol=1e-14)
    _, _, singular = system.solve_accelerations(q, qd, 0.0, {"f": 1.0})
    assert singular


def test_sparse_range_space_equals_dense_elimination():
    rng = np.random.default_rng(1)
    n, k = 6, 3
    diag = rng.uniform(1, 2, n)
    mass_pattern = np.eye(n, dtype=bool)
    mass_pattern[0, 1] = mass_pattern[1, 0] = True
    mass = np.diag(diag)
    mass[0, 1] = mass[1, 0] = 0.3
    jac_pattern = np.zeros((k, n), bool)
    for r in range(k):
        jac_pattern[r, 2 * r : 2 * r + 3] = True
    jac = np.where(jac_pattern, rng.normal(size=(k, n)), 0.0)
    rhs, bias = rng.normal(size=n), rng.normal(size=k)
    sparse_mass = SparseMatrix.from_dense(mass, mass_pattern)
    sparse_jac = SparseMatrix.from_dense(jac, jac_pattern)
    x_s, lam_s, sing_s = solve_with(RangeSpaceLDL())(sparse_mass, sparse_jac, rhs, bias)
    x_d, lam_d, sing_d = solve_with(RangeSpaceLDL())(
        jnp.asarray(mass), jnp.asarray(jac), rhs, bias
    )
    assert not sing_s and not sing_d
    np.testing.assert_allclose(x_s, x_d, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(lam_s, lam_d, rtol=1e-14, atol=1e-14)
    matrix = np.block([[mass, -jac.T], [jac, np.zeros((k, k))]])
    ref = np.linalg.solve(matrix, np.concatenate([rhs, -bias]))
    np.testing.assert_allclose(np.concatenate([x_s, lam_s]), ref, rtol=1e-12)


def _kkt(mass, k):
    """A saddle-point system with the mass block `mass` and `k` dense rows."""
    n = mass.shape[0]
    jac = SparseMatrix.dense(jnp.ones((k, n)))
    return cjax.SaddlePointSystem(mass, jac, jnp.zeros(n), jnp.zeros(k))


def test_automatic_choice():
    auto = Automatic()
    small = SparseMatrix.from_dense(np.eye(3), np.eye(3, dtype=bool))
    diag = SparseMatrix.from_dense(np.eye(20), np.eye(20, dtype=bool))
    assert isinstance(auto.choose(_kkt(small, 2)), RangeSpaceLDL)
    assert isinstance(auto.choose(_kkt(diag, 10)), SparseSchur)
    assert isinstance(auto.choose(_kkt(SparseMatrix.dense(jnp.eye(20)), 10)), FullKKTLU)
    coupled = np.eye(20, dtype=bool)
    coupled[0, 19] = coupled[19, 0] = True
    assert isinstance(
        auto.choose(_kkt(SparseMatrix.from_dense(np.eye(20), coupled), 10)), FullKKTLU
    )
    assert isinstance(chain.system().saddle_point_solver, Automatic)


def test_larger_chain_uses_sparse_matrices_and_agrees():
    args = chain.default_args()
    q, qd = chain.state(6, 0.5, args, thetadot0=0.9)
    system = chain.system()
    kkt = system.saddle_point_system(q, qd, jnp.asarray(0.0), args)
    mass, jac = kkt.mass, kkt.jac
    assert not mass.is_dense and len(mass.values) == 12
    assert not jac.is_dense and len(jac.values) == 22
    _assert_same(system, q, qd, jnp.asarray(0.0), args)


def test_projection_uses_structure_and_agrees():
    args = chain.default_args()
    q, qd = chain.state(2, 0.5, args, thetadot0=0.9)
    q_off = q + 0.01 * jnp.cos(jnp.arange(4.0))
    qd_off = qd + 0.02
    system = chain.system()
    q1, qd1 = jax.jit(lambda q_, qd_: project_state(system, q_, qd_, 0.0, args, 3))(
        q_off, qd_off
    )
    q2, qd2 = project_state(_dense(chain.system()), q_off, qd_off, 0.0, args, 3)
    np.testing.assert_allclose(q1, q2, atol=1e-13)
    np.testing.assert_allclose(qd1, qd2, atol=1e-13)
    np.testing.assert_allclose(chain.link_lengths(q1), 1.0, atol=1e-9)


def test_constraint_products_keep_temporaries_the_size_of_q():
    """`Holonomic.jacobian_products` applies its linearisation to a few directions
    one by one: its arithmetic runs on arrays the size of `q` (under `jax.vmap` over
    states, temporaries `s + 1` times larger would stream through memory and slow
    the chain's batched equations of motion).
    Checked on the traced program (fails when the directions are vmapped), and the
    products against the dense Jacobian."""
    args = chain.default_args()
    n_links = 16
    q, qd = chain.state(n_links, 0.4, args, thetadot0=0.3)
    n = q.shape[0]
    rods = chain.system().constraints[0]
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(5, n))  # as many as the chain's colours + probe
    fn = lambda q_, qd_: rods.jacobian_products(q_, qd_, 0.0, args, directions)
    jaxpr = jax.make_jaxpr(fn)(q, qd)
    arithmetic = {"add", "sub", "mul", "div", "neg", "integer_pow", "square"}

    def sizes(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name in arithmetic:
                yield from (int(np.prod(v.aval.shape)) for v in eqn.outvars)
            for sub in jax.extend.core.jaxprs_in_params(eqn.params):
                yield from sizes(sub)

    assert max(sizes(jaxpr.jaxpr)) <= n
    products, bias = jax.jit(fn)(q, qd)
    jac = jax.jacfwd(lambda q_: rods.fn(q_, 0.0, args))(q)
    np.testing.assert_allclose(products, jac @ directions.T, rtol=1e-12, atol=1e-12)
    velocity = lambda q_: jax.jvp(lambda x: rods.fn(x, 0.0, args), (q_,), (qd,))[1]
    np.testing.assert_allclose(
        bias, jax.jvp(velocity, (q,), (qd,))[1], rtol=1e-12, atol=1e-12
    )
