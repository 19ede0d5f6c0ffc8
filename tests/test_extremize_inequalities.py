"""Inequality constraints and bounds in `extremize`: closed forms, scipy as an
independent reference, the sign convention of `mu`, the envelope theorem, implicit
derivatives, batches with different active sets, and careless inputs."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
from jax.scipy.special import xlogy

import constrained_jax as cjax
from constrained_jax.scenes import cylinder_volume as cyl

from .helpers import run_python


INF = jnp.inf


# ---------------------------------------------------------------------------------
# 1. A weighted box QP and a half-space projection: closed forms
# ---------------------------------------------------------------------------------


def _box_qp(x, args):
    """`sum_i w_i (x_i - t_i)^2`: the box-constrained minimum is `clip(t, lo, up)`."""
    return jnp.sum(args["w"] * (x - args["t"]) ** 2)


W = jnp.array([1.0, 2.0, 0.5, 3.0, 1.5])
T = jnp.array([2.0, -3.0, 0.3, 0.9, -0.2])
LO = jnp.array([-1.0, -1.0, -INF, 0.0, 0.0])
UP = jnp.array([1.0, 1.0, 0.5, INF, 2.0])


@jax.jit
def _solve_box(t, lo, up, x0):
    return cjax.extremize(
        _box_qp,
        x0,
        {"w": W, "t": t},
        lower=lo,
        upper=up,
        sense="minimize",
        throw=False,
    )


@jax.jit
def _solve_box_max(t, lo, up, x0):
    return cjax.extremize(
        lambda x, a: -_box_qp(x, a),
        x0,
        {"w": W, "t": t},
        lower=lo,
        upper=up,
        sense="maximize",
        throw=False,
    )


def _box_closed_form(t, lo, up):
    x = np.clip(t, lo, up)
    # Rows: lower (H = lo - x), upper (H = x - up). grad F + mu . grad H = 0.
    mu_lo = np.where(t < lo, 2 * W * (lo - t), 0.0)
    mu_up = np.where(t > up, 2 * W * (t - up), 0.0)
    return x, np.concatenate([mu_lo, mu_up])


def test_box_qp_closed_form():
    sol = _solve_box(T, LO, UP, jnp.zeros(5))
    x_ref, mu_ref = _box_closed_form(np.asarray(T), np.asarray(LO), np.asarray(UP))
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, x_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.inequality_multipliers, mu_ref, atol=1e-10)
    assert sol.inequality_multipliers.shape == (10,)
    # x0 = 1.0 upper, x1 = -1.0 lower, x4 = 0.0 lower; the infinite bounds never.
    active = np.zeros(10, bool)
    active[[1, 4, 5]] = True
    np.testing.assert_array_equal(sol.active, active)
    assert np.all(sol.inequality_multipliers >= 0)
    assert sol.multipliers.shape == (0,)
    np.testing.assert_allclose(sol.value, np.sum(W * (x_ref - T) ** 2), rtol=1e-12)
    # Every coordinate is fixed or free with curvature 2 w > 0.
    assert sol.kind == cjax.EXTREMUM.minimum


def test_box_qp_maximize_flips_the_sign_of_mu():
    """The same stationarity formula in both senses: maximizing -F gives the same x
    and multipliers of the opposite sign (mu <= 0)."""
    sol = _solve_box_max(T, LO, UP, jnp.zeros(5))
    x_ref, mu_ref = _box_closed_form(np.asarray(T), np.asarray(LO), np.asarray(UP))
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, x_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.inequality_multipliers, -mu_ref, atol=1e-10)
    assert sol.kind == cjax.EXTREMUM.maximum


def test_box_qp_from_far_infeasible_start():
    sol = _solve_box(T, LO, UP, jnp.array([1e3, -5e2, 7e2, -1e3, 3e2]))
    x_ref, mu_ref = _box_closed_form(np.asarray(T), np.asarray(LO), np.asarray(UP))
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, x_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.inequality_multipliers, mu_ref, atol=1e-10)


def _halfspace(x, args):
    return jnp.dot(args["a"], x) - args["b"]


@jax.jit
def _project(t, a, b):
    """Nearest point to `t` with `sum x = 0` and `a . x <= b`."""
    return cjax.extremize(
        lambda x, args: jnp.sum((x - args["t"]) ** 2),
        jnp.zeros(4),
        {"t": t, "a": a, "b": b},
        constraints=lambda x, args: jnp.sum(x),
        inequalities=_halfspace,
        sense="minimize",
        throw=False,
    )


@pytest.mark.parametrize("b", [0.5, 5.0])
def test_halfspace_projection_with_an_equality(b):
    t = np.array([1.0, 2.0, -0.5, 0.3])
    a = np.array([1.0, 1.0, 0.0, -2.0])
    sol = _project(jnp.asarray(t), jnp.asarray(a), jnp.asarray(b))
    # Closed form: project onto sum x = 0, then (if a . x > b) along the part of a
    # in that plane. grad F = 2 (x - t), so lambda = 2 mean(t) - mu mean(a).
    e = np.ones(4) / 2.0
    p = t - np.dot(e, t) * e
    a_p = a - np.dot(e, a) * e
    excess = max(np.dot(a, p) - b, 0.0)
    x_ref = p - excess / np.dot(a_p, a_p) * a_p
    mu_ref = 2 * excess / np.dot(a_p, a_p)
    lam_ref = 2 * np.mean(t) - mu_ref * np.mean(a)
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, x_ref, atol=1e-12)
    np.testing.assert_allclose(sol.inequality_multipliers, [mu_ref], atol=1e-10)
    np.testing.assert_allclose(sol.multipliers, [lam_ref], atol=1e-10)
    assert bool(sol.active[0]) == (excess > 0)
    assert sol.kind == cjax.EXTREMUM.minimum


# ---------------------------------------------------------------------------------
# 2. Maximum entropy
# ---------------------------------------------------------------------------------


def _simplex(p, args):
    return jnp.sum(p) - 1.0


def _entropy(p, args):
    return -jnp.sum(xlogy(p, p)) + jnp.dot(args, p)


def _gini(p, args):
    """The quadratic (Gini) entropy `1 - sum p^2` plus `c . p`: its slope at `p = 0`
    is finite, so a strong linear term drives some `p_i` to zero."""
    return 1.0 - jnp.sum(p**2) + jnp.dot(args, p)


@jax.jit(static_argnums=0)
def _maxent(fn_index, c):
    fn = (_entropy, _gini)[fn_index]
    return cjax.extremize(
        fn,
        jnp.full(c.shape, 1.0 / c.shape[0]),
        c,
        constraints=_simplex,
        lower=0.0,
        sense="maximize",
        throw=False,
    )


def test_shannon_entropy_closed_form():
    """`-sum p log p` has an infinite slope at `p_i = 0`, so the bound `p >= 0` is
    never active, however strong the linear term: the maximum is `softmax(c)`, with
    `lambda = 1 - logsumexp(c)` and `mu = 0`, even where `p_i` is 1e-8."""
    c = jnp.array([2.0, -16.0, 0.0, 1.0, -3.0])
    sol = _maxent(0, c)
    assert sol.result == cjax.RESULTS.successful
    p_ref = jax.nn.softmax(c)
    np.testing.assert_allclose(sol.x, p_ref, rtol=1e-10)
    np.testing.assert_allclose(
        sol.multipliers, [1 - jax.scipy.special.logsumexp(c)], rtol=1e-10
    )
    np.testing.assert_allclose(sol.inequality_multipliers, 0.0, atol=1e-10)
    assert sol.kind == cjax.EXTREMUM.maximum


def _gini_scipy(c):
    res = scipy.optimize.minimize(
        lambda p: -(1.0 - np.sum(p**2) + np.dot(c, p)),
        np.full(c.shape, 1.0 / c.shape[0]),
        jac=lambda p: 2 * p - c,
        method="SLSQP",
        bounds=[(0.0, None)] * c.shape[0],
        constraints=[{"type": "eq", "fun": lambda p: np.sum(p) - 1.0}],
        options={"ftol": 1e-15, "maxiter": 500},
    )
    assert res.success
    return res.x


def test_gini_entropy_with_zeros_against_scipy_and_closed_form():
    c = np.array([1.5, -2.0, 0.8, 0.0, -0.7, 1.1])
    sol = _maxent(1, jnp.asarray(c))
    assert sol.result == cjax.RESULTS.successful
    # Closed form: p = max((c + lambda) / 2, 0) with sum p = 1, lambda by bisection.
    lam = scipy.optimize.brentq(
        lambda lam: np.sum(np.maximum((c + lam) / 2, 0.0)) - 1.0, -10, 10, xtol=1e-15
    )
    p_ref = np.maximum((c + lam) / 2, 0.0)
    assert np.sum(p_ref == 0) >= 2  # the bound is active for some p_i
    np.testing.assert_allclose(sol.x, p_ref, atol=1e-12)
    np.testing.assert_allclose(sol.x, _gini_scipy(c), atol=1e-7)
    np.testing.assert_allclose(sol.multipliers, [lam], rtol=1e-10)
    # Stationarity -2 p + c + lambda + mu . grad(-p) = 0, so mu = c + lambda where
    # p = 0, and mu <= 0 (maximize).
    mu_ref = np.where(p_ref == 0, c + lam, 0.0)
    np.testing.assert_allclose(sol.inequality_multipliers, mu_ref, atol=1e-10)
    assert np.all(sol.inequality_multipliers <= 0)
    np.testing.assert_array_equal(sol.active, p_ref == 0)
    assert sol.kind == cjax.EXTREMUM.maximum


# ---------------------------------------------------------------------------------
# 3.-5. The lecture's cylinder with a cap on the height
# ---------------------------------------------------------------------------------


@jax.jit
def _capped_cylinder(b, l, h_max):
    args = {"b": b, "l": l}
    return cjax.extremize(
        cyl.volume,
        cyl.initial_guess(b, l),
        args,
        constraints=cyl.constraint,
        upper=jnp.stack([jnp.asarray(INF), h_max]),
        sense="maximize",
        throw=False,
    )


def _capped_closed_form(b, l, h_max):
    """By hand: the cap is active when `h_max < sqrt(b l / 5)`; then `h = h_max`,
    `a = (l - h^2 / b) / (2 pi)` from G, and stationarity
    `(2 pi a h, pi a^2) + lambda (2 pi, 2 h / b) + mu (0, 1) = 0` gives
    `lambda = -a h`, `mu = a (2 h^2 / b - pi a)`. Otherwise the lecture's answer."""
    h_star = np.sqrt(b * l / 5)
    if h_max >= h_star:
        h, a = h_star, 2 * l / (5 * np.pi)
        mu = 0.0
    else:
        h = h_max
        a = (l - h**2 / b) / (2 * np.pi)
        mu = a * (2 * h**2 / b - np.pi * a)
    return {"a": a, "h": h, "lambda": -a * h, "mu": mu, "V": np.pi * a**2 * h}


