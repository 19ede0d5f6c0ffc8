"""The implicit derivative of the saddle-point solve (`_solver/saddle_point.py`)
against the plain derivative through the elimination and against finite differences:
first and second derivatives, forward and reverse mode, under `jax.vmap`, for a
nonsingular system with a singular `M` (two cylinders with `I = 0`), a free gauge
(the cylinder in free flight with `I = 0`) and a singular system (a force on the
massless spin)."""

import functools
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import two_cylinders as cyl

from .helpers import finite_difference_grad


SOLVERS = {
    "automatic": cjax.Automatic(),
    "range-space-dense": cjax.RangeSpaceLDL(sparse=False),
    "full-lu": cjax.FullKKTLU(),
}


def _spin_potential(q, qd, t, args):
    """A torque on the spin `theta2` (`-dV/dtheta2` for `V = kappa theta2^2 / 2`)."""
    return jnp.stack([0.0, 0.0, -args["kappa"] * q[2]])


def _systems(solver):
    return {
        "attached": cjax.LagrangianSystem(
            cyl.lagrangian,
            constraints=cjax.Pfaffian(cyl.pfaffian_rows),
            saddle_point_solver=solver,
        ),
        "free": cjax.LagrangianSystem(cyl.lagrangian, saddle_point_solver=solver),
        "forced-free": cjax.LagrangianSystem(
            cyl.lagrangian, forces=_spin_potential, saddle_point_solver=solver
        ),
    }


def _split(p):
    args = {"M": p[0], "I": p[1], "a": p[2], "R": p[3], "g": p[4], "kappa": p[5]}
    return p[6:9], p[9:12], args


def _point(inertia):
    return jnp.array(
        [1.3, inertia, 0.3, 1.0, 9.81, 0.7, 1.25, 0.4, 0.9, 0.2, -0.5, 1.1]
    )


def _custom(system):
    def fn(p):
        q, qd, args = _split(p)
        qdd, lam, _ = system.solve_accelerations(q, qd, 0.0, args)
        return jnp.concatenate([qdd, lam])

    return fn


def _plain(system):
    """The same solve, differentiated through the solver's elimination."""

    def fn(p):
        q, qd, args = _split(p)
        kkt = system.saddle_point_system(q, qd, jnp.asarray(0.0), args)
        qdd, lam, _ = system.saddle_point_solver.solve(kkt, 0.0)
        return jnp.concatenate([qdd, lam])

    return fn


def _close(a, b, rtol=1e-10):
    a, b = np.asarray(a), np.asarray(b)
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    scale = max(np.max(np.abs(b)), 1.0)
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


CASES = [("attached", 0.09), ("attached", 0.0), ("free", 0.09), ("free", 0.0)]


@functools.cache
def _first_derivative_programs(solver, name):
    """The jitted functions of `test_first_derivatives_match_plain` for one system,
    built once: the point (and with it the inertia) and the weights are traced
    arguments, so the cases `I = 0.09` and `I = 0` run the same compiled programs."""
    system = _systems(SOLVERS[solver])[name]
    custom, plain = _custom(system), _plain(system)
    scalar = lambda p, weights: weights @ custom(p)
    return types.SimpleNamespace(
        custom=jax.jit(custom),
        plain=jax.jit(plain),
        plain_jacobian=jax.jit(jax.jacfwd(plain)),
        jacfwd=jax.jit(jax.jacfwd(custom)),
        jacrev=jax.jit(jax.jacrev(custom)),
        jvp=jax.jit(lambda p, v: jax.jvp(custom, (p,), (v,))[1]),
        grad=jax.jit(jax.grad(scalar)),
        vmap_grad=jax.jit(jax.vmap(jax.grad(scalar), in_axes=(0, None))),
    )


@pytest.mark.parametrize("solver", SOLVERS.keys(), ids=SOLVERS.keys())
@pytest.mark.parametrize("name, inertia", CASES)
def test_first_derivatives_match_plain(solver, name, inertia):
    """jvp, jacfwd, jacrev, grad and vmap(grad) agree with the plain derivative (free
    with `I = 0`: `theta2` is a free gauge, its acceleration and tangent are 0)."""
    programs = _first_derivative_programs(solver, name)
    p = _point(inertia)
    _close(programs.custom(p), programs.plain(p), 1e-13)
    ref = programs.plain_jacobian(p)
    _close(programs.jacfwd(p), ref)
    _close(programs.jacrev(p), ref)
    v = jnp.linspace(-1.0, 1.0, p.shape[0])
    _close(programs.jvp(p, v), ref @ v)
    weights = jnp.arange(1.0, ref.shape[0] + 1)
    _close(programs.grad(p, weights), weights @ ref)
    batch = jnp.stack([p, p.at[6].add(0.1), p.at[7].add(-0.2)])
    refs = jnp.stack([weights @ programs.plain_jacobian(b) for b in batch])
    _close(programs.vmap_grad(batch, weights), refs)
    if name == "free" and inertia == 0.0:
        assert np.all(np.asarray(ref[2]) == 0.0)  # the gauge's acceleration


