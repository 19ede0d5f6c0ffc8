"""JAX's persistent compilation cache, in a folder of the user's cache directory.

Compilation dominates a first run (seconds per program, the solves take
milliseconds); with the cache a second process that compiles the same programs reads
them back from disk. Never turned on by importing the library: the command line and
the notebooks call [`constrained_jax.enable_compilation_cache`][] first.
"""

import os
import pathlib

import jax


# The environment switch: `0`, `false`, `off` or `no` turns the cache off; any other
# non-empty value is the folder to use.
COMPILATION_CACHE_ENV = "CONSTRAINED_JAX_COMPILATION_CACHE"
_OFF = frozenset({"0", "false", "off", "no"})


def default_compilation_cache_dir() -> pathlib.Path:
    """`$XDG_CACHE_HOME/constrained_jax/jax`, or `~/.cache/constrained_jax/jax` when
    `XDG_CACHE_HOME` is not set."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join("~", ".cache")
    return pathlib.Path(base).expanduser() / "constrained_jax" / "jax"


def enable_compilation_cache(
    path: str | os.PathLike | None = None, *, min_compile_time_secs: float = 0.5
) -> pathlib.Path | None:
    """Turn on JAX's persistent compilation cache, in a folder of the user's cache
    directory, so that a program compiled once is read back from disk by the next
    process that compiles it (the second `constrained-jax tour` skips nearly all of
    its compilation).

    Call it at startup, before the first `jax.jit` call compiles anything: JAX decides
    once per process whether the cache is used. `constrained-jax` (the command line)
    and the notebooks call it; importing `constrained_jax` does not.

    **Arguments:**

    - `path`: the folder (created if missing). `None` (default): the environment
        variable `CONSTRAINED_JAX_COMPILATION_CACHE` if it names a folder, else
        `$XDG_CACHE_HOME/constrained_jax/jax` (`~/.cache/constrained_jax/jax`
        without `XDG_CACHE_HOME`).
    - `min_compile_time_secs`: programs that compile faster than this are not
        written (JAX's `jax_persistent_cache_min_compile_time_secs`).

    **Returns:** the folder, or `None` when the cache is turned off: the environment
    variable `CONSTRAINED_JAX_COMPILATION_CACHE` set to `0`, `false`, `off` or `no`
    (the command line's `--no-compilation-cache` does the same) leaves JAX's
    configuration as it is.

    !!! note

        The entries are keyed by the program, the JAX version and the device, so a
        stale entry is never used, but the folder is not pruned: delete it to reclaim
        the space. Several processes may share it.
    """
    switch = os.environ.get(COMPILATION_CACHE_ENV, "").strip()
    if switch.lower() in _OFF:
        return None
    if path is None:
        path = switch or default_compilation_cache_dir()
    path = pathlib.Path(path).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update(
        "jax_persistent_cache_min_compile_time_secs", min_compile_time_secs
    )
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