B, L = 2.0, 3.0  # h* = sqrt(6 / 5) = 1.095


@pytest.mark.parametrize("h_max", [0.6, 1.0, 1.5])
def test_capped_cylinder_closed_form(h_max):
    sol = _capped_cylinder(jnp.asarray(B), jnp.asarray(L), jnp.asarray(h_max))
    ref = _capped_closed_form(B, L, h_max)
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, [ref["a"], ref["h"]], rtol=1e-12)
    np.testing.assert_allclose(sol.multipliers, [ref["lambda"]], rtol=1e-12)
    np.testing.assert_allclose(
        sol.inequality_multipliers, [0.0, ref["mu"]], rtol=1e-10, atol=1e-12
    )
    np.testing.assert_allclose(sol.value, ref["V"], rtol=1e-12)
    np.testing.assert_array_equal(sol.active, [False, h_max < np.sqrt(B * L / 5)])
    assert sol.inequality_multipliers[1] <= 0  # maximize
    # Active cap: G and the cap fix both unknowns (no tangent space to test).
    capped = h_max < np.sqrt(B * L / 5)
    assert sol.kind == (cjax.EXTREMUM.isolated if capped else cjax.EXTREMUM.maximum)


def test_scene_capped_closed_form_is_the_hand_derivation():
    """`scenes.cylinder_volume.capped_closed_form` (the tour's reference) against the
    derivation above, and `solve_capped` against both."""
    for h_max in (0.6, 1.0, 1.5):
        ref = _capped_closed_form(B, L, h_max)
        scene = cyl.capped_closed_form(B, L, h_max)
        for key, name in [("a", "a"), ("h", "h"), ("lambda", "multiplier"),
                          ("mu", "cap_multiplier"), ("V", "volume")]:  # fmt: skip
            np.testing.assert_allclose(scene[name], ref[key], rtol=1e-14, atol=1e-15)
        assert bool(scene["active"]) == (h_max < np.sqrt(B * L / 5))
    ref = _capped_closed_form(B, L, 0.6)
    sol = cyl.solve_capped(B, L, 0.6)
    np.testing.assert_allclose(sol.x, [ref["a"], ref["h"]], rtol=1e-12)
    np.testing.assert_allclose(sol.inequality_multipliers[1], ref["mu"], rtol=1e-10)


