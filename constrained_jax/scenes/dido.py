"""Dido's problem: the isoperimetric problem with a straight shore.

Enclose the largest area between the shore `y = 0` and a curve `y(x)` of fixed length
`C` from `(-a, 0)` to `(a, 0)`:

    A[y] = int_{-a}^{a} y dx,        int_{-a}^{a} sqrt(1 + y'^2) dx = C.

With `L* = y + lambda sqrt(1 + y'^2)`, the Euler-Lagrange equation is
`d/dx(lambda y' / sqrt(1 + y'^2)) = 1`, i.e. the curvature is constant,
`lambda kappa = 1`: the curve is an arc of a circle of radius `R = -lambda` (the
arc bulges upwards, `kappa = -1/R`). With half-opening angle `theta`,

    R sin(theta) = a,   2 R theta = C   =>   sin(theta) / theta = 2a / C,
    y(x) = sqrt(R^2 - x^2) - R cos(theta),
    A = R^2 (theta - sin(theta) cos(theta)).

For `C < pi a` the arc is a graph with finite slopes. At `C = pi a` it is a
semicircle, with vertical tangents at both ends (the integrand `sqrt(1 + y'^2)` is
singular there); beyond, it is no longer a graph `y(x)`.

`L` does not depend on `x`, so `y' dL*/dy' - L* = -y - lambda / sqrt(1 + y'^2)` is
constant, equal to `R cos(theta)` along the arc.
"""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._discretization import AbstractDiscretization, Chebyshev
from .._functional import (
    Functional,
    FunctionalSolution,
    IntegralConstraint,
    solve_functional,
)


def area(y, yp, x, args) -> Float[Array, ""]:
    """The Lagrangian `L = y` (area under the curve)."""
    return y


def arc_length(y, yp, x, args) -> Float[Array, ""]:
    """`N = sqrt(1 + y'^2)`, constrained to integrate to `C = args["length"]`."""
    return jnp.sqrt(1 + yp**2)


def functional(a) -> Functional:
    """`A[y]` on `[-a, a]` with `y(-a) = y(a) = 0` and the length constraint."""
    return Functional(
        area,
        interval=(-a, a),
        boundary=(0.0, 0.0),
        integral_constraints=(IntegralConstraint(arc_length, lambda p: p["length"]),),
    )


def closed_form(a, length) -> dict:
    """The circular arc: `y` (NumPy function), `radius`, `theta`, `multiplier`
    (`lambda = -R`), `value` (the area) and `first_integral` (`R cos(theta)`).

    Raises `ValueError` unless `2a < C <= pi a` (longer than the shore, and a graph).
    """
    a, length = float(a), float(length)
    if not 2 * a < length <= math.pi * a * (1 + 1e-15):
        raise ValueError("Dido's arc is a graph y(x) for 2a < C <= pi a only.")
    target = 2 * a / length
    lo, hi = 0.0, math.pi / 2
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if math.sin(mid) / mid > target:
            lo = mid
        else:
            hi = mid
    theta = 0.5 * (lo + hi)
    radius = a / math.sin(theta)
    centre = -radius * math.cos(theta)

    def y(x):
        x = np.asarray(x, dtype=np.float64)
        return np.sqrt(np.maximum(radius**2 - x**2, 0.0)) + centre

    return {
        "y": y,
        "radius": radius,
        "theta": theta,
        "multiplier": -radius,
        "value": radius**2 * (theta - math.sin(theta) * math.cos(theta)),
        "first_integral": radius * math.cos(theta),
    }


def initial_guess(a, length):
    """A parabola `s (1 - (x/a)^2)` with the sag `s` of the shallow-arc estimate
    `C ~ 2a + 4 s^2 / (3a)` (not the arc)."""
    sag = jnp.sqrt(0.75 * a * jnp.maximum(length - 2 * a, 0.0))
    return lambda x: sag * (1 - (x / a) ** 2)


def solve(
    a=1.0,
    length=2.5,
    *,
    discretization: AbstractDiscretization = Chebyshev(32),
    throw: bool = True,
) -> FunctionalSolution:
    """Solve Dido's problem with the library, from `initial_guess`."""
    return solve_functional(
        functional(a),
        {"length": jnp.asarray(length, float)},
        discretization=discretization,
        y0=initial_guess(a, length),
        throw=throw,
    )
