"""Exactness, Frobenius integrability and integration of Pfaffian constraints.

Closed forms throughout: the lecture's two cylinders (exact), a rheonomic exact row,
`y dx - x dy` (integrable, not exact), the rolling disk and the contact form
`dz - y dx` (not integrable).
"""

import functools as ft

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax._constraints import Holonomic, Pfaffian
from constrained_jax._integrability import (
    exterior_derivative,
    integrate_pfaffian,
    is_exact,
    is_integrable,
)

from .helpers import TraceCounter


def _uniform(rng, shape, low, high, dtype=np.float64):
    # numpy draws: jax.random would compile a kernel per shape, slowing the tests.
    return jnp.asarray(rng.uniform(low, high, shape).astype(dtype))


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# ---------------------------------------------------------------------------------
# The lecture's two cylinders: q = (r, theta1, theta2)
# ---------------------------------------------------------------------------------


def _cylinder_rows(q, t, args):
    big_r, a = args["R"], args["a"]
    zero, one = jnp.zeros_like(a), jnp.ones_like(a)
    return jnp.stack([jnp.stack([one, zero, zero]), jnp.stack([zero, big_r + a, -a])])


CYLINDERS = Pfaffian(_cylinder_rows)


def _cylinder_args(dtype=jnp.float64):
    return {"R": jnp.asarray(1.0, dtype), "a": jnp.asarray(0.3, dtype)}


def test_cylinders_exact_and_integrable(rng):
    args = _cylinder_args()
    qs = _uniform(rng, (20, 3), -3.0, 3.0)
    ts = _uniform(rng, (20,), 0.0, 5.0)
    assert is_exact(CYLINDERS, qs, ts, args).tolist() == [True, True]
    assert is_integrable(CYLINDERS, qs, ts, args).tolist() == [True, True]
    f = exterior_derivative(CYLINDERS, qs[0], ts[0], args)
    assert f.shape == (2, 4, 4)
    assert jnp.all(f == 0)


@pytest.mark.parametrize("num_points", [1, 16])
def test_cylinders_integrate_closed_form(rng, num_points):
    # Constant coefficients: even the one-point (midpoint) rule is exact.
    args = _cylinder_args()
    big_r, a = args["R"], args["a"]
    q_ref = jnp.array([1.3, 0.2, -0.4])
    hol = integrate_pfaffian(CYLINDERS, q_ref, 0.0, args, num_points=num_points)
    assert isinstance(hol, Holonomic)
    qs = _uniform(rng, (10, 3), -3.0, 3.0)
    ts = _uniform(rng, (10,), -2.0, 2.0)
    got = jax.vmap(lambda q, t: hol.fn(q, t, args))(qs, ts)
    d = qs - q_ref
    expected = jnp.stack([d[:, 0], (big_r + a) * d[:, 1] - a * d[:, 2]], axis=1)
    np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-13)
    assert jnp.all(hol.fn(q_ref, jnp.asarray(0.0), args) == 0)
    for q, t in zip(qs[:3], ts[:3], strict=True):
        jac = jax.jacobian(hol.fn)(q, t, args)
        np.testing.assert_allclose(jac, _cylinder_rows(q, t, args), atol=1e-14)
        np.testing.assert_allclose(
            jax.jacobian(hol.fn, argnums=1)(q, t, args), [0.0, 0.0], atol=1e-14
        )


def test_cylinders_integrated_surface_is_the_lectures():
    # Through the reference point (R + a, 0, 0) the integrated constraints are
    # r = R + a and theta2 = (1 + R/a) theta1.
    args = _cylinder_args()
    big_r, a = args["R"], args["a"]
    hol = integrate_pfaffian(CYLINDERS, jnp.stack([big_r + a, 0.0, 0.0]), 0.0, args)
    theta1 = jnp.linspace(-1.0, 1.0, 7)
    on = jnp.stack(
        [jnp.full_like(theta1, big_r + a), theta1, (1 + big_r / a) * theta1], axis=1
    )
    g = jax.vmap(lambda q: hol.fn(q, jnp.asarray(0.0), args))(on)
    np.testing.assert_allclose(g, 0.0, atol=1e-14)
    off = on.at[:, 2].add(0.1)  # slipped by 0.1 rad: G_2 = -0.1 a
    g = jax.vmap(lambda q: hol.fn(q, jnp.asarray(0.0), args))(off)
    np.testing.assert_allclose(g[:, 1], -0.1 * a, rtol=1e-12)


# ---------------------------------------------------------------------------------
# Rheonomic: G = x - A cos(w t), so g = (1, 0), h = A w sin(w t); q = (x, y)
# ---------------------------------------------------------------------------------


def _rheo_g(q, t, args):
    return jnp.stack([jnp.ones_like(q[0]), jnp.zeros_like(q[0])])[None, :]


def _rheo_h(q, t, args):
    amp, omega = args["A"], args["omega"]
    return (amp * omega * jnp.sin(omega * t))[None]


RHEONOMIC = Pfaffian(_rheo_g, _rheo_h)
RHEO_ARGS = {"A": jnp.asarray(0.7), "omega": jnp.asarray(2.3)}


def test_rheonomic_exact(rng):
    qs = _uniform(rng, (16, 2), -2.0, 2.0)
    ts = _uniform(rng, (16,), -3.0, 3.0)
    assert is_exact(RHEONOMIC, qs, ts, RHEO_ARGS).tolist() == [True]
    assert is_integrable(RHEONOMIC, qs, ts, RHEO_ARGS).tolist() == [True]
    # The time condition dg/dt = dh/dq matters: h + x breaks it (dh/dx = 1 != 0).
    broken = Pfaffian(_rheo_g, lambda q, t, args: _rheo_h(q, t, args) + q[0])
    assert is_exact(broken, qs, ts, RHEO_ARGS).tolist() == [False]
    f = exterior_derivative(broken, qs[0], ts[0], RHEO_ARGS)
    np.testing.assert_allclose(f[0, 0, 2], 1.0)  # dh/dx - dg_x/dt, with t last
    np.testing.assert_allclose(f[0, 2, 0], -1.0)


def test_rheonomic_integrate_closed_form(rng):
    amp, omega = RHEO_ARGS["A"], RHEO_ARGS["omega"]
    q_ref, t_ref = jnp.array([0.4, -1.0]), jnp.asarray(0.5)
    hol = integrate_pfaffian(RHEONOMIC, q_ref, t_ref, RHEO_ARGS)
    qs = _uniform(rng, (12, 2), -2.0, 2.0)
    ts = _uniform(rng, (12,), -2.0, 3.0)
    got = jax.vmap(lambda q, t: hol.fn(q, t, RHEO_ARGS))(qs, ts)[:, 0]
    closed = lambda q, t: q[..., 0] - amp * jnp.cos(omega * t)
    expected = closed(qs, ts) - closed(q_ref, t_ref)
    np.testing.assert_allclose(got, expected, rtol=1e-13, atol=1e-13)
    # dG/dq = g, dG/dt = h, through the Holonomic constraint's own velocity form.
    for q, t in zip(qs[:3], ts[:3], strict=True):
        jac, dt = hol.velocity_form(q, t, RHEO_ARGS)
        np.testing.assert_allclose(jac, _rheo_g(q, t, RHEO_ARGS), atol=1e-13)
        np.testing.assert_allclose(dt, _rheo_h(q, t, RHEO_ARGS), rtol=1e-12)


# ---------------------------------------------------------------------------------
# y dx - x dy: integrable (= -y^2 d(x/y)) but not exact; q = (x, y)
# ---------------------------------------------------------------------------------

ROTATION = Pfaffian(lambda q, t, args: jnp.stack([q[1], -q[0]])[None, :])
# Times the integrating factor 1/y^2: d(x/y).
ROTATION_SCALED = Pfaffian(
    lambda q, t, args: jnp.stack([1 / q[1], -q[0] / q[1] ** 2])[None, :]
)


def test_integrating_factor(rng):
    qs = _uniform(rng, (16, 2), 0.5, 2.0)
    assert is_exact(ROTATION, qs).tolist() == [False]
    assert is_integrable(ROTATION, qs).tolist() == [True]
    f = exterior_derivative(ROTATION, qs[0])
    np.testing.assert_allclose(f[0, 0, 1], -2.0)  # d(-x)/dx - d(y)/dy
    assert is_exact(ROTATION_SCALED, qs).tolist() == [True]
    q_ref = jnp.array([1.0, 1.5])
    hol = integrate_pfaffian(ROTATION_SCALED, q_ref)
    got = jax.vmap(lambda q: hol.fn(q, jnp.asarray(0.0), None))(qs)[:, 0]
    expected = qs[:, 0] / qs[:, 1] - q_ref[0] / q_ref[1]
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-13)


# ---------------------------------------------------------------------------------
# Rolling disk: q = (x, y, theta, phi); dx - R cos(theta) dphi, dy - R sin(theta) dphi
# ---------------------------------------------------------------------------------


def _disk_rows(q, t, args):
    theta, big_r = q[2], args["R"]
    zero, one = jnp.zeros_like(theta), jnp.ones_like(theta)
    return jnp.stack(
        [
            jnp.stack([one, zero, zero, -big_r * jnp.cos(theta)]),
            jnp.stack([zero, one, zero, -big_r * jnp.sin(theta)]),
        ]
    )


DISK = Pfaffian(_disk_rows)
DISK_X = Pfaffian(lambda q, t, args: _disk_rows(q, t, args)[:1])
DISK_ARGS = {"R": jnp.asarray(0.8)}


def _generic_disk_points(rng, m):
    qs = _uniform(rng, (m, 4), -3.0, 3.0)
    # Keep theta away from multiples of pi/2, where one of the rows is closed.
    theta = jnp.linspace(0.2, 1.3, m) + jnp.pi * jnp.arange(m, dtype=jnp.float64) / 2
    return qs.at[:, 2].set(theta)


def _three_forms(constraint, qs, t, args):
    """`(omega ^ d omega)_{abc} = w_a F_bc + w_b F_ca + w_c F_ab` for one row, at each
    of the points `qs`, as a numpy array of shape `(m, n + 1, n + 1, n + 1)`."""

    @eqx.filter_jit
    def forms(qs_):
        def one(q):
            g, h = constraint.velocity_form(q, jnp.asarray(t), args)
            w = jnp.concatenate([g[0], h[:1]])
            f = exterior_derivative(constraint, q, t, args)[0]
            return (
                jnp.einsum("a,bc->abc", w, f)
                + jnp.einsum("b,ca->abc", w, f)
                + jnp.einsum("c,ab->abc", w, f)
            )

        return jax.vmap(one)(qs_)

    return np.asarray(forms(qs))


def test_rolling_disk_not_exact_not_integrable(rng):
    qs = _generic_disk_points(rng, 12)
    assert is_exact(DISK, qs, 0.0, DISK_ARGS).tolist() == [False, False]
    assert is_integrable(DISK_X, qs, 0.0, DISK_ARGS).tolist() == [False]
    assert is_integrable(DISK, qs, 0.0, DISK_ARGS).tolist() == [False, False]
    # omega ^ d omega = R sin(theta) dx ^ dtheta ^ dphi, in closed form: the component
    # (x, theta, phi) = (0, 2, 3), antisymmetric, and nothing else.
    forms = _three_forms(DISK_X, qs, 0.0, DISK_ARGS)
    coefficient = DISK_ARGS["R"] * np.sin(np.asarray(qs[:, 2]))
    expected = np.zeros_like(forms)
    for perm, sign in [((0, 2, 3), 1), ((2, 3, 0), 1), ((3, 0, 2), 1)]:
        for p, s in [(perm, sign), (perm[::-1], -sign)]:
            expected[(slice(None), *p)] = s * coefficient
    np.testing.assert_allclose(forms, expected, rtol=1e-13, atol=1e-15)