@functools.cache
def _finite_difference_program(name):
    """`weights @ solve(p)` for the Automatic solver, jitted once per system (shared
    by `I = 0.09` and `I = 0`), with its jitted gradient."""
    system = _systems(cjax.Automatic())[name]
    weights = jnp.array([1.0, -2.0, 0.5, 3.0, -1.0])[: 3 + (name == "attached") * 2]
    scalar = lambda p: weights @ _custom(system)(p)
    return jax.jit(scalar), jax.jit(jax.grad(scalar))


@pytest.mark.parametrize("name, inertia", CASES)
def test_gradient_matches_finite_differences(name, inertia):
    scalar, scalar_grad = _finite_difference_program(name)
    p = _point(inertia)
    grad = np.asarray(scalar_grad(p))
    # Away from I = 0 only (a one-sided perturbation of I there is another system).
    keep = np.arange(p.shape[0]) != 1
    fd = finite_difference_grad(scalar, p)
    np.testing.assert_allclose(grad[keep], fd[keep], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("solver", SOLVERS.values(), ids=SOLVERS.keys())
def test_singular_zero_tangents(solver):
    """A torque on the massless spin: singular, zero solution and zero derivatives
    (no NaN) in both modes."""
    system = _systems(solver)["forced-free"]
    p = _point(0.0)
    q, qd, args = _split(p)
    assert bool(jax.jit(system.solve_accelerations)(q, qd, 0.0, args)[2])
    custom = _custom(system)
    jacrev = jax.jit(jax.jacrev(custom))
    for jac in (jax.jit(jax.jacfwd(custom))(p), jacrev(p)):
        np.testing.assert_array_equal(np.asarray(jac), 0.0)
    # Nonsingular with inertia: the force is then ordinary.
    plain = jax.jit(jax.jacfwd(_plain(system)))
    _close(jacrev(_point(0.09)), plain(_point(0.09)))


@pytest.mark.parametrize("name, inertia", [("attached", 0.09), ("free", 0.0)])
def test_second_derivatives_match_plain(name, inertia):
    system = _systems(cjax.Automatic())[name]
    weights = jnp.arange(1.0, 4.0 + (name == "attached") * 2)
    custom = lambda p: weights @ _custom(system)(p)
    plain = lambda p: weights @ _plain(system)(p)
    p = _point(inertia)
    ref = jax.jit(jax.hessian(plain))(p)
    _close(jax.jit(jax.hessian(custom))(p), ref, 1e-9)
    _close(jax.jit(jax.jacfwd(jax.jacfwd(custom)))(p), ref, 1e-9)


# The default adjoint of `simulate` (`_adjoint.ForwardJacobianAdjoint`): reverse mode
# by forward-mode tangents for a few inputs, by the fallback otherwise; the same
# derivatives as `diffrax.RecursiveCheckpointAdjoint`.

FINAL = cjax.SaveAt(t1=True, multipliers=False, energy=False, violation=False)


def _final_state(adjoint):
    """`(r, theta1)` at `t1 = 0.3` of the attached cylinders, as a function of
    `(I, theta0, ...)`; `extra` further inputs enter the gravity (so that more than
    `max_tangents` scalars are differentiated: they are also in `args`)."""

    def fn(p):
        args = {**cyl.default_args(), "I": p[0], "g": 9.81 + jnp.sum(p[2:] ** 2)}
        args["extra"] = p[2:]  # unused by the Lagrangian, differentiated all the same
        q0, qd0 = cyl.state(p[1], jnp.zeros_like(p[1]), args)
        traj = cjax.simulate(
            cyl.system(), (0.0, 0.3), q0, qd0, args, saveat=FINAL, adjoint=adjoint
        )
        return traj.q[-1, :2]

    return fn


def _inputs(extra: int = 0):
    return jnp.concatenate([jnp.array([0.045, 0.3]), jnp.full((extra,), 0.1)])


@pytest.mark.parametrize("extra", [0, 15], ids=["forward-mode", "fallback"])
def test_default_adjoint_matches_recursive_checkpoint(extra):
    """`jax.jacrev` and `jax.vmap(jax.grad)` with the default adjoint: 2 inputs (the
    forward-mode path) and 17 (above `max_tangents`: the fallback)."""
    import diffrax

    from constrained_jax._adjoint import ForwardJacobianAdjoint

    p = _inputs(extra)
    reference = jax.jit(jax.jacrev(_final_state(diffrax.RecursiveCheckpointAdjoint())))
    ref = reference(p)
    _close(jax.jit(jax.jacrev(_final_state(None)))(p), ref, 1e-12)
    if extra == 0:
        # Above `max_tangents` the default already is the fallback.
        forced = ForwardJacobianAdjoint(max_tangents=0)
        _close(jax.jit(jax.jacrev(_final_state(forced)))(p), ref, 1e-12)
    batch = jnp.stack([p, p.at[1].add(0.1)])
    theta1 = lambda p: _final_state(None)(p)[1]
    grads = jax.jit(jax.vmap(jax.grad(theta1)))(batch)
    # The reference Jacobian's theta1 row at each member (one compiled program).
    refs = jnp.stack([ref[1], reference(batch[1])[1]])
    _close(grads, refs, 1e-12)
