"""XLA:CPU's older code generator: faster compilation, for compile-bound work.

XLA compiles each program once per process (seconds for a simulation; the solves take
milliseconds), so a first run, a notebook or a tour is mostly compilation. On the CPU,
XLA's newer fusion emitters compile our programs about 2x slower than its older code
generator (`benchmarks/code_generator.py`; table in `benchmarks/README.md`, "XLA:CPU's
older code generator, opt-in"): in a fresh process the first `jit(simulate)` of the
two rolling cylinders takes 1.5 s instead of 2.5 s (XLA's part 0.7 s instead of 1.6
s), the tour's release program 4.8 s instead of 6.1 s, and `constrained-jax tour` 24-27
s instead of 36-41 s. The price is run time: 0-27 % slower (the two cylinders'
equations of motion batched over 1e4 states 27 %, a gradient through `simulate` 22 %,
one trajectory 5 %). So it is not the library's default: the command line turns it on
(`--xla-defaults` keeps XLA's), and users opt in with
[`constrained_jax.use_fast_compilation`][] at the top of a script or a notebook.

XLA reads its flags (the environment variable `XLA_FLAGS`) once, when JAX starts its
CPU backend at the first computation: not at `import jax` or
`import constrained_jax`. A flag XLA does not know aborts the process, so the flag is
only set for the jaxlib it was measured with.
"""

import importlib.metadata
import os
import warnings

from jax._src import xla_bridge


_FLAG = "--xla_cpu_use_fusion_emitters"
# jaxlib 0.11 no longer knows the flag (`benchmarks/gpu.md`: a fatal abort at backend
# start), so it is set only for the versions it was measured with.
_KNOWN_JAXLIB = frozenset({"0.10.2"})


def _jaxlib_version() -> str:
    try:
        return importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


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
    """Compile with XLA:CPU's older code generator for the rest of the process: about
    2x faster compilation by XLA, the same results to round-off, and up to 27 % slower
    run time.

    For work that compiles more than it runs (first runs, notebooks, small studies):
    `constrained-jax tour` takes 24-27 s instead of 36-41 s, the first
    `jit(simulate)` of the two rolling cylinders 1.5 s instead of 2.5 s (XLA's part
    0.7 s instead of 1.6 s). Compiled programs run 0-27 % slower: the two cylinders'
    equations of motion batched over 1e4 states 27 %, a gradient through `simulate`
    22 %, one trajectory 5 %, a batch of 1,000 trajectories 11 %. Measured on a
    2-core CPU (`benchmarks/code_generator.py`, fresh processes, medians). Only the
    CPU is affected (the flag is XLA:CPU's).

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
    if xla_bridge.backends_are_initialized():
        raise RuntimeError(
            "use_fast_compilation() must be called before the first JAX computation: "
            "JAX's backend has already started and read XLA_FLAGS. Call it at the top "
            "of the script or notebook (after the imports is fine), or set "
            f"XLA_FLAGS={_FLAG}=false in the environment before starting Python."
        )
    os.environ["XLA_FLAGS"] = f"{flags} {_FLAG}=false".strip()
    return True