def test_rolling_disk_pointwise(rng):
    # At theta = 0 the first row is closed (d omega_1 = R sin(theta) dtheta ^ dphi):
    # a pointwise test passes there, which is why tests take many samples.
    q0 = jnp.array([0.3, -0.2, 0.0, 1.1])
    assert is_exact(DISK_X, q0, 0.0, DISK_ARGS).tolist() == [True]
    # For the pair, flag j is d omega_j on the joint distribution: at theta = 0 the
    # first vanishes and the second (-R cos(theta) dtheta ^ dphi) does not.
    assert is_integrable(DISK, q0, 0.0, DISK_ARGS).tolist() == [True, False]
    # vmap over single points gives per-point flags.
    thetas = jnp.array([0.0, 0.5, jnp.pi, 2.0])
    qs = jnp.tile(q0, (4, 1)).at[:, 2].set(thetas)
    flags = jax.vmap(lambda q: is_exact(DISK_X, q, 0.0, DISK_ARGS))(qs)
    # At theta = pi, d omega_1 = R sin(pi) ~ 1e-16 R is round-off, but it is also the
    # whole Jacobian, so the relative test rejects it; an absolute floor accepts it.
    assert flags[:, 0].tolist() == [True, False, False, False]
    flags = jax.vmap(lambda q: is_exact(DISK_X, q, 0.0, DISK_ARGS, atol=1e-12))(qs)
    assert flags[:, 0].tolist() == [True, False, True, False]
    # A batch including generic points fails, as it must.
    assert is_exact(DISK_X, qs, 0.0, DISK_ARGS).tolist() == [False]


# ---------------------------------------------------------------------------------
# R^3: the contact form dz - y dx, and the exact dz - y dx - x dy = d(z - x y)
# ---------------------------------------------------------------------------------

CONTACT = Pfaffian(
    lambda q, t, args: jnp.stack([-q[1], jnp.zeros_like(q[0]), 1.0])[None]
)
EXACT3 = Pfaffian(lambda q, t, args: jnp.stack([-q[1], -q[0], 1.0])[None])


def test_contact_form(rng):
    qs = _uniform(rng, (10, 3), -2.0, 2.0)
    assert is_exact(CONTACT, qs).tolist() == [False]
    assert is_integrable(CONTACT, qs).tolist() == [False]
    # omega ^ d omega = dz ^ dx ^ dy = dx ^ dy ^ dz, at every point.
    forms = _three_forms(CONTACT, qs, 0.0, None)
    np.testing.assert_array_equal(forms[:, 0, 1, 2], 1.0)
    np.testing.assert_array_equal(forms[:, 1, 0, 2], -1.0)
    np.testing.assert_array_equal(forms[:, 2, 0, 1], 1.0)
    np.testing.assert_array_equal(forms[..., 3], 0.0)  # nothing along t


def test_exact_in_r3(rng):
    qs = _uniform(rng, (10, 3), -2.0, 2.0)
    assert is_exact(EXACT3, qs).tolist() == [True]
    assert is_integrable(EXACT3, qs).tolist() == [True]
    q_ref = jnp.array([0.5, -1.0, 2.0])
    hol = integrate_pfaffian(EXACT3, q_ref)
    got = jax.vmap(lambda q: hol.fn(q, jnp.asarray(0.0), None))(qs)[:, 0]
    potential = lambda q: q[..., 2] - q[..., 0] * q[..., 1]
    np.testing.assert_allclose(got, potential(qs) - potential(q_ref), rtol=1e-13)


# ---------------------------------------------------------------------------------
# Holonomic round trip and quadrature order
# ---------------------------------------------------------------------------------


def _smooth_g(q, t, args):
    return jnp.stack(
        [jnp.sin(q[0]) * q[1] + jnp.exp(0.3 * t) * q[2], q[0] ** 2 * q[2] - jnp.cos(t)]
    )


