"""The volume of a cylinder under a constraint (the lecture's first example).

Extremize `V(a, h) = pi a^2 h` (radius `a`, height `h`) subject to

    G(a, h) = 2 pi a + h^2 / b - l = 0        (b, l fixed).

With `V* = V + lambda G` the stationarity conditions give `lambda = -a h`,
`a = 2 h^2 / (pi b)`, and then

    h = sqrt(b l / 5),   a = 2 l / (5 pi),
    lambda = -2 b^(1/2) l^(3/2) / (5^(3/2) pi),   V* = 4 b^(1/2) l^(5/2) / (5^(5/2) pi).

By the envelope theorem `dV*/dl = lambda dG/dl = -lambda`.

**With a cap on the height**, `h <= h_max` (an inequality, `H = h - h_max <= 0`,
multiplier `mu`; maximizing, so `mu <= 0` in the convention
`grad V + lambda grad G + mu grad H = 0`): the cap binds when
`h_max < sqrt(b l / 5)`, and then `h = h_max`, `a = (l - h^2 / b) / (2 pi)` from `G`,
`lambda = -a h` and `mu = a (2 h^2 / b - pi a)` from stationarity; otherwise the answer
above with `mu = 0`. The envelope theorem gives `dV*/dh_max = -mu`.
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._extremize import extremize, Extremum
from .._solver.kkt_solver import AbstractKKTSolver
from .._solver.newton import Newton


def volume(x: Float[Array, "2"], args: dict) -> Float[Array, ""]:
    """`V = pi a^2 h`, with `x = (a, h)`."""
    a, h = x[0], x[1]
    return jnp.pi * a**2 * h


def constraint(x: Float[Array, "2"], args: dict) -> Float[Array, "1"]:
    """`G = 2 pi a + h^2 / b - l`."""
    a, h = x[0], x[1]
    return jnp.stack([2 * jnp.pi * a + h**2 / args["b"] - args["l"]])


def closed_form(b, l) -> dict[str, Float[Array, ""]]:
    """The lecture's closed form: `a`, `h`, the multiplier and the extremal volume."""
    b, l = jnp.asarray(b), jnp.asarray(l)
    return {
        "a": 2 * l / (5 * jnp.pi),
        "h": jnp.sqrt(b * l / 5),
        "multiplier": -2 * jnp.sqrt(b) * l**1.5 / (5**1.5 * jnp.pi),
        "volume": 4 * jnp.sqrt(b) * l**2.5 / (5**2.5 * jnp.pi),
    }


def capped_closed_form(b, l, h_max) -> dict[str, Float[Array, ""]]:
    """The closed form with the cap `h <= h_max`: `a`, `h`, the multipliers `lambda`
    and `mu` (of the cap), the volume, and whether the cap binds (`active`)."""
    b, l, h_max = jnp.asarray(b), jnp.asarray(l), jnp.asarray(h_max)
    free = closed_form(b, l)
    active = h_max < free["h"]
    h = jnp.where(active, h_max, free["h"])
    a = jnp.where(active, (l - h**2 / b) / (2 * jnp.pi), free["a"])
    return {
        "a": a,
        "h": h,
        "multiplier": -a * h,
        "cap_multiplier": jnp.where(active, a * (2 * h**2 / b - jnp.pi * a), 0.0),
        "volume": jnp.pi * a**2 * h,
        "active": active,
    }


def initial_guess(b, l) -> Float[Array, "2"]:
    """A feasible start: half of the budget `l` on the radius, half on the height."""
    b, l = jnp.asarray(b), jnp.asarray(l)
    return jnp.stack([l / (4 * jnp.pi), jnp.sqrt(b * l / 2)])


def solve(
    b=1.0, l=1.0, *, solver: AbstractKKTSolver = Newton(), throw: bool = True
) -> Extremum:
    """Extremize the volume for the given `b` and `l`."""
    args = {"b": jnp.asarray(b, float), "l": jnp.asarray(l, float)}
    return extremize(
        volume,
        initial_guess(b, l),
        args,
        constraints=constraint,
        solver=solver,
        throw=throw,
    )


def solve_capped(
    b=1.0,
    l=1.0,
    h_max=0.4,
    *,
    solver: AbstractKKTSolver = Newton(),
    throw: bool = True,
) -> Extremum:
    """Maximize the volume for the given `b` and `l` with the height capped,
    `h <= h_max` (as the bound `upper = (inf, h_max)`; the cap's multiplier is
    `sol.inequality_multipliers[1]`)."""
    args = {"b": jnp.asarray(b, float), "l": jnp.asarray(l, float)}
    upper = jnp.stack([jnp.asarray(jnp.inf), jnp.asarray(h_max, float)])
    return extremize(
        volume,
        initial_guess(b, l),
        args,
        constraints=constraint,
        upper=upper,
        sense="maximize",
        solver=solver,
        throw=throw,
    )
