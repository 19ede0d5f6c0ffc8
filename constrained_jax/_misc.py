"""Small helpers shared by the entry points."""

import functools
import os
import warnings

import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jaxtyping import Array, Bool, PyTree


def default_float_dtype() -> np.dtype:
    """The floating dtype of Python floats and new arrays: `float64` with
    `jax_enable_x64`, `float32` without. The one place the library asks."""
    return np.dtype(jnp.result_type(float))


def float_tolerance(float64_value: float, eps_multiple: float, dtype=None) -> float:
    """A default tolerance that follows the dtype: `float64_value` or
    `eps_multiple * eps`, whichever is larger (`dtype` defaults to
    `default_float_dtype()`). In float64 the first wins for every default of the
    library; in float32 (`eps = 1.2e-7`) the second."""
    dtype = default_float_dtype() if dtype is None else dtype
    return max(float64_value, eps_multiple * float(jnp.finfo(dtype).eps))


# In `simulate`: the step-size controller's default `rtol = atol`, and the default
# `consistency_tol` (1e-8 in float64; 1.2e-5 and 1.2e-4 in float32).
SIMULATE_TOLERANCE = (1e-8, 100.0)
CONSISTENCY_TOLERANCE = (1e-8, 1000.0)


@functools.cache
def _warn_float32_once() -> None:
    eps = float(jnp.finfo(jnp.float32).eps)
    rtol = float_tolerance(*SIMULATE_TOLERANCE, jnp.float32)
    consistency = float_tolerance(*CONSISTENCY_TOLERANCE, jnp.float32)
    warnings.warn(
        "constrained_jax: JAX runs without 64-bit floats (`jax_enable_x64` is off), "
        f"so computations are in float32 (eps = {eps:.1e}): expect about 1e-5 "
        "relative accuracy, not 1e-10. Default tolerances follow the dtype "
        f"(`simulate`: step-size controller rtol = atol = {rtol:.1e}, "
        f"`consistency_tol` = {consistency:.1e}; Newton tolerances are raised to "
        "100 eps); explicit tolerances below what float32 can reach are warned "
        "about and may not be met. For float64 call "
        "`jax.config.update('jax_enable_x64', True)` (or set JAX_ENABLE_X64=1) at "
        "startup, before creating any array.",
        UserWarning,
        stacklevel=5,
    )


def warn_if_float32() -> None:
    """Warn once per process, on first use of the library, when `jax_enable_x64` is
    off (float32 by default)."""
    if default_float_dtype() != np.float64:
        _warn_float32_once()


def progress_bar(progress: bool, **kwargs):
    """A tqdm progress bar (`kwargs` go to `tqdm.tqdm`), disabled when `progress` is
    false or when the environment variable `TQDM_DISABLE` is set to a non-empty value.

    Any non-empty value disables it, `0`, `false` and `off` included: tqdm itself reads
    the variable so (as `bool` of the string), and every tqdm bar in the process,
    diffrax's `TqdmProgressMeter` included, then agrees. Unlike tqdm, which reads it
    once on import, it is read here on every call."""
    from tqdm import tqdm

    disable = not progress or bool(os.environ.get("TQDM_DISABLE", ""))
    return tqdm(disable=disable, **kwargs)


def as_traced_args(args: PyTree) -> PyTree:
    """Turn Python numbers in `args` into arrays, so that they are traced.

    `eqx.filter_jit` treats Python scalars as static: a new value would recompile. The
    library's contract is that parameters in `args` are traced and never baked in.
    Booleans are left alone (they are flags, not parameters). Called first by every
    entry point, it also warns once when the library runs in float32
    (`warn_if_float32`).
    """
    warn_if_float32()

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


def check_max_steps(max_steps, name: str = "max_steps") -> None:
    if not isinstance(max_steps, int) or isinstance(max_steps, bool) or max_steps < 1:
        raise ValueError(f"`{name}` must be a positive int, got {max_steps!r}.")


def inexact_asarray(x) -> Array:
    """A strongly typed floating array: floating inputs keep their precision (float32
    stays float32), others become the default float. Weak types would recompile on
    every change."""
    warn_if_float32()
    dtype = jnp.result_type(x)
    if not jnp.issubdtype(dtype, jnp.inexact):
        dtype = default_float_dtype()
    return jnp.asarray(x, dtype=dtype)


def full_precision(fn):
    """`fn`, traced and run with matrix products at full precision.

    XLA:GPU computes a float32 `dot` by default in TF32 (a 10-bit mantissa, relative
    errors about 1e-3): the library's products (quadrature and interpolation tables,
    Schur complements, Newton and Gauss-Newton steps) and the user's own inside a
    solve would then miss float32's tolerances, or fail to converge (the float32 sphere
    geodesic stalled at 256 Newton steps on an H100; `benchmarks/README.md`). Each
    public solve is therefore traced under `jax.default_matmul_precision("highest")`,
    for its own products and the user's functions it calls. (XLA:CPU computes every
    float32 and float64 product in full precision anyway: on a CPU nothing
    changes.)"""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapper
