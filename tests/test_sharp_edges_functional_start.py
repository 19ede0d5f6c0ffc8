"""Sharp edges of `solve_functional`: natural starts, and constraints it must refuse.

- plain catenary, no `y0` (ends (0,0), (1,0), length 1.5): solves from the default
  start; y, the multiplier and U match the closed form; d(solution)/d(length) matches
  finite differences.
- lengths 1.01x .. 50x the chord, symmetric and asymmetric ends, `Chebyshev` and
  `PiecewiseLinear`, no `y0`: successful and equal to the closed form (the deep sags
  by continuation in the length, inside the compiled solve; never a spurious
  discrete extremal); `scenes.catenary.solve` needs no warm start.
- two integral constraints (`int y^2 = 1`, `int y sin(pi x) = 0`): the second
  eigenfunction from the default start; Dido from the default start: the minimizing
  (downward) arc, documented.
- the straight line as `y0` (where the length has no gradient): moved onto the
  length like the default start, then the catenary (issue 41; a singular start
  is `functional_singular_start`, tested in `test_sharp_edges_functional_issue41`).
- holonomic constraint violated by the end values: `ValueError` for concrete values,
  `RESULTS.inconsistent_boundary` under `jax.jit` (`throw=True` raises); ends on the
  surface up to rounding are accepted.
- NaN in `args` or in the boundary: `invalid_input` (with and without holonomic).
- a length shorter than the chord: `infeasible_constraints`; exactly the chord:
  `functional_redundant_constraints` (no multiplier exists); never successful.
- a user `y0` wildly off: right (the closed form of the hanging rope, or of its
  mirror image, the arch, which is an extremal too) or refused, never wrong.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import constrained_jax as cjax
from constrained_jax.scenes import catenary as cat, dido, sphere_geodesic as sg

from .helpers import finite_difference_grad


def _rope_solver(discretization):
    @jax.jit
    def solve(ends, length):
        xl, yl, xr, yr = ends
        return cjax.solve_functional(
            cat.functional(xl, yl, xr, yr),
            {"rho_g": 1.0, "length": length},
            discretization=discretization,
            throw=False,
        )

    return solve


_CHEB = _rope_solver(cjax.Chebyshev(32))
_MESH = _rope_solver(cjax.PiecewiseLinear(201))
_MESH_COARSE = _rope_solver(cjax.PiecewiseLinear(101))


def _ends(*values):
    return tuple(jnp.asarray(v, float) for v in values)


def _check_closed_form(sol, ends, length, atol_y, rtol):
    ref = cat.closed_form(*ends, length)
    assert sol.result == cjax.RESULTS.successful
    xs = np.linspace(ends[0], ends[2], 41)
    np.testing.assert_allclose(sol(jnp.asarray(xs)), ref["y"](xs), atol=atol_y)
    np.testing.assert_allclose(
        sol.multipliers.integral[0], ref["multiplier"], rtol=rtol
    )
    np.testing.assert_allclose(sol.value, ref["value"], rtol=rtol)


def test_plain_catenary_default_start():
    ends = (0.0, 0.0, 1.0, 0.0)
    sol = cjax.solve_functional(
        cat.functional(*ends),
        {"rho_g": 1.0, "length": 1.5},
        discretization=cjax.Chebyshev(32),
    )
    # Chebyshev(32) on the entire function cosh: round-off level.
    _check_closed_form(sol, ends, 1.5, 1e-12, 1e-12)
    # The default start hangs down (the lower energy of the two candidates).
    assert float(sol(0.5)) < 0


def test_plain_catenary_gradient_wrt_length():
    """Implicit differentiation from the default start, against finite differences
    of the solve and against the closed form's derivative."""
    fun = cat.functional(0.0, 0.0, 1.0, 0.0)

    @jax.jit
    def mid_height(length):
        sol = cjax.solve_functional(
            fun,
            {"rho_g": 1.0, "length": length},
            discretization=cjax.Chebyshev(32),
        )
        return sol(0.5) + sol.multipliers.integral[0]

    grad = jax.grad(mid_height)(1.5)
    fd = finite_difference_grad(lambda c: mid_height(c), np.array(1.5))
    np.testing.assert_allclose(grad, fd, rtol=1e-7)
    h = 1e-5
    ref = lambda c: cat.closed_form(0, 0, 1, 0, c)
    ref_grad = (
        ref(1.5 + h)["y"](0.5)
        + ref(1.5 + h)["multiplier"]
        - ref(1.5 - h)["y"](0.5)
        - ref(1.5 - h)["multiplier"]
    ) / (2 * h)
    np.testing.assert_allclose(grad, ref_grad, rtol=1e-7)


_ENDS = {
    "level": (0.0, 0.0, 1.0, 0.0),
    "slanted": (0.0, 0.0, 1.0, 0.5),
    "steep": (0.0, 1.0, 2.0, -1.0),
    "offset": (-1.0, 3.0, 0.5, 2.0),
}


@pytest.mark.parametrize("ends", _ENDS.keys())
@pytest.mark.parametrize("ratio", [1.01, 1.5, 3.0, 20.0, 50.0])
def test_catenary_lengths_default_start(ends, ratio):
    ends = _ENDS[ends]
    xl, yl, xr, yr = ends
    length = ratio * math.hypot(xr - xl, yr - yl)
    ref = cat.closed_form(*ends, length)
    if ratio <= 3:
        # Spectral: cosh(k x), an entire function, with k <= 2.5: round-off level.
        sol = _CHEB(_ends(*ends), jnp.asarray(length))
        _check_closed_form(sol, ends, length, 1e-10 * ref["multiplier"], 1e-10)
    # The mesh: second order, h -> h/2 divides the error by 4 (the slope, not a
    # constant, is what the theory fixes).
    errors = []
    for solve in (_MESH_COARSE, _MESH):
        mesh = solve(_ends(*ends), jnp.asarray(length))
        assert mesh.result == cjax.RESULTS.successful
        errors.append(abs(float(mesh.multipliers.integral[0]) - ref["multiplier"]))
    assert 1.8 < np.log2(errors[0] / errors[1]) < 2.2, errors


def test_deep_sag_spectral_no_spurious_extremal():
    """Chebyshev(64), ends (0, 1) and (2, -1), 20 times the chord: Newton straight
    from a deep default start converged to a spurious discrete extremal (KKT
    residual 1e-14, first integral not constant). A deep start (sag over twice the
    interval) now goes to the continuation at once: the catenary."""
    ends = (0.0, 1.0, 2.0, -1.0)
    length = 20 * math.hypot(2.0, 2.0)
    sol = _rope_solver(cjax.Chebyshev(64))(_ends(*ends), jnp.asarray(length))
    ref = cat.closed_form(*ends, length)
    _check_closed_form(sol, ends, length, 1e-10 * ref["multiplier"], 1e-10)


def test_scene_without_warm_start_under_vmap():
    lengths = jnp.array([1.5, 20.0, 50.0])
    sols = jax.vmap(lambda c: cat.solve(length=c, throw=False))(lengths)
    assert np.all(sols.result._value == cjax.RESULTS.successful._value)
    for i, c in enumerate(np.asarray(lengths)):
        ref = cat.closed_form(0, 0, 1, 0, c)
        lam = sols.multipliers.integral[i, 0]
        # Chebyshev(48) resolves cosh(k x) for k <= 25 to round-off.
        np.testing.assert_allclose(lam, ref["multiplier"], rtol=1e-10)


def test_two_integral_constraints_second_eigenfunction():
    """min int y'^2 with int y^2 = 1 and int y sin(pi x) = 0: sqrt(2) sin(2 pi x),
    lambda_1 = -(2 pi)^2 (L* = y'^2 + l1 y^2 + l2 y sin(pi x)), value (2 pi)^2."""
    fun = cjax.Functional(
        lambda y, yp, x, a: yp**2,
        (0.0, 1.0),
        (0.0, 0.0),
        (
            cjax.IntegralConstraint(lambda y, yp, x, a: y**2, 1.0),
            cjax.IntegralConstraint(lambda y, yp, x, a: y * jnp.sin(jnp.pi * x), 0.0),
        ),
    )
    sol = cjax.solve_functional(fun, discretization=cjax.Chebyshev(24))
    xs = np.linspace(0, 1, 41)
    sign = np.sign(float(sol(0.25)))
    np.testing.assert_allclose(
        sign * sol(jnp.asarray(xs)), math.sqrt(2) * np.sin(2 * np.pi * xs), atol=1e-10
    )
    np.testing.assert_allclose(sol.multipliers.integral[0], -4 * np.pi**2, rtol=1e-10)
    np.testing.assert_allclose(sol.multipliers.integral[1], 0.0, atol=1e-9)
    np.testing.assert_allclose(sol.value, 4 * np.pi**2, rtol=1e-10)


def test_dido_default_start_minimizing_arc():
    """The default start looks for the minimizing extremal: for Dido's area (to be
    maximised) that is the arc below the shore, -y(x), with lambda = +R."""
    length = 2.5
    ref = dido.closed_form(1.0, length)
    sol = cjax.solve_functional(
        dido.functional(1.0), {"length": length}, discretization=cjax.Chebyshev(32)
    )
    rho = ref["radius"] + math.sqrt(ref["radius"] ** 2 - 1)  # as in the scene tests
    xs = np.linspace(-1, 1, 41)
    np.testing.assert_allclose(sol(jnp.asarray(xs)), -ref["y"](xs), atol=rho**-32)
    np.testing.assert_allclose(sol.multipliers.integral[0], ref["radius"], rtol=1e-10)
    np.testing.assert_allclose(sol.value, -ref["value"], rtol=1e-12)
    # A user start overrides: the scene's upper arc.
    up = dido.solve(1.0, length)
    np.testing.assert_allclose(up.value, ref["value"], rtol=1e-12)


def test_straight_line_user_start_is_moved_onto_the_length():
    """The line as `y0` was `functional_singular_kkt` (the length's gradient
    vanishes there); it is now moved onto the length like the default start."""
    fun = cat.functional(0.0, 0.0, 1.0, 0.0)
    args = {"rho_g": 1.0, "length": 1.5}
    sol = cjax.solve_functional(
        fun,
        args,
        discretization=cjax.Chebyshev(32),
        y0=lambda x: 0.0 * x,
        throw=False,
    )
    _check_closed_form(sol, (0, 0, 1, 0), 1.5, 1e-10, 1e-10)


# A curve on the unit sphere: (x, Y(x), Z(x)).
_ON = (jnp.asarray([-0.6, 0.0, 0.8]), jnp.asarray([0.6, 0.8, 0.0]))


def _sphere(start, end):
    return sg.functional(start, end)


def test_boundary_off_constraint_is_refused():
    start, end = _ON
    off = end.at[1].add(0.1)  # |end| = 1.07
    with pytest.raises(ValueError, match="violates the holonomic constraint"):
        cjax.solve_functional(_sphere(start, off), {"radius": 1.0})
    with pytest.raises(ValueError, match="y\\(xL\\)"):
        cjax.solve_functional(_sphere(start * 1.01, end), {"radius": 1.0})
    # Traced: a status; throw=True raises it.
    solve = jax.jit(
        lambda e, throw: cjax.solve_functional(
            _sphere(start, e), {"radius": 1.0}, throw=throw
        ),
        static_argnums=1,
    )
    sol = solve(off, False)
    assert sol.result == cjax.RESULTS.inconsistent_boundary
    assert int(sol.stats["num_steps"]) == 0
    with pytest.raises(Exception, match="violate its holonomic"):
        jax.block_until_ready(solve(off, True))  # (on a GPU: raised when waited for)
    # The radius in args traced: the same.
    sol = jax.jit(
        lambda r: cjax.solve_functional(_sphere(start, end), {"radius": r}, throw=False)
    )(1.001)
    assert sol.result == cjax.RESULTS.inconsistent_boundary


def test_boundary_on_constraint_up_to_rounding_is_accepted():
    # End points computed in floating point (not exactly on the sphere) and a
    # sphere of radius 1000: the tolerance scales with the values.
    theta = 0.3
    start = jnp.asarray([-0.6, 0.8 * math.cos(theta), 0.8 * math.sin(theta)])
    _, end = _ON
    ref = sg.closed_form(np.asarray(start), np.asarray(end))
    sol = cjax.solve_functional(_sphere(start, end), {"radius": 1.0})
    np.testing.assert_allclose(sol.value, ref["value"], rtol=1e-10)
    big = cjax.solve_functional(_sphere(1e3 * start, 1e3 * end), {"radius": 1e3})
    np.testing.assert_allclose(big.value, 1e3 * ref["value"], rtol=1e-10)


@pytest.mark.parametrize("where", ["args", "boundary"])
def test_nan_is_invalid_input(where):
    length = jnp.nan if where == "args" else 1.5
    yr = jnp.nan if where == "boundary" else 0.0
    sol = cjax.solve_functional(
        cat.functional(0.0, 0.0, 1.0, yr),
        {"rho_g": 1.0, "length": length},
        discretization=cjax.PiecewiseLinear(11),
        throw=False,
    )
    assert sol.result == cjax.RESULTS.invalid_input
    start, end = _ON
    if where == "boundary":
        end = end.at[1].set(jnp.nan)
    radius = jnp.nan if where == "args" else 1.0
    sol = cjax.solve_functional(_sphere(start, end), {"radius": radius}, throw=False)
    assert sol.result == cjax.RESULTS.invalid_input


