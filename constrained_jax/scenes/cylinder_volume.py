"""The volume of a cylinder under a constraint (the lecture's first example).

Extremize `V(a, h) = pi a^2 h` (radius `a`, height `h`) subject to

    G(a, h) = 2 pi a + h^2 / b - l = 0        (b, l fixed).

With `V* = V + lambda G` the stationarity conditions give `lambda = -a h`,
`a = 2 h^2 / (pi b)`, and then

    h = sqrt(b l / 5),   a = 2 l / (5 pi),
    lambda = -2 b^(1/2) l^(3/2) / (5^(3/2) pi),   V* = 4 b^(1/2) l^(5/2) / (5^(5/2) pi).

By the envelope theorem `dV*/dl = lambda dG/dl = -lambda`.
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._extremize import extremize, Extremum
from .._solver.newton import AbstractKKTSolver, Newton


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