def test_holonomic_round_trip(rng):
    holonomic = Holonomic(_smooth_g)
    qs = _uniform(rng, (8, 3), -1.5, 1.5)
    ts = _uniform(rng, (8,), -1.0, 1.0)
    assert is_exact(holonomic, qs, ts).tolist() == [True, True]
    assert is_integrable(holonomic, qs, ts).tolist() == [True, True]
    pfaffian = Pfaffian(
        lambda q, t, args: holonomic.velocity_form(q, t, args)[0],
        lambda q, t, args: holonomic.velocity_form(q, t, args)[1],
    )
    q_ref, t_ref = jnp.array([0.2, -0.3, 0.9]), jnp.asarray(0.1)
    hol = integrate_pfaffian(pfaffian, q_ref, t_ref)
    got = jax.vmap(lambda q, t: hol.fn(q, t, None))(qs, ts)
    expected = jax.vmap(lambda q, t: _smooth_g(q, t, None))(qs, ts)
    expected = expected - _smooth_g(q_ref, t_ref, None)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-13)


def test_quadrature_exact_to_degree():
    # G = x^5 y^2: along a segment from the origin d/ds G(s q) = 7 s^6 G(q), degree 6,
    # integrated exactly by 4 Gauss-Legendre points (degree <= 7) but not by 3.
    pfaffian = Pfaffian(
        lambda q, t, args: jnp.stack([5 * q[0] ** 4 * q[1] ** 2, 2 * q[0] ** 5 * q[1]])[
            None
        ]
    )
    q = jnp.array([1.3, -0.7])
    exact = q[0] ** 5 * q[1] ** 2
    t = jnp.asarray(0.0)

    def value(num_points, rtol=None):
        hol = integrate_pfaffian(
            pfaffian, jnp.zeros(2), num_points=num_points, rtol=rtol
        )
        return hol.fn(q, t, None)[0]

    # Without the refusal: 4 points are exact, 3 are not.
    np.testing.assert_allclose(value(4, rtol=np.inf), exact, rtol=1e-14)
    assert abs(value(3, rtol=np.inf) - exact) > 1e-6 * abs(exact)
    # With it (the default), the estimate compares with one node fewer: 3 points are
    # refused, and so are 4 (conservative: the 3-point rule it is compared with is not
    # exact); 5 points (compared with the exact 4) are returned.
    assert jnp.isnan(value(3)) and jnp.isnan(value(4))
    np.testing.assert_allclose(value(5), exact, rtol=1e-14)


def _oscillating_form(q, t, args):
    # d(sin(k x) + y): exact, with G = sin(k x) + y - (sin(k x_ref) + y_ref).
    return jnp.stack([args["k"] * jnp.cos(args["k"] * q[0]), jnp.ones_like(q[1])])[None]


OSCILLATING = Pfaffian(_oscillating_form)


def test_unresolved_quadrature_is_refused():
    """Right or refused: 16 nodes do not resolve sin(20 x) over a segment of length 5.
    The value used to come back as 19.37 against the true -0.206, without a word."""
    args = {"k": jnp.asarray(20.0)}
    q, t = jnp.array([5.0, 0.5]), jnp.asarray(0.0)
    exact = jnp.sin(20.0 * 5.0) + 0.5
    coarse = integrate_pfaffian(OSCILLATING, jnp.zeros(2), 0.0, args)
    assert jnp.isnan(coarse.fn(q, t, args)).all()
    unchecked = integrate_pfaffian(OSCILLATING, jnp.zeros(2), 0.0, args, rtol=np.inf)
    assert abs(unchecked.fn(q, t, args)[0] - exact) > 1.0  # what was returned before
    fine = integrate_pfaffian(OSCILLATING, jnp.zeros(2), 0.0, args, num_points=96)
    np.testing.assert_allclose(fine.fn(q, t, args), [exact], rtol=1e-12, atol=1e-13)
    # Near the reference point the same 16 nodes resolve it, and are accurate.
    near = jnp.array([0.1, 0.5])
    np.testing.assert_allclose(
        coarse.fn(near, t, args), [jnp.sin(2.0) + 0.5], rtol=1e-13
    )
    # A NaN point is NaN, a zero-length segment is 0 (not refused).
    assert jnp.isnan(coarse.fn(jnp.array([jnp.nan, 0.0]), t, args)).all()
    assert coarse.fn(jnp.zeros(2), t, args).tolist() == [0.0]
    with pytest.raises(ValueError, match="rtol"):
        integrate_pfaffian(OSCILLATING, jnp.zeros(2), 0.0, args, rtol=-1.0)


