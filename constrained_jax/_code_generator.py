"""XLA:CPU settings, opted into before the first computation: the older code generator
(faster compilation, for compile-bound work) and small loops compiled into one
function each (faster single trajectories).

XLA compiles each program once per process (seconds for a simulation; the solves take
milliseconds), so a first run, a notebook or a tour is mostly compilation. On the CPU,
XLA's newer fusion emitters compile our programs markedly slower than its older code
generator, which in turn runs some programs slower (`benchmarks/code_generator.py`;
`benchmarks/README.md`, "XLA:CPU settings"). So it is not the library's default: the
command line turns it on (`--xla-defaults` keeps XLA's), and users opt in with
[`constrained_jax.settings.use_fast_compilation`][] at the top of a script or a
notebook.

XLA:CPU runs a program as a sequence of kernels, one launch per fusion, except for a
`while` loop small enough for its `SmallWhileLoopHoistingPass`, which it compiles into
one function. A single trajectory of a small system is such a loop, above XLA's
default limit (1 kB): [`constrained_jax.settings.use_loop_kernels`][] raises the limit
(`benchmarks/README.md`, "XLA:CPU settings").

XLA reads its flags (the environment variable `XLA_FLAGS`) once, when JAX starts its
CPU backend at the first computation: not at `import jax` or
`import constrained_jax`. A flag or backend option XLA does not know aborts the
process, so both are only set for the jaxlib they were measured with.
"""

import importlib.metadata
import operator
import os
import warnings

from ._compat import backends_started


_FLAG = "--xla_cpu_use_fusion_emitters"
# jaxlib 0.11 no longer knows the flag (a fatal abort at backend start: `benchmarks/
# README.md`, "On a GPU"), so it is set only for the versions it was measured with.
_KNOWN_JAXLIB = frozenset({"0.10.2"})


def _jaxlib_version() -> str:
    try:
        return importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _too_late(name: str) -> bool:
    """Whether JAX's backend has started (and read `XLA_FLAGS`). Where this JAX does
    not say, the flag is set with a warning that it takes effect only if the backend
    has not started yet."""
    started = backends_started()
    if started is None:
        warnings.warn(
            f"{name}: this JAX does not say whether its backend has started; the "
            "setting takes effect only if no computation has run yet.",
            stacklevel=3,
        )
        return False
    return started


def _user_choice(flags: str) -> bool | None:
    """The user's own setting of the flag in `flags`: `True` (the older generator),
    `False` (the fusion emitters) or `None` (not set)."""
    choice = None
    for token in flags.split():
        name, _, value = token.partition("=")
        if name == _FLAG:
            choice = value.strip().lower() in ("false", "0")
    return choice


