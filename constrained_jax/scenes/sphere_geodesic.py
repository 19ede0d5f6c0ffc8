"""A geodesic on a sphere: a vector-valued problem with a holonomic constraint.

The curve `(x, Y(x), Z(x))`, parametrised by `x`, joins two points of the sphere of
radius `R` and must stay on it. Minimise its length:

    F[Y, Z] = int sqrt(1 + Y'^2 + Z'^2) dx,     G(Y, Z, x) = x^2 + Y^2 + Z^2 - R^2 = 0.

With the multiplier function `lambda(x)`, in the library's convention

    d/dx (dL/dy') - dL/dy = lambda(x) dG/dy,   y = (Y, Z).

The solution is the arc of the great circle through the two points (in the plane
through the centre). Along it, with arc length `s`, `d2r/ds2 = -r / R^2`, and
`dL/dY' = dY/ds`, so `d/dx(dY/ds) = (ds/dx) d2Y/ds2 = -(ds/dx) Y / R^2 = 2 lambda Y`:

    lambda(x) = -(ds/dx) / (2 R^2),

which varies along the curve (the curve is not parametrised by arc length).
"""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._discretization import AbstractDiscretization, Chebyshev
from .._functional import Functional, FunctionalSolution, solve_functional


def length_density(y, yp, x, args) -> Float[Array, ""]:
    """`L = sqrt(1 + Y'^2 + Z'^2)`, `y = (Y, Z)`."""
    return jnp.sqrt(1 + jnp.sum(yp**2))


def on_sphere(y, x, args) -> Float[Array, ""]:
    """`G = x^2 + Y^2 + Z^2 - R^2`."""
    return x**2 + jnp.sum(y**2) - args["radius"] ** 2


def functional(start, end) -> Functional:
    """Points `start = (xL, YL, ZL)` and `end = (xR, YR, ZR)` on the sphere."""
    return Functional(
        length_density,
        interval=(start[0], end[0]),
        boundary=(jnp.asarray(start[1:]), jnp.asarray(end[1:])),
        holonomic=on_sphere,
    )


def closed_form(start, end, radius=1.0) -> dict:
    """The great-circle arc as functions of `x` (NumPy): `y(x) -> (..., 2)`,
    `multiplier(x)` (`lambda(x)`), and `value` (the arc length `R phi`).

    Raises `ValueError` if the points are not on the sphere or the arc is not a
    graph over `x` (x not monotonic along it).
    """
    p, q = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    for point in (p, q):
        if abs(np.linalg.norm(point) - radius) > 1e-12 * radius:
            raise ValueError("Both points must lie on the sphere.")
    e1 = p / radius
    e2 = q - (q @ e1) * e1
    e2 = e2 / np.linalg.norm(e2)
    phi_end = math.atan2(q @ e2, q @ e1)
    # x(phi) = R rho cos(phi - beta).
    rho = math.hypot(e1[0], e2[0])
    beta = math.atan2(e2[0], e1[0])
    phis = np.linspace(0.0, phi_end, 1001)
    dxdphi = -radius * rho * np.sin(phis - beta)
    if not (np.all(dxdphi > 0) or np.all(dxdphi < 0)):
        raise ValueError("The great-circle arc is not a graph over x.")
    sign = 1.0 if dxdphi[0] > 0 else -1.0

    def phi_of_x(x):
        x = np.asarray(x, dtype=np.float64)
        # cos(phi - beta) = x / (R rho), phi - beta in (-pi, 0) if x increases.
        return beta - sign * np.arccos(np.clip(x / (radius * rho), -1.0, 1.0))

    def y(x):
        phi = phi_of_x(x)[..., None]
        r = radius * (np.cos(phi) * e1 + np.sin(phi) * e2)
        return r[..., 1:]

    def multiplier(x):
        phi = phi_of_x(x)
        ds_dx = 1.0 / (rho * np.abs(np.sin(phi - beta)))
        return -ds_dx / (2 * radius**2)

    return {"y": y, "multiplier": multiplier, "value": radius * abs(phi_end)}


def initial_guess(start, end, radius=1.0):
    """The chord from `start` to `end`, pushed radially (at fixed `x`) onto the
    sphere: feasible, but not the geodesic."""
    p, q = jnp.asarray(start), jnp.asarray(end)

    def guess(x):
        t = (x - p[0]) / (q[0] - p[0])
        yz = (1 - t) * p[1:] + t * q[1:]
        return yz * jnp.sqrt(radius**2 - x**2) / jnp.linalg.norm(yz)

    return guess


START = (-0.5, math.sqrt(0.75), 0.0)
END = (0.5, math.sqrt(0.75) * math.cos(0.8), math.sqrt(0.75) * math.sin(0.8))
"""Default ends: 0.8 rad apart around the x-axis, 1.7 rad apart on the great circle."""


def solve(
    start=START,
    end=END,
    radius=1.0,
    *,
    discretization: AbstractDiscretization = Chebyshev(24),
    throw: bool = True,
) -> FunctionalSolution:
    """The geodesic between two points of the sphere, from `initial_guess`."""
    return solve_functional(
        functional(start, end),
        {"radius": jnp.asarray(radius, float)},
        discretization=discretization,
        y0=initial_guess(start, end, radius),
        throw=throw,
    )
