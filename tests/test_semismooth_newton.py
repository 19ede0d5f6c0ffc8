"""`SemismoothNewton`, the public solver of `extremize` with inequalities, configured
by a user: its tolerances honoured, its linear solver used in the backward pass,
`Newton` handing over to it, and jit / vmap / grad through it, against the closed
form of a projection onto a disk and against finite differences."""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import cylinder_volume as cyl

from .helpers import finite_difference_grad


# Minimize |x - c|^2 subject to |x|^2 <= r: for r < |c|^2 the projection of c onto
# the disk, x = sqrt(r) c / |c|, with mu = |c| / sqrt(r) - 1 (from 2 (x - c) + 2 mu x
# = 0) and value (|c| - sqrt(r))^2, whose derivative in r is -mu (envelope theorem).
# For r > |c|^2 the constraint is inactive: x = c, mu = 0.
C = jnp.array([2.0, 1.0])


def _distance(x, args):
    return jnp.sum((x - args["c"]) ** 2)


def _disk(x, args):
    return x @ x - args["r"]


def _closed_form(c, r):
    c = np.asarray(c, float)
    norm = np.linalg.norm(c)
    if r >= norm**2:
        return c, 0.0, 0.0
    x = np.sqrt(r) * c / norm
    return x, norm / np.sqrt(r) - 1, (norm - np.sqrt(r)) ** 2


@eqx.filter_jit
def _project(c, r, solver):
    return cjax.extremize(
        _distance,
        jnp.zeros(2),
        {"c": c, "r": r},
        inequalities=_disk,
        sense="minimize",
        solver=solver,
        throw=False,
    )


@pytest.mark.parametrize("tol", [1e-12, 1e-6, 1e-2])
def test_tolerances_are_honoured(tol):
    """The iteration stops when the full step is within `atol + rtol |z|` (root mean
    square below 1) and takes it, so the error is within that bound; the KKT
    conditions are checked to `sqrt(max(rtol, atol, 100 eps))`."""
    solver = cjax.SemismoothNewton(rtol=tol, atol=tol)
    sol = _project(C, 1.0, solver)
    assert sol.result == cjax.RESULTS.successful
    x_ref, mu_ref, _ = _closed_form(C, 1.0)
    z = np.concatenate([np.asarray(sol.x), np.asarray(sol.inequality_multipliers)])
    z_ref = np.concatenate([x_ref, [mu_ref]])
    bound = np.sqrt(z.size) * (tol + tol * np.abs(z_ref))
    assert np.all(np.abs(z - z_ref) <= bound)
    expected = np.sqrt(max(tol, 100 * np.finfo(np.float64).eps))
    np.testing.assert_allclose(sol.stats["kkt_tolerance"], expected, rtol=1e-15)


def test_a_looser_tolerance_stops_sooner():
    steps = [
        int(_project(C, 1.0, cjax.SemismoothNewton(rtol=t, atol=t)).stats["num_steps"])
        for t in (1e-1, 1e-12)
    ]
    assert steps[0] < steps[1]


def test_newton_hands_over_to_the_semismooth_newton_of_its_fields():
    minres = cjax.MINRES(rtol=1e-12, atol=0.0)
    newton = cjax.Newton(rtol=1e-8, atol=1e-9, linear_solver=minres, max_backtracks=7)
    twin = cjax.SemismoothNewton(
        rtol=1e-8, atol=1e-9, linear_solver=minres, max_backtracks=7
    )
    assert eqx.tree_equal(newton.complementarity_solver(), twin)
    assert twin.complementarity_solver() is twin
    a, b = _project(C, 1.0, newton), _project(C, 1.0, twin)
    assert eqx.tree_equal(a, b)


@pytest.mark.parametrize(
    "linear_solver",
    [cjax.DenseLU(), cjax.MINRES(rtol=1e-12, atol=0.0), lx.LU()],
    ids=["DenseLU", "MINRES", "lineax LU"],
)
def test_the_linear_solver_serves_the_backward_pass(linear_solver):
    """Derivatives by the implicit function theorem with the configured solver: the
    envelope theorem for the value, the derivative of the projection for x."""
    solver = cjax.SemismoothNewton(linear_solver=linear_solver)
    r = 1.0
    _, mu_ref, _ = _closed_form(C, r)
    grad_r = jax.grad(lambda r_: _project(C, r_, solver).value)(r)
    np.testing.assert_allclose(grad_r, -mu_ref, rtol=1e-9)
    jac_c = jax.jacfwd(lambda c: _project(c, r, solver).x)(C)
    c = np.asarray(C)
    norm = np.linalg.norm(c)
    jac_ref = np.sqrt(r) * (np.eye(2) / norm - np.outer(c, c) / norm**3)
    np.testing.assert_allclose(jac_c, jac_ref, rtol=1e-9, atol=1e-12)


