"""Small helpers shared by the entry points."""

import functools
import inspect
import operator
import os
import types
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


def _mapping_count_and_limit() -> tuple[int, int] | None:
    """`(memory mappings of this process, vm.max_map_count)`, or `None` off Linux."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            limit = int(f.read())
        with open("/proc/self/maps", "rb") as f:
            count = sum(1 for _ in f)
    except (OSError, ValueError):
        return None
    return count, limit


def warn_near_mapping_limit(fraction: float = 0.75) -> None:
    """Warn where this process holds more than `fraction` of the memory mappings
    Linux allows it: called when a solve is traced (a new program is about to be
    compiled). Each compiled program keeps hundreds of mappings of its code while
    JAX's caches hold it, and XLA:CPU aborts the process at a compilation past
    `vm.max_map_count` (docs/upstream/xla.md)."""
    found = _mapping_count_and_limit()
    if found is None:
        return
    count, limit = found
    if count > fraction * limit:
        warnings.warn(
            f"This process holds {count} memory mappings of the {limit} that Linux "
            "allows it (`vm.max_map_count`), mostly the code of compiled programs "
            "that JAX's caches keep. XLA aborts the process when a compilation "
            "passes the limit. Call `jax.clear_caches()` now (the programs are "
            "compiled again when next needed), or raise the limit (`sysctl "
            "vm.max_map_count=262144`, as root).",
            RuntimeWarning,
            stacklevel=2,
        )


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


def _is_text(leaf) -> bool:
    """A string, or an array of strings or Python objects: nothing JAX can trace."""
    if isinstance(leaf, (str, bytes)):
        return True
    return isinstance(leaf, np.ndarray) and leaf.dtype.kind in "USO"


def as_traced_args(args: PyTree) -> PyTree:
    """Turn Python numbers in `args` into arrays, so that they are traced.

    `eqx.filter_jit` treats Python scalars as static: a new value would recompile. The
    library's contract is that parameters in `args` are traced and never baked in.
    Booleans are left alone (they are flags, not parameters). Integers and complex
    numbers are parameters like any other (a count used in arithmetic, a complex
    amplitude): they stay traced, of their own dtype. A string (or an array of
    strings or objects) cannot be traced and is refused, naming its path in `args`:
    static values belong in the closure of the function. Called first by every entry
    point, it also warns once when the library runs in float32 (`warn_if_float32`).
    """
    warn_if_float32()
    for path, leaf in jtu.tree_flatten_with_path(args)[0]:
        if _is_text(leaf):
            raise ValueError(
                f"args{jtu.keystr(path)} is a {type(leaf).__name__} "
                f"({_short_repr(leaf)}): every leaf of `args` is passed traced, as an "
                "array, and text cannot be. Keep strings and other static settings "
                "out of `args`: close over them in your function (or bind them with "
                "`functools.partial`)."
            )

    def convert(leaf):
        if isinstance(leaf, (bool, np.bool_)):
            return leaf
        if isinstance(leaf, (int, float, complex, np.number)):
            return jnp.asarray(leaf)
        return leaf

    return jtu.tree_map(convert, args)


def _short_repr(leaf) -> str:
    text = repr(leaf)
    return text if len(text) <= 40 else text[:37] + "..."


def _is_number_list(x) -> bool:
    """A (nested) list or tuple of Python or NumPy numbers, as NumPy users write an
    array; named tuples are pytrees, not arrays."""
    if not isinstance(x, (list, tuple)) or hasattr(x, "_fields") or not x:
        return False
    return all(
        _is_number_list(v)
        if isinstance(v, (list, tuple))
        else isinstance(v, (int, float, complex, np.number, np.bool_))
        for v in x
    )


def lists_as_arrays(tree: PyTree) -> PyTree:
    """`tree` with every (nested) list or tuple of plain numbers turned into a NumPy
    array, as NumPy users expect (`x0=[1.0, 2.0]` is the array, not a pytree of two
    scalars); a list of integers is a floating-point array (`x0=[1, 2]`, as SciPy
    reads it); lists holding arrays stay pytrees."""

    def as_array(x):
        array = np.asarray(x)
        if array.dtype.kind in "iu":
            array = array.astype(default_float_dtype())
        return array

    if _is_number_list(tree):
        return as_array(tree)
    return jtu.tree_map(
        lambda x: as_array(x) if _is_number_list(x) else x,
        tree,
        is_leaf=_is_number_list,
    )


def check_unknowns(tree: PyTree, name: str) -> None:
    """Refuse, naming the leaf by its path, a leaf of the unknowns `tree` (`x0`)
    that is not a real floating-point number or array: every leaf is an unknown, so
    an integer or boolean one (perhaps meant as a fixed count) would silently become
    one, and a complex or text one cannot be."""
    leaves = jtu.tree_flatten_with_path(tree)[0]
    if not leaves:
        raise ValueError(f"`{name}` has no arrays in it: pass the starting point.")
    for path, leaf in leaves:
        where = f"{name}{jtu.keystr(path)}" if path else f"`{name}`"
        if _is_text(leaf):
            raise ValueError(
                f"{where} is a {type(leaf).__name__} ({_short_repr(leaf)}): every leaf "
                f"of `{name}` is an unknown and must be a floating-point number or "
                "array. Pass text and other fixed settings by closure."
            )
        try:
            dtype = jnp.result_type(leaf)
        except TypeError:
            raise ValueError(
                f"{where} is a {type(leaf).__name__}, not a number or an array: every "
                f"leaf of `{name}` is an unknown and must be a floating-point array."
            ) from None
        if jnp.issubdtype(dtype, jnp.complexfloating):
            raise ValueError(
                f"{where} is complex ({dtype}): the unknowns are real. Write a complex "
                "unknown as two real ones (its real and imaginary parts)."
            )
        if not jnp.issubdtype(dtype, jnp.floating):
            raise ValueError(
                f"{where} has the dtype {dtype} ({_short_repr(leaf)}): every leaf of "
                f"`{name}` is an unknown, so an integer or boolean leaf would become "
                "one silently. Pass floats (`1.0`, not `1`; `np.array([1.0, 2.0])` or "
                "`.astype(float)`) for an unknown, and put fixed values (counts, "
                "flags) in `args` or the closure of your functions."
            )


def all_finite(tree: PyTree) -> Bool[Array, ""]:
    """True if every floating-point leaf of `tree` is finite (other leaves ignored)."""
    ok = jnp.array(True)
    for leaf in jtu.tree_leaves(tree):
        is_array = isinstance(leaf, (jax.Array, np.ndarray, np.generic))
        if is_array and jnp.issubdtype(leaf.dtype, jnp.inexact):
            ok = ok & jnp.all(jnp.isfinite(leaf))
    return ok


def check_max_steps(max_steps, name: str = "max_steps") -> int:
    """`max_steps` as a positive Python `int`. It sizes buffers, so it is static: a
    NumPy integer (`np.int64(100)`) is accepted (`operator.index`), also inside
    `jax.jit`; a float, a bool or a traced value is not."""
    try:
        if isinstance(max_steps, (bool, np.bool_)):
            raise TypeError
        value = operator.index(max_steps)
    except TypeError:
        raise ValueError(
            f"`{name}` must be a positive integer (a Python or NumPy int: it sizes "
            f"the buffers, so it cannot be traced), got {max_steps!r}."
        ) from None
    if value < 1:
        raise ValueError(f"`{name}` must be a positive integer, got {value!r}.")
    return value


def check_consistency_tol(consistency_tol):
    """A concrete `consistency_tol`, refused unless a number `>= 0` (a negative or
    NaN tolerance would refuse every start, saying that the state is off the
    constraints); a traced one is taken as it is."""
    if isinstance(consistency_tol, jax.core.Tracer):
        return consistency_tol
    number = (int, float, np.number, np.ndarray, jax.Array)
    if (
        isinstance(consistency_tol, (bool, np.bool_))
        or not isinstance(consistency_tol, number)
        or np.ndim(consistency_tol) != 0
    ):
        raise ValueError(
            "`consistency_tol` must be a number >= 0 (or None for the default that "
            f"follows the dtype), got {consistency_tol!r}."
        )
    if not float(consistency_tol) >= 0:  # (NaN fails too.)
        raise ValueError(
            "`consistency_tol` is the largest constraint residual accepted at the "
            "start, relative to `1 + max|q0|`: it must be >= 0 (or None for the "
            f"default that follows the dtype), got {consistency_tol!r}."
        )
    # A Python number stays one (static); an array stays traced.
    if isinstance(consistency_tol, (int, float, np.number)):
        return float(consistency_tol)
    return consistency_tol


def check_signature(fn, what: str, call: str) -> None:
    """Refuse, with a `ValueError` that names `fn`, the call expected and the
    signature given, a user function that cannot be called as `call` (e.g.
    `"G(q, t, args)"`: as many positional arguments as it lists).

    Read from `inspect.signature`, so `functools.partial`, callable objects
    (`equinox.Module`s with `__call__`), jitted functions and `*args` functions are
    judged by what they accept. A callable without a readable signature (some
    built-ins) is not checked here."""
    if not callable(fn):
        raise ValueError(f"{what} must be a callable {call}, got {fn!r}.")
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        return
    names = call[call.index("(") + 1 : call.rindex(")")].split(", ")
    try:
        signature.bind(*names)
    except TypeError:
        pass
    else:
        return
    name = getattr(fn, "__qualname__", None) or type(fn).__qualname__
    name = "the lambda" if name.endswith("<lambda>") else f"`{name}`"
    count = f"{len(names)} positional argument" + ("s" if len(names) > 1 else "")
    advice = ""
    if names[-1] == "args":
        advice = (
            " Every user function takes the parameters `args` last, even when it does "
            f"not use them (`lambda {', '.join(names)}: ...`; see the conventions "
            "page)."
        )
    raise ValueError(
        f"{what} is called as {call}, with {count}, but {name} has the signature "
        f"{signature}.{advice}"
    )


def inexact_asarray(x) -> Array:
    """A strongly typed floating array: floating inputs keep their precision (float32
    stays float32), others become the default float. Weak types would recompile on
    every change."""
    warn_if_float32()
    if isinstance(x, (list, tuple)):
        x = jnp.asarray(x)  # a NumPy user's list of numbers
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


def publish(namespace: dict, module: str) -> None:
    """Names `module` as the home of the public classes and functions in
    `namespace` (a public module's `globals()`) that a private module of the package
    defines, as NumPy and JAX do: their reprs, `help()` and pickles say
    `constrained_jax.Holonomic`, not `constrained_jax._constraints.Holonomic`.
    (`inspect.getsource` of such a class then looks in `module`'s file and fails:
    the source is in the private module named by its methods' `__code__`.)"""
    package = module.split(".")[0]
    for name, obj in namespace.items():
        home = getattr(obj, "__module__", None)
        if (
            not name.startswith("_")
            and isinstance(obj, (type, types.FunctionType))
            and isinstance(home, str)
            and home.startswith(package + ".")
            and any(part.startswith("_") for part in home.split(".")[1:])
        ):
            obj.__module__ = module
