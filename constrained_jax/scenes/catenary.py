"""The hanging rope of fixed length (the lecture's catenary).

A rope of length `C` and weight `rho g` per unit length hangs between `(xL, yL)` and
`(xR, yR)`. Its potential energy and its length are

    U[y] = rho g int y ds = int rho g y sqrt(1 + y'^2) dx,
    C[y] = int ds = int sqrt(1 + y'^2) dx = C.

With one multiplier for the length, `L* = (rho g y + lambda) sqrt(1 + y'^2)`. It does
not depend on `x`, so the "Hamiltonian"

    y' dL*/dy' - L* = -(rho g y + lambda) / sqrt(1 + y'^2) = -H

is constant (`H > 0` is the horizontal tension), and integrating gives the catenary

    y(x) = -lambda / (rho g) + (H / (rho g)) cosh(rho g (x - a) / H).

The constants follow from the ends and the length. With `k = rho g / H`,
`dx = xR - xL`, `dy = yR - yL` and `u = k dx / 2`, subtracting the squares of the
length and height conditions leaves one transcendental equation,

    sinh(u) / u = sqrt(C^2 - dy^2) / dx,

which has a root `u > 0` exactly when the rope is longer than the chord,
`C > sqrt(dx^2 + dy^2)`. Then `tanh(k ((xL + xR)/2 - a)) = dy / C` gives `a`, and
`y(xL) = yL` gives `lambda`.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._discretization import AbstractDiscretization, Chebyshev
from .._functional import (
    Functional,
    FunctionalSolution,
    IntegralConstraint,
    solve_functional,
)


def potential_energy(y, yp, x, args) -> Float[Array, ""]:
    """The Lagrangian `L = rho g y sqrt(1 + y'^2)`."""
    return args["rho_g"] * y * jnp.sqrt(1 + yp**2)


def arc_length(y, yp, x, args) -> Float[Array, ""]:
    """The length density `N = sqrt(1 + y'^2)`, constrained to integrate to `C`."""
    return jnp.sqrt(1 + yp**2)


def rope_length(args) -> Float[Array, ""]:
    """`C`, read from `args["length"]`."""
    return args["length"]


def functional(xl, yl, xr, yr) -> Functional:
    """`U[y]` with fixed ends and the length constraint `int ds = args["length"]`."""
    return Functional(
        potential_energy,
        interval=(xl, xr),
        boundary=(yl, yr),
        integral_constraints=(IntegralConstraint(arc_length, rope_length),),
    )


def _sinhc_minus_one(u: float) -> float:
    """`sinh(u)/u - 1` without cancellation for small `u`."""
    if u < 0.5:
        term, total = 1.0, 0.0
        for j in range(1, 12):
            term *= u * u / ((2 * j) * (2 * j + 1))
            total += term
        return total
    return math.sinh(u) / u - 1


def closed_form(xl, yl, xr, yr, length, rho_g=1.0) -> dict:
    """The catenary through the ends with the given length (float64, NumPy).

    Solves `sinh(u)/u - 1 = sqrt(C^2 - dy^2)/dx - 1` (both sides computed without
    cancellation, so that a nearly taut rope is as accurate as a slack one) by
    bisection to full precision.

    **Returns:** a dict with `y` (a NumPy function of `x`), `slope`, `multiplier`
    (`lambda`), `horizontal_tension` (`H`), `first_integral` (`-H`), `a`, `k`
    (`rho g / H`) and `value` (`U`, the potential energy).

    Raises `ValueError` if `C <= sqrt(dx^2 + dy^2)`: no rope can span the ends.
    """
    xl, yl, xr, yr, length, rho_g = map(float, (xl, yl, xr, yr, length, rho_g))
    dx, dy = xr - xl, yr - yl
    chord = math.hypot(dx, dy)
    if not dx > 0:
        raise ValueError("The catenary needs xL < xR.")
    if not length > chord:
        raise ValueError(
            f"A rope of length {length} cannot span the distance {chord} between the "
            "ends: the length must exceed the chord."
        )
    # sqrt(C^2 - dy^2)/dx - 1 = (C^2 - dy^2 - dx^2) / (dx (sqrt(C^2 - dy^2) + dx)).
    excess = (length - chord) * (length + chord)
    target = excess / (dx * (math.sqrt(length**2 - dy**2) + dx))
    lo, hi = 0.0, 1.0
    while _sinhc_minus_one(hi) < target:
        hi *= 2
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _sinhc_minus_one(mid) < target:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 2e-16 * hi:
            break
    u = 0.5 * (lo + hi)
    k = 2 * u / dx
    xm = 0.5 * (xl + xr)
    a = xm - math.atanh(dy / length) / k
    tension = rho_g / k
    y_c = yl - math.cosh(k * (xl - a)) / k
    multiplier = -rho_g * y_c

    def y(x):
        x = np.asarray(x, dtype=np.float64)
        # y - yL = (cosh(k(x - a)) - cosh(k(xL - a))) / k, without cancellation.
        return yl + 2 / k * np.sinh(k * (x + xl - 2 * a) / 2) * np.sinh(
            k * (x - xl) / 2
        )

    def slope(x):
        return np.sinh(k * (np.asarray(x, dtype=np.float64) - a))

    def antiderivative_cosh2(x):
        t = x - a
        return t / 2 + math.sinh(2 * k * t) / (4 * k)

    value = rho_g * (
        y_c * length + (antiderivative_cosh2(xr) - antiderivative_cosh2(xl)) / k
    )
    return {
        "y": y,
        "slope": slope,
        "multiplier": multiplier,
        "horizontal_tension": tension,
        "first_integral": -tension,
        "a": a,
        "k": k,
        "value": value,
    }


def initial_guess(xl, yl, xr, yr, length):
    """A parabola through the ends with the rope's length (not the catenary).

    `y = line(x) - s 4 t (1 - t)`, `t = (x - xL)/(xR - xL)`, with the sag `s` found by
    bisection so that the parabola's arc length (Gauss-Legendre, 64 points) is `C`.
    Traceable (jit, vmap). Returns a function of `x` for `solve_functional(y0=...)`.
    """
    xl, yl, xr, yr, length = (jnp.asarray(v) for v in (xl, yl, xr, yr, length))
    dtype = jnp.result_type(xl, yl, xr, yr, length)
    tq, wq = np.polynomial.legendre.leggauss(64)
    tq = jnp.asarray((tq + 1) / 2, dtype)
    wq = jnp.asarray(wq / 2, dtype)
    dx = xr - xl
    line_slope = (yr - yl) / dx

    def parabola_length(s):
        slope = line_slope - s * 4 * (1 - 2 * tq) / dx
        return dx * jnp.dot(wq, jnp.sqrt(1 + slope**2))

    def bisect(_, bounds):
        lo, hi = bounds
        mid = (lo + hi) / 2
        short = parabola_length(mid) < length
        return jnp.where(short, mid, lo), jnp.where(short, hi, mid)

    zero = jnp.zeros((), dtype)
    lo, hi = jax.lax.fori_loop(0, 100, bisect, (zero, jnp.asarray(length, dtype)))
    sag = (lo + hi) / 2

    def guess(x):
        t = (x - xl) / dx
        return yl + (yr - yl) * t - sag * 4 * t * (1 - t)

    return guess


def solve(
    xl=0.0,
    yl=0.0,
    xr=1.0,
    yr=0.0,
    length=1.5,
    rho_g=1.0,
    *,
    discretization: AbstractDiscretization = Chebyshev(48),
    throw: bool = True,
) -> FunctionalSolution:
    """Hang the rope with the library, from `solve_functional`'s default start.

    The default start corrects the straight line in smooth modes until it has the
    rope's length and hangs down (the lower of the two candidates), and continues
    in the length from a shallow sag when Newton's method does not converge from
    it directly (deep sags, 20 or 50 times the chord). Works under `jax.jit` and
    `jax.vmap` (all inputs traced).

    Raises `ValueError` (for concrete values) if the rope is not longer than the
    chord; traced, the solver reports `RESULTS.infeasible_constraints` (or, for a
    rope exactly as long as the chord, `RESULTS.redundant_constraints`).
    """
    _check_length(xl, yl, xr, yr, length)
    args = {"rho_g": jnp.asarray(rho_g, float), "length": jnp.asarray(length, float)}
    return solve_functional(
        functional(xl, yl, xr, yr), args, discretization=discretization, throw=throw
    )


def _check_length(xl, yl, xr, yr, length: ArrayLike) -> None:
    try:
        values = [float(v) for v in (xl, yl, xr, yr, length)]
    except (TypeError, jax.errors.ConcretizationTypeError):
        return  # traced: the solver reports failure through `result` instead
    xl, yl, xr, yr, length = values
    chord = math.hypot(xr - xl, yr - yl)
    if not length > chord:
        raise ValueError(
            f"A rope of length {length} cannot span the distance {chord} between the "
            "ends: the length must exceed the chord."
        )
