"""Type aliases used in signatures throughout the library.

Shapes follow the physics: `n` unknowns (or generalized coordinates), `k` constraints.
"""

from collections.abc import Callable
from typing import Any, TypeAlias

from jaxtyping import Array, ArrayLike, Float, PyTree


Args: TypeAlias = PyTree[Any]
"""Parameters passed last to every user callable; traced, never baked in."""

X: TypeAlias = PyTree[Float[Array, "..."]]
"""The unknowns of an extremization: an array of shape `(n,)` or a pytree of arrays."""

Scalar: TypeAlias = Float[Array, ""]
ScalarLike: TypeAlias = float | Float[ArrayLike, ""]
"""A scalar, e.g. a time `t`: a Python float or a 0-dimensional array."""

ObjectiveFn: TypeAlias = Callable[[X, Args], Scalar]
"""`F(x, args) -> scalar`: the function to extremize."""

ConstraintFn: TypeAlias = Callable[[X, Args], Float[Array, " k"]]
"""`G(x, args) -> (k,)`: the equality constraints `G_j(x) = 0`."""