def use_fast_compilation() -> bool:
    """Compile with XLA:CPU's older code generator for the rest of the process:
    faster compilation by XLA, the same results to round-off, and slower run time for
    some programs (batched equations of motion, gradients through `simulate`).

    For work that compiles more than it runs (first runs, notebooks, small studies);
    the trade is measured by `benchmarks/code_generator.py` (`benchmarks/README.md`,
    "XLA:CPU settings"). Only the CPU is affected (the flag is XLA:CPU's).

    Call it at the top of a script or notebook, before the first computation: XLA
    reads its flags once, when JAX starts its backend (importing `jax` and
    `constrained_jax` does not start it). The command line `constrained-jax` calls it
    (`--xla-defaults` to keep XLA's defaults).

    It appends `--xla_cpu_use_fusion_emitters=false` to the environment variable
    `XLA_FLAGS`, so processes started from this one inherit it (the processes of a
    multi-process `constrained_jax.sweep` are started by the user: call it in each),
    and JAX's persistent compilation cache keys its entries by it.

    **Returns:** `True` when the older code generator will be used: the flag is set
    (now or already by the user). `False`, with a warning, where it is not set: the
    user's `XLA_FLAGS` asks for the fusion emitters
    (`--xla_cpu_use_fusion_emitters=true`), which is respected, or this jaxlib is not
    one the flag was measured with (an unknown flag aborts the process in XLA, so
    XLA's defaults are kept).

    **Raises:** `RuntimeError` if JAX's backend has already started and the flag is
    not set: the call comes too late to change the code generator.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    choice = _user_choice(flags)
    if choice is not None:
        if not choice:
            warnings.warn(
                "use_fast_compilation: XLA_FLAGS sets "
                "--xla_cpu_use_fusion_emitters=true; the user's setting is kept "
                "(XLA's newer fusion emitters).",
                stacklevel=2,
            )
        return choice
    version = _jaxlib_version()
    if version not in _KNOWN_JAXLIB:
        warnings.warn(
            f"use_fast_compilation: the flag {_FLAG}=false is only set for jaxlib "
            f"{', '.join(sorted(_KNOWN_JAXLIB))} (an unknown flag aborts XLA); this "
            f"is jaxlib {version}, so XLA's defaults are kept.",
            stacklevel=2,
        )
        return False
    if _too_late("use_fast_compilation"):
        raise RuntimeError(
            "use_fast_compilation() must be called before the first JAX computation: "
            "JAX's backend has already started and read XLA_FLAGS. Call it at the top "
            "of the script or notebook (after the imports is fine), or set "
            f"XLA_FLAGS={_FLAG}=false in the environment before starting Python."
        )
    os.environ["XLA_FLAGS"] = f"{flags} {_FLAG}=false".strip()
    return True


# XLA:CPU's `SmallWhileLoopHoistingPass` compiles a `while` loop whose body accesses at
# most this many bytes into one function, where XLA's default (1 kB) leaves most
# loops to the thunk runtime: a kernel launch per fusion per iteration.
_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
_EXTRA = "--xla_backend_extra_options"
LOOP_KERNEL_BYTES = 1 << 20  # 1 MB


def _extra_options(flags: str) -> tuple[int | None, dict[str, str]]:
    """The index of the last `--xla_backend_extra_options` token in `flags` (split
    on whitespace; XLA reads the last one) and its options (`key=value`,
    comma-separated)."""
    index, options = None, {}
    for i, token in enumerate(flags.split()):
        name, _, value = token.partition("=")
        if name == _EXTRA:
            index, options = i, {}
            for item in filter(None, value.split(",")):
                key, _, val = item.partition("=")
                options[key] = val
    return index, options


def use_loop_kernels(max_bytes: int = LOOP_KERNEL_BYTES) -> bool:
    """Let XLA:CPU compile each small `while` loop into one function, for the rest of
    the process: single trajectories run several times faster.

    On the CPU, XLA runs a compiled program as a sequence of kernels, one per fusion,
    each launched by its runtime (tens of nanoseconds per launch). A `simulate` of a
    small system is a `while` loop whose body is dozens of tiny kernels, so the
    launches, not the arithmetic, take most of the time. XLA has a pass that compiles
    a loop into a single function instead, but by default only a loop whose body
    touches at most 1 kB. This raises that limit to `max_bytes` (XLA's backend option
    `xla_cpu_small_while_loop_byte_threshold`).

    Single trajectories run several times faster, XLA compiles `simulate` faster (one
    function instead of a kernel per fusion), and the equations of motion inside the
    loop cost about what hand-written ones do (`benchmarks/code_generator.py
    --settings default,loops,fast,fast+loops`; `benchmarks/README.md`, "XLA:CPU
    settings"). Results are the same to round-off. Small batches (`jax.vmap` over
    about a hundred trajectories) run faster too; larger batches, whose loops touch
    more than `max_bytes`, run as before. XLA skips loops that contain custom calls
    (LAPACK, callbacks), `sort`, `scatter` or FFTs.

    Call it at the top of a script or notebook, before the first computation: XLA
    reads its flags once, when JAX starts its backend (importing `jax` and
    `constrained_jax` does not start it). It may be combined with
    [`constrained_jax.settings.use_fast_compilation`][]; the command line
    `constrained-jax` turns both on.

    It appends `--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=`
    `max_bytes` to the environment variable `XLA_FLAGS` (or adds the option to the
    user's `--xla_backend_extra_options`), so processes started from this one
    inherit it, and JAX's persistent compilation cache keys its entries by it.

    **Arguments:**

    - `max_bytes`: the largest number of bytes a loop's body may access to be
        compiled into one function (a positive integer). Single runs are taken from
        16 kB on, batches of about 100 states from 1 MB on (the default); much larger
        limits take large batches onto one thread, which does not pay.

    **Returns:** `True` when the limit is set (now, or already by the user's
    `XLA_FLAGS`, whose value is kept); `False`, with a warning, where the user's
    `XLA_FLAGS` turns the pass off (a limit of 0), or where this jaxlib is not one
    the option was measured with (XLA aborts on a backend option it does not know,
    so XLA's defaults are kept).

    **Raises:** `ValueError` for a `max_bytes` that is not a positive integer;
    `RuntimeError` if JAX's backend has already started and the limit is not set:
    the call comes too late.
    """
    try:
        limit = operator.index(max_bytes)  # an int, a NumPy integer
    except TypeError:
        limit = None
    if isinstance(max_bytes, bool) or limit is None or limit < 1:
        raise ValueError(
            f"use_loop_kernels: `max_bytes` must be a positive integer, got "
            f"{max_bytes!r}."
        )
    flags = os.environ.get("XLA_FLAGS", "")
    index, options = _extra_options(flags)
    if _LOOP_OPTION in options:
        value = options[_LOOP_OPTION]
        if value.strip() in ("0", ""):
            warnings.warn(
                f"use_loop_kernels: XLA_FLAGS sets {_LOOP_OPTION}={value}, which "
                "turns the pass off; the user's setting is kept.",
                stacklevel=2,
            )
            return False
        return True
    version = _jaxlib_version()
    if version not in _KNOWN_JAXLIB:
        warnings.warn(
            f"use_loop_kernels: the backend option {_LOOP_OPTION} is only set for "
            f"jaxlib {', '.join(sorted(_KNOWN_JAXLIB))} (an unknown option aborts "
            f"XLA); this is jaxlib {version}, so XLA's defaults are kept.",
            stacklevel=2,
        )
        return False
    if _too_late("use_loop_kernels"):
        raise RuntimeError(
            "use_loop_kernels() must be called before the first JAX computation: "
            "JAX's backend has already started and read XLA_FLAGS. Call it at the top "
            "of the script or notebook (after the imports is fine), or set "
            f"XLA_FLAGS={_EXTRA}={_LOOP_OPTION}={limit} in the environment before "
            "starting Python."
        )
    option = f"{_LOOP_OPTION}={limit}"
    if index is None:
        os.environ["XLA_FLAGS"] = f"{flags} {_EXTRA}={option}".strip()
        return True
    # The user's own backend options (XLA reads the last such flag): the option is
    # added to them, the rest of `XLA_FLAGS` left as it is.
    token = flags.split()[index]
    value = token.partition("=")[2].rstrip(",")
    merged = f"{_EXTRA}={value},{option}" if value else f"{_EXTRA}={option}"
    start = flags.rindex(token)
    os.environ["XLA_FLAGS"] = flags[:start] + merged + flags[start + len(token) :]
    return True