def test_derivatives_are_the_form_not_the_quadrature():
    """dG/dq = g and dG/dt = h by the Poincare lemma, exactly and to every order, even
    where the quadrature itself is coarse; dG/dargs goes through the quadrature."""
    args = {"k": jnp.asarray(1.7)}
    q_ref = jnp.array([0.3, -0.2])
    hol = integrate_pfaffian(OSCILLATING, q_ref, 0.0, args, num_points=2, rtol=np.inf)
    q, t = jnp.array([1.4, 0.9]), jnp.asarray(0.0)
    closed = lambda q_, a: (
        jnp.sin(a["k"] * q_[0]) + q_[1] - (jnp.sin(a["k"] * q_ref[0]) + q_ref[1])
    )
    # Two nodes on a segment of length 1.1 at frequency 1.7: the value is off.
    assert abs(hol.fn(q, t, args)[0] - closed(q, args)) > 1e-4
    # Its Jacobian and Hessian (the acceleration bias) are those of the closed form.
    np.testing.assert_allclose(
        jax.jacfwd(hol.fn)(q, t, args)[0], jax.grad(closed)(q, args), rtol=1e-15
    )
    np.testing.assert_allclose(
        jax.jacrev(hol.fn)(q, t, args)[0], jax.grad(closed)(q, args), rtol=1e-15
    )
    np.testing.assert_allclose(
        jax.hessian(hol.fn)(q, t, args)[0], jax.hessian(closed)(q, args), rtol=1e-15
    )
    # The args derivative differentiates the quadrature: with enough nodes, the
    # closed form's.
    fine = integrate_pfaffian(OSCILLATING, q_ref, 0.0, args)
    d_args = jax.grad(lambda a: fine.fn(q, t, a)[0])(args)
    np.testing.assert_allclose(
        d_args["k"], jax.grad(lambda a: closed(q, a))(args)["k"], rtol=1e-13
    )


# ---------------------------------------------------------------------------------
# Transformations: jit, vmap, grad, no recompiles, float32
# ---------------------------------------------------------------------------------


def test_jit_no_recompile(rng):
    qs = _uniform(rng, (6, 2), -1.0, 1.0)
    ts = _uniform(rng, (6,), -1.0, 1.0)
    counter = TraceCounter(lambda q, t, args: is_exact(RHEONOMIC, q, t, args))
    jitted = jax.jit(counter)
    for amp in (0.5, 1.5, 3.0):
        args = {"A": jnp.asarray(amp), "omega": jnp.asarray(2.0 * amp)}
        assert jitted(qs, ts, args).tolist() == [True]
    assert counter.count == 1
    jit_disk = jax.jit(lambda q, args: is_integrable(DISK, q, 0.0, args))
    assert jit_disk(_generic_disk_points(rng, 5), DISK_ARGS).tolist() == [
        False,
        False,
    ]


def test_integrated_constraint_through_jit_and_grad(rng):
    q_ref, t_ref = jnp.array([0.4, -1.0]), jnp.asarray(0.5)
    hol = integrate_pfaffian(RHEONOMIC, q_ref, t_ref, RHEO_ARGS)
    q, t = jnp.array([1.1, 0.3]), jnp.asarray(2.0)
    eager = hol.fn(q, t, RHEO_ARGS)
    jitted = eqx.filter_jit(lambda c, q_, t_, a: c.position_residual(q_, t_, a))
    np.testing.assert_allclose(jitted(hol, q, t, RHEO_ARGS), eager, rtol=1e-15)
    # For an exact form, dG/dq_ref = -g(q_ref) and dG/dt_ref = -h(q_ref, t_ref).
    build = lambda qr, tr: integrate_pfaffian(RHEONOMIC, qr, tr, RHEO_ARGS).fn(
        q, t, RHEO_ARGS
    )
    d_qref, d_tref = jax.jacobian(build, argnums=(0, 1))(q_ref, t_ref)
    np.testing.assert_allclose(d_qref, -_rheo_g(q_ref, t_ref, RHEO_ARGS), atol=1e-14)
    np.testing.assert_allclose(d_tref, -_rheo_h(q_ref, t_ref, RHEO_ARGS), rtol=1e-12)
    # and vmap over evaluation points.
    qs = _uniform(rng, (5, 2), -1.0, 1.0)
    batched = jax.vmap(hol.fn, in_axes=(0, None, None))(qs, t, RHEO_ARGS)
    assert batched.shape == (5, 1)