def _value_and_x(l, h_max):
    sol = _capped_cylinder(jnp.asarray(B), l, h_max)
    return sol.value, sol.x


# Forward mode with respect to (l, h_max): one compilation for every point.
_VALUE_AND_X_JAC = jax.jit(jax.jacfwd(_value_and_x, argnums=(0, 1)))


def test_envelope_theorem_and_implicit_derivatives():
    """`dV*/dh_max = -mu` for `H = h - h_max` (in both senses), by forward-mode
    autodiff, by finite differences, and in closed form; `da/dh_max = -h_max /
    (pi b)` through the active cap (the implicit function theorem on the reduced
    system). Reverse mode: `test_envelope_theorem_bounds_of_the_qp`."""
    b, l, h_max = jnp.asarray(B), jnp.asarray(L), jnp.asarray(0.7)
    value = lambda hm: _capped_cylinder(b, l, hm).value
    (dv_dl, dv_dh), (dx_dl, dx_dh) = _VALUE_AND_X_JAC(l, h_max)
    mu = _capped_cylinder(b, l, h_max).inequality_multipliers[1]
    np.testing.assert_allclose(dv_dh, -mu, rtol=1e-10)
    step = 1e-6
    fd = (value(h_max + step) - value(h_max - step)) / (2 * step)
    np.testing.assert_allclose(dv_dh, fd, rtol=1e-7)
    hm = 0.7
    a = (L - hm**2 / B) / (2 * np.pi)
    closed = np.pi * a * (a - 2 * hm**2 / (np.pi * B))  # d(pi a^2 h)/dh along G
    np.testing.assert_allclose(dv_dh, closed, rtol=1e-10)
    np.testing.assert_allclose(dx_dh, [-0.7 / (np.pi * B), 1.0], rtol=1e-10)
    # Capped, h = h_max whatever l: da/dl = 1 / (2 pi), and dV/dl = -lambda = a h.
    np.testing.assert_allclose(dx_dl, [1 / (2 * np.pi), 0.0], atol=1e-12)
    np.testing.assert_allclose(dv_dl, a * hm, rtol=1e-10)
    # With the cap inactive, nothing depends on it, and d/dl is the lecture's.
    (dv_dl, dv_dh), (dx_dl, dx_dh) = _VALUE_AND_X_JAC(l, jnp.asarray(1.5))
    np.testing.assert_allclose(dx_dh, [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(dv_dh, 0.0, atol=1e-12)
    np.testing.assert_allclose(
        dx_dl, [2 / (5 * np.pi), 0.5 * np.sqrt(B / (5 * L))], rtol=1e-10
    )


def test_envelope_theorem_bounds_of_the_qp():
    """For a lower bound, `H = lo - x`, so `dF*/dlo = +mu`; for an upper bound
    `dF*/dup = -mu` (reverse mode)."""
    value = lambda lo, up: _solve_box(T, lo, up, jnp.zeros(5)).value
    grad_lo, grad_up = jax.grad(value, argnums=(0, 1))(LO, UP)
    sol = _solve_box(T, LO, UP, jnp.zeros(5))
    np.testing.assert_allclose(grad_lo, sol.inequality_multipliers[:5], atol=1e-10)
    np.testing.assert_allclose(grad_up, -sol.inequality_multipliers[5:], atol=1e-10)
    assert np.all(np.isfinite(grad_lo)) and np.all(np.isfinite(grad_up))
    # A failed solve (crossed bounds: infeasible) has NaN derivatives, never zeros
    # (an infinite bound, a placeholder row, has none).
    crossed = UP.at[1].set(-2.0)
    grad_lo, grad_up = jax.grad(value, argnums=(0, 1))(LO, crossed)
    finite_lo, finite_up = np.isfinite(LO), np.isfinite(crossed)
    assert np.all(np.isnan(grad_lo[finite_lo])) and np.all(np.isnan(grad_up[finite_up]))


def test_weakly_active_bound_is_treated_as_inactive():
    """`t_0 = up_0`: the bound holds with `mu = 0` (degenerate). It is reported
    active, and differentiated as if it were absent (the documented one-sided
    derivative, `dx_0/dup_0 = 0`; the other side would give 1), while the strictly
    active lower bounds of `x_1`, `x_4` move their coordinates one for one."""
    t = T.at[0].set(UP[0])
    sol = _solve_box(t, LO, UP, jnp.zeros(5))
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(sol.x, np.clip(t, LO, UP), atol=1e-12)
    assert bool(sol.active[5]) and sol.inequality_multipliers[5] == 0
    assert sol.kind == cjax.EXTREMUM.minimum
    dx_dlo, dx_dup = jax.jacfwd(
        lambda lo, up: _solve_box(t, lo, up, jnp.zeros(5)).x, argnums=(0, 1)
    )(LO, UP)
    np.testing.assert_allclose(dx_dlo, np.diag([0.0, 1.0, 0.0, 0.0, 1.0]), atol=1e-12)
    np.testing.assert_allclose(dx_dup, np.zeros((5, 5)), atol=1e-12)


def test_vmap_active_set_differs():
    h_maxes = jnp.array([0.4, 0.9, 1.2, 3.0])
    sols = jax.vmap(lambda hm: _capped_cylinder(jnp.asarray(B), jnp.asarray(L), hm))(
        h_maxes
    )
    assert np.all(sols.result == cjax.RESULTS.successful)
    for i, h_max in enumerate(np.asarray(h_maxes)):
        ref = _capped_closed_form(B, L, h_max)
        np.testing.assert_allclose(sols.x[i], [ref["a"], ref["h"]], rtol=1e-12)
        np.testing.assert_allclose(
            sols.inequality_multipliers[i, 1], ref["mu"], rtol=1e-10, atol=1e-12
        )
        assert bool(sols.active[i, 1]) == (h_max < np.sqrt(B * L / 5))
    # The box QP, with targets that cross the bounds differently per member.
    ts = jnp.stack([T, -T, 0.1 * T])
    sols = jax.vmap(lambda t: _solve_box(t, LO, UP, jnp.zeros(5)))(ts)
    for i in range(3):
        x_ref, mu_ref = _box_closed_form(
            np.asarray(ts[i]), np.asarray(LO), np.asarray(UP)
        )
        np.testing.assert_allclose(sols.x[i], x_ref, atol=1e-12)
        np.testing.assert_allclose(sols.inequality_multipliers[i], mu_ref, atol=1e-10)


# ---------------------------------------------------------------------------------
# 6. Careless inputs
# ---------------------------------------------------------------------------------


def _square(x, args):
    return jnp.sum(x**2)


def _contradictory(x, args):
    return jnp.concatenate([x + 1.0, 1.0 - x])  # x <= -1 and x >= 1


def test_infeasible_inequalities():
    sol = cjax.extremize(
        _square,
        jnp.zeros(1),
        inequalities=_contradictory,
        sense="minimize",
        throw=False,
    )
    assert sol.result == cjax.RESULTS.infeasible_inequalities
    assert sol.kind == cjax.EXTREMUM.unknown
    with pytest.raises(eqx.EquinoxRuntimeError, match="H_i"):
        cjax.extremize(
            _square, jnp.zeros(1), inequalities=_contradictory, sense="minimize"
        )


def test_crossed_traced_bounds_are_infeasible():
    lo = jnp.array([1.0, 1.0, 0.5, 1.0, 2.0])
    up = jnp.array([-1.0, 2.0, 2.0, 2.0, 3.0])
    sol = _solve_box(T, lo, up, jnp.zeros(5))  # lower > upper, traced under jit
    assert sol.result == cjax.RESULTS.infeasible_inequalities


@pytest.mark.parametrize("where", ["x0", "lower", "upper", "lower_inf"])
def test_nonfinite_inputs(where):
    x0, lo, up = jnp.zeros(5), LO, UP
    if where == "x0":
        x0 = x0.at[2].set(jnp.nan)
    elif where == "lower":
        lo = lo.at[0].set(jnp.nan)
    elif where == "upper":
        up = up.at[1].set(jnp.nan)
    else:
        lo = lo.at[0].set(INF)  # x >= inf: no x satisfies it
        up = up.at[0].set(INF)
    sol = _solve_box(T, lo, up, x0)
    assert sol.result == cjax.RESULTS.invalid_input


def _solve_simple(**kwargs):
    kwargs = {"sense": "minimize", **kwargs}
    return cjax.extremize(_square, jnp.zeros(3), **kwargs)


def test_bad_structure_raises():
    with pytest.raises(ValueError, match=r"shape \(m,\)"):
        _solve_simple(inequalities=lambda x, a: jnp.outer(x, x))
    with pytest.raises(ValueError, match="does not broadcast"):
        _solve_simple(lower=jnp.zeros(2))
    with pytest.raises(ValueError, match="lower > upper"):
        _solve_simple(lower=jnp.ones(3), upper=jnp.array([2.0, 0.0, 2.0]))
    with pytest.raises(ValueError, match="sense"):
        cjax.extremize(_square, jnp.zeros(3), lower=0.0)
    with pytest.raises(ValueError, match="sense"):
        _solve_simple(lower=0.0, sense="min")
    with pytest.raises(ValueError, match="Newton"):
        _solve_simple(lower=0.0, solver=cjax.MINRES(rtol=1e-10, atol=0.0))
    with pytest.raises(ValueError, match="empty"):
        _solve_simple(inequalities=lambda x, a: x[:0])


def test_scalar_inequality_and_pytree_bounds():
    x0 = {"u": jnp.zeros(2), "v": jnp.zeros(())}
    target = {"u": jnp.array([3.0, -3.0]), "v": jnp.asarray(0.5)}

    def f(x, args):
        return jnp.sum((x["u"] - target["u"]) ** 2) + (x["v"] - target["v"]) ** 2

    sol = cjax.extremize(
        f,
        x0,
        inequalities=lambda x, a: x["v"] - 0.25,  # a scalar: one inequality
        lower={"u": -1.0, "v": -INF},
        upper={"u": jnp.array([2.0, 2.0]), "v": INF},
        sense="minimize",
    )
    np.testing.assert_allclose(sol.x["u"], [2.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(sol.x["v"], 0.25, atol=1e-12)
    # Rows: H, lower (u0, u1, v), upper (u0, u1, v).
    np.testing.assert_allclose(
        sol.inequality_multipliers, [0.5, 0, 4.0, 0, 2.0, 0, 0], atol=1e-10
    )


def test_not_an_optimum_is_not_a_success():
    """Minimizing `-x^2` on [-1, 1]: x = 0 satisfies the KKT conditions (mu = 0)
    but is a maximum: started there, the solve stays and is never reported as a
    successful minimum. From anywhere else, inside the box or outside, the
    regularised step descends to the nearer bound, x = sign(x0), a local minimum
    with mu = 2 on that bound."""

    def f(x, args):
        return -jnp.sum(x**2)

    sol = cjax.extremize(
        f, jnp.array([0.0]), lower=-1.0, upper=1.0, sense="minimize", throw=False
    )
    assert sol.result == cjax.RESULTS.not_an_optimum
    assert sol.kind == cjax.EXTREMUM.unknown
    for x0, mu in ((0.9, [0.0, 2.0]), (1.5, [0.0, 2.0]), (-0.4, [2.0, 0.0])):
        sol = cjax.extremize(
            f, jnp.array([x0]), lower=-1.0, upper=1.0, sense="minimize", throw=False
        )
        assert sol.result == cjax.RESULTS.successful
        np.testing.assert_allclose(sol.x, [np.sign(x0)], atol=1e-12)
        np.testing.assert_allclose(sol.inequality_multipliers, mu, atol=1e-10)
        assert sol.kind == cjax.EXTREMUM.isolated


def test_sense_without_inequalities_checks_the_kind():
    """The lecture's cylinder is a maximum of V on G = 0: asking to minimize is
    `not_an_optimum`, never a silent success."""
    args = {"b": jnp.asarray(B), "l": jnp.asarray(L)}
    sol = cjax.extremize(
        cyl.volume,
        cyl.initial_guess(B, L),
        args,
        constraints=cyl.constraint,
        sense="minimize",
        throw=False,
    )
    assert sol.result == cjax.RESULTS.not_an_optimum
    assert sol.kind == cjax.EXTREMUM.unknown
    # Without inequalities the new fields are empty.
    assert sol.inequality_multipliers.shape == (0,)
    assert sol.active.shape == (0,) and sol.active.dtype == bool


def _rosenbrock(x, args):
    return (1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2


def _disk(x, args):
    return jnp.sum(x**2) - args


@jax.jit
def _rosenbrock_in_disk(r2, x0):
    return cjax.extremize(
        _rosenbrock, x0, r2, inequalities=_disk, sense="minimize", throw=False
    )


@pytest.mark.parametrize(
    "r2, x0",
    [(1.5, (-1.2, 1.0)), (1.0, (3.0, -4.0)), (0.5, (0.0, 0.0)), (3.0, (9.0, 9.0))],
)
def test_rosenbrock_in_a_disk_against_scipy(r2, x0):
    """A nonconvex objective from feasible and infeasible starts (the classic
    (-1.2, 1) among them), against SLSQP; the disk binds unless it holds (1, 1)."""
    sol = _rosenbrock_in_disk(jnp.asarray(r2), jnp.asarray(x0))
    ref = scipy.optimize.minimize(
        lambda x: (1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2,
        np.zeros(2),
        jac=lambda x: np.array(
            [
                -2 * (1 - x[0]) - 400 * x[0] * (x[1] - x[0] ** 2),
                200 * (x[1] - x[0] ** 2),
            ]
        ),
        method="SLSQP",
        constraints=[
            {"type": "ineq", "fun": lambda x: r2 - x @ x, "jac": lambda x: -2 * x}
        ],
        options={"ftol": 1e-15, "maxiter": 1000},
    )
    assert sol.result == cjax.RESULTS.successful
    assert sol.kind == cjax.EXTREMUM.minimum
    binds = r2 < 2.0
    if binds:  # (SLSQP stops 1e-5 short of (1, 1) in the free case)
        np.testing.assert_allclose(sol.x, ref.x, atol=1e-7)
        np.testing.assert_allclose(sol.x @ sol.x, r2, rtol=1e-12)
    assert bool(sol.active[0]) == binds
    if binds:
        # Stationarity along x: grad F + 2 mu x = 0, mu > 0.
        grad = np.asarray(jax.grad(_rosenbrock)(sol.x, None))
        mu = -grad[0] / (2 * sol.x[0])
        np.testing.assert_allclose(sol.inequality_multipliers, [mu], rtol=1e-8)
        assert mu > 0
    else:
        np.testing.assert_allclose(sol.x, [1.0, 1.0], atol=1e-12)
        assert sol.inequality_multipliers[0] == 0


# ---------------------------------------------------------------------------------
# A large batch (once a deadlock in XLA's CPU runtime)
# ---------------------------------------------------------------------------------

_BATCH_SCRIPT = """
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import constrained_jax as cjax

def solve(c, p0):
    return cjax.extremize(
        lambda p, c: jnp.sum(p**2) - jnp.dot(c, p), p0, c,
        constraints=lambda p, c: jnp.sum(p) - 1.0,
        lower=0.0, sense="minimize", throw=False,
    )

def exact(c):  # the projection of c / 2 onto the simplex (sort-based)
    u = np.sort(c / 2)[::-1]
    css = np.cumsum(u) - 1.0
    k = np.nonzero(u - css / np.arange(1, len(u) + 1) > 0)[0][-1]
    return np.maximum(c / 2 - css[k] / (k + 1), 0.0)

size, n = 300, 10
cs = (2.0 + 4.0 * np.random.default_rng(1010).normal(size=(size, n))) / n
out = jax.jit(jax.vmap(solve))(jnp.asarray(cs), jnp.full((size, n), 1.0 / n))
assert np.all(np.asarray(out.result._value) == cjax.RESULTS.successful._value)
err = np.max(np.abs(np.asarray(out.x) - np.stack([exact(c) for c in cs])))
assert err < 1e-12, err
print("ok", err)
"""


def test_large_vmapped_batch_finishes():
    """`jit(vmap)` over 300 simplex projections (n = 10, about half the bounds
    active) finishes and is exact. It used to deadlock XLA's CPU runtime (two
    batched LAPACK factorisations in one loop body); run in a subprocess with a
    time limit, so that a regression fails instead of hanging the suite."""
    import subprocess

    try:
        done = run_python(_BATCH_SCRIPT, timeout=240)
    except subprocess.TimeoutExpired:
        pytest.fail("jit(vmap(extremize)) over 300 problems did not finish in 240 s")
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.startswith("ok")


@jax.jit
@jax.vmap
def _steep_cap(c, u, x0):
    return cjax.extremize(
        lambda x, a: a[0] * (x[0] - 3 * a[1]) ** 2,
        x0[None],
        (c, u),
        upper=u[None],
        sense="minimize",
        throw=False,
    )


def test_badly_scaled_multipliers():
    """`min c (x - 3u)^2` with `x <= u`: `x = u`, `mu = 4 c u`, for curvatures `c`
    up to 1e15 and caps `u` from 1e-5 to 1e5 (multipliers up to 4e20, constraints
    of order 1e-5), from `x0 = 0` and from the infeasible unconstrained optimum
    `3u`. (Before the fallback's merit function weighed the rows by the Jacobian,
    every `c >= 1e12` stopped after 256 steps with `infeasible_inequalities`.)"""
    grid = np.array([(c, u) for c in (1.0, 1e6, 1e12, 1e15) for u in (1e-5, 1.0, 1e5)])
    c, u = np.repeat(grid, 2, axis=0).T
    x0 = np.where(np.arange(len(c)) % 2 == 0, 0.0, 3 * u)
    sol = _steep_cap(jnp.asarray(c), jnp.asarray(u), jnp.asarray(x0))
    assert np.all(np.asarray(sol.result._value) == cjax.RESULTS.successful._value)
    np.testing.assert_allclose(sol.x[:, 0], u, rtol=1e-12)
    np.testing.assert_allclose(sol.inequality_multipliers[:, 0], 4 * c * u, rtol=1e-10)
    assert np.all(np.asarray(sol.active[:, 0]))