@pytest.mark.parametrize("length", [0.5, 0.9, 1.0 - 1e-9])
def test_length_shorter_than_chord_is_refused(length):
    for solve in (_CHEB, _MESH):
        sol = solve(_ends(0.0, 0.0, 1.0, 0.0), jnp.asarray(length))
        if length < 1 - 1e-6:
            assert sol.result == cjax.RESULTS.infeasible_constraints
        else:
            # Within sqrt(eps) of the chord the start counts as feasible: Newton's
            # own failure status.
            assert sol.result != cjax.RESULTS.successful
    if length >= 1 - 1e-6:
        return
    with pytest.raises(eqx.EquinoxRuntimeError, match="length shorter"):
        cjax.solve_functional(
            cat.functional(0.0, 0.0, 1.0, 0.0),
            {"rho_g": 1.0, "length": length},
            discretization=cjax.PiecewiseLinear(11),
        )


def test_length_equal_to_chord_is_refused():
    """Only the straight line has that length, and there its gradient vanishes: no
    multiplier (the tension is infinite)."""
    for ends in [(0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 3.0, 4.0)]:
        chord = math.hypot(ends[2] - ends[0], ends[3] - ends[1])
        for solve in (_CHEB, _MESH):
            sol = solve(_ends(*ends), jnp.asarray(chord))
            assert sol.result == cjax.RESULTS.functional_redundant_constraints


def test_length_equal_to_chord_from_a_given_start_is_refused():
    """The same from a start the user gives (the check then runs after the solve,
    only where it can matter), for a start that sags and for the line itself."""
    fun = cat.functional(0.0, 0.0, 1.0, 0.0)
    args = {"rho_g": jnp.asarray(1.0), "length": jnp.asarray(1.0)}
    starts = (lambda x: -0.1 * jnp.sin(jnp.pi * x), lambda x: 0.0 * x)
    for disc in (cjax.Chebyshev(16), cjax.PiecewiseLinear(21)):
        for y0 in starts:
            sol = cjax.solve_functional(
                fun, args, discretization=disc, y0=y0, throw=False
            )
            assert sol.result == cjax.RESULTS.functional_redundant_constraints


def test_nearly_taut_rope_is_right():
    """A rope 1e-6 longer than the chord: lambda ~ 1/sqrt(excess), ill-conditioned
    but right to the conditioning (excess known to eps / 1e-6 relative)."""
    ref = cat.closed_form(0, 0, 1, 0, 1 + 1e-6)
    sol = _CHEB(_ends(0.0, 0.0, 1.0, 0.0), jnp.asarray(1 + 1e-6))
    assert sol.result == cjax.RESULTS.successful
    np.testing.assert_allclose(
        sol.multipliers.integral[0], ref["multiplier"], rtol=1e-8
    )


@pytest.mark.parametrize("scale", [1e3, -1e3, 1e6])
def test_far_user_start_is_right_or_refused(scale):
    fun = cat.functional(0.0, 0.0, 1.0, 0.0)
    sol = cjax.solve_functional(
        fun,
        {"rho_g": 1.0, "length": 1.5},
        discretization=cjax.Chebyshev(32),
        y0=lambda x: scale * jnp.sin(3 * jnp.pi * x),
        throw=False,
    )
    if sol.result == cjax.RESULTS.successful:
        # Any extremal it returns satisfies the constraint and is the catenary or
        # its mirror image, the arch (multiplier -lambda): the extremals with
        # these ends and length that are graphs. (The start, moved onto the
        # length from itself, may end on either side.)
        ref = cat.closed_form(0, 0, 1, 0, 1.5)
        sign = np.sign(float(sol.multipliers.integral[0]) * ref["multiplier"])
        xs = np.linspace(0, 1, 41)
        np.testing.assert_allclose(
            sol(jnp.asarray(xs)), sign * ref["y"](xs), atol=1e-10
        )
        np.testing.assert_allclose(
            sol.multipliers.integral[0], sign * ref["multiplier"], rtol=1e-10
        )
        np.testing.assert_allclose(sol.value, sign * ref["value"], rtol=1e-10)


def test_continuation_from_a_solution_on_another_interval():
    """A solution as `y0` is mapped affinely onto the new interval. Its values at the
    same x used to be taken, extrapolated beyond its ends: from the rope on (0, 1)
    to (0, 1.05) the polynomial's growth there made the line search fail."""
    first = _CHEB(_ends(0, 0, 1, 0), jnp.asarray(1.55))
    assert first.result == cjax.RESULTS.successful
    for ends in [(0.0, 0.0, 1.05, 0.0), (-0.2, 0.1, 1.0, 0.0)]:
        sol = cjax.solve_functional(
            cat.functional(*ends),
            {"rho_g": 1.0, "length": 1.55},
            discretization=cjax.Chebyshev(32),
            y0=first,
            throw=False,
        )
        _check_closed_form(sol, ends, 1.55, 1e-10, 1e-10)
        assert int(sol.stats["num_steps"]) <= 8
