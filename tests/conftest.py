import os

import jax
import pytest


# The tests never write JAX's persistent compilation cache: the tour run in-process
# (`test_cli.py`) and the notebooks' kernels call `cjax.enable_compilation_cache()`,
# which would turn it on for the rest of the worker and fill the user's
# `~/.cache/constrained_jax` (an xdist worker crashed inside XLA while compiling with
# the cache on). `test_compilation_cache.py` turns it on where it is the subject, in
# subprocesses and under `monkeypatch`.
os.environ["CONSTRAINED_JAX_COMPILATION_CACHE"] = "0"


# Tests run in float64 with strict dtype promotion (no silent float32 <-> float64
# mixing); float32 checks opt back in explicitly.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def getkey():
    """Fresh PRNG keys on demand, deterministic per test."""
    key = jax.random.key(5678)

    def _getkey():
        nonlocal key
        key, subkey = jax.random.split(key)
        return subkey

    return _getkey
