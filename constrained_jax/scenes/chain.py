"""An N-link pendulum chain in Cartesian coordinates: the scaling scene.

`N` point masses `m` hang in a chain of massless rods of length `l` from a fixed pivot
at the origin. Coordinates are the Cartesian positions, `q = (x_1, y_1, ..., x_N,
y_N)` (`n = 2N`, `y` up), and each rod is one holonomic constraint (`k = N`)

    G_j = (|P_j - P_{j-1}|^2 - l^2) / (2 l) = 0,    P_0 = 0,

so `L = m |qdot|^2 / 2 - m g sum_i y_i`. The mass matrix is diagonal and the
constraint Jacobian has 4 nonzeros per row (2 in the first): the Schur complement
`A M^-1 A^T` is tridiagonal, and a solver that sees this structure solves the
equations of motion in `O(N)` where a dense one needs `O(N^3)`.

For `N = 1` it is the Cartesian pendulum (`constrained_jax.scenes.pendulum`, with the
squared form of the rod constraint): `theta(t)` has the same closed-form period. For
any `N` the motion conserves the energy `T + V` and keeps the rods at length `l`.
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._constraints import Holonomic
from .._system import LagrangianSystem


def _points(q):
    return q.reshape(-1, 2)


def lagrangian(q, qd, t, args) -> Float[Array, ""]:
    """`L = m |qdot|^2 / 2 - m g sum_i y_i`."""
    m, g = args["m"], args["g"]
    return 0.5 * m * jnp.dot(qd, qd) - m * g * jnp.sum(_points(q)[:, 1])


def rods(q, t, args) -> Float[Array, " N"]:
    """`G_j = (|P_j - P_{j-1}|^2 - l^2) / (2 l)`, `P_0 = 0`."""
    p = _points(q)
    prev = jnp.concatenate([jnp.zeros((1, 2), p.dtype), p[:-1]])
    d = p - prev
    l = args["l"]
    return (jnp.sum(d * d, axis=1) - l * l) / (2 * l)


def system(**kwargs) -> LagrangianSystem:
    """The chain's `LagrangianSystem` (keyword arguments go to its constructor)."""
    return LagrangianSystem(lagrangian, constraints=(Holonomic(rods),), **kwargs)


def default_args(m=1.0, g=9.81, l=1.0) -> dict:
    return {
        "m": jnp.asarray(m, float),
        "g": jnp.asarray(g, float),
        "l": jnp.asarray(l, float),
    }


def state(num_links: int, theta0, args, thetadot0=0.0):
    """`(q, qd)` of a straight chain at angle `theta0` from the downward vertical,
    turning rigidly about the pivot at rate `thetadot0` (admissible: every rod
    keeps its length to first order, `A qdot = 0`)."""
    theta0 = jnp.asarray(theta0, float)
    l = args["l"]
    radius = l * jnp.arange(1, num_links + 1, dtype=theta0.dtype)
    x, y = radius * jnp.sin(theta0), -radius * jnp.cos(theta0)
    xd, yd = radius * jnp.cos(theta0) * thetadot0, radius * jnp.sin(theta0) * thetadot0
    q = jnp.stack([x, y], axis=1).reshape(-1)
    qd = jnp.stack([xd, yd], axis=1).reshape(-1)
    return q, qd


def energy(q, qd, args) -> Float[Array, ""]:
    """`T + V`, conserved."""
    m, g = args["m"], args["g"]
    return 0.5 * m * jnp.dot(qd, qd) + m * g * jnp.sum(_points(q)[:, 1])


def link_lengths(q) -> Float[Array, " N"]:
    """`|P_j - P_{j-1}|`, all equal to `l` on the constraint manifold."""
    p = _points(q)
    prev = jnp.concatenate([jnp.zeros((1, 2), p.dtype), p[:-1]])
    return jnp.linalg.norm(p - prev, axis=1)