def test_float32(rng):
    args = _cylinder_args(jnp.float32)
    qs = _uniform(rng, (8, 3), -3.0, 3.0, np.float32)
    ts = jnp.zeros(8, jnp.float32)
    assert is_exact(CYLINDERS, qs, ts, args).tolist() == [True, True]
    disk_args = {"R": jnp.asarray(0.8, jnp.float32)}
    disk_qs = _generic_disk_points(rng, 6).astype(jnp.float32)
    assert is_exact(DISK, disk_qs, 0.0, disk_args).tolist() == [False, False]
    assert is_integrable(DISK, disk_qs, 0.0, disk_args).tolist() == [False, False]
    q_ref = jnp.array([1.3, 0.2, -0.4], jnp.float32)
    hol = integrate_pfaffian(CYLINDERS, q_ref, 0.0, args)
    got = hol.fn(qs[0], jnp.asarray(0.0, jnp.float32), args)
    assert got.dtype == jnp.float32
    d = qs[0] - q_ref
    expected = jnp.stack([d[0], (args["R"] + args["a"]) * d[1] - args["a"] * d[2]])
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------------------------
# Bad structure: trace-time ValueError
# ---------------------------------------------------------------------------------


def test_bad_structure():
    q = jnp.zeros(3)
    args = _cylinder_args()
    with pytest.raises(ValueError, match="Pfaffian"):
        is_exact(_cylinder_rows, q, 0.0, args)  # a bare function, not a constraint
    with pytest.raises(ValueError, match="shape"):
        is_exact(CYLINDERS, jnp.asarray(1.0), 0.0, args)
    with pytest.raises(ValueError, match="shape"):
        is_integrable(CYLINDERS, jnp.zeros((2, 2, 3)), 0.0, args)
    with pytest.raises(ValueError, match="columns"):
        is_exact(CYLINDERS, jnp.zeros(4), 0.0, args)  # g has 3 columns, n = 4
    with pytest.raises(ValueError, match=r"\(k, n\)"):
        is_exact(Pfaffian(lambda q, t, args: q), q)  # g of shape (n,)
    with pytest.raises(ValueError, match="h"):
        is_exact(Pfaffian(_cylinder_rows, lambda q, t, args: q), q, 0.0, args)
    with pytest.raises(ValueError, match=r"\(5,\)"):
        is_exact(CYLINDERS, jnp.zeros((5, 3)), jnp.zeros(4), args)
    with pytest.raises(ValueError, match="scalar"):
        is_integrable(CYLINDERS, q, jnp.zeros(2), args)
    with pytest.raises(ValueError, match="one point"):
        exterior_derivative(CYLINDERS, jnp.zeros((2, 3)), 0.0, args)
    with pytest.raises(ValueError, match="num_points"):
        integrate_pfaffian(CYLINDERS, q, 0.0, args, num_points=0)
    with pytest.raises(ValueError, match="q_ref"):
        integrate_pfaffian(CYLINDERS, jnp.zeros((2, 3)), 0.0, args)
    hol = integrate_pfaffian(CYLINDERS, q, 0.0, args)
    with pytest.raises(ValueError, match="q_ref"):
        hol.fn(jnp.zeros(4), jnp.asarray(0.0), args)
    with pytest.raises(ValueError, match="scalar"):
        hol.fn(q, jnp.zeros(2), args)


