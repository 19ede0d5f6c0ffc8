"""Constrained extremization: closed forms, sign conventions, derivatives, batching."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import constrained_jax as cjax
from constrained_jax.scenes import cylinder_volume as cyl

from .helpers import finite_difference_grad, TraceCounter, tree_allclose


def _args(b, l):
    return {"b": jnp.asarray(b, jnp.float64), "l": jnp.asarray(l, jnp.float64)}


@pytest.fixture(scope="module")
def cylinder():
    """One jit-compiled solve shared by the tests (args are traced: no recompiles)."""

    @jax.jit
    def solve(args):
        x0 = cyl.initial_guess(args["b"], args["l"])
        return cjax.extremize(cyl.volume, x0, args, constraints=cyl.constraint)

    return solve


CASES = [(1.0, 1.0), (2.0, 3.0), (0.5, 10.0), (1e-3, 1e3), (1e3, 1e-3), (1e-6, 1e6)]


@pytest.mark.parametrize("b, l", CASES)
def test_cylinder_closed_form(cylinder, b, l):
    sol = cylinder(_args(b, l))
    ref = cyl.closed_form(b, l)
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, [ref["a"], ref["h"]], rtol=1e-12)
    np.testing.assert_allclose(sol.multipliers, [ref["multiplier"]], rtol=1e-12)
    np.testing.assert_allclose(sol.value, ref["volume"], rtol=1e-12)


@settings(max_examples=30, deadline=None)
@given(log_b=st.floats(-4, 4, allow_nan=False), log_l=st.floats(-4, 4, allow_nan=False))
def test_cylinder_closed_form_property(log_b, log_l):
    b, l = 10.0**log_b, 10.0**log_l
    sol = _CYLINDER_JIT(_args(b, l))
    ref = cyl.closed_form(b, l)
    np.testing.assert_allclose(sol.x, [ref["a"], ref["h"]], rtol=1e-11)
    np.testing.assert_allclose(sol.multipliers, [ref["multiplier"]], rtol=1e-11)


_CYLINDER_JIT = jax.jit(
    lambda args: cjax.extremize(
        cyl.volume,
        cyl.initial_guess(args["b"], args["l"]),
        args,
        constraints=cyl.constraint,
    )
)


def test_cylinder_multiplier_sign_convention(cylinder):
    """grad F + lambda grad G = 0, with hand-written gradients (DESIGN.md)."""
    b, l = 2.0, 3.0
    sol = cylinder(_args(b, l))
    a, h = np.asarray(sol.x)
    lam = float(sol.multipliers[0])
    grad_v = np.array([2 * np.pi * a * h, np.pi * a**2])
    grad_g = np.array([2 * np.pi, 2 * h / b])
    np.testing.assert_allclose(grad_v + lam * grad_g, 0.0, atol=1e-12)
    # The lecture's equation (1): lambda = -a h.
    np.testing.assert_allclose(lam, -a * h, rtol=1e-12)


def test_cylinder_is_a_maximum(cylinder):
    """On the constraint curve V(h) = pi ((l - h^2/b) / 2pi)^2 h vanishes at both ends
    of h in (0, sqrt(b l)) and is positive between: the single critical point is the
    maximum."""
    sol = cylinder(_args(1.0, 1.0))
    assert sol.kind == cjax.EXTREMUM.maximum
    # The reduced Hessian, by hand: second derivative of V along the curve at h*.
    b, l = 1.0, 1.0
    v = lambda h: np.pi * ((l - h**2 / b) / (2 * np.pi)) ** 2 * h
    h = float(sol.x[1])
    eps = 1e-4
    d2v_dh2 = (v(h + eps) - 2 * v(h) + v(h - eps)) / eps**2
    assert d2v_dh2 < 0


def test_envelope_theorem_and_finite_differences(cylinder):
    """dV*/dl = lambda dG/dl = -lambda; dV*/db = lambda dG/db = -lambda h^2/b^2."""
    b, l = 2.0, 3.0
    value = lambda args: cylinder(args).value
    grads = jax.grad(value)(_args(b, l))
    sol = cylinder(_args(b, l))
    lam, h = float(sol.multipliers[0]), float(sol.x[1])
    np.testing.assert_allclose(grads["l"], -lam, rtol=1e-10)
    np.testing.assert_allclose(grads["b"], -lam * h**2 / b**2, rtol=1e-10)
    # Against the closed form V* = 4 b^1/2 l^5/2 / (5^5/2 pi).
    ref = cyl.closed_form(b, l)["volume"]
    np.testing.assert_allclose(grads["l"], 2.5 * ref / l, rtol=1e-10)
    np.testing.assert_allclose(grads["b"], 0.5 * ref / b, rtol=1e-10)
    # Against central finite differences of the whole solve.
    fd = finite_difference_grad(lambda p: value(_args(p[0], p[1])), np.array([b, l]))
    np.testing.assert_allclose([grads["b"], grads["l"]], fd, rtol=1e-7)


def test_solution_derivatives(cylinder):
    """Implicit-function derivatives of x and lambda against the closed form."""
    b, l = 0.7, 2.0
    jac = jax.jacobian(lambda args: (cylinder(args).x, cylinder(args).multipliers))(
        _args(b, l)
    )
    (dx, dlam) = jac
    # a = 2l/(5 pi), h = sqrt(bl/5), lambda = -2 b^1/2 l^3/2 / (5^3/2 pi).
    np.testing.assert_allclose(dx["l"], [2 / (5 * np.pi), 0.5 * np.sqrt(b / (5 * l))])
    np.testing.assert_allclose(dx["b"], [0.0, 0.5 * np.sqrt(l / (5 * b))], atol=1e-14)
    lam = -2 * np.sqrt(b) * l**1.5 / (5**1.5 * np.pi)
    np.testing.assert_allclose(dlam["l"], [1.5 * lam / l], rtol=1e-10)
    np.testing.assert_allclose(dlam["b"], [0.5 * lam / b], rtol=1e-10)


def test_reverse_and_forward_mode_agree(cylinder):
    fn = lambda l: cylinder(_args(1.3, l)).value
    l = jnp.asarray(2.5)
    np.testing.assert_allclose(jax.grad(fn)(l), jax.jacfwd(fn)(l), rtol=1e-12)


def test_vmap_matches_loop(cylinder):
    bs = jnp.array([0.5, 1.0, 2.0, 1e-3])
    ls = jnp.array([1.0, 3.0, 0.2, 1e3])
    batched = jax.vmap(lambda b, l: cylinder({"b": b, "l": l}))(bs, ls)
    for i in range(len(bs)):
        single = cylinder({"b": bs[i], "l": ls[i]})
        assert tree_allclose(batched.x[i], single.x, rtol=1e-13)
        assert tree_allclose(batched.multipliers[i], single.multipliers, rtol=1e-13)
        assert (batched.kind == single.kind)[i]
        assert (batched.result == cjax.RESULTS.successful)[i]


def test_no_recompilation_when_args_change():
    volume = TraceCounter(cyl.volume)
    x0 = jnp.array([0.1, 0.4])
    cjax.extremize(volume, x0, _args(1.0, 1.0), constraints=cyl.constraint)
    traced = volume.count
    assert traced > 0
    for b, l in [(2.0, 3.0), (1e-3, 1e3), (5.0, 0.5)]:
        sol = cjax.extremize(
            volume, cyl.initial_guess(b, l), _args(b, l), constraints=cyl.constraint
        )
        np.testing.assert_allclose(
            sol.value, cyl.closed_form(b, l)["volume"], rtol=1e-12
        )
    assert volume.count == traced
    # Python floats in args are traced too.
    args = {"b": 1.5, "l": 2.0}
    cjax.extremize(volume, x0, args, constraints=cyl.constraint)
    traced = volume.count
    cjax.extremize(volume, x0, {"b": 2.5, "l": 4.0}, constraints=cyl.constraint)
    assert volume.count == traced


def test_pytree_unknowns():
    def volume(x, args):
        return jnp.pi * x["a"] ** 2 * x["h"]

    def constraint(x, args):
        return 2 * jnp.pi * x["a"] + x["h"] ** 2 / args["b"] - args["l"]

    b, l = 2.0, 3.0
    sol = cjax.extremize(
        volume, {"a": 0.2, "h": 1.0}, _args(b, l), constraints=constraint
    )
    ref = cyl.closed_form(b, l)
    np.testing.assert_allclose(sol.x["a"], ref["a"], rtol=1e-12)
    np.testing.assert_allclose(sol.x["h"], ref["h"], rtol=1e-12)
    assert sol.multipliers.shape == (1,)


def test_float32():
    """float32 works, at float32 tolerances (1e-5 relative)."""
    with jax.numpy_dtype_promotion("standard"):
        args = {"b": jnp.float32(2.0), "l": jnp.float32(3.0)}
        x0 = jnp.array([0.2, 1.0], jnp.float32)
        sol = cjax.extremize(
            cyl.volume,
            x0,
            args,
            constraints=cyl.constraint,
            solver=cjax.Newton(rtol=1e-6, atol=1e-6),
        )
    assert sol.x.dtype == jnp.float32
    ref = cyl.closed_form(2.0, 3.0)
    np.testing.assert_allclose(sol.x, [ref["a"], ref["h"]], rtol=1e-5)
    np.testing.assert_allclose(sol.multipliers, [ref["multiplier"]], rtol=1e-5)
    assert sol.kind == cjax.EXTREMUM.maximum


def test_all_stationary_points_and_far_starts():
    """V* has four stationary points: (a, h) = (2l/5pi, +-sqrt(bl/5)) with
    lambda = -a h (a maximum for h > 0, a minimum for h < 0), and (0, +-sqrt(bl))
    with lambda = 0 (V = pi a^2 h: a minimum for h > 0, a maximum for h < 0). From
    far starts that overshoot, the globalised Newton lands on one of them, correctly
    classified."""
    b, l = 1.0, 1.0
    a_star, h_star = 2 * l / (5 * np.pi), np.sqrt(b * l / 5)
    known = [
        ((a_star, h_star), -a_star * h_star, cjax.EXTREMUM.maximum),
        ((a_star, -h_star), a_star * h_star, cjax.EXTREMUM.minimum),
        ((0.0, np.sqrt(b * l)), 0.0, cjax.EXTREMUM.minimum),
        ((0.0, -np.sqrt(b * l)), 0.0, cjax.EXTREMUM.maximum),
    ]
    starts = [
        [0.1, 0.4],
        [0.1, -0.4],
        [0.01, 1.1],
        [0.01, -1.1],
        [5.0, 3.0],
        [1e-3, 1e-3],
        [0.01, 2.0],
        [-3.0, 0.5],
        [40.0, -7.0],
    ]
    found = set()
    for x0 in starts:
        sol = cjax.extremize(
            cyl.volume, jnp.array(x0), _args(b, l), constraints=cyl.constraint
        )
        matches = [
            i
            for i, (x, lam, kind) in enumerate(known)
            if np.allclose(sol.x, x, rtol=1e-12, atol=1e-12)
            and np.allclose(sol.multipliers, [lam], rtol=1e-12, atol=1e-12)
            and bool(sol.kind == kind)
        ]
        assert len(matches) == 1, (x0, sol.x, sol.multipliers)
        found.add(matches[0])
    assert found == {0, 1, 2, 3}


# --------------------------------------------------------------------------------
# Classification
# --------------------------------------------------------------------------------


def _sum_constraint(x, args):
    return jnp.sum(x) - 1.0


@pytest.mark.parametrize(
    "objective, constraints, x0, kind, x_ref",
    [
        # min |x|^2 on x + y = 1: x = y = 1/2.
        (
            lambda x, a: jnp.sum(x**2),
            _sum_constraint,
            [0.9, 0.3],
            "minimum",
            [0.5, 0.5],
        ),
        # max -|x|^2 on the same line.
        (
            lambda x, a: -jnp.sum(x**2),
            _sum_constraint,
            [0.9, 0.3],
            "maximum",
            [0.5, 0.5],
        ),
        # x^2 - y^2 + z^2 on z = 0 (and k = 1, n = 3): the tangent plane (x, y) is a
        # saddle even though z is fixed.
        (
            lambda x, a: x[0] ** 2 - x[1] ** 2 + x[2] ** 2,
            lambda x, a: x[2],
            [0.3, 0.2, 0.1],
            "saddle",
            [0.0, 0.0, 0.0],
        ),
        # Unconstrained: a minimum, a saddle.
        (lambda x, a: jnp.sum((x - 1.0) ** 2), None, [3.0, -2.0], "minimum", [1, 1]),
        (lambda x, a: x[0] ** 2 - x[1] ** 2, None, [0.3, -0.2], "saddle", [0, 0]),
        # Quartic: a minimum, but the Hessian vanishes there.
        (lambda x, a: jnp.sum(x**4), None, [0.5], "degenerate", [0.0]),
        # Two independent constraints on two unknowns: a single feasible point.
        (
            lambda x, a: x[0] + x[1],
            lambda x, a: jnp.stack([x[0] - 1.0, x[1] - 2.0]),
            [0.0, 0.0],
            "isolated",
            [1.0, 2.0],
        ),
        # max x + y on the unit circle: (1/sqrt2, 1/sqrt2) (a maximum), min at minus.
        (
            lambda x, a: x[0] + x[1],
            lambda x, a: x[0] ** 2 + x[1] ** 2 - 1.0,
            [0.6, 0.9],
            "maximum",
            [2**-0.5, 2**-0.5],
        ),
        (
            lambda x, a: x[0] + x[1],
            lambda x, a: x[0] ** 2 + x[1] ** 2 - 1.0,
            [-0.6, -0.9],
            "minimum",
            [-(2**-0.5), -(2**-0.5)],
        ),
    ],
)
def test_classification(objective, constraints, x0, kind, x_ref):
    sol = cjax.extremize(objective, jnp.asarray(x0, float), constraints=constraints)
    np.testing.assert_allclose(
        sol.x, x_ref, atol=1e-6 if kind == "degenerate" else 1e-12
    )
    assert sol.kind == getattr(cjax.EXTREMUM, kind), cjax.EXTREMUM[sol.kind]


def test_classification_in_higher_dimension():
    """Quadratic form with known inertia on the tangent space of a linear constraint.

    F = x^T D x / 2 with D = diag(d) on sum(x) = 1. On ker J, the reduced Hessian's
    eigenvalues interlace those of D, so all-positive d gives a minimum and mixed
    signs with two negative entries a saddle.
    """
    d_min = jnp.array([1.0, 2.0, 3.0, 4.0, 5.0])
    d_saddle = jnp.array([-1.0, -2.0, 3.0, 4.0, 5.0])
    for d, kind in [(d_min, cjax.EXTREMUM.minimum), (d_saddle, cjax.EXTREMUM.saddle)]:
        sol = cjax.extremize(
            lambda x, d: 0.5 * jnp.sum(d * x**2),
            jnp.full(5, 0.2),
            d,
            constraints=_sum_constraint,
        )
        # x_i = -lambda / d_i, sum = 1.
        lam = -1 / jnp.sum(1 / d)
        np.testing.assert_allclose(sol.x, -lam / d, rtol=1e-12)
        np.testing.assert_allclose(sol.multipliers, [lam], rtol=1e-12)
        assert sol.kind == kind


def test_closure_over_arrays_is_differentiable():
    """F may close over arrays; derivatives flow through them too."""
    target = jnp.array([1.0, 2.0, 3.0])

    def solve(t):
        F = lambda x, args: jnp.sum((x - t) ** 2)
        return cjax.extremize(F, jnp.zeros(3), constraints=_sum_constraint).x

    # Projection of t onto sum(x) = 1: x = t - (sum(t) - 1)/3.
    np.testing.assert_allclose(solve(target), target - (6.0 - 1.0) / 3, rtol=1e-12)
    jac = jax.jacobian(solve)(target)
    np.testing.assert_allclose(jac, jnp.eye(3) - 1 / 3, atol=1e-12)


@pytest.mark.parametrize("k", [0, 3, 9])
def test_reduced_hessian_extremes_formed_and_lanczos(k):
    """The extreme eigenvalues of `Z^T H Z` (`Z` an orthonormal basis of `ker J`):
    the formed matrix (small `n`) and the exact Lanczos run (`n - k` steps) both
    against NumPy's eigenvalues; with `k = n - 3` and a projector onto a subspace
    of dimension 3, the directions outside it must not show up."""
    from constrained_jax._kkt import reduced_hessian_extremes

    n = 12
    rng = np.random.default_rng(k)
    a = rng.normal(size=(n, n))
    hess = a + a.T
    jac = rng.normal(size=(k, n))
    z = np.linalg.svd(jac)[2][k:].T if k else np.eye(n)  # orthonormal basis of ker J
    expected = np.linalg.eigvalsh(z.T @ hess @ z)[[0, -1]]
    proj = jnp.asarray(z @ z.T)
    hvp = lambda v: jnp.asarray(hess) @ v
    project = lambda v: proj @ v
    formed = reduced_hessian_extremes(hvp, project, n, k, jnp.float64)
    np.testing.assert_allclose(formed, expected, rtol=1e-10, atol=1e-10)
    if k:  # `n > num_steps = n - k`: Lanczos, exact after `n - k` steps
        lanczos = reduced_hessian_extremes(
            hvp, project, n, k, jnp.float64, num_steps=n - k
        )
        np.testing.assert_allclose(lanczos, expected, rtol=1e-8, atol=1e-8)
    # A projector onto {0}: no tangent space.
    nothing = reduced_hessian_extremes(hvp, lambda v: 0 * v, n, k, jnp.float64)
    assert bool(jnp.all(jnp.isnan(nothing)))
