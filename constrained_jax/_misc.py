"""Small helpers shared by the entry points."""

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Bool, PyTree


def as_traced_args(args: PyTree) -> PyTree:
    """Turn Python numbers in `args` into arrays, so that they are traced.

    `eqx.filter_jit` treats Python scalars as static: a new value would recompile. The
    library's contract is that parameters in `args` are traced and never baked in.
    Booleans are left alone (they are flags, not parameters).
    """

    def convert(leaf):
        if isinstance(leaf, (bool, np.bool_)):
            return leaf
        if isinstance(leaf, (int, float, complex, np.number)):
            return jnp.asarray(leaf)
        return leaf

    return jtu.tree_map(convert, args)


def all_finite(tree: PyTree) -> Bool[Array, ""]:
    """True if every floating-point leaf of `tree` is finite (other leaves ignored)."""
    ok = jnp.array(True)
    for leaf in jtu.tree_leaves(tree):
        is_array = isinstance(leaf, (jax.Array, np.ndarray, np.generic))
        if is_array and jnp.issubdtype(leaf.dtype, jnp.inexact):
            ok = ok & jnp.all(jnp.isfinite(leaf))
    return ok


def check_max_steps(max_steps) -> None:
    if not isinstance(max_steps, int) or isinstance(max_steps, bool) or max_steps < 1:
        raise ValueError(f"`max_steps` must be a positive int, got {max_steps!r}.")


def inexact_asarray(x) -> Array:
    """A strongly typed floating array: floating inputs keep their precision (float32
    stays float32), others become the default float. Weak types would recompile on
    every change."""
    dtype = jnp.result_type(x)
    if not jnp.issubdtype(dtype, jnp.inexact):
        dtype = jnp.result_type(float)
    return jnp.asarray(x, dtype=dtype)