def test_a_failing_linear_solver_gives_nan_derivatives_not_a_wrong_one():
    """The backward pass uses the configured solver, not the steps' LU: MINRES
    allowed one iteration cannot solve the tangent system, so the derivative is NaN
    while the solve itself (dense LU steps) succeeds."""
    solver = cjax.SemismoothNewton(
        linear_solver=cjax.MINRES(rtol=1e-12, atol=0.0, max_steps=1)
    )
    sol = _project(C, 1.0, solver)
    assert sol.result == cjax.RESULTS.successful
    x_ref, _, _ = _closed_form(C, 1.0)
    np.testing.assert_allclose(sol.x, x_ref, rtol=1e-12)
    grad_r = jax.grad(lambda r_: _project(C, r_, solver).value)(1.0)
    assert np.isnan(grad_r)


def test_jit_vmap_grad_against_closed_form_and_finite_differences():
    solver = cjax.SemismoothNewton(rtol=1e-11, atol=1e-12)
    rs = jnp.array([0.5, 2.0, 9.0])  # the last one leaves the constraint inactive
    sols = jax.vmap(lambda r: _project(C, r, solver))(rs)
    assert np.all(sols.result == cjax.RESULTS.successful)
    for i, r in enumerate(np.asarray(rs)):
        x_ref, mu_ref, value_ref = _closed_form(C, r)
        np.testing.assert_allclose(sols.x[i], x_ref, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(
            sols.inequality_multipliers[i, 0], mu_ref, rtol=1e-10, atol=1e-12
        )
        np.testing.assert_allclose(sols.value[i], value_ref, rtol=1e-11, atol=1e-12)
    np.testing.assert_array_equal(sols.active[:, 0], [True, True, False])

    def value(r):
        return _project(C, r[0], solver).value

    grads = jax.vmap(jax.grad(value))(rs[:, None])[:, 0]
    for i, r in enumerate(np.asarray(rs)):
        _, mu_ref, _ = _closed_form(C, r)
        np.testing.assert_allclose(grads[i], -mu_ref, rtol=1e-9, atol=1e-12)
        fd = finite_difference_grad(value, np.array([r]))
        np.testing.assert_allclose(grads[i], fd[0], rtol=1e-6, atol=1e-9)


def test_without_inequalities_it_solves_the_equality_kkt_system():
    """A dense semismooth Newton on the smooth KKT residual: the cylinder's closed
    form."""
    sol = cyl.solve(1.0, 1.0, solver=cjax.SemismoothNewton(), throw=False)
    ref = cyl.closed_form(1.0, 1.0)
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, [ref["a"], ref["h"]], rtol=1e-12)
    np.testing.assert_allclose(sol.multipliers[0], ref["multiplier"], rtol=1e-12)


class _PlainSolver(cjax.AbstractKKTSolver):
    """A solver with no `complementarity_solver` of its own."""

    linear_solver: lx.AbstractLinearSolver = cjax.DenseLU()

    def init(self, residual, z, args):
        return None

    def step(self, residual, z, args, state):
        return z, state

    def terminate(self, residual, z, args, state):
        return jnp.array(True), cjax.RESULTS.successful

    def postprocess(self, residual, z, args, state):
        return z, {}


def test_argument_checks():
    with pytest.raises(ValueError, match="non-negative"):
        cjax.SemismoothNewton(atol=-1.0)
    with pytest.raises(ValueError, match="positive"):
        cjax.SemismoothNewton(rtol=0.0, atol=0.0)
    with pytest.raises(ValueError, match="SemismoothNewton"):
        _project(C, 1.0, _PlainSolver())
    with pytest.raises(ValueError, match="SemismoothNewton"):
        _project(C, 1.0, cjax.MINRES(rtol=1e-10, atol=0.0))