def test_non_finite_point_is_refused():
    """A comparison with NaN is false: at a NaN point (or where the form is not
    finite, the angle form at the origin) an exact form was reported not exact and
    not integrable, which a `False` claims to prove. Refused at run time instead; the
    finite points of the same forms as before."""
    exact = Pfaffian(lambda q, t, args: 2 * q[None])
    angle = Pfaffian(
        lambda q, t, args: (jnp.stack([-q[1], q[0]]) / (q[0] ** 2 + q[1] ** 2))[None]
    )
    good = jnp.array([[0.3, 0.4], [1.0, -2.0]])
    assert bool(is_exact(exact, good)[0]) and bool(is_integrable(exact, good)[0])
    assert bool(is_exact(angle, good)[0])
    for form, q in [
        (exact, jnp.array([jnp.nan, 0.4])),
        (exact, good.at[1, 0].set(jnp.inf)),
        (angle, jnp.zeros(2)),
    ]:
        for test in (is_exact, is_integrable):
            with pytest.raises(Exception, match="cannot decide"):
                jax.block_until_ready(test(form, q))


def _bead(q, qd, t, args):
    return 0.5 * qd @ qd - args["g"] * q[1]


@pytest.fixture(scope="module")
def bead_run():
    """A bead sliding under gravity on the wire sin(k x) + y = 0, the wire given as
    the exact form d(sin(k x) + y) and integrated from `q_ref`."""

    @ft.partial(jax.jit, static_argnums=4)
    def run(q_ref, x0, v0, args, integrated):
        exact = cjax.Holonomic(lambda q, t, a: jnp.sin(a["k"] * q[0]) + q[1])
        hol = integrate_pfaffian(OSCILLATING, q_ref, 0.0, args)
        system = cjax.LagrangianSystem(_bead, hol if integrated else exact)
        q0 = jnp.stack([x0, -jnp.sin(args["k"] * x0)])
        qd0 = v0 * jnp.stack([jnp.ones_like(x0), -args["k"] * jnp.cos(args["k"] * x0)])
        return cjax.simulate(
            system,
            (0.0, 1.0),
            q0,
            qd0,
            args,
            stabilization=cjax.Baumgarte(alpha=5.0, beta=5.0),
            stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
            throw=False,
        )

    return run


def test_integrated_wire_in_simulate(bead_run):
    """The integrated wire moves the bead as the closed-form wire does (its Jacobian
    and bias are the form's); where 16 nodes cannot resolve the segment from `q_ref`
    to the start, `simulate` refuses the start instead of following a wrong G, and
    where the motion leaves the resolved segment it stops."""
    args = {"k": jnp.asarray(1.3), "g": jnp.asarray(9.81)}
    x0, v0 = jnp.asarray(0.4), jnp.asarray(1.0)
    closed = bead_run(jnp.zeros(2), x0, v0, args, False)
    traj = bead_run(jnp.zeros(2), x0, v0, args, True)
    assert closed.result == traj.result == cjax.RESULTS.successful
    np.testing.assert_allclose(traj.q, closed.q, rtol=1e-9, atol=1e-9)
    far = {"k": jnp.asarray(20.0), "g": jnp.asarray(9.81)}
    # Slow, so that the bead stays in one well of the wire, 5 <= x <= 5.21.
    x0, v0 = jnp.asarray(5.0), jnp.asarray(0.05)
    refused = bead_run(jnp.zeros(2), x0, v0, far, True)
    assert refused.result == cjax.RESULTS.inconsistent_initial_state
    # The same start from a reference point next to it is resolved.
    near_ref = jnp.array([5.1, -jnp.sin(20.0 * 5.1)])
    traj = bead_run(near_ref, x0, v0, far, True)
    closed = bead_run(near_ref, x0, v0, far, False)
    assert jnp.abs(closed.q[:, 0] - 5.1).max() < 0.12
    assert traj.result == closed.result == cjax.RESULTS.successful
    np.testing.assert_allclose(traj.q, closed.q, rtol=1e-8, atol=1e-8)
    # Fast, the bead leaves the segment the quadrature resolves: G turns NaN ahead of
    # the state, and the run stops when the step falls to round-off, after some
    # twenty rejected steps (it used to run on to `max_steps`, 16,384 steps).
    escaped = bead_run(near_ref, x0, jnp.asarray(3.0), far, True)
    assert escaped.result == cjax.RESULTS.step_size_underflow
    assert escaped.stats["num_steps"] < 4000
